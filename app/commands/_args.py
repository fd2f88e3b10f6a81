"""Argument types shared by the subcommands (kept in reflab.core.options beside the options tables,
which name them) and the one-line text of a stage's error."""
from __future__ import annotations

from reflab.core.options import (float_list, flag_for, image_size, name_value, nonneg_float, nonneg_int,  # noqa: F401
                                 positive_float, positive_int)


def error_text(exc: Exception, args=None) -> str:
    """A stage's error for the command line: an OptionError names the flag (``--rod-height: ...``),
    as the command's options table spells it (``args._tables``)."""
    from reflab.core.workspace import OptionError

    if isinstance(exc, OptionError):
        return f"{flag_for(getattr(args, '_tables', ()), exc.option)}: {exc.message}"
    return str(exc)
