"""``robotctl``: the command-line entry point.

Each feature registers its subcommands from its own ``robot/cli_*.py`` module (a ``register``
function taking the argparse subparsers). This module owns the one place where user errors
become exit status 2 and a single line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
from typing import List, Optional

# The controller's matrices are tiny: a multi-threaded BLAS only adds thread wake-ups and steals
# the cores the control loop and capture threads need (12 ms instead of 20 ms per localization).
# Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from robot.errors import RobotError  # noqa: E402

# Modules that add subcommands; each has ``register(subparsers)``.
COMMAND_MODULES = [
    "robot.cli_localize",
    "robot.cli_map",
    "robot.cli_cameras",
    "robot.cli_chassis",
    "robot.cli_sim",
    "robot.cli_run",
    "robot.cli_teleop",
    "robot.cli_replay",
    "robot.cli_bench",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robotctl", description="Plane-map localization controller for a Mecanum robot")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


class UsageError(RobotError):
    """Bad command-line arguments that argparse cannot catch."""


def print_json(obj) -> None:
    sys.stdout.write(json.dumps(obj, indent=None, separators=(",", ": ")) + "\n")


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        rc = args.func(args)
    except RobotError as e:
        sys.stderr.write(f"robotctl {args.command}: error: {e}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"robotctl {args.command}: interrupted\n")
        return 130
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
