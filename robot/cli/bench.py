"""``robotctl bench``: a short hardware check of the robot, as a pass/fail/skip table.

Cameras stream for 5 s at their configured rate without timeouts and report intrinsics that
match the config; the motor board handshakes; each wheel alone turns at 3 rad/s within 5 % by
its encoder (2 s each); the board's watchdog stops the wheels within 250 ms of the last command.
PUT THE ROBOT ON BLOCKS: the wheels turn (``--skip-motion`` leaves them still). Before they do,
the bench asks on the terminal (``--yes`` answers for it; without a terminal and without
``--yes`` nothing turns), then a short pulse with the wheels working against each other checks
that they turn freely: a wheel that lags under load stops the motion checks. The full-length
versions are the hardware-in-the-loop tests (``pytest --hil tests/hil``).

Every configured camera and the motor board are required: a missing one fails (``--skip-cameras``
checks the chassis alone).

Exit status: 0 when no check failed (skipped checks say why), 1 when one failed, 2 on bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from typing import List

from robot.app.bench_checks import FAIL, BenchOptions, CheckResult, exit_code, run_bench, summary
from robot.base.errors import InputError
from robot.cli.common import DEFAULT_ROBOT, confirm_motion, print_json

ROBOT_CONFIG = "/etc/robot-controller/robot.yaml"  # where systemd/install.sh puts it


def register(subparsers) -> None:

    p = subparsers.add_parser("bench", help="short hardware check: cameras, motor board, wheels, watchdog",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", help=f"robot config YAML (default: {ROBOT_CONFIG} on the robot, else {DEFAULT_ROBOT})")
    p.add_argument("--port", help="motor board serial port or pyserial URL (default: chassis.port of the config)")
    p.add_argument("--emulate", action="store_true",
                   help="check the built-in motor board emulator instead of a board (tests the tool itself)")
    p.add_argument("--skip-motion", action="store_true", help="no wheel and watchdog checks: the wheels stay still")
    p.add_argument("--yes", action="store_true",
                   help="the robot is on blocks: turn the wheels without asking (needed without a terminal)")
    p.add_argument("--skip-cameras", action="store_true",
                   help="check the chassis only (without it, every configured camera must be connected)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.set_defaults(func=run)


def run(args) -> int:
    from robot.config import load_robot_config

    if args.emulate and args.port:
        raise InputError("--port and --emulate exclude each other: the emulator brings its own port")
    robot = load_robot_config(args.config or default_config())
    opts = BenchOptions(motion=not args.skip_motion, cameras=not args.skip_cameras)
    if opts.motion and not args.emulate:  # the emulator has no wheels to ask about
        refused = confirm_motion(args.yes, "robotctl bench")
        if refused is not None:
            opts = dataclasses.replace(opts, motion=False, motion_skipped=refused)
            _say(f"robotctl bench: {refused} (--yes once the robot is on blocks, or --skip-motion)")
    if opts.motion:
        _say("robotctl bench: the wheels will turn: the robot must be ON BLOCKS (--skip-motion to skip)")
    results = run_bench(robot, opts, port=args.port, chassis_kind="emulator" if args.emulate else "serial")
    if args.json:
        print_json({"ok": exit_code(results) == 0, "summary": summary(results),
                    "checks": [r.to_json() for r in results]})
    else:
        sys.stdout.write(format_table(results))
    return exit_code(results)


def default_config() -> str:

    return ROBOT_CONFIG if os.path.exists(ROBOT_CONFIG) else str(DEFAULT_ROBOT)


def format_table(results: List[CheckResult]) -> str:
    width = max([len("check")] + [len(r.name) for r in results])
    lines = [f"{'check':<{width}}  result  detail"]
    for r in results:
        lines.append(f"{r.name:<{width}}  {r.status.upper() if r.status == FAIL else r.status:<6}  {r.detail}")
    s = summary(results)
    lines.append(f"{s['pass']} passed, {s['fail']} failed, {s['skip']} skipped")
    return "\n".join(lines) + "\n"


def _say(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


__all__ = ["register", "run", "format_table"]
