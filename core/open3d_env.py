"""Load Open3D once, without its plotly/dash viewer.

``import open3d`` loads ``open3d.visualization.draw_plotly``, which imports plotly and dash: 0.3 s
of every command that reads a mesh or casts rays (half of Open3D's import), for a browser viewer no
stage uses. :func:`open3d` puts a stand-in there that loads the real module on first use.
"""
from __future__ import annotations

import functools
import importlib.util
import sys
import types

_PLOTLY = "open3d.visualization.draw_plotly"
_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _real_plotly():
    """The real draw_plotly module (imports plotly and dash), replacing the stand-in."""
    module = sys.modules.get(_PLOTLY)
    if module is not None and not getattr(module, "_reflab_stand_in", False):
        return module
    import open3d

    spec = importlib.util.spec_from_file_location(_PLOTLY, f"{open3d.__path__[0]}/visualization/draw_plotly.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[_PLOTLY] = module
    spec.loader.exec_module(module)
    return module


def _stand_in() -> types.ModuleType:
    module = types.ModuleType(_PLOTLY, "Loads open3d's plotly viewer on first use (reflab.core.open3d_env).")
    module._reflab_stand_in = True
    for name in _NAMES:
        def call(*args, _name=name, **kwargs):
            return getattr(_real_plotly(), _name)(*args, **kwargs)
        call.__name__ = name
        setattr(module, name, call)
    return module


@functools.lru_cache(maxsize=None)
def open3d():
    """Return the ``open3d`` module (its plotly viewer loaded only when called)."""
    if "open3d" not in sys.modules:
        sys.modules.setdefault(_PLOTLY, _stand_in())
    import open3d as o3d

    return o3d
