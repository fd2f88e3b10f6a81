"""The simulated lab end to end, from its captures, with no truth handed to any stage.

`reflab demo WORKSPACE` runs, on the simulated board and camera (hardware/sim/), exactly the
commands a user runs by hand (README, "The simulated lab step by step"; :func:`commands`):
devices -> target shots -> calibrate camera -> rod shots -> calibrate lights -> sweep (the
simulated user marks the mirror and the sheet and names the surfaces) -> reconstruct -> input
photograph -> fit -> texture -> render (novel view, relit view) -> report. Each reads only what
the earlier ones wrote. The truth goes to WORKSPACE/truth/ (INTERFACES.md, "The simulated lab's
truth") and after each stage the demo prints its error against it and its time.

`--from-truth` keeps the inverse-only demo: the true camera, lamps and geometry are written and
only the photograph is recovered (fit, texture, render).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from app.commands._args import image_size, nonneg_float

HELP = "the simulated lab end to end: capture, calibrate, reconstruct, fit, texture, render, report; scored against truth/"

#: The simulated lab's turntable axis (x, y), metres.
CENTRE = "0,0"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", nargs="?", default="demo-workspace", help="folder to write (default ./demo-workspace)")
    parser.add_argument("--size", type=image_size, default=None,
                        help="image size WIDTHxHEIGHT (default 480x360, the simulated camera's; --from-truth 320x240)")
    parser.add_argument("--quick", action="store_true",
                        help="a shorter run for tests: 24 sweep shots, one texture round, coarser texels")
    parser.add_argument("--from-truth", action="store_true",
                        help="the inverse-only demo: true camera, lamps and geometry; fit, texture and render only")
    parser.add_argument("--noise", type=nonneg_float, default=0.0,
                        help="--from-truth: standard deviation of Gaussian noise added to input.exr (linear units)")
    parser.add_argument("--seed", type=int, default=0, help="--from-truth: noise seed")
    parser.add_argument("--depth", type=int, default=3, choices=range(1, 7), metavar="D",
                        help="internal nodes per path for the photograph and the model (default 3)")
    parser.add_argument("--truth-only", action="store_true",
                        help="write WORKSPACE/truth/ and stop (to score the stepwise commands of README by hand)")


def commands(workspace, size=(480, 360), quick: bool = False) -> list[tuple[str, list[str]]]:
    """The stepwise commands of the demo, (stage, argv of `reflab`), as README lists them."""
    from hardware.sim.props import LabProps
    from hardware.workspace import Workspace

    ws, props = str(workspace), LabProps()
    truth = Workspace(Workspace(workspace).truth)
    sim = ["--port", "sim", "--camera", "sim"]  # later captures take camera.json's size
    x0, x1, y0, y1 = props.card
    inset = 0.005  # the card's region, inside its edges
    card = [f"{x0 + inset:g}", f"{x1 - inset:g}", f"{y0 + inset:g}", f"{y1 - inset:g}"]
    return [
        ("devices", ["hardware", "--port", "sim", "status"]),
        ("target shots", ["capture", "calibration", ws, *sim, "--size", f"{size[0]}x{size[1]}"]),
        ("calibrate camera", ["calibrate", "camera", ws, "--grid", props.grid, "--spacing", f"{props.spacing:g}"]),
        ("rod shots", ["capture", "lights", ws, *sim]),
        ("calibrate lights", ["calibrate", "lights", ws, "--rod-height", f"{props.rod_height:g}",
                              "--sheet-reflectance", f"{props.card_reflectance:g}", "--sheet-region", *card]),
        ("sweep", ["capture", "sweep", ws, *sim] + (["--count", "24"] if quick else [])),
        ("reconstruct", ["reconstruct", ws, "--turntable-centre", CENTRE]),
        ("input", ["capture", "input", ws, *sim]),
        ("fit", ["fit", ws] + (["--texture-rounds", "1"] if quick else [])),
        ("texture", ["texture", ws]),
        ("render novel", ["render", ws, "--camera", str(truth.view("novel")[0]), "-o", str(Workspace(ws).view("novel")[1])]),
        ("render relit", ["render", ws, "--lights", str(truth.view("relit")[0]), "-o", str(Workspace(ws).view("relit")[1])]),
        ("report", ["report", ws]),
    ]


def run(args) -> int:
    if args.from_truth:
        from app.demo_from_truth import run_from_truth

        return run_from_truth(args)
    from app.cli import main
    from app import demo_score as score
    from hardware.workspace import Workspace

    root = Path(args.workspace)
    size = args.size or (480, 360)
    start = time.perf_counter()
    t0 = time.perf_counter()
    truth = score.write_truth(root, size, depth=args.depth)
    print(f"[demo] wrote the truth to {Workspace(root).truth} ({time.perf_counter() - t0:.1f} s)")
    if args.truth_only:
        return 0
    rows = []
    for stage, argv in commands(root, size, args.quick):
        print(f"[demo] $ reflab {' '.join(argv)}", flush=True)
        t0 = time.perf_counter()
        code = main(argv)
        seconds = time.perf_counter() - t0
        if code:
            print(f"[demo] stage {stage} failed (exit {code}) after {seconds:.1f} s: later stages skipped")
            return code
        error = score.score_stage(stage, root, truth)
        rows.append((stage, seconds, error))
        print(f"[demo] {stage}: {seconds:.1f} s{'; ' + error if error else ''}", flush=True)
    print("[demo] stage             time (s)  error against truth/")
    for stage, seconds, error in rows:
        print(f"[demo] {stage:<17} {seconds:8.1f}  {error}")
    print(f"[demo] done in {time.perf_counter() - start:.1f} s")
    return 0
