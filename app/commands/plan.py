"""Plan the further photographs that would fix what the fit left undetermined or loose.

`reflab plan WORKSPACE [--max-shots N] [--angles A,B,...] [--turntable-centre X,Y]` reads fit.json,
the photographs (input.exr and inputs/) and the rig (lights.json, the turntable axis reconstruct
found, or --turntable-centre), predicts for every lamp subset at every turntable angle how much
that photograph would shrink each parameter's σ, and writes plan.json: the best shots in order,
each with what it would determine (docs/fit.md, "Several photographs and the plan").
`reflab capture inputs WORKSPACE --plan` then takes them.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

HELP = "plan further photographs (lamps x turntable angle) that would determine what is undetermined (plan.json)"
LOG = logging.getLogger("reflab")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.stages import PlanOptions

    parser.add_argument("workspace", type=Path, help="workspace folder with fit.json")
    table_arguments(parser, PlanOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.core.options import options_from_args
    from reflab.inverse.plan import why
    from reflab.inverse.stages import PlanOptions, plan

    with running("plan") as task:
        r = plan(options_from_args(PlanOptions, args, workspace=args.workspace), task,
                 log=lambda line: LOG.info(f"reflab plan: {line}"))
    rep = r.report
    LOG.info(f"reflab plan: {len(rep['targets'])} parameters undetermined or loose over {len(rep['photographs'])} "
             f"photograph(s); {rep['candidates']} shots considered in {rep['time_s']:.1f} s")
    for s in rep["shots"]:
        LOG.info(f"  {s['name']}: turntable {s['angle_deg']:g} deg, lamps {s['lamps']}: determines {why(s)}")
    if not rep["shots"]:
        LOG.info("reflab plan: no further shot would gain enough")
    if rep["left_open"]:
        LOG.info(f"reflab plan: still open after these shots: {', '.join(rep['left_open'])}")
    LOG.info(f"reflab plan: wrote {r.path}")
    return 0
