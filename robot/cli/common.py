"""Argument helpers shared by the subcommands: default config paths, pose parsing, loading."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Optional

from robot.base.errors import ConfigError
from robot.config import RobotConfig, load_robot_config
from robot.config.defaults import DEFAULT_MAP, DEFAULT_ROBOT  # noqa: F401 (the subcommands' defaults)
from robot.maps.plane_map import PlaneMap, load_plane_map


def add_robot_map_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot config YAML (default: %(default)s)")
    p.add_argument("--map", default=str(DEFAULT_MAP), help="plane map YAML (default: %(default)s)")


def load_robot_and_map(args) -> tuple[RobotConfig, PlaneMap]:
    return load_robot_config(args.robot), load_plane_map(args.map)


MAX_POSE_COORDINATE = 1000.0  # m, as for map and path coordinates
MAX_POSE_ANGLE = 2.0 * math.pi  # rad; more than a turn is degrees given as radians


def pose_arg(values, what: str):
    """Three finite floats (x m, y m, phi rad) from argparse's nargs=3 strings, within the site."""
    out = []
    for v in values:
        try:
            f = float(v)
        except ValueError:
            raise ConfigError(f"{what}: '{str(v)[:40]}' is not a number") from None
        if not math.isfinite(f):
            raise ConfigError(f"{what}: '{str(v)[:40]}' is not a finite number")
        out.append(f)
    if any(abs(c) > MAX_POSE_COORDINATE for c in out[:2]):
        raise ConfigError(f"{what}: x and y must be within +-{MAX_POSE_COORDINATE:g} m, got {out[0]:.6g} {out[1]:.6g}")
    if len(out) > 2 and abs(out[2]) > MAX_POSE_ANGLE:
        raise ConfigError(f"{what}: the heading is in radians and must be within +-2 pi, got {out[2]:.6g} (degrees?)")
    return tuple(out)


def int_in(lo: int, hi: int):
    """An argparse ``type``: an integer in [lo, hi] (bad values: exit 2 naming the option)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer from {lo} to {hi}, got '{text[:40]}'") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer from {lo} to {hi}, got {text[:40]}")
        return v

    parse.__name__ = f"integer in [{lo}, {hi}]"
    parse.bounds = (lo, hi, "", False)  # read by scripts/gen_config_doc.py for docs/configuration.md
    return parse


def float_in(lo: float, hi: float, unit: str = "", lo_open: bool = False):
    """An argparse ``type``: a finite number in [lo, hi] ((lo, hi] with ``lo_open``)."""
    span = f"{'above' if lo_open else 'from'} {lo:g} to {hi:g}{' ' + unit if unit else ''}"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number {span}, got '{text[:40]}'") from None
        if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
            raise argparse.ArgumentTypeError(f"must be a number {span}, got {text[:40]}")
        return v

    parse.__name__ = f"number in [{lo:g}, {hi:g}]"
    parse.bounds = (lo, hi, unit, lo_open)
    return parse


def confirm_motion(yes: bool, what: str, stdin=None, stderr=None) -> Optional[str]:
    """Ask before the wheels turn: None when allowed (``--yes``, or "y" typed on a terminal), else why not.

    Without a terminal (a script, a service, CI) there is nobody to ask: the wheels stay still,
    unless ``--yes`` says the robot is on blocks.
    """
    stdin = stdin if stdin is not None else sys.stdin
    stderr = stderr if stderr is not None else sys.stderr
    if yes:
        return None
    try:
        interactive = stdin is not None and stdin.isatty()
    except (AttributeError, ValueError):  # closed or replaced stdin
        interactive = False
    if not interactive:
        return "not confirmed: no terminal to ask and no --yes, so the wheels stay still"
    stderr.write(f"{what}: the wheels will turn. Is the robot ON BLOCKS with every wheel free? [y/N] ")
    stderr.flush()
    try:
        answer = stdin.readline()
    except (OSError, ValueError, KeyboardInterrupt):
        answer = ""
    if answer.strip().lower() in ("y", "yes"):
        return None
    return "not confirmed at the prompt: the wheels stay still"


class OneLineParser(argparse.ArgumentParser):
    """Usage mistakes are one line on stderr and exit status 2, like every other bad input."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def print_json(obj) -> None:
    """One JSON document on one line of stdout (what ``--json`` prints)."""
    sys.stdout.write(json.dumps(obj, indent=None, separators=(",", ": ")) + "\n")
