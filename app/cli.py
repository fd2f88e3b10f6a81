"""`reflab`: one subcommand per stage over a shared workspace (docs/formats.md, "Command line").

Each subcommand is a module of ``app/commands`` with ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``. Those modules import nothing heavy at module level, so ``reflab --help``
answers without loading Mitsuba, Open3D, pycolmap or Qt.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import reflab.app.commands


def _command_modules():
    for info in sorted(pkgutil.iter_modules(reflab.app.commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), importlib.import_module(f"reflab.app.commands.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reflab",
        description="Recover reflectance and texture of a table-top scene from one linear photograph.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in _command_modules():
        p = sub.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
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
    import errno

    from reflab.core.workspace import OptionError, WorkspaceError

    try:
        check_inputs(args)
        return int(args._run(args) or 0)
    except WorkspaceError as exc:
        print(f"reflab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OptionError as exc:  # a stage's bad option, named by its flag
        print(f"reflab {args.command}: error: {exc.cli_text}", file=sys.stderr)
        return 2
    except OSError as exc:  # what no check foresaw (disk full, a folder made read-only meanwhile): one line
        if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT):
            raise
        print(f"reflab {args.command}: error: {exc.filename or ''}: {exc.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"reflab {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
