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
import warnings
from typing import List, Optional

# The controller's matrices are tiny: a multi-threaded BLAS only adds thread wake-ups and steals
# the cores the control loop and capture threads need (12 ms instead of 20 ms per localization).
# Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from robot.app.logs import journal_prefix, setup_logging  # noqa: E402
from robot.base.errors import RobotError  # noqa: E402
from robot.cli import bench, calibrate, cameras, chassis, control, kernels, localize, maps, relocalize, replay, run, sim, teleop  # noqa: E402
from robot.cli.common import OneLineParser  # noqa: E402

# The modules that add subcommands, in the order `robotctl --help` lists them.
COMMAND_MODULES = (localize, relocalize, maps, cameras, chassis, calibrate, sim, run, teleop, control, replay, bench, kernels)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="robotctl", description="Plane-map localization controller for a Mecanum robot")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


# Commands that read their files and end. Their warnings are held until they end, so that a bad
# file is still one line: a warning that explains the error (a skipped channel, say) joins it.
BATCH_COMMANDS = {"localize", "visible", "render", "demo", "relocalize", "map", "replay"}


class _HeldWarnings(logging.Filter):
    def __init__(self) -> None:
        super().__init__()
        self.records: List[logging.LogRecord] = []
        self.handlers = [h for h in logging.getLogger().handlers if getattr(h, "_robotctl", False)]
        for h in self.handlers:
            h.addFilter(self)

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            self.records.append(record)
            return False
        return True

    def release(self, show: bool) -> None:
        for h in self.handlers:
            h.removeFilter(self)
            for record in self.records if show else ():
                h.handle(record)

    def summary(self) -> str:
        if not self.records:
            return ""
        n = len(self.records)
        return f" (after {n} warning{'s' if n > 1 else ''}: {self.records[0].getMessage()[:160]})"


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    return f"{category.__name__}: {message} ({os.path.basename(filename)}:{lineno})"


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(verbose=args.verbose)  # under systemd: syslog priorities, for `journalctl -p`
    # A library's Python warning (numpy's "invalid value encountered" on a hostile file, found by
    # the long fuzz run) goes through logging as one line, held like the other warnings of a
    # batch command, not two raw lines on stderr before the error.
    saved_format = warnings.formatwarning
    warnings.formatwarning = _one_line_warning  # type: ignore[assignment]
    logging.captureWarnings(True)
    held = _HeldWarnings() if args.command in BATCH_COMMANDS and not args.verbose else None
    failed = False
    try:
        rc = args.func(args)
    except RobotError as e:
        failed = True
        note = held.summary() if held is not None else ""
        # One line whatever the message quotes from a hostile file (the journal and scripts read lines).
        text = f"{e}{note}".replace("\r", "\\r").replace("\n", "\\n")
        sys.stderr.write(f"{journal_prefix(logging.ERROR)}robotctl {args.command}: error: {text}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write(f"robotctl {args.command}: interrupted\n")
        return 130
    finally:
        if held is not None:
            held.release(show=not failed)
        logging.captureWarnings(False)
        warnings.formatwarning = saved_format  # type: ignore[assignment]
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
