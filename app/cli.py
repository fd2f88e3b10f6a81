"""`reflab`: one subcommand per stage over a shared workspace (INTERFACES.md, "Command line").

Each subcommand is a module of ``app/commands`` with ``HELP`` (one line), ``add_arguments(parser)``
and ``run(args) -> int``. Those modules import nothing heavy at module level, so ``reflab --help``
answers without loading Mitsuba, Open3D, pycolmap or Qt.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import app.commands


def _command_modules():
    for info in sorted(pkgutil.iter_modules(app.commands.__path__), key=lambda i: i.name):
        if not info.name.startswith("_"):
            yield info.name.replace("_", "-"), importlib.import_module(f"app.commands.{info.name}")


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


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from hardware.workspace import WorkspaceError

    try:
        return int(args._run(args) or 0)
    except WorkspaceError as exc:
        print(f"reflab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"reflab {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
