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
from pathlib import Path

from reflab.app.commands._args import positive_int

HELP = "plan further photographs (lamps x turntable angle) that would determine what is undetermined (plan.json)"


def _floats(text: str) -> tuple:
    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers separated by commas, got {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", type=Path, help="workspace folder with fit.json")
    parser.add_argument("--max-shots", type=positive_int, default=3, help="shots to plan at most (default 3)")
    parser.add_argument("--angles", type=_floats, default=None,
                        help="turntable angles to consider, degrees, comma-separated (default -165,-150,...,180)")
    parser.add_argument("--turntable-centre", type=_floats, default=None, metavar="X,Y",
                        help="where the turntable axis meets the ground, metres (default: from reconstruct's sweep)")
    parser.add_argument("--reduce", type=positive_int, default=4,
                        help="candidate views are ray-cast at 1/REDUCE of the camera's size (default 4)")


def run(args) -> int:
    from reflab.inverse.stages import PlanOptions, plan

    kw = {} if args.angles is None else {"angles": args.angles}
    r = plan(PlanOptions(args.workspace, max_shots=args.max_shots, turntable_centre=args.turntable_centre,
                         reduce=args.reduce, **kw), log=lambda line: print(f"reflab plan: {line}"))
    rep = r.report
    print(f"reflab plan: {len(rep['targets'])} parameters undetermined or loose over {len(rep['photographs'])} "
          f"photograph(s); {rep['candidates']} shots considered in {rep['time_s']:.1f} s")
    for s in rep["shots"]:
        print(f"  {s['name']}: turntable {s['angle_deg']:g} deg, lamps {s['lamps']}: determines "
              f"{', '.join(s['determines']) or 'nothing new (narrows)'}")
    if not rep["shots"]:
        print("reflab plan: no further shot would gain enough")
    if rep["left_open"]:
        print(f"reflab plan: still open after these shots: {', '.join(rep['left_open'])}")
    print(f"reflab plan: wrote {r.path}")
    return 0
