"""The protective-stop experiment: drive at a person standing in the path, on the simulated clock.

The robot starts at rest in a large empty room (an 8 m square from ``drivers.sim.building``) and
is sent 4 m straight ahead at ``speed``; a person (an elliptic cylinder 0.5 x 0.3 x 1.75 m) stands
``distance`` ahead of the robot's front edge, moved sideways at random by up to ``lateral``. The run
ends after the simulated time a free run would need. What it measures: the smallest clearance
between the robot's footprint and the person over the run (the robot must never touch them), and
where it came to rest.

``cluttered_run`` is the other half: a planned path through a building full of site items kept
clear of the path, where every tick held in the stop zone is a false stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import List, Optional, Tuple

import numpy as np

from drivers.sim.building import room_grid_map
from drivers.sim.clutter import person
from drivers.sim.world import WorldSettings, sample_world
from robot.config import RobotConfig
from robot.control.path_file import PathPlan, parse_path
from robot.maps.plane_map import PlaneMap
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


def path_course(plan: PathPlan, step: float = 0.1) -> List[Tuple[float, float]]:
    """Points every ``step`` metres along a path's straight legs, start included: what random
    clutter is kept clear of when a run must meet nothing in its way (false stops)."""
    if plan.start is None:
        raise ValueError(f"{plan.source}: the course needs the path's start pose")
    pts = [(plan.start.x, plan.start.y)] + [(w.x, w.y) for w in plan.waypoints]
    course = [pts[0]]
    for (x0, y0), (x1, y1) in zip(pts, pts[1:]):
        n = max(1, int(math.ceil(math.hypot(x1 - x0, y1 - y0) / step)))
        course += [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n) for k in range(1, n + 1)]
    return course


@dataclass(frozen=True)
class ClutteredRun:
    seed: int
    finished: bool
    reason: str  # why a run did not finish (the runner's words), "" when it did
    stop_ticks: int  # control ticks held in the protective stop zone: each is a false stop here
    limited_ticks: int  # ticks slowed or limited for any reason (slow-down zone, blind creep)
    items: List[str]  # the kinds of site items placed


def cluttered_run(robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, seed: int, items: int = 10,
                  clearance_step: float = 0.1) -> ClutteredRun:
    """One run of ``plan`` with vision through a building with ``items`` random site items
    (people, pallets, shelving, boards and panels at walls, doors in openings) kept 0.5 m clear of
    the path's course, and its walls as built: nothing stands in the way, so any tick held in the
    stop zone is a false stop."""
    world = WorldSettings(seed=seed, site=items, as_built=True, keep_clear=tuple(path_course(plan, clearance_step)))
    start = (plan.start.x, plan.start.y, plan.start.heading)  # path_course has refused a plan without one
    # The same seed draws the same scene as the run's world (sample_world is what SimWorld calls).
    _, scene = sample_world(plane_map, start, seed, world.radius_error_std, world.clutter, world.site,
                            world.as_built, world.keep_clear)
    res = run_path(robot, plane_map, plan, RunSettings(vision=True, world=world))
    return ClutteredRun(seed, res.finished, "" if res.finished else res.reason, stop_ticks(res.counters),
                        int(res.counters.get("safety_limited", 0)), [getattr(c, "kind", "?") for c in scene.clutter])
