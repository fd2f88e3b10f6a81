"""Merge an exposure bracket (several exposures of one view) into one linear photograph.

`reflab merge OUT.exr IN1 IN2 ... [--exposures T1,T2,...]`: camera RAW, EXR and 16-bit PNG/TIFF
frames are merged linearly (each divided by its exposure time, weighted by a hat that gives
clipped pixels and the noise floor no weight); 8-bit JPEG/PNG/TIFF frames through the camera
response curve OpenCV recovers from them (Debevec, or Robertson with --response). The exposure
times come from --exposures, else from the files' EXIF. The result is radiance as an unclipped
frame of --reference-exposure seconds would read it (docs/formats.md, "Exposure brackets"); an
8-bit bracket's is known up to its response curve's scale per band.
"""
from __future__ import annotations

import argparse

from reflab.app.console import LOG

HELP = "merge an exposure bracket (RAW, EXR, 16-bit or 8-bit frames of one view) into one linear EXR"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.brackets import MergeOptions
    from reflab.core.options import add_arguments as table_arguments

    parser.add_argument("output", help="the merged linear image to write (.exr)")
    parser.add_argument("inputs", nargs="+", metavar="INPUT", help="the bracket's frames (two or more)")
    table_arguments(parser, MergeOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.core.brackets import MergeOptions, merge
    from reflab.core.options import options_from_args

    with running("merge") as task:
        r = merge(options_from_args(MergeOptions, args, output=args.output, inputs=args.inputs), task)
    times = ", ".join(f"{t:g}" for t in r.exposures)
    LOG.info(f"reflab merge: {len(r.exposures)} {r.kind} frames, exposures {times} s (from {r.times_from})")
    if r.clipped:
        LOG.warning(f"reflab merge: {100 * r.clipped:.2f} % of the pixels are clipped in every frame (a lower bound "
                    "stands there); add a shorter exposure")
    elif r.unseen:
        LOG.info(f"{100 * r.unseen:.2f} % of the pixels lie in the noise floor of every frame")
    h, w = r.image.shape[:2]
    LOG.info(f"reflab merge: wrote {r.path} ({w}x{h})")
    return 0
