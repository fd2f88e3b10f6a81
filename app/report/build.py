"""Assemble report.html: read the workspace, render the model, draw the figures, fill the template.

The result is one self-contained HTML file (docs/formats.md, "report.html"): every picture is an
embedded PNG data URI, the style sheet is inline, and nothing is fetched from anywhere.
"""
from __future__ import annotations

import datetime
import tempfile
import time
from pathlib import Path

from reflab.app.report.data import Sources, summarise
from reflab.core.workspace import Workspace

#: Largest width at which the novel and relit views are rendered when there is no truth to match.
VIEW_WIDTH = 320
#: Turn of the synthesized novel view about the vertical axis through the point the input camera looks at.
NOVEL_TURN_DEG = 30.0


def render_model(src: Sources, depth: int) -> dict | None:
    """The recovered model at the input view, beside the input photograph (None without a scene)."""
    if src.scene is None or src.camera is None or src.lights is None:
        return None
    from reflab.inverse.stages import render_workspace

    photo = src.image(src.ws.input_image.relative_to(src.root))
    try:
        image, info = render_workspace(src.root, depth=depth)
    except Exception as err:  # noqa: BLE001 - the report shows what failed and goes on
        return {"image": None, "error": f"{type(err).__name__}: {err}"}
    return {"image": image, "photo": photo, "textured": info.get("texture_nodes") is not None,
            "trees_s": info.get("trees_s"), "render_s": info.get("render_s")}


def render_albedo(src: Sources, depth: int) -> dict | None:
    """The recovered model's albedo AOV at the input view (``reflab render --aov albedo``'s code, the
    trees from the cache) and the recovered surface seen at each pixel, to compare with
    truth/albedo.exr; None without that file or textures/."""
    import numpy as np

    if (not src.ws.truth_albedo.is_file() or src.textures is None or src.scene is None or src.camera is None
            or src.lights is None):
        return None
    from reflab.inverse.stages import render_workspace

    try:
        albedo, info = render_workspace(src.root, aov="albedo", depth=depth)
    except Exception as err:  # noqa: BLE001 - the report shows what failed and goes on
        return {"error": f"could not render the albedo ({type(err).__name__}: {err})"}
    trees = info["trees"]
    if trees is None:  # a photograph above --tile-pixels is rendered in tiles, its trees released
        return {"error": "not compared: the photograph is rendered in tiles (above --tile-pixels), "
                         "whose trees are not kept for the per-surface comparison"}
    first = trees.level == 1
    surface = np.full(trees.width * trees.height, -1, dtype=np.int64)
    surface[trees.pixel[first]] = trees.surface[first]
    return {"albedo": albedo, "surface": surface.reshape(trees.height, trees.width)}


def _turned(cam, degrees: float):
    """A Camera turned about the vertical axis through the ground point on its optical axis."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.rotations import axis_rotation

    C, forward = cam.center, cam.R[2]
    s = -C[2] / forward[2] if abs(forward[2]) > 1e-9 and -C[2] / forward[2] > 0 else 1.0
    pivot = C + s * forward
    Rz = axis_rotation((0.0, 0.0, 1.0), degrees)
    R = cam.R @ Rz.T
    return Camera(cam.width, cam.height, cam.K, cam.dist, R, -R @ (pivot + Rz @ (C - pivot)))


def _small(cam, width: int = VIEW_WIDTH):
    return cam if cam.width <= width else cam.scaled(width, max(1, round(cam.height * width / cam.width)))


def render_views(src: Sources, depth: int) -> dict:
    """A novel and a relit view of the recovered model: truth/'s camera and lamps when present, else made up.

    Returns {"novel"|"relit": {"image", "truth", "truth_file", "how"} or {"error"}}; {} when there
    is no recovered model (no fit.json or textures/).
    """
    import numpy as np

    from reflab.inverse.stages import render_workspace
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights, PointLight

    if src.scene is None or src.camera is None or src.lights is None or (src.fit is None and src.textures is None):
        return {}
    out = {}
    with tempfile.TemporaryDirectory(prefix="reflab-report-") as tmp:
        for key in ("novel", "relit"):
            pose, truth_image = Workspace(src.ws.truth).view(key)
            truth_file = src.rel(truth_image).as_posix()
            try:
                cam, lights, how = None, None, src.rel(pose).as_posix()
                if key == "novel":
                    cam = pose
                    if not cam.is_file():
                        cam = _small(_turned(Camera.load(src.ws.camera), NOVEL_TURN_DEG)).save(Path(tmp) / "novel.json")
                        how, truth_file = f"input camera turned {NOVEL_TURN_DEG:g}° about the vertical", None
                else:
                    lights = pose
                    if not lights.is_file():
                        turned = [PointLight([-l.position[1], l.position[0], l.position[2]], l.intensity)
                                  for l in Lights.load(src.ws.lights)]
                        lights = Lights(turned).save(Path(tmp) / "relit.json")
                        cam = _small(Camera.load(src.ws.camera)).save(Path(tmp) / "relit_camera.json")
                        how, truth_file = "lamps turned 90° about the vertical", None
                image, info = render_workspace(src.root, cam, lights, depth=depth)
                # Which pixels the recovered model knows the albedo of (same trees, from the cache).
                albedo, ainfo = render_workspace(src.root, cam, lights, aov="albedo", depth=depth)
            except Exception as err:  # noqa: BLE001 - the report shows what failed and goes on
                out[key] = {"error": f"could not render ({type(err).__name__}: {err})"}
                continue
            truth = src.image(truth_file) if truth_file else None
            out[key] = {"image": np.asarray(image), "albedo": np.asarray(albedo), "unknown": ainfo.get("unknown_pixels"),
                        "known": np.all(np.isfinite(albedo), axis=2), "truth": truth,
                        "truth_file": truth_file, "how": how, "undetermined": info["undetermined_pixels"]}
    return out


def build_report(workspace, *, render: bool = True) -> tuple[Path, dict]:
    """Write WORKSPACE/report.html; return its path and the summary (with ``unreadable`` files).

    Parameters
    ----------
    workspace : path-like
    render : bool
        Re-render the model at the input view (its radiance, and its albedo where truth/albedo.exr
        is there to compare) and render a novel and a relit view (the report's costliest part: one
        tree build per view).
    """
    from reflab.app.report.sections.camera import camera_section
    from reflab.app.report.sections.captures import captures_section
    from reflab.app.report.sections.error_vs_time import error_section
    from reflab.app.report.sections.export import export_section
    from reflab.app.report.sections.fit import fit_section
    from reflab.app.report.sections.geometry import geometry_section
    from reflab.app.report.sections.lights import lights_section
    from reflab.app.report.sections.section import Section
    from reflab.app.report.sections.summary import summary_section
    from reflab.app.report.sections.texture import texture_section
    from reflab.app.report.sections.views import views_section
    from reflab.core.workspace import atomic_write

    t0 = time.perf_counter()
    src = Sources(workspace)
    depth = int((src.fit or {}).get("depth") or 3) if isinstance((src.fit or {}).get("depth"), int) else 3
    model = render_model(src, depth) if render and src.fit is not None else None
    views = render_views(src, depth) if render else {}
    albedo = render_albedo(src, depth) if render else None
    parts = [("summary", "Summary", summary_section, (model, views)), ("captures", "Captures", captures_section, ()), ("camera", "Camera", camera_section, ()),
             ("lights", "Lights", lights_section, ()), ("geometry", "Geometry", geometry_section, ()),
             ("fit", "Fit", fit_section, (model,)), ("texture", "Texture", texture_section, (model, albedo)),
             ("views", "Novel and relit views", views_section, (views,)), ("export", "Export", export_section, ()),
             ("error", "Error against run time", error_section, ())]
    sections = []
    for sid, title, make, extra in parts:
        try:
            section = make(src, *extra)
        except Exception as err:  # noqa: BLE001 - a field of an unexpected shape spoils its section, not the report
            section = Section(sid, title)
            section.note(f"this section could not be drawn from the workspace's files: {type(err).__name__}: {err}", "bad")
        if section is not None:
            sections.append(section)
    summary = summarise(src)
    html = _template().render(
        workspace=str(src.root.resolve()), generated=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        sections=sections, unreadable=src.unreadable, truth=src.truth_dir.is_dir(),
        build_s=f"{time.perf_counter() - t0:.1f}")
    path = src.ws.report
    with atomic_write(path, "w") as f:
        f.write(html)
    return path, summary


def _template():
    from importlib.resources import files

    import jinja2

    env = jinja2.Environment(autoescape=True, undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)
    return env.from_string((files("reflab.app.report") / "templates" / "report.html.j2").read_text(encoding="utf-8"))
