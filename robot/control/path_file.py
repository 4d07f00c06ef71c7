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
values outside their ranges (declared on the fields below, listed in ``docs/configuration.md``)
and an empty list are refused with a ConfigError naming the file and the waypoint, before any
motion. The file is read through ``robot.base.files`` (regular files up to 1 MiB).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import MISSING, dataclass
from typing import Optional, Sequence, Tuple

from robot.base.errors import ConfigError
from robot.base.files import PATH_FILE
from robot.config.ranges import check_fields, field_range, number
from robot.config.schema import Section, check_number, load_yaml_file

DEFAULT_SPEED = 0.15  # m/s
DEFAULT_TOLERANCE = 0.01  # m
DEFAULT_HEADING_TOLERANCE = math.radians(2.0)
MAX_SPEED = 2.0  # m/s: anything faster in a path file is a typo (the controller clamps further)
MAX_ANGLE = 2.0 * math.pi  # |heading| beyond one turn is almost surely degrees
MAX_COORDINATE = 1000.0  # m: a site is smaller than 2 km across; larger values are unit mistakes
MAX_WAYPOINTS = 10_000
MAX_DESCRIPTION_CHARS = 10_000


def _coordinate(axis: str):
    return number(MISSING, -MAX_COORDINATE, MAX_COORDINATE, "m", f"{axis} in the ground frame G")


def _heading_field(default, doc: str):
    return number(default, -MAX_ANGLE, MAX_ANGLE, "rad", doc, text="-2 pi to 2 pi rad")


@dataclass(frozen=True)
class StartPose:
    x: float = _coordinate("x")
    y: float = _coordinate("y")
    heading: float = _heading_field(0.0, "heading in G, counter-clockwise from +x")

    def __post_init__(self):
        check_fields(self, "start")


@dataclass(frozen=True)
class Waypoint:
    x: float = _coordinate("x")
    y: float = _coordinate("y")
    heading: Optional[float] = _heading_field(None, "heading in G; absent: keep the heading the robot has")
    speed: float = number(DEFAULT_SPEED, 0.0, MAX_SPEED, "m/s", "cruise speed towards the waypoint", lo_open=True)
    tolerance: float = number(DEFAULT_TOLERANCE, 0.0, 1.0, "m", "arrival radius", lo_open=True)
    heading_tolerance: float = number(DEFAULT_HEADING_TOLERANCE, 0.0, math.pi, "rad",
                                      "heading arrival tolerance, when a heading is given", lo_open=True,
                                      text="above 0 up to pi rad")
    dwell: float = number(0.0, 0.0, 3600.0, "s", "stop at the waypoint after arrival")

    def __post_init__(self):
        if self.heading is None:  # None is allowed here and only here
            check_fields(dataclasses.replace(self, heading=0.0), "waypoint")
        else:
            check_fields(self, "waypoint")


_RANGES = {f.name: field_range(f) for f in dataclasses.fields(Waypoint)}


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
    val = check_number(sec.raw(key), key, sec)
    if abs(val) > MAX_ANGLE:
        sec.fail(f"'{key}' is in radians and must be within +-2 pi, got {val:.6g} (degrees?)")
    return val


def parse_path(data, source: str = "<path>") -> PathPlan:
    top = Section(data, "", source)
    description = top.string("description", "") if top.has("description") else ""
    if len(description) > MAX_DESCRIPTION_CHARS:
        top.fail(f"'description' is longer than {MAX_DESCRIPTION_CHARS} characters")
    start = None
    if top.has("start"):
        s = top.sub("start")
        start = StartPose(s.ranged("x", _RANGES["x"]), s.ranged("y", _RANGES["y"]), _heading(s, "heading") or 0.0)
        s.done()
    d = top.sub("defaults")
    defaults = {key: d.ranged(key, _RANGES[key], getattr(Waypoint, key))
                for key in ("speed", "tolerance", "heading_tolerance", "dwell")}
    d.done()
    raw = top.raw("waypoints")
    if not isinstance(raw, list) or not raw:
        top.fail("'waypoints' must be a non-empty list")
    if len(raw) > MAX_WAYPOINTS:
        top.fail(f"'waypoints' lists {len(raw)} waypoints, at most {MAX_WAYPOINTS} are allowed")
    waypoints = []
    for i, item in enumerate(raw):
        w = Section(item, f"waypoints[{i}]", source)
        waypoints.append(Waypoint(
            x=w.ranged("x", _RANGES["x"]),
            y=w.ranged("y", _RANGES["y"]),
            heading=_heading(w, "heading"),
            **{key: w.ranged(key, _RANGES[key], value) for key, value in defaults.items()},
        ))
        w.done()
    top.done()
    return PathPlan(waypoints=tuple(waypoints), start=start, description=description, source=source)


def load_path(path) -> PathPlan:
    return parse_path(load_yaml_file(path, PATH_FILE), source=str(path))


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
