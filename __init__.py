"""reflab: the reflectance of a table-top scene from calibrated photographs, global illumination included.

The package's folders are its layers (docs/architecture.md): ``reflab.core`` (workspace, task,
images), ``reflab.hardware`` (GRBL board, cameras, capture; the simulated lab in
``reflab.hardware.sim``), ``reflab.calibration``, ``reflab.reconstruction``, ``reflab.inverse``
and ``reflab.app`` (command line, GUI, report). Each stage is one function, options in and a typed
result out, with an optional :class:`Task` for progress and cancellation::

    import reflab
    reflab.fit(reflab.FitOptions("demo-workspace"))

Names are loaded on first use, so ``import reflab`` stays light.
"""
from __future__ import annotations

import importlib

__all__ = ["__version__", "Task", "Cancelled", "Workspace", "WorkspaceError", "OptionError",
           "CaptureOptions", "run_capture", "CameraOptions", "calibrate_camera", "LightsOptions",
           "calibrate_lights", "ReconstructOptions", "reconstruct", "FitOptions", "fit",
           "TextureOptions", "texture", "RenderOptions", "render", "ExportOptions", "export",
           "MergeOptions", "merge"]

#: Public name -> module that defines it.
_API = {
    "Task": "reflab.core.task", "Cancelled": "reflab.core.task",
    "Workspace": "reflab.core.workspace", "WorkspaceError": "reflab.core.workspace",
    "OptionError": "reflab.core.workspace",
    "CaptureOptions": "reflab.hardware.capture", "run_capture": "reflab.hardware.capture",
    "CameraOptions": "reflab.calibration.stages", "calibrate_camera": "reflab.calibration.stages",
    "LightsOptions": "reflab.calibration.stages", "calibrate_lights": "reflab.calibration.stages",
    "ReconstructOptions": "reflab.reconstruction.stages", "reconstruct": "reflab.reconstruction.stages",
    "FitOptions": "reflab.inverse.stages", "fit": "reflab.inverse.stages",
    "TextureOptions": "reflab.inverse.stages", "texture": "reflab.inverse.stages",
    "RenderOptions": "reflab.inverse.stages", "render": "reflab.inverse.stages",
    "ExportOptions": "reflab.inverse.export.stage", "export": "reflab.inverse.export.stage",
    "MergeOptions": "reflab.core.brackets", "merge": "reflab.core.brackets",
}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("reflab")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "0+unknown"


def __getattr__(name: str):
    if name == "__version__":
        value = _version()
    elif name in _API:
        value = getattr(importlib.import_module(_API[name]), name)
    else:
        raise AttributeError(f"module 'reflab' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
