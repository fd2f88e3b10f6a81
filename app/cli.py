"""`reflab`: one subcommand per stage over a shared workspace (docs/formats.md, "Command line").

Each subcommand is a module of ``app/commands`` with ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``. Those modules import nothing heavy at module level, so ``reflab --help``
answers without loading Mitsuba, Open3D, pycolmap or Qt. A stage's flags come from its options
table (reflab.core.options). The global options (-v, -q) are accepted before or after the
command and its subcommand; output goes through the ``reflab`` logger (app/console.py).
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import reflab.app.commands
from reflab.app.console import LOG, setup

#: Exit status of every command, listed in `reflab --help`.
EXIT_CODES = (
    (0, "done"),
    (1, "the stage ran but failed: a device or camera fault, a calibration that found no solution"),
    (2, "bad input: a usage error, a bad option (named by its flag), a bad workspace file (named with its field), "
        "a serial port that cannot be opened or lamp wiring the board cannot follow"),
    (3, "reflab fit: fit.json written with status 'poor fit' (the model does not explain the image)"),
    (130, "cancelled (Ctrl-C): nothing half-written; a capture keeps its finished shots for --resume"),
)


def _command_modules():
    for info in sorted(pkgutil.iter_modules(reflab.app.commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), importlib.import_module(f"reflab.app.commands.{info.name}")


def _global_options(parser: argparse.ArgumentParser, default) -> None:
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="say more (debug lines); global: before or after the command")
    parser.add_argument("-q", "--quiet", action="count", default=default,
                        help="warnings and errors only; global: before or after the command")


def _subparsers(parser: argparse.ArgumentParser):
    """Every parser below ``parser`` (commands and their subcommands)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                yield child
                yield from _subparsers(child)


def build_parser() -> argparse.ArgumentParser:
    import reflab

    parser = argparse.ArgumentParser(
        prog="reflab",
        description="Recover reflectance and texture of a table-top scene from one linear photograph.",
        epilog="exit status:\n" + "\n".join(f"  {code:<4} {text}" for code, text in EXIT_CODES),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"reflab {reflab.__version__}")
    _global_options(parser, 0)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _command_modules():
        p = sub.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    for child in _subparsers(parser):  # a subcommand's value replaces the parent's only when given
        _global_options(child, argparse.SUPPRESS)
    return parser


#: Commands whose WORKSPACE is checked here, before devices open or a report is built
#: (reflab.core.workspace.check_folder): "create" may make it (its parent writable), "write" needs it
#: writable. The stage functions (calibrate, reconstruct, fit, texture, render) check their own.
_WORKSPACE = {"capture": "create", "demo": "create", "report": "write"}


def check_inputs(args) -> None:
    """The workspace of a command without a stage function, checked before any work."""
    from reflab.core.workspace import check_folder

    mode = _WORKSPACE.get(args.command)
    if mode and getattr(args, "workspace", None) is not None:
        check_folder(args.workspace, write=True, create=mode == "create")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    setup((args.verbose or 0) - (args.quiet or 0))
    import errno

    from reflab.app.commands._args import error_text
    from reflab.core.task import Cancelled
    from reflab.core.workspace import OptionError, WorkspaceError

    try:
        check_inputs(args)
        return int(args._run(args) or 0)
    except (WorkspaceError, OptionError) as exc:  # an OptionError names the command's flag
        LOG.error(f"reflab {args.command}: error: {error_text(exc, args)}")
        return 2
    except OSError as exc:  # what no check foresaw (disk full, a folder made read-only meanwhile): one line
        if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT):
            raise
        LOG.error(f"reflab {args.command}: error: {exc.filename or ''}: {exc.strerror}")
        return 2
    except Cancelled:
        LOG.error(f"reflab {args.command}: cancelled; nothing half-written")
        return 130
    except KeyboardInterrupt:
        LOG.error(f"reflab {args.command}: interrupted")
        return 130


if __name__ == "__main__":
    sys.exit(main())
