"""The simulated lab end to end, from its captures, with no truth handed to any stage.

`reflab demo WORKSPACE` runs the guided acquisition's steps (app/steps.py, the list the GUI
runs) on the simulated board and camera, with the options README's commands give by hand, and
scores each stage against WORKSPACE/truth/ (app/demo_lab.py).

`--from-truth` keeps the inverse-only demo: the true camera, lamps and geometry are written and
only the photograph is recovered (fit, texture, results).
"""
from __future__ import annotations

import argparse

from reflab.app.commands._args import image_size, nonneg_float

HELP = "the simulated lab end to end: capture, calibrate, reconstruct, fit, texture, render, report; scored against truth/"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", nargs="?", default="demo-workspace", help="folder to write (default ./demo-workspace)")
    parser.add_argument("--size", type=image_size, default=None,
                        help="image size WIDTHxHEIGHT (default 480x360, the simulated camera's; --from-truth 320x240)")
    parser.add_argument("--quick", action="store_true", help="a shorter run for tests: 24 sweep shots, one texture round")
    parser.add_argument("--further-rounds", type=int, default=2, metavar="N",
                        help="rounds of plan -> further photographs -> fit after the first fit (default 2; 0: the "
                             "single photograph of the dissertation)")
    parser.add_argument("--from-truth", action="store_true",
                        help="the inverse-only demo: true camera, lamps and geometry; fit, texture and render only")
    parser.add_argument("--noise", type=nonneg_float, default=0.0,
                        help="--from-truth: standard deviation of Gaussian noise added to input.exr (linear units)")
    parser.add_argument("--seed", type=int, default=0, help="--from-truth: noise seed")
    from reflab.core.options import default
    from reflab.inverse.stages import RenderOptions

    parser.add_argument("--depth", type=int, default=default(RenderOptions, "depth"), choices=range(1, 7), metavar="D",
                        help="maximum internal nodes per path of the forward model, for the photograph and the model "
                             f"(1 to 6; default {default(RenderOptions, 'depth')})")
    parser.add_argument("--truth-only", action="store_true",
                        help="write WORKSPACE/truth/ and stop (to score the stepwise commands of README by hand)")


def run(args) -> int:
    if args.from_truth:
        from reflab.app.demo_from_truth import run_from_truth

        return run_from_truth(args)
    from reflab.app.demo_lab import run_lab

    return run_lab(args)
