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


#: What a command does with its WORKSPACE, checked before it starts (hardware.workspace.check_folder):
#: "read" it must exist; "write" it must exist and be writable; "create" it may be made (its parent
#: writable). Commands not listed check nothing here.
_WORKSPACE = {"calibrate": "write", "capture": "create", "demo": "create", "fit": "write", "reconstruct": "write",
              "render": "read", "report": "write", "texture": "write"}


def check_inputs(args) -> None:
    """Folders a command reads and writes, checked before any work (one line naming the path)."""
    from pathlib import Path

    from hardware.workspace import check_folder

    mode = _WORKSPACE.get(args.command)
    if mode == "write" and args.command == "calibrate" and args.what == "camera":
        mode = "create"  # a first calibration may start the workspace
    output = getattr(args, "output", None) if args.command == "render" else None
    if mode == "read" and not output:
        mode = "write"  # render's default output goes into the workspace
    if mode and getattr(args, "workspace", None) is not None:
        check_folder(args.workspace, write=mode != "read", create=mode == "create")
    if output:
        check_folder(Path(output).parent, write=True, create=True, what="output folder")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import errno

    from hardware.workspace import WorkspaceError

    try:
        check_inputs(args)
        return int(args._run(args) or 0)
    except WorkspaceError as exc:
        print(f"reflab {args.command}: error: {exc}", file=sys.stderr)
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
