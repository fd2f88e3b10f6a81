"""Talk to the turntable and lamp controller (GRBL 1.1) directly: status, rotate, lamps, unlock.

`--port sim` starts the simulated board on a pseudo-terminal for the duration of the command.
docs/hardware.md describes the wiring, the configuration file and the fault messages.
"""
from __future__ import annotations

import argparse

from reflab.app.console import LOG

HELP = "turntable and lamps over serial (GRBL 1.1): status | rotate DEG | lamp N on|off | unlock"


def _board_options(parser: argparse.ArgumentParser, default) -> None:
    """--port and --config: on `hardware` and on each action, so they go before or after it."""
    parser.add_argument("--port", default=default,
                        help="serial port (/dev/ttyUSB0, COM3) or 'sim' for the simulated board (required)")
    parser.add_argument("--config", default=default,
                        help="hardware JSON (axis, steps per degree, lamp outputs, timeouts; docs/hardware.md)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    _board_options(parser, None)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    status = actions.add_parser("status", help="print state, turntable angle and lamp states")
    rotate = actions.add_parser("rotate", help="turn the turntable to an absolute angle (degrees) and wait")
    rotate.add_argument("degrees", type=float)
    rotate.add_argument("--relative", action="store_true", help="turn by DEG from the current angle")
    lamp = actions.add_parser("lamp", help="switch lamp N (index in the configuration's lamps) on or off")
    lamp.add_argument("index", type=int)
    lamp.add_argument("state", choices=["on", "off"])
    unlock = actions.add_parser("unlock", help="leave an ALARM state: soft reset, then $X")
    for action in (status, rotate, lamp, unlock):
        _board_options(action, argparse.SUPPRESS)


def describe(ctl) -> str:
    """State, angle and lamps as the board confirms them (``?`` and ``$G``, not the rare ``A:`` field)."""
    now = ctl.confirm()
    lamps = ", ".join(f"{k} {'on' if on else 'off'}" for k, on in enumerate(now.lamps))
    return f"{now.state}  angle {now.angle:.3f} deg  lamps: {lamps}  (GRBL {ctl.version} on {ctl.port})"


def run(args) -> int:
    from reflab.app.devices import load_config, open_port
    from reflab.hardware.grbl import GrblAlarm, GrblController, GrblError

    if args.port is None:
        LOG.error("reflab hardware: error: --port is required (a serial port, or 'sim' for the simulated board)")
        return 2
    config = load_config(args.config)
    port, sim = open_port(args.port, log=LOG.info)
    ctl = GrblController(port, config, log=LOG.info)
    try:
        try:
            ctl.connect()
        except GrblAlarm:
            if args.action != "unlock":
                raise
        if args.action == "unlock":
            for line in ctl.unlock():
                LOG.info(line)
        elif args.action == "rotate":
            target = ctl.angle + args.degrees if args.relative else args.degrees
            ctl.rotate_to(target)
        elif args.action == "lamp":
            if not 0 <= args.index < len(config.lamps):
                LOG.error(f"reflab hardware: error: lamp {args.index} is not configured (lamps 0..{len(config.lamps) - 1}: "
                          f"{config.lamps})")
                return 2
            ctl.set_lamp(args.index, args.state == "on")
        LOG.info(describe(ctl))
        return 0
    except KeyboardInterrupt:  # GRBL finishes a move it has unless told: feed hold, then reset
        if ctl.serial is not None:
            try:
                ctl.halt()
            except GrblError as exc:
                print(f"reflab hardware: could not stop the board: {exc}", file=sys.stderr)
        print("reflab hardware: interrupted; the board was stopped (feed hold, soft reset: lamps off)", file=sys.stderr)
        return 130
    except GrblError as exc:  # a port or wiring the board cannot use is bad input (2), a fault 1
        LOG.error(f"reflab hardware: error: {exc}")
        return 2 if exc.bad_input else 1
    finally:
        ctl.close()
        if sim is not None:
            sim.stop()
