"""Argument types shared by the subcommands: each names the bad value in argparse's message."""
from __future__ import annotations

import argparse
import math


def _number(text: str, kind, what: str):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None


def error_text(exc: Exception) -> str:
    """A stage's error for the command line: an OptionError names the flag (``--rod-height: ...``)."""
    from reflab.core.workspace import OptionError

    return exc.cli_text if isinstance(exc, OptionError) else str(exc)


def positive_int(text: str) -> int:
    """An integer >= 1 (depths, iteration caps)."""
    value = _number(text, int, "an integer >= 1")
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {value}")
    return value


def nonneg_int(text: str) -> int:
    """An integer >= 0 (round counts, where 0 turns a step off)."""
    value = _number(text, int, "an integer >= 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text, float, "a positive number")
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text, float, "a number >= 0")
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def image_size(text: str) -> tuple[int, int]:
    """WIDTHxHEIGHT, at least 2x2."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 320x240, got {text!r}") from None
    if w < 2 or h < 2:
        raise argparse.ArgumentTypeError(f"image size must be at least 2x2, got {text!r}")
    return w, h


def name_value(kind, what: str):
    """The argument type ``NAME=VALUE`` -> (NAME, kind(VALUE)); ``what`` names VALUE in the message."""
    def parse(text: str) -> tuple[str, object]:
        name, sep, value = text.partition("=")
        if not sep or not name or not value:
            raise argparse.ArgumentTypeError(f"expected NAME={what}, got {text!r}")
        return name, _number(value, kind, f"NAME={what}")

    return parse


def float_list(text: str) -> list[float]:
    """Comma-separated numbers."""
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
