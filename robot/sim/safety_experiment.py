"""The protective-stop experiment: drive at a person standing in the path, on the simulated clock.

The robot starts at rest in a large empty room (an 8 m square from ``drivers.sim.building``) and
is sent 4 m straight ahead at ``speed``; a person (an elliptic cylinder 0.5 x 0.3 x 1.75 m) stands
``distance`` ahead of the robot's front edge, moved sideways at random by up to ``lateral``. The run
ends after the simulated time a free run would need. What it measures: the smallest clearance
between the robot's footprint and the person over the run (the robot must never touch them), and
where it came to rest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import List, Optional

import numpy as np

from drivers.sim.building import room_grid_map
from drivers.sim.clutter import person
from drivers.sim.world import WorldSettings
from robot.config import RobotConfig
from robot.control.path_file import parse_path
from robot.sim.runner import RunSettings, run_path

ROOM = 8.0  # m, inside


@dataclass(frozen=True)
class ObstacleRun:
    seed: int
    speed: float
    distance: float  # m from the front edge at the start to the person's near side
    lateral: float  # m the person stands off the path's centre line
    min_clearance: float  # m between footprint and person over the run (<= 0: contact)
    travelled: float  # m the robot moved along the path
    stopped: bool  # it stood still at the end, short of the person
    counters: dict


def _clearance(trace: np.ndarray, half_x: float, half_y: float, offset_x: float, px: float, py: float,
               radius: float) -> float:
    """Smallest distance from the footprint rectangle to a circle around the person, over the trace."""
    best = math.inf
    for _, x, y, phi in trace:
        c, s = math.cos(phi), math.sin(phi)
        lx = c * (px - x) + s * (py - y) - offset_x
        ly = -s * (px - x) + c * (py - y)
        dx, dy = max(abs(lx) - half_x, 0.0), max(abs(ly) - half_y, 0.0)
        best = min(best, math.hypot(dx, dy) - radius)
    return best


def obstacle_run(robot: RobotConfig, seed: int, speed: float = 0.3, distance: float = 1.0, lateral: float = 0.1,
                 vision: bool = True, obstacle: bool = True) -> ObstacleRun:
    rng = np.random.default_rng(seed)
    plane_map = room_grid_map(1, 1, room=ROOM, seed=seed)
    lo, hi = plane_map.bounds()
    y0 = float((lo[1] + hi[1]) / 2.0)
    x0 = float(lo[0]) + 1.0
    goal = x0 + 4.0
    plan = parse_path({"start": {"x": x0, "y": y0, "heading": 0.0},
                       "defaults": {"speed": speed, "tolerance": 0.01, "dwell": 0.5},
                       "waypoints": [{"x": goal, "y": y0, "heading": 0.0}]}, source="<protective-stop run>")
    c = robot.safety
    front = c.footprint_offset_x + c.footprint_length / 2.0
    off = float(rng.uniform(-lateral, lateral))
    depth = 0.3
    px = x0 + front + distance + depth / 2.0
    obstacles = (person(px, y0 + off, yaw=float(rng.uniform(-0.3, 0.3))),) if obstacle else ()
    control = replace(robot.control, max_speed=max(robot.control.max_speed, speed))
    robot = replace(robot, control=control)
    world = WorldSettings(seed=seed, obstacles=obstacles)
    free_time = 4.0 / speed + 6.0
    res = run_path(robot, plane_map, plan, RunSettings(vision=vision, world=world, max_time=free_time))
    trace = res.truth_trace
    clearance = _clearance(trace, c.footprint_length / 2.0, c.footprint_width / 2.0, c.footprint_offset_x,
                           px, y0 + off, 0.25) if obstacle else math.inf
    travelled = float(trace[-1, 1] - x0) if len(trace) else 0.0
    still = len(trace) > 2 and math.hypot(trace[-1, 1] - trace[-2, 1], trace[-1, 2] - trace[-2, 2]) < 1e-4
    return ObstacleRun(seed, speed, distance, off, clearance, travelled, bool(still and travelled < goal - x0 - 0.05),
                       dict(res.counters))


def obstacle_runs(robot: RobotConfig, seeds: List[int], speed: float = 0.3, distance: float = 1.0,
                  vision: bool = True) -> List[ObstacleRun]:
    return [obstacle_run(robot, s, speed=speed, distance=distance, vision=vision) for s in seeds]


def stop_ticks(counters: Optional[dict]) -> int:
    """Control ticks the protective stop held the robot in its stop zone, from a run's counters."""
    return int((counters or {}).get("safety_stop", 0))
