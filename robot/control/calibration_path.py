"""The motion ``robotctl calibrate`` drives: planned from where the robot stands, within the path limits.

Each part of it observes something (docs/calibration.md):

* a turn in place, in quarter turns, shows every camera every wall, at every distance the room
  offers; the wheels say the robot stayed where it was, so a camera mount that is off shows as a
  circle in the vision poses (mount x, y);
* a square of short drives (forward, to the left, a half turn, forward, to the left) at two
  headings moves each
  camera towards and away from walls it sees and past walls it sees side-on: the wheels'
  distance against the walls' (wheel radius, depth scale), the direction they say against the
  walls' (mount yaw), and the turn they give against the walls' (lx + ly, the wheels'
  differences); near and far walls separate a depth scale from a mount offset.

The drives go as far as the room allows, at most ``max_drive`` and always ``clearance`` from
every wall, and are planned at the path-following speeds; a robot too close to a wall to turn
is refused before anything moves.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.geometry import wrap_angle
from robot.config import RobotConfig
from robot.control.path_file import PathPlan, StartPose, Waypoint
from robot.maps.plane_map import PlaneMap

DEFAULT_CLEARANCE = 0.30  # m from a wall to the robot's centre: its half-diagonal (0.14 m) and a margin
DEFAULT_MAX_DRIVE = 0.45  # m per side of a square
MIN_DRIVE = 0.08  # m: a shorter drive shows too little to be worth its time


def clearance_for(robot: RobotConfig) -> float:
    """How far from every wall the robot's centre stays: its body, and each camera at least its
    minimum range plus 5 cm from the wall it faces (nearer, a D435i sees nothing, and the protective
    stop takes a blinded view for an obstacle at the lens)."""
    reach = max(math.hypot(c.mount_xyz[0], c.mount_xyz[1]) for c in robot.cameras)
    return max(DEFAULT_CLEARANCE, reach + robot.localizer.min_range + 0.05)


def wall_segments(plane_map: PlaneMap) -> List[Tuple[np.ndarray, np.ndarray]]:
    """Each wall's footprint as a 2-D segment (the extent of its polygons along the wall)."""
    out = []
    for p in plane_map.planes:
        if abs(p.normal[2]) > 0.5:
            continue  # a floor or a ceiling is no obstacle for the plan
        t = np.array([-p.normal[1], p.normal[0]]) / max(float(np.linalg.norm(p.normal[:2])), 1e-12)
        v = p.vertices[:, :2]
        s = v @ t
        c = v.mean(axis=0) - t * float(s.mean())
        out.append((c + t * float(s.min()), c + t * float(s.max())))
    return out


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    u = 0.0 if float(ab @ ab) == 0 else float(np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + u * ab)))


def clearance_at(p: Sequence[float], walls) -> float:
    q = np.asarray(p[:2], float)
    return min((_distance_to_segment(q, a, b) for a, b in walls), default=math.inf)


def free_distance(p: Sequence[float], direction: float, walls, clearance: float, limit: float) -> float:
    """How far from ``p`` along ``direction`` (rad) the robot may drive keeping ``clearance`` to every wall."""
    q = np.asarray(p[:2], float)
    u = np.array([math.cos(direction), math.sin(direction)])
    step = 0.01
    s = 0.0
    while s + step <= limit and clearance_at(q + u * (s + step), walls) >= clearance:
        s += step
    return s


def plan_calibration_motion(plane_map: PlaneMap, start: Sequence[float], speed: float = 0.30,
                            clearance: float = DEFAULT_CLEARANCE, max_drive: float = DEFAULT_MAX_DRIVE,
                            tolerance: float = 0.02, heading_tolerance: float = math.radians(2.0),
                            source: str = "<calibration motion>") -> PathPlan:
    """The calibration motion from ``start`` (x, y, phi): a turn in place in quarter turns, then two
    squares of drives along the robot's own axes, one at a heading a quarter turn from the start's
    and one 45 degrees from that, each where the room has most space. ConfigError when the start
    is too close to a wall to turn or no square of at least ``MIN_DRIVE`` fits."""
    walls = wall_segments(plane_map)
    if not walls:
        raise ConfigError(f"{plane_map.source}: the map has no walls to calibrate against")
    x, y, phi = (float(v) for v in start)
    room = clearance_at((x, y), walls)
    if room < clearance:
        raise ConfigError(f"calibration: the robot at ({x:.2f}, {y:.2f}) is {room:.2f} m from a wall; it needs "
                          f"{clearance:.2f} m to turn in place: move it further into the room")
    wps: List[Waypoint] = []

    def go(px: float, py: float, heading: float) -> None:
        wps.append(Waypoint(x=px, y=py, heading=float(wrap_angle(heading)), speed=speed, tolerance=tolerance,
                            heading_tolerance=heading_tolerance))

    for k in range(1, 5):
        go(x, y, phi + k * math.pi / 2)
    squares = 0
    c = np.array([x, y])
    heading = phi
    for base in (phi, phi + math.pi / 4):
        # Of the four headings a quarter turn apart, the one whose square (ahead and to the left) fits
        # best; of equals, the one nearest the current heading.
        options = []
        for k in range(4):
            g = base + k * math.pi / 2
            side = _square_side(c, _unit(g), _unit(g + math.pi / 2), walls, clearance, max_drive)
            options.append((round(side, 2), -abs(float(wrap_angle(g - heading))), side, g))
        _, _, side, g = max(options)
        if side < MIN_DRIVE:
            continue
        f, left = _unit(g), _unit(g + math.pi / 2)
        # Only forward and to the left, where the cameras look (the protective stop slows a robot
        # driving blind): forward, left, a half turn, then forward and left again back to the start.
        if abs(float(wrap_angle(g - heading))) > 1e-9:
            go(x, y, g)
        go(*(c + side * f), g)
        go(*(c + side * (f + left)), g)
        go(*(c + side * (f + left)), g + math.pi)
        go(*(c + side * left), g + math.pi)
        go(x, y, g + math.pi)
        heading = g + math.pi
        squares += 1
    if squares == 0:
        raise ConfigError(f"calibration: from ({x:.2f}, {y:.2f}) the room leaves no room for drives of "
                          f"{MIN_DRIVE:.2f} m keeping {clearance:.2f} m from the walls")
    return PathPlan(tuple(wps), StartPose(x, y, float(wrap_angle(phi))), "calibration motion", source)


def _unit(angle: float) -> np.ndarray:
    return np.array([math.cos(angle), math.sin(angle)])


def _square_side(c: np.ndarray, f: np.ndarray, left: np.ndarray, walls, clearance: float, limit: float) -> float:
    """The largest side (<= limit, in 1 cm steps) of the square c, c + s f, c + s (f + left), c + s left
    whose edges all keep ``clearance`` from the walls."""
    side = 0.0
    while side + 0.01 <= limit + 1e-9:
        s = side + 0.01
        corners = [c, c + s * f, c + s * (f + left), c + s * left]
        ok = all(clearance_at(a + (b - a) * u, walls) >= clearance
                 for a, b in zip(corners, corners[1:] + corners[:1]) for u in np.linspace(0.0, 1.0, 6))
        if not ok:
            break
        side = s
    return side


def plan_duration_estimate(plan: PathPlan, speed: float, yaw_rate: float) -> float:
    """A rough duration (s) of ``plan`` at cruise speed and turn rate, with a second per stop."""
    t = 0.0
    prev: Optional[Tuple[float, float, float]] = None
    if plan.start is not None:
        prev = (plan.start.x, plan.start.y, plan.start.heading)
    for w in plan.waypoints:
        if prev is not None:
            t += math.hypot(w.x - prev[0], w.y - prev[1]) / speed
            if w.heading is not None:
                t += abs(float(wrap_angle(w.heading - prev[2]))) / yaw_rate
        t += 1.0
        prev = (w.x, w.y, prev[2] if w.heading is None else w.heading) if prev else (w.x, w.y, w.heading or 0.0)
    return t
