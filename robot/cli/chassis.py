"""``robotctl chassis``: check a motor board on the bench (or the emulator with ``--emulate``).

Handshake, live odometry and status, then with ``--motion`` a short test motion: each wheel alone
at a set speed, checked by its own encoder, and the board's watchdog timed. Put the robot on
blocks first: the wheels turn. The command asks before they do (``--yes`` answers for it; with
no terminal and no ``--yes`` there is no motion), and a short pulse with the wheels working
against each other first checks that they turn freely (not loaded by the floor).
"""

from __future__ import annotations

import asyncio
import math
import sys

from robot.app.assemble import board_port
from robot.app.chassis_checks import bench
from robot.base.errors import DriverError
from robot.cli.common import confirm_motion, float_in, print_json
from robot.config import ChassisConfig, load_robot_config


def register(subparsers) -> None:
    p = subparsers.add_parser("chassis", help="bench check of the motor board: handshake, odometry, status, motion",
                              description=__doc__)
    p.add_argument("--port", help="serial port or pyserial URL (default: chassis.port of the config)")
    p.add_argument("--config", help="robot config YAML (default: built-in chassis defaults)")
    p.add_argument("--emulate", action="store_true", help="use the built-in board emulator on a pseudo-terminal")
    p.add_argument("--duration", type=float_in(0.0, 600.0, "s"), default=2.0,
                   help="seconds of live odometry and status, up to 600 (default 2)")
    p.add_argument("--motion", action="store_true",
                   help="spin each wheel alone and time the watchdog (ROBOT ON BLOCKS: the wheels turn)")
    p.add_argument("--speed", type=float_in(0.0, 50.0, "rad/s", lo_open=True), default=3.0,
                   help="test motion wheel speed in rad/s (default 3)")
    p.add_argument("--hold", type=float_in(0.1, 60.0, "s"), default=1.0,
                   help="seconds each wheel turns in the test motion, 0.1 to 60 (default 1)")
    p.add_argument("--yes", action="store_true",
                   help="the robot is on blocks: turn the wheels without asking (needed without a terminal)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=run)


def run(args) -> int:
    cfg = load_robot_config(args.config).chassis if args.config else ChassisConfig()
    for name in ("duration", "speed", "hold"):
        v = getattr(args, name)
        if not math.isfinite(v) or v < 0:
            raise DriverError(f"--{name} must be a non-negative number, got {v}")
    if args.motion and not 0 < args.speed <= cfg.max_wheel_speed:
        raise DriverError(f"--speed must be in (0, {cfg.max_wheel_speed}] rad/s (chassis.max_wheel_speed)")
    motion, refused = args.motion, None
    if motion and not args.emulate:  # the emulator has no wheels to ask about
        refused = confirm_motion(args.yes, "robotctl chassis")
        if refused is not None:
            motion = False
            sys.stderr.write(f"robotctl chassis: {refused}: no test motion (--yes once the robot is on blocks)\n")
    with board_port("emulator" if args.emulate else "serial", cfg, args.port) as board:
        report = asyncio.run(bench(board.config, board.port, args.duration, motion, args.speed, args.hold,
                                   None if args.json else _print))
    if refused is not None:
        report["motion_skipped"] = refused
    if args.json:
        print_json(report)
    return 0 if report["ok"] else 1


def _print(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()






















