"""What the stages left in a workspace, read defensively, and the terminal summary built from it.

Every file is optional: a stage that did not run leaves nothing and its section is skipped. A file
that exists but cannot be read (cut off mid-write, not JSON, a broken image) is *unreadable*: it
is recorded with the reason, named in the report and on stderr, and never taken for absent.
Fields are read with ``.get`` so that files written before a field existed (or by a later version
with more fields) still report what they hold.
"""
from __future__ import annotations

import json
from pathlib import Path

from reflab.core.workspace import CAPTURE_FOLDERS, Workspace


class Sources:
    """The workspace's files, each read at most once; unreadable ones recorded in ``unreadable``."""

    def __init__(self, root):
        self.ws = Workspace(root)
        self.root = self.ws.root
        self.unreadable: dict[str, str] = {}
        self._json: dict[Path, object] = {}
        self._images: dict[Path, object] = {}

    def path(self, rel) -> Path:
        return self.root / rel

    def rel(self, path: Path) -> Path:
        """A path the Workspace object gave, relative to the workspace (what :meth:`json` and :meth:`image` take)."""
        return path.relative_to(self.root)

    def json(self, rel) -> dict | None:
        """The JSON object at ``rel`` (relative to the workspace), None when absent or unreadable."""
        path = self.path(rel)
        if path not in self._json:
            self._json[path] = None
            if path.is_file():
                try:
                    obj = json.loads(path.read_text())
                    if not isinstance(obj, dict):
                        raise ValueError(f"expected a JSON object at the top level, got {type(obj).__name__}")
                    self._json[path] = obj
                except (OSError, ValueError) as err:
                    self.unreadable[str(path)] = f"{type(err).__name__}: {err}"
        return self._json[path]

    def image(self, rel):
        """The linear image at ``rel`` as float (H, W, 3), None when absent or unreadable."""
        import numpy as np

        from reflab.core.images import read_image

        path = self.path(rel)
        if path not in self._images:
            self._images[path] = None
            if path.is_file():
                try:
                    img = np.asarray(read_image(path), dtype=np.float64)
                    self._images[path] = img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2)
                except Exception as err:  # noqa: BLE001 - any reader failure makes the file unreadable
                    self.unreadable[str(path)] = f"{type(err).__name__}: {err}"
        return self._images[path]

    def albedo_image(self, rel):
        """An albedo image at ``rel`` (``reflab render --aov albedo``'s form: kd per band, NaN where
        unknown) as float (H, W, 3); None when absent or unreadable. read_image refuses NaN, which
        here is data; inf or another shape makes the file unreadable."""
        import numpy as np

        path = self.path(rel)
        if path not in self._images:
            self._images[path] = None
            if path.is_file():
                try:
                    from reflab.core.images import read_exr

                    img = read_exr(path, np.float64)
                    if img.shape[2] < 3 or np.isinf(img).any():
                        raise ValueError(f"expected finite or NaN kd in 3 bands, got {img.shape[2]} bands"
                                         + (" with inf" if np.isinf(img).any() else ""))
                    self._images[path] = img[:, :, :3]
                except Exception as err:  # noqa: BLE001 - any reader failure makes the file unreadable
                    self.unreadable[str(path)] = f"{type(err).__name__}: {err}"
        return self._images[path]

    # ------------------------------------------------------------------ the stages' files
    camera = property(lambda self: self.json(self.rel(self.ws.camera)))
    lights = property(lambda self: self.json(self.rel(self.ws.lights)))
    marks = property(lambda self: self.json(self.rel(self.ws.marks)))
    sfm = property(lambda self: self.json(self.rel(self.ws.sfm)))
    scene = property(lambda self: self.json(self.rel(self.ws.scene)))
    fit = property(lambda self: self.json(self.rel(self.ws.fit)))
    textures = property(lambda self: self.json(self.rel(self.ws.texture_index)))

    def manifests(self) -> dict[str, dict]:
        """captures/<folder>/manifest.json for each capture folder that has a readable one."""
        out = {}
        for kind, folder in CAPTURE_FOLDERS.items():
            m = self.json(self.rel(self.ws.manifest(kind)))
            if m is not None:
                out[folder] = m
        return out

    # ------------------------------------------------------------------ the simulated lab's truth
    @property
    def truth_dir(self) -> Path:
        return self.ws.truth

    def truth(self, name: str) -> dict | None:
        """The JSON file of truth/ that :class:`Workspace` calls ``name`` (``camera``, ``lights``, ``scene``;
        docs/formats.md, "The simulated lab's truth"), None when there is none."""
        return self.json(self.rel(getattr(Workspace(self.ws.truth), name)))

    def truth_materials(self) -> tuple[dict[str, dict], str]:
        """True material per surface name and the file they came from: truth/scene.json, else the older
        truth.json beside the workspace's files; ({}, "") without either."""
        truth = Workspace(self.ws.truth)
        obj, source = self.json(self.rel(truth.scene)), self.rel(truth.scene).as_posix()
        if obj is None:
            obj, source = self.json(self.rel(self.ws.truth_materials)) or {}, self.rel(self.ws.truth_materials).as_posix()
        out = {}
        for s in obj.get("surfaces", []) if isinstance(obj.get("surfaces"), list) else []:
            if isinstance(s, dict) and isinstance(s.get("material"), dict):
                out[str(s.get("name"))] = s["material"]
        return out, source if out else ""


def as_list(x) -> list:
    """``x`` when it is a list, else [] (a field of another shape reads as empty)."""
    return x if isinstance(x, list) else []


def as_dict(x) -> dict:
    """``x`` when it is a dict, else {}."""
    return x if isinstance(x, dict) else {}


def summarise(src: Sources) -> dict:
    """A JSON-ready summary of what each stage left (the terminal text and report.json)."""
    out = {}
    manifests = src.manifests()
    if manifests:
        out["captures"] = {k: {"status": m.get("status"), "shots": len(as_list(m.get("shots"))),
                               "planned": len(as_list(m.get("plan"))), "started": m.get("started"),
                               "updated": m.get("updated"), "error": m.get("error")}
                           for k, m in manifests.items()}
    cam = src.camera
    if cam:
        cal = as_dict(cam.get("calibration"))
        out["camera"] = {"size": [cam.get("width"), cam.get("height")], "K": cam.get("K"), "dist": cam.get("dist"),
                         "rms_px": cal.get("rms_px"), "sigma": cal.get("sigma"), "time_s": cal.get("time_s")}
    lights = src.lights
    if lights:
        out["lights"] = [{"position": l.get("position"), "intensity": l.get("intensity"),
                          "sigma_position": l.get("sigma_position")}
                         for l in as_list(lights.get("lights")) if isinstance(l, dict)]
    sfm = src.sfm
    if sfm:
        out["reconstruction"] = {k: sfm.get(k) for k in ("sfm", "rigid_turntable", "turntable", "reference", "time_s")
                                 if k in sfm}
    scene = src.scene
    if scene:
        out["scene"] = [{"name": s.get("name"), "brdf": as_dict(s.get("material")).get("brdf"),
                         "ior": as_dict(s.get("material")).get("ior"), "textured": s.get("textured", True)}
                        for s in as_list(scene.get("surfaces")) if isinstance(s, dict)]
    fit = src.fit
    if fit:
        out["fit"] = {"method": fit.get("method"), "depth": fit.get("depth"), "time_s": fit.get("time_s"),
                      "rms": fit.get("rms"), "trace_points": len(as_list(fit.get("trace"))),
                      "status": fit.get("status"), "warnings": fit.get("warnings"),
                      "texture_rounds": len(as_list(as_dict(fit.get("texture_rounds")).get("rounds"))),
                      "undetermined": {s.get("name"): s.get("undetermined", []) for s in as_list(fit.get("surfaces"))
                                       if isinstance(s, dict)}}
    tex = src.textures
    if tex:
        out["texture"] = {k: v for k, v in tex.items() if k != "surfaces"}
    if src.unreadable:
        out["unreadable"] = dict(src.unreadable)
    return out


def _fmt(x, digits=4) -> str:
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    if isinstance(x, list):
        return "[" + ", ".join(_fmt(v, digits) for v in x) + "]"
    if isinstance(x, dict):
        return "{" + ", ".join(f"{k}: {_fmt(v, digits)}" for k, v in x.items()) + "}"
    return str(x)


def summary_text(summary: dict) -> str:
    """The terminal text: one block per stage, every value whole (nothing cut)."""
    lines = []
    for stage, info in summary.items():
        if stage == "unreadable":
            continue
        lines.append(f"[{stage}]")
        if isinstance(info, list):
            for item in info:
                lines.append("  " + ", ".join(f"{k} {_fmt(v)}" for k, v in as_dict(item).items() if v is not None))
        elif not isinstance(info, dict):
            lines.append(f"  {_fmt(info)}")
        else:
            for k, v in info.items():
                if v is not None:
                    lines.append(f"  {k}: {_fmt(v)}")
    return "\n".join(lines)
