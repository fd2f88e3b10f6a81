"""One table per stage: its options dataclass, each field carrying its help, unit and flag.

A stage's ``*Options`` dataclass is the only place an option's default is written. Its fields are
declared with :func:`opt` (a dataclass field whose metadata says how to ask for it); the CLI
builds its flags from them (:func:`add_arguments`, :func:`options_from_args`), the GUI reads
its widgets' starting values, units and tips from them (:func:`default`, :func:`info`,
:func:`describe`), and ``app/steps.py`` passes them on. Fields without :func:`opt` metadata (the
workspace, opened devices, callbacks) are not options a user sets.

Each flag has one meaning in every command that has it (``--depth``: the forward model's
maximum internal nodes per path; ``--grid``: the circle target's COLSxROWS; ``--turntable-centre``:
where the turntable axis meets the ground). An old spelling stays as a hidden alias.

The argument types below (``positive_int``, ...) name the bad value in argparse's message.
"""
from __future__ import annotations

import argparse
import dataclasses
import math

_KEY = "reflab"


def opt(default=dataclasses.MISSING, help: str = "", *, factory=dataclasses.MISSING, unit: str | None = None,
        flag: str | None = None, aliases: tuple = (), type=None, choices=None, metavar=None, nargs=None,
        action: str | None = None, convert=None, required: bool = False, typical=None):
    """A dataclass field that is a user option.

    Parameters
    ----------
    default, factory : the field's default (or a factory for a mutable one).
    help : what it is, one phrase (the unit and the default are added by :func:`describe`).
    unit : its unit ("m", "s", "px", "mm", "deg", "W/sr"), shown in help texts and as GUI suffixes.
    flag : the command-line flag when it is not ``--<name-with-dashes>`` (for a bool that
        defaults to True, the flag that turns it off: ``--no-fit``); a tuple for a short and a long one.
    aliases : old spellings, accepted and hidden.
    type, choices, metavar, nargs, action : as argparse's (``action="append"`` collects a list).
    convert : applied to the parsed value before it goes into the options (``dict`` for pairs).
    required : the CLI requires the flag (the library keeps the default).
    typical : a starting value for a GUI field where the stage itself has no default.
    """
    meta = {_KEY: {"help": help, "unit": unit, "flag": flag, "aliases": tuple(aliases), "type": type,
                   "choices": choices, "metavar": metavar, "nargs": nargs, "action": action, "convert": convert,
                   "required": required, "typical": typical}}
    if factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _field(cls, name: str) -> dataclasses.Field:
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f
    raise KeyError(f"{cls.__name__} has no option {name!r}")


def names(cls) -> list[str]:
    """The fields of ``cls`` that are user options, in declaration order."""
    return [f.name for f in dataclasses.fields(cls) if _KEY in f.metadata]


def default(cls, name: str):
    """The default of option ``name`` of ``cls`` (read from the field each time)."""
    f = _field(cls, name)
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else None


def info(cls, name: str) -> dict:
    """The option's metadata (:func:`opt`'s arguments) with its ``default`` and ``flag`` filled in."""
    out = dict(_field(cls, name).metadata[_KEY])
    out["default"] = default(cls, name)
    flags = out["flag"] or "--" + name.replace("_", "-")
    out["flags"] = flags if isinstance(flags, tuple) else (flags,)
    out["flag"] = out["flags"][-1]  # the long spelling names it in messages
    return out


def show(value) -> str:
    """A default as a user writes it: 480x360, 0,0, 0.015."""
    if isinstance(value, tuple) and len(value) == 2 and all(isinstance(v, int) for v in value):
        return f"{value[0]}x{value[1]}"
    if isinstance(value, (list, tuple)):
        return ",".join(show(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def describe(cls, name: str) -> str:
    """Help text: the phrase, then the unit and the default (none for flags and empty defaults)."""
    i = info(cls, name)
    extra = [f"in {i['unit']}"] if i["unit"] else []
    d = i["default"]
    if d is not None and not isinstance(d, bool) and d != [] and d != {}:
        extra.append(f"default {show(d)}")
    return i["help"] + (f" ({'; '.join(extra)})" if extra else "")


def flag_for(tables, option: str) -> str:
    """The flag of options field ``option`` in the first of ``tables`` that has it (``--<option>`` else)."""
    for cls in tables or ():
        if option in names(cls):
            return info(cls, option)["flag"]
    return "--" + option.replace("_", "-")


def add_arguments(parser, cls, *, only=None, skip=(), override: dict | None = None) -> None:
    """Add a flag per option of ``cls`` to ``parser`` (or an argument group); ``dest`` is the field's name.

    ``only``/``skip`` pick fields; ``override`` maps a field to argparse keywords that replace the
    table's for this command (a command-specific default such as ``None`` meaning "camera.json's").
    The parser remembers ``cls`` (``args._tables``) so that an OptionError names the flag.
    """
    for name in names(cls):
        if (only is not None and name not in only) or name in skip:
            continue
        i = info(cls, name)
        kw = {"dest": name, "default": i["default"], "help": describe(cls, name).replace("%", "%%")}
        if isinstance(i["default"], bool):
            kw["action"] = "store_false" if i["default"] else "store_true"
        else:
            if i["action"]:
                kw["action"] = i["action"]
                kw["default"] = []
            kind = i["type"] or (type(i["default"]) if isinstance(i["default"], (int, float, str)) else None)
            if kind is None and i["default"] is None and i["choices"] is None:
                raise TypeError(f"{cls.__name__}.{name}: an option without a default needs type=")
            if kind is not None:
                kw["type"] = kind
            for key in ("choices", "metavar", "nargs"):
                if i[key] is not None:
                    kw[key] = i[key]
            if i["required"]:
                kw["required"] = True
        kw.update((override or {}).get(name, {}))
        parser.add_argument(*i["flags"], **kw)
        for alias in i["aliases"]:  # accepted, not shown
            hidden = {**kw, "help": argparse.SUPPRESS, "default": argparse.SUPPRESS}
            hidden.pop("required", None)
            parser.add_argument(alias, **hidden)
    tables = parser.get_default("_tables") or ()
    if cls not in tables:
        parser.set_defaults(_tables=(*tables, cls))


def values(cls, args) -> dict:
    """The options of ``cls`` that ``args`` (an argparse namespace) holds, converted."""
    out = {}
    for name in names(cls):
        if hasattr(args, name):
            value, convert = getattr(args, name), info(cls, name)["convert"]
            out[name] = convert(value) if convert is not None and value is not None else value
    return out


def options_from_args(cls, args, **given):
    """``cls(**values(cls, args), **given)``: the stage's options from a command's arguments."""
    return cls(**{**values(cls, args), **given})


# ---------------------------------------------------------------------- argument types
def _number(text: str, kind, what: str):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None


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
