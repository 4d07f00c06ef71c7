"""Argument helpers shared by the subcommands: default config paths, pose parsing, loading."""

from __future__ import annotations

import argparse
import json
import math
import sys

from robot.base.errors import ConfigError
from robot.config import RobotConfig, load_robot_config
from robot.config.defaults import DEFAULT_MAP, DEFAULT_ROBOT  # noqa: F401 (the subcommands' defaults)
from robot.maps.plane_map import PlaneMap, load_plane_map


def add_robot_map_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot config YAML (default: %(default)s)")
    p.add_argument("--map", default=str(DEFAULT_MAP), help="plane map YAML (default: %(default)s)")


def load_robot_and_map(args) -> tuple[RobotConfig, PlaneMap]:
    return load_robot_config(args.robot), load_plane_map(args.map)


def pose_arg(values, what: str):
    """Three finite floats (x m, y m, phi rad) from argparse's nargs=3 strings."""
    out = []
    for v in values:
        try:
            f = float(v)
        except ValueError:
            raise ConfigError(f"{what}: '{v}' is not a number") from None
        if not math.isfinite(f):
            raise ConfigError(f"{what}: '{v}' is not a finite number")
        out.append(f)
    return tuple(out)


def print_json(obj) -> None:
    """One JSON document on one line of stdout (what ``--json`` prints)."""
    sys.stdout.write(json.dumps(obj, indent=None, separators=(",", ": ")) + "\n")
