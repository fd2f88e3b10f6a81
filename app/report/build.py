"""Assemble report.html: read the workspace, render the model, draw the figures, fill the template.

The result is one self-contained HTML file (INTERFACES.md, "report.html"): every picture is an
embedded PNG data URI, the style sheet is inline, and nothing is fetched from anywhere.
"""
from __future__ import annotations

import datetime
import json
import tempfile
import time
from pathlib import Path

from app.report.data import Sources, summarise

#: Largest width at which the novel and relit views are rendered when there is no truth to match.
VIEW_WIDTH = 320
#: Turn of the synthesized novel view about the vertical axis through the point the input camera looks at.
NOVEL_TURN_DEG = 30.0


def render_model(src: Sources, depth: int) -> dict | None:
    """The recovered model at the input view, beside the input photograph (None without a scene)."""
    if src.scene is None or src.camera is None or src.lights is None:
        return None
    from app.commands.render import render_workspace

    photo = src.image(src.ws.input_image.relative_to(src.root))
    try:
        image, info = render_workspace(src.root, depth=depth)
    except Exception as err:  # noqa: BLE001 - the report shows what failed and goes on
        return {"image": None, "error": f"{type(err).__name__}: {err}"}
    return {"image": image, "photo": photo, "textured": info.get("texture_nodes") is not None,
            "trees_s": info.get("trees_s"), "render_s": info.get("render_s")}


def _turned(cam: dict, degrees: float) -> dict:
    """camera.json turned about the vertical axis through the ground point on its optical axis."""
    import numpy as np

    R, t = np.asarray(cam["R"], float), np.asarray(cam["t"], float)
    C, forward = -R.T @ t, R[2]
    s = -C[2] / forward[2] if abs(forward[2]) > 1e-9 and -C[2] / forward[2] > 0 else 1.0
    pivot = C + s * forward
    a = np.radians(degrees)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    R2 = R @ Rz.T
    C2 = pivot + Rz @ (C - pivot)
    return dict(cam, R=R2.tolist(), t=(-R2 @ C2).tolist())


def _scaled(cam: dict, width: int) -> dict:
    from calibration.camera import Camera

    c = Camera.from_json(cam)
    if c.width <= width:
        return cam
    s = c.scaled(width, max(1, round(c.height * width / c.width)))
    return dict(cam, width=s.width, height=s.height, K=s.K.tolist())


def render_views(src: Sources, depth: int) -> dict:
    """A novel and a relit view of the recovered model: truth/'s camera and lamps when present, else made up."""
    import numpy as np

    from app.commands.render import render_workspace

    if src.scene is None or src.camera is None or src.lights is None or (src.fit is None and src.textures is None):
        return {}
    out = {}
    with tempfile.TemporaryDirectory(prefix="reflab-report-") as tmp:
        jobs = {}
        novel_cam = src.truth("novel_camera.json")
        if novel_cam is not None:
            jobs["novel"] = dict(camera=novel_cam, lights=None, truth="truth/novel.exr", how="truth/novel_camera.json")
        else:
            jobs["novel"] = dict(camera=_scaled(_turned(src.camera, NOVEL_TURN_DEG), VIEW_WIDTH), lights=None, truth=None,
                                 how=f"input camera turned {NOVEL_TURN_DEG:g}° about the vertical")
        relit = src.truth("relit_lights.json")
        if relit is not None:
            jobs["relit"] = dict(camera=None, lights=relit, truth="truth/relit.exr", how="truth/relit_lights.json")
        else:
            lamps = json.loads(json.dumps(src.lights))
            for l in lamps.get("lights", []):
                x, y, z = l["position"]
                l["position"] = [-y, x, z]  # each lamp turned 90° about the world's vertical axis
            jobs["relit"] = dict(camera=_scaled(src.camera, VIEW_WIDTH), lights=lamps, truth=None,
                                 how="lamps turned 90° about the vertical")
        for key, job in jobs.items():
            paths = {}
            for what in ("camera", "lights"):
                if job[what] is not None:
                    paths[what] = Path(tmp) / f"{key}_{what}.json"
                    paths[what].write_text(json.dumps(job[what]))
            try:
                image, _ = render_workspace(src.root, paths.get("camera"), paths.get("lights"), depth=depth)
            except Exception as err:  # noqa: BLE001
                out[key] = {"error": f"could not render ({type(err).__name__}: {err})"}
                continue
            truth = src.image(job["truth"]) if job["truth"] else None
            out[key] = {"image": np.asarray(image), "truth": truth, "truth_file": job["truth"], "how": job["how"]}
    return out


def build_report(workspace, *, render: bool = True) -> tuple[Path, dict]:
    """Write WORKSPACE/report.html; return its path and the summary (with ``unreadable`` files).

    Parameters
    ----------
    workspace : path-like
    render : bool
        Re-render the model at the input view and render a novel and a relit view (the report's
        costliest part: one tree build per view).
    """
    from app.report import sections as S
    from hardware.workspace import atomic_write

    t0 = time.perf_counter()
    src = Sources(workspace)
    depth = int((src.fit or {}).get("depth") or 3) if isinstance((src.fit or {}).get("depth"), int) else 3
    model = render_model(src, depth) if render and src.fit is not None else None
    views = render_views(src, depth) if render else {}
    sections = [s for s in (S.captures_section(src), S.camera_section(src), S.lights_section(src),
                            S.geometry_section(src), S.fit_section(src, model), S.texture_section(src),
                            S.views_section(src, views), S.error_section(src)) if s is not None]
    summary = summarise(src)
    html = _template().render(
        workspace=str(src.root.resolve()), generated=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        sections=sections, unreadable=src.unreadable, truth=src.truth_dir.is_dir(),
        build_s=f"{time.perf_counter() - t0:.1f}")
    path = src.root / "report.html"
    with atomic_write(path, "w") as f:
        f.write(html)
    return path, summary


def _template():
    from importlib.resources import files

    import jinja2

    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    return env.from_string((files("app.report") / "templates" / "report.html.j2").read_text(encoding="utf-8"))
