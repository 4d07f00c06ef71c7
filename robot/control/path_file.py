"""Path files: where the robot starts and the waypoints it visits, in the ground frame G.

YAML (SI units, angles in radians)::

    description: optional text
    start: {x: 0.0, y: 1.0, heading: -1.5708}     # optional; heading defaults to 0
    defaults: {speed: 0.15, tolerance: 0.005, heading_tolerance: 0.035, dwell: 0.0}  # optional
    waypoints:                                    # non-empty
      - {x: 0.5, y: 1.0}                          # heading free: keep the current one
      - {x: 1.0, y: 1.0, heading: 3.1416, speed: 0.1, tolerance: 0.01, heading_tolerance: 0.02, dwell: 2.0}

``speed`` is the cruise speed towards that waypoint (m/s), ``tolerance`` the arrival radius (m),
``heading_tolerance`` (rad) applies when a heading is given, ``dwell`` (s) is a stop at the
waypoint after arrival. Reading is strict: unknown keys, missing x/y, non-numbers, NaN,
non-positive speeds or tolerances and an empty list are refused with a ConfigError naming the
file and the waypoint, before any motion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

from robot.base.errors import ConfigError
from robot.config.schema import Section, load_yaml_file

DEFAULT_SPEED = 0.15  # m/s
DEFAULT_TOLERANCE = 0.01  # m
DEFAULT_HEADING_TOLERANCE = math.radians(2.0)
MAX_SPEED = 2.0  # m/s: anything faster in a path file is a typo (the controller clamps further)
MAX_ANGLE = 2.0 * math.pi  # |heading| beyond one turn is almost surely degrees


@dataclass(frozen=True)
class StartPose:
    x: float
    y: float
    heading: float = 0.0


@dataclass(frozen=True)
class Waypoint:
    x: float
    y: float
    heading: Optional[float] = None  # rad in G; None = keep the heading the robot has
    speed: float = DEFAULT_SPEED
    tolerance: float = DEFAULT_TOLERANCE
    heading_tolerance: float = DEFAULT_HEADING_TOLERANCE
    dwell: float = 0.0


@dataclass(frozen=True)
class PathPlan:
    waypoints: Tuple[Waypoint, ...]
    start: Optional[StartPose] = None
    description: str = ""
    source: str = "<path>"


def _heading(sec: Section, key: str) -> Optional[float]:
    if not sec.has(key):
        sec.raw(key, None)
        return None
    val = sec.number(key)
    if abs(val) > MAX_ANGLE:
        sec.fail(f"'{key}' is in radians and must be within +-2 pi, got {val} (degrees?)")
    return val


def parse_path(data, source: str = "<path>") -> PathPlan:
    top = Section(data, "", source)
    description = top.string("description", "") if top.has("description") else ""
    start = None
    if top.has("start"):
        s = top.sub("start")
        start = StartPose(s.number("x"), s.number("y"), _heading(s, "heading") or 0.0)
        s.done()
    d = top.sub("defaults")
    speed = d.number("speed", DEFAULT_SPEED, positive=True, hi=MAX_SPEED)
    tolerance = d.number("tolerance", DEFAULT_TOLERANCE, positive=True, hi=1.0)
    heading_tolerance = d.number("heading_tolerance", DEFAULT_HEADING_TOLERANCE, positive=True, hi=math.pi)
    dwell = d.number("dwell", 0.0, lo=0.0, hi=3600.0)
    d.done()
    raw = top.raw("waypoints")
    if not isinstance(raw, list) or not raw:
        top.fail("'waypoints' must be a non-empty list")
    waypoints = []
    for i, item in enumerate(raw):
        w = Section(item, f"waypoints[{i}]", source)
        waypoints.append(Waypoint(
            x=w.number("x"),
            y=w.number("y"),
            heading=_heading(w, "heading"),
            speed=w.number("speed", speed, positive=True, hi=MAX_SPEED),
            tolerance=w.number("tolerance", tolerance, positive=True, hi=1.0),
            heading_tolerance=w.number("heading_tolerance", heading_tolerance, positive=True, hi=math.pi),
            dwell=w.number("dwell", dwell, lo=0.0, hi=3600.0),
        ))
        w.done()
    top.done()
    return PathPlan(waypoints=tuple(waypoints), start=start, description=description, source=source)


def load_path(path) -> PathPlan:
    return parse_path(load_yaml_file(path), source=str(path))


def check_path_in_bounds(plan: PathPlan, lo: Sequence[float], hi: Sequence[float], margin: float = 0.0) -> None:
    """Refuse a path whose start or waypoints lie outside [lo + margin, hi - margin] in x and y.

    ``lo``/``hi`` are the map's bounds (``PlaneMap.bounds()``); ``margin`` keeps the robot's
    body off the walls.
    """
    points = [("start", plan.start.x, plan.start.y)] if plan.start else []
    points += [(f"waypoints[{i}]", w.x, w.y) for i, w in enumerate(plan.waypoints)]
    for where, x, y in points:
        if not (lo[0] + margin <= x <= hi[0] - margin and lo[1] + margin <= y <= hi[1] - margin):
            raise ConfigError(
                f"{plan.source}: {where}: ({x:.3f}, {y:.3f}) is outside the map's area "
                f"x in [{lo[0] + margin:.3f}, {hi[0] - margin:.3f}], y in [{lo[1] + margin:.3f}, {hi[1] - margin:.3f}]"
                f" (bounds less a {margin:.2f} m margin)")
