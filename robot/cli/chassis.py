"""``robotctl chassis``: check a motor board on the bench (or the emulator with ``--emulate``).

Handshake, live odometry and status, then with ``--motion`` a short test motion: each wheel alone
at a set speed, checked by its own encoder, and the board's watchdog timed. Put the robot on
blocks first: the wheels turn.
"""

from __future__ import annotations

import asyncio
import math
import sys

from robot.app.chassis_checks import bench
from robot.base.errors import DriverError
from robot.cli.common import print_json
from robot.config import ChassisConfig, load_robot_config


def register(subparsers) -> None:
    p = subparsers.add_parser("chassis", help="bench check of the motor board: handshake, odometry, status, motion",
                              description=__doc__)
    p.add_argument("--port", help="serial port or pyserial URL (default: chassis.port of the config)")
    p.add_argument("--config", help="robot config YAML (default: built-in chassis defaults)")
    p.add_argument("--emulate", action="store_true", help="use the built-in board emulator on a pseudo-terminal")
    p.add_argument("--duration", type=float, default=2.0, help="seconds of live odometry and status (default 2)")
    p.add_argument("--motion", action="store_true",
                   help="spin each wheel alone and time the watchdog (ROBOT ON BLOCKS: the wheels turn)")
    p.add_argument("--speed", type=float, default=3.0, help="test motion wheel speed in rad/s (default 3)")
    p.add_argument("--hold", type=float, default=1.0, help="seconds each wheel turns in the test motion (default 1)")
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
    emulator = None
    port = args.port or cfg.port
    if args.emulate:
        from drivers.chassis.emulator import FirmwareEmulator

        emulator = FirmwareEmulator(cfg).start()
        port = emulator.port
    try:
        report = asyncio.run(bench(cfg, port, args.duration, args.motion, args.speed, args.hold,
                                   None if args.json else _print))
    finally:
        if emulator is not None:
            emulator.close()
    if args.json:
        print_json(report)
    return 0 if report["ok"] else 1


def _print(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()






















