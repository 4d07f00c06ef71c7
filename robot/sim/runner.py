"""Whole-robot simulation on a simulated clock: faster than real time and deterministic.

The same ``ControllerCore`` as on the robot, fed by the simulated world instead of threads and
ports: the emulated board (``BoardModel``, real protocol bytes through ``LoopbackChassis``)
produces encoder reports every 10 ms of simulated time, the fake cameras render the true pose,
the localizer runs on each frame and its planes reach the filter a fixed latency after capture
(exercising the lagged-measurement replay), and the control tick runs at the configured rate.
Time is integer microseconds so event order never depends on float rounding.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from drivers.chassis.loopback import LoopbackChassis
from drivers.sim.world import SimWorld, WorldSettings
from robot.base.errors import ConfigError
from robot.config import RobotConfig
from robot.control.core import ControllerCore
from robot.control.path_file import PathPlan
from robot.control.trajectory import ARRIVED, DONE, TrajectoryController
from robot.localization.localizer import Localizer
from robot.maps.plane_map import PlaneMap

_US = 1_000_000


@dataclass(frozen=True)
class RunSettings:
    vision: bool = True
    vision_rate: float = 5.0  # Hz, frames per camera (the robot does 30; the experiment needs far fewer)
    latency: float = 0.05  # s from capture to the fused planes (the robot measured ~50 ms)
    method: str = "joint"
    max_time: float = 240.0  # s of simulated time before the run is called failed
    initial_std: Tuple[float, float] = (0.005, math.radians(0.5))  # placement std at the start (m, rad)
    trace_rate: float = 10.0  # Hz, trajectory samples kept for plots
    world: WorldSettings = field(default_factory=WorldSettings)


@dataclass
class TargetResult:
    index: int
    target: Tuple[float, float]
    truth: Tuple[float, float, float]  # true pose at the end of the dwell
    estimate: Tuple[float, float, float]  # fused pose at the same instant
    t: float

    @property
    def error(self) -> float:
        """Distance (m) from the true position to the target: what the paper's Fig 18 plots."""
        return math.hypot(self.truth[0] - self.target[0], self.truth[1] - self.target[1])

    @property
    def estimate_error(self) -> float:
        return math.hypot(self.truth[0] - self.estimate[0], self.truth[1] - self.estimate[1])


@dataclass
class RunResult:
    vision: bool
    seed: int
    targets: List[TargetResult]
    finished: bool
    reason: str
    sim_time: float
    wall_time: float
    truth_trace: np.ndarray  # (N, 4) t, x, y, phi
    estimate_trace: np.ndarray  # (N, 4)
    counters: Dict[str, int]
    localize_ms: List[float]
    render_ms: List[float]
    nees: List[float]  # normalized estimation error squared of the fused pose at each trace sample

    def to_json(self) -> Dict[str, object]:
        return {"vision": self.vision, "seed": self.seed, "finished": self.finished, "reason": self.reason,
                "sim_time": round(self.sim_time, 3), "wall_time": round(self.wall_time, 3),
                "targets": [{"index": r.index, "target": list(r.target), "truth": [round(v, 5) for v in r.truth],
                             "estimate": [round(v, 5) for v in r.estimate], "error_m": round(r.error, 5),
                             "estimate_error_m": round(r.estimate_error, 5)} for r in self.targets],
                "counters": self.counters}


class DwellWatcher:
    """Tells when the trajectory has finished dwelling at a waypoint: the instant the paper's
    experiment measures the error at that target. Feed it the controller after every tick."""

    def __init__(self) -> None:
        self._prev: Optional[Tuple[int, str]] = None

    def finished_dwell(self, trajectory: TrajectoryController) -> Optional[int]:
        """Index of the waypoint whose dwell ended at this tick, else None."""
        index, state = trajectory.waypoint_index, trajectory.state
        prev, self._prev = self._prev, (index, state)
        if prev is not None and prev[1] == ARRIVED and (index != prev[0] or state == DONE):
            return prev[0]
        return None


def run_path(robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, settings: RunSettings) -> RunResult:
    """Drive ``plan`` once in the simulated world; the start pose is the plan's (exactly)."""
    if plan.start is None:
        raise ConfigError(f"{plan.source}: the simulation needs a 'start' pose in the path file")
    wall0 = time.perf_counter()
    start = (plan.start.x, plan.start.y, plan.start.heading)
    world = SimWorld(robot, plane_map, start, settings.world)
    chassis = LoopbackChassis(world.board, robot.chassis.ticks_per_rev, robot.chassis.max_wheel_speed)
    chassis.connect()
    core = ControllerCore(robot, vision=settings.vision, t_start=0.0)
    sp, sa = settings.initial_std
    core.set_pose(0.0, *start, np.diag([sp * sp, sp * sp, sa * sa]))
    core.set_chassis_link(True)
    core.follow(plan)
    localizer = Localizer(robot, plane_map) if settings.vision else None

    control_us = int(round(_US / robot.control.rate))
    vision_us = int(round(_US / settings.vision_rate)) if settings.vision else None
    latency_us = int(round(settings.latency * _US))
    trace_us = int(round(_US / settings.trace_rate))
    end_us = int(settings.max_time * _US)
    # (time, order, kind): order breaks ties so fusion precedes the control tick at the same instant
    events: List[Tuple[int, int, str, object]] = [(control_us, 2, "control", None), (0, 3, "trace", None)]
    if vision_us is not None:
        events.append((vision_us // 2, 1, "capture", None))
    heapq.heapify(events)
    truth_trace: List[Tuple[float, ...]] = []
    est_trace: List[Tuple[float, ...]] = []
    nees: List[float] = []
    targets: List[TargetResult] = []
    localize_ms: List[float] = []
    render_ms: List[float] = []
    dwell = DwellWatcher()
    reason = f"not finished within {settings.max_time:.0f} s of simulated time"
    finished = False
    now_us = 0
    while events:
        t_us, order, kind, payload = heapq.heappop(events)
        if t_us > end_us:
            break
        if t_us > now_us:
            world.step((t_us - now_us) / _US)
            now_us = t_us
        t = now_us / _US
        for odo in chassis.poll():
            core.on_odometry(odo, chassis.odometry.speed_variance(odo.dt))
        if kind == "capture":
            r0 = time.perf_counter()
            frames = [world.render(cam.name, t) for cam in robot.cameras]
            render_ms.append((time.perf_counter() - r0) * 1e3)
            (x, y, phi), P = core.coarse_pose(t)
            result = localizer.localize(frames, (x, y, phi), P, method=settings.method)
            localize_ms.append(result.ms)
            heapq.heappush(events, (now_us + latency_us, 0, "fuse", (result, t)))
            heapq.heappush(events, (now_us + vision_us, 1, "capture", None))
        elif kind == "fuse":
            result, t_capture = payload
            core.on_localization(result, t_capture)
        elif kind == "trace":
            truth = world.truth
            (x, y, phi), P = core.pose(t)
            truth_trace.append((t, *truth))
            est_trace.append((t, x, y, phi))
            e = np.array([x - truth[0], y - truth[1], math.remainder(phi - truth[2], 2 * math.pi)])
            try:
                nees.append(float(e @ np.linalg.solve(P, e)))
            except np.linalg.LinAlgError:
                pass
            heapq.heappush(events, (now_us + trace_us, 3, "trace", None))
        elif kind == "control":
            out = core.control_step(t)
            if out.wheels is not None:
                chassis.send_wheel_speeds(out.wheels)
            state = core.trajectory.state
            reached = dwell.finished_dwell(core.trajectory)
            if reached is not None:
                wp = plan.waypoints[reached]
                (x, y, phi), _ = core.pose(t)
                targets.append(TargetResult(reached, (wp.x, wp.y), world.truth, (x, y, phi), t))
            if core.finished:
                finished, reason = True, "path complete"
                break
            if state in ("aborted", "error"):
                reason = f"trajectory {state}: {out.reason}"
                break
            heapq.heappush(events, (now_us + control_us, 2, "control", None))
    chassis.stop()
    counters = dict(core.counters)
    counters["implausible_reports"] = chassis.odometry.implausible
    return RunResult(settings.vision, settings.world.seed, targets, finished, reason, now_us / _US,
                     time.perf_counter() - wall0, np.array(truth_trace), np.array(est_trace), counters,
                     localize_ms, render_ms, nees)
