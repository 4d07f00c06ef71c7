"""``robotctl``: the command-line entry point.

Each feature registers its subcommands from its own module in this package (a ``register``
function taking the argparse subparsers). This module owns the one place where user errors
become exit status 2 and a single line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import List, Optional

# The controller's matrices are tiny: a multi-threaded BLAS only adds thread wake-ups and steals
# the cores the control loop and capture threads need (12 ms instead of 20 ms per localization).
# Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from robot.base.errors import RobotError  # noqa: E402
from robot.cli import bench, cameras, chassis, localize, maps, replay, run, sim, teleop  # noqa: E402

# The modules that add subcommands, in the order `robotctl --help` lists them.
COMMAND_MODULES = (localize, maps, cameras, chassis, sim, run, teleop, replay, bench)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robotctl", description="Plane-map localization controller for a Mecanum robot")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


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
