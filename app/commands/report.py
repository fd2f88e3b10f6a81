"""Summarise a workspace stage by stage: what each stage wrote, its error and its run time.

Prints one block per stage and writes WORKSPACE/report.json. With --bench it also times the
forward model (tree building and re-rendering at 160x120, 320x240, 640x480) on the workspace's
scene, the benchmark quoted in docs/forward-model.md.
"""
from __future__ import annotations

import json
import sys

HELP = "summarise each stage's outputs, errors and run times (and benchmark the forward model)"


def add_arguments(p):
    p.add_argument("workspace", help="workspace folder")
    p.add_argument("--bench", action="store_true", help="also time the forward model on this scene")
    p.add_argument("--depth", type=int, default=3, help="tree depth for --bench (default 3)")


def _loader(unreadable: dict):
    """A JSON reader that returns None for a missing file and records why a present one failed."""
    def load(path):
        if not path.is_file():
            return None
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as err:
            unreadable[str(path)] = f"{type(err).__name__}: {err}"
            return None
    return load


def _fmt(x, digits=4):
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    if isinstance(x, list):
        return "[" + ", ".join(_fmt(v, digits) for v in x) + "]"
    return str(x)


def summarise(ws) -> dict:
    """A JSON-ready summary of what each stage left in the workspace ``ws`` (a Workspace)."""
    out, unreadable = {}, {}
    _load = _loader(unreadable)
    cam = _load(ws.camera)
    if cam:
        cal = cam.get("calibration", {})
        out["camera"] = {"size": [cam.get("width"), cam.get("height")], "K": cam.get("K"), "dist": cam.get("dist"),
                         "rms_px": cal.get("rms_px"), "sigma": cal.get("sigma"), "time_s": cal.get("time_s")}
    lights = _load(ws.lights)
    if lights:
        out["lights"] = [{"position": l.get("position"), "intensity": l.get("intensity"),
                          "sigma_position": l.get("sigma_position")} for l in lights.get("lights", [])]
    sfm = _load(ws.root / "sfm.json")
    if sfm:
        out["reconstruction"] = {k: sfm.get(k) for k in ("sfm", "rigid_turntable", "turntable", "reference", "time_s")
                                 if k in sfm}
    scene = _load(ws.scene)
    if scene:
        out["scene"] = [{"name": s.get("name"), "brdf": s.get("material", {}).get("brdf"),
                         "ior": s.get("material", {}).get("ior"), "textured": s.get("textured", True)}
                        for s in scene.get("surfaces", [])]
    fit = _load(ws.fit)
    if fit:
        out["fit"] = {"method": fit.get("method"), "depth": fit.get("depth"), "time_s": fit.get("time_s"),
                      "rms": fit.get("rms"), "trace_points": len(fit.get("trace", [])),
                      "status": fit.get("status"), "warnings": fit.get("warnings"),
                      "texture_rounds": len((fit.get("texture_rounds") or {}).get("rounds", [])),
                      "undetermined": {s.get("name"): s.get("undetermined", []) for s in fit.get("surfaces", [])}}
    tex = _load(ws.textures / "index.json")
    if tex:
        out["texture"] = {k: v for k, v in tex.items() if k != "surfaces"}
    if unreadable:
        out["unreadable"] = unreadable
    return out


def run(args) -> int:
    from pathlib import Path

    from hardware.workspace import Workspace, WorkspaceError, write_json

    ws = Workspace(args.workspace)
    if not Path(args.workspace).is_dir():
        raise WorkspaceError(args.workspace, expected="a workspace folder", got="missing")
    summary = summarise(ws)
    for path, why in summary.get("unreadable", {}).items():
        print(f"warning: {path} is unreadable, its stage is left out of the report ({why})", file=sys.stderr)
    if not summary:
        print(f"{ws.root}: no stage output found (camera.json, lights.json, scene.json, fit.json, textures/)")
    for stage, info in summary.items():
        if stage == "unreadable":
            continue
        print(f"[{stage}]")
        if isinstance(info, list):
            for item in info:
                print("  " + ", ".join(f"{k} {_fmt(v)}" for k, v in item.items() if v is not None))
        else:
            for k, v in info.items():
                if v is not None:
                    print(f"  {k}: {_fmt(v) if not isinstance(v, dict) else json.dumps(v, default=str)[:200]}")
    if args.bench:
        from inverse.benchmarks import load_scene, machine, run as bench, table

        scene, camera, lights = load_scene(ws.root)
        rows = bench(scene, camera, lights, depth=args.depth)
        summary["benchmark"] = {"machine": machine(), "depth": args.depth, "rows": rows}
        print(f"[benchmark] {machine()}\n{table(rows)}")
    path = write_json(ws.root / "report.json", summary)
    print(f"wrote {path}")
    return 0
