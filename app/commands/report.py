"""Report on a workspace: WORKSPACE/report.html (pictures, residual plots, error against run time,
comparison with truth/ on the simulated lab), a text summary per stage and report.json.

With --bench it also times the forward model (tree building and re-rendering at 160x120,
320x240, 640x480) on the workspace's scene, the benchmark quoted in docs/forward-model.md.
"""
from __future__ import annotations

from reflab.app.console import LOG

HELP = "write report.html (images, residual plots, error against run time) and summarise each stage"


def add_arguments(p):
    p.add_argument("workspace", help="workspace folder")
    p.add_argument("--no-render", action="store_true",
                   help="skip re-rendering the model and the novel and relit views (faster, fewer pictures)")
    p.add_argument("--bench", action="store_true", help="also time the forward model on this scene")
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.stages import RenderOptions

    # --depth means what it means for render: the forward model's depth, here of the benchmark
    table_arguments(p, RenderOptions, only=("depth",))


def run(args) -> int:
    from pathlib import Path

    from reflab.app.report.build import build_report
    from reflab.app.report.data import summary_text
    from reflab.core.workspace import Workspace, WorkspaceError, write_json

    root = Path(args.workspace)
    if not root.is_dir():
        raise WorkspaceError(args.workspace, expected="a workspace folder", got="missing")
    html, summary = build_report(root, render=not args.no_render)
    for path, why in summary.get("unreadable", {}).items():
        LOG.warning(f"warning: {path} is unreadable, left out of the report ({why})")
    text = summary_text(summary)
    LOG.info(text or f"{root}: no stage output found (captures/, camera.json, lights.json, scene.json, fit.json, textures/)")
    if args.bench:
        from reflab.inverse.forward.benchmarks import load_scene, machine, run as bench, table

        scene, camera, lights = load_scene(root)
        rows = bench(scene, camera, lights, depth=args.depth)
        summary["benchmark"] = {"machine": machine(), "depth": args.depth, "rows": rows}
        LOG.info(f"[benchmark] {machine()}\n{table(rows)}")
    LOG.info(f"wrote {write_json(Workspace(root).report_json, summary)}")
    LOG.info(f"wrote {html}")
    return 0
