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
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from drivers.chassis.base import LinkState
from drivers.chassis.loopback import LoopbackChassis
from drivers.sim.world import SimWorld, WorldSettings
from robot.base.errors import ConfigError, DriverError
from robot.base.frames import FrameCheck
from robot.base.geometry import wrap_angle
from robot.config import RobotConfig
from robot.config.calibration import calibrated_frame
from robot.control.core import ControllerCore
from robot.control.path_file import PathPlan
from robot.control.recovery import views_from_latest
from robot.control.trajectory import ARRIVED, DONE, TrajectoryController
from robot.fusion.calibration_filter import CalibrationFilter
from robot.fusion.quality import LOCALIZED
from robot.localization.localizer import Localizer
from robot.localization.relocalize import Relocalizer
from robot.localization.viewpoint import ViewpointPlanner, plan_recovery_move
from robot.maps.plane_map import PlaneMap
from robot.sim.faults import FaultPlan, FaultyLine

_US = 1_000_000
CONNECT_ATTEMPTS = 100  # handshakes tried at the start before the run is called failed


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
    online_calibration: bool = False  # estimate depth scales, mounts and wheel radii while driving (fusion.calibration_filter)
    world_robot: Optional[RobotConfig] = None  # the simulated robot itself, if not the config the controller runs with
    # (t, x, y, phi): at simulated time t the robot is carried to (x, y, phi) without its wheels
    # turning (the kidnapped robot).
    kidnap_at: Optional[Tuple[float, float, float, float]] = None
    known_start: bool = True  # False: the robot starts without a pose and must relocalize
    faults: Optional[FaultPlan] = None  # host stalls, serial line faults, bad frames (robot.sim.faults)


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
    commands: List[Tuple[float, float, float, float, bool]] = field(default_factory=list)  # per tick: t, vx, vy, wz, sent
    calibration: Optional[Dict[str, object]] = None  # the online calibration at the end: names, mean, cov, observed
    # At each trace sample with a quality report: (t, state, horizontal protection level m, true position error m).
    quality_trace: List[Tuple[float, str, float, float]] = field(default_factory=list)

    def to_json(self) -> Dict[str, object]:
        return {"vision": self.vision, "seed": self.seed, "finished": self.finished, "reason": self.reason,
                "sim_time": round(self.sim_time, 3), "wall_time": round(self.wall_time, 3),
                "targets": [{"index": r.index, "target": list(r.target), "truth": [round(v, 5) for v in r.truth],
                             "estimate": [round(v, 5) for v in r.estimate], "error_m": round(r.error, 5),
                             "estimate_error_m": round(r.estimate_error, 5)} for r in self.targets],
                "counters": self.counters}


def localized_share(runs: Sequence[RunResult]) -> float:
    """Share of all trace samples of ``runs`` at which the fused pose was ``localized`` (NaN without any)."""
    states = [state for r in runs for _, state, _, _ in r.quality_trace]
    return sum(1 for s in states if s == LOCALIZED) / len(states) if states else math.nan


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


def run_path(robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, settings: RunSettings, tap=None) -> RunResult:
    """Drive ``plan`` once in the simulated world; the start pose is the plan's (exactly).

    ``tap`` (optional) sees what the core sees: ``on_odometry(odo)``, ``on_capture(frames, result)``
    and ``on_fused(result, t_capture, report)`` (the calibration routine collects its data so)."""
    if plan.start is None:
        raise ConfigError(f"{plan.source}: the simulation needs a 'start' pose in the path file")
    wall0 = time.perf_counter()
    # Put the robot at the plan's start in the simulated world and give the plan to the core.
    run = _PathRun(robot, plane_map, plan, settings)
    run.tap = tap
    # Play the events on the simulated clock until the path ends, fails or runs out of time.
    run.drive()
    # Stop the wheels and collect what the run measured.
    run.chassis.stop()
    return run.result(time.perf_counter() - wall0)


class _PathRun:
    """The state of one run_path: the simulated world, the core, and the events between them on a
    clock of integer microseconds. Each kind of event has its handler."""

    # Tie-breaking order at the same instant: fusion precedes the control tick.
    _ORDER = {"fuse": 0, "capture": 1, "control": 2, "trace": 3, "kidnap": 4}

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, plan: PathPlan, settings: RunSettings) -> None:
        self.robot, self.plan, self.settings = robot, plan, settings
        start = (plan.start.x, plan.start.y, plan.start.heading)
        self.world = SimWorld(settings.world_robot or robot, plane_map, start, settings.world)
        self.faults = settings.faults
        board = self.world.board if self.faults is None else FaultyLine(self.world.board, self.faults, lambda: self.now_us / _US)
        chassis = LoopbackChassis(board, robot.chassis)
        self.now_us = 0
        for attempt in range(CONNECT_ATTEMPTS):  # a faulty line may garble the first handshakes, as the app retries
            try:
                chassis.connect_now()
                break
            except DriverError:
                if chassis.link_state is LinkState.FAULT or attempt == CONNECT_ATTEMPTS - 1:
                    raise
        self.chassis = chassis
        self._odometry = chassis.odometry_queue()  # read like the app reads it: merged, never dropped, when behind
        self._reconnects = 0
        self.frame_check = FrameCheck(robot.health.frame_max_ahead, robot.health.frame_max_age)
        self.commands: List[Tuple[float, float, float, float, bool]] = []
        calibration = CalibrationFilter(robot, plane_map=plane_map) if settings.online_calibration and settings.vision else None
        self.core = ControllerCore(robot, vision=settings.vision, t_start=0.0, plane_map=plane_map,
                                   calibration=calibration)
        self.tap = None
        sp, sa = settings.initial_std
        if settings.known_start:
            self.core.set_pose(0.0, *start, np.diag([sp * sp, sp * sp, sa * sa]))
        else:
            self.core.recovery.start_without_pose(0.0)
        self.core.set_chassis_link(True)
        self.core.follow(plan)
        self.localizer = Localizer(robot, plane_map) if settings.vision else None
        self.plane_map = plane_map
        self._relocalizer: Optional[Relocalizer] = None
        self._planner: Optional[ViewpointPlanner] = None
        self.relocalizations: List[Tuple[float, str]] = []  # (t, verdict)
        self.relocalization_views: List[Tuple[float, Tuple[float, float, float]]] = []  # (t, odometry pose from view 0)
        self._views: List[Tuple[list, Tuple[float, float, float]]] = []  # of the present relocalization sequence
        self.recovery_log: List[Tuple[float, str]] = []  # (t, recovery state) at every change

        self.control_us = int(round(_US / robot.control.rate))
        # Frames are rendered for the protective stop even without vision fusion (it needs fresh
        # depth to let the robot move at all), at the vision rate either way.
        self.vision_us = int(round(_US / settings.vision_rate)) if (settings.vision or robot.safety.enabled) else 0
        self.latency_us = int(round(settings.latency * _US))
        self.trace_us = int(round(_US / settings.trace_rate))
        self.end_us = int(settings.max_time * _US)
        self.events: List[Tuple[int, int, str, object]] = []  # (time, order, kind, payload), a heap
        self.now_us = 0
        self._schedule_at(self.control_us, "control")
        self._schedule_at(0, "trace")
        if self.vision_us:
            self._schedule_at(self.vision_us // 2, "capture")
        if settings.kidnap_at is not None:
            self._schedule_at(int(round(settings.kidnap_at[0] * _US)), "kidnap", tuple(settings.kidnap_at[1:]))

        self.truth_trace: List[Tuple[float, ...]] = []
        self.est_trace: List[Tuple[float, ...]] = []
        self.nees: List[float] = []
        self.quality_trace: List[Tuple[float, str, float, float]] = []
        self.targets: List[TargetResult] = []
        self.localize_ms: List[float] = []
        self.render_ms: List[float] = []
        self.dwell = DwellWatcher()
        self.finished = False
        self.reason = f"not finished within {settings.max_time:.0f} s of simulated time"

    def drive(self) -> None:
        handlers = {"capture": self._capture, "fuse": self._fuse, "trace": self._trace, "control": self._control,
                    "kidnap": self._kidnap}
        while self.events:
            t_us, _, kind, payload = heapq.heappop(self.events)
            if t_us > self.end_us:
                return
            resume = self._frozen_until(t_us)
            if resume is not None and kind in ("capture", "fuse", "control", "trace"):
                # The event loop is frozen: what falls due runs when it thaws. The port's reader
                # thread still reads and stamps reports (at each trace instant here), but nothing
                # consumes them, and a frozen host reports no estimate to trace.
                if kind == "trace":
                    self._advance_to(t_us)
                    self._schedule_at(t_us + self.trace_us, kind, payload)
                else:
                    self._schedule_at(resume, kind, payload)
                continue
            self._advance_to(t_us)
            if not handlers[kind](self.now_us / _US, payload):
                return

    def result(self, wall_time: float) -> RunResult:
        counters = dict(self.core.counters)
        counters["implausible_reports"] = self.chassis.encoders.implausible
        counters["frames_refused"] = self.frame_check.total
        for key in ("odometry_coalesced", "reconnects", "link_losses"):
            counters[key] = int(self.chassis.stats.get(key, 0) or 0)
        cal = self.core.calibration
        calibration = None if cal is None else {"names": list(cal.names), "mean": cal.mean.tolist(),
                                                 "cov": cal.cov.tolist(), "observed": cal.observed().tolist()}
        return RunResult(self.settings.vision, self.settings.world.seed, self.targets, self.finished, self.reason,
                         self.now_us / _US, wall_time, np.array(self.truth_trace), np.array(self.est_trace), counters,
                         self.localize_ms, self.render_ms, self.nees, self.commands, calibration, self.quality_trace)

    def _frozen_until(self, t_us: int) -> Optional[int]:
        """While the host is frozen at ``t_us``: the microsecond it runs again; else None."""
        end = self.faults.frozen_until(t_us / _US) if self.faults is not None else None
        return None if end is None else max(t_us + 1, int(round(end * _US)))

    def _schedule_at(self, t_us: int, kind: str, payload: object = None) -> None:
        heapq.heappush(self.events, (t_us, self._ORDER[kind], kind, payload))

    def _advance_to(self, t_us: int) -> None:
        """Move the world on to ``t_us`` and feed the core the wheel odometry the board sent meanwhile."""
        if t_us > self.now_us:
            self.world.step((t_us - self.now_us) / _US)
            self.now_us = t_us
        self.chassis.poll()
        if self._frozen_until(t_us) is not None:
            return  # the queue fills (and merges) while the loop is frozen
        while not self._odometry.empty():
            odo = self._odometry.get_nowait()
            self.core.on_odometry(odo, self.chassis.encoders.speed_variance(odo.dt))
            if self.tap is not None:
                self.tap.on_odometry(odo)

    def _capture(self, t: float, _payload: object) -> bool:
        """Render every camera at the true pose and localize; the result is fused ``latency`` later."""
        r0 = time.perf_counter()
        frames = [calibrated_frame(self.world.render(cam.name, t), cam.depth_scale) for cam in self.robot.cameras]
        self.render_ms.append((time.perf_counter() - r0) * 1e3)
        if self.faults is not None:
            frames = [self.faults.frame(f, t) for f in frames]
        frames = [f for f in frames if self.frame_check.admit(f, t)]  # a bad frame is counted, never used
        if not frames:
            self._schedule_at(self.now_us + self.vision_us, "capture")
            return True
        pose, P = self.core.coarse_pose(t) if self.core.initialized else (None, None)
        scan_pose = pose if self.core.walls_explain_obstacles else None
        for f in frames:  # the protective stop sees every frame, with or without vision fusion
            self.core.safety.update_scan(f.camera, t, f.depth, f.K, scan_pose, float(f.depth_scale))
        if self.localizer is not None and self.core.relocalization_due(t):
            self._relocalize(t, frames)
        if self.localizer is not None and self.core.initialized:
            pose, P = self.core.coarse_pose(t)
            result = self.localizer.localize(frames, pose, P, method=self.settings.method)
            self.localize_ms.append(result.ms)
            if self.tap is not None:
                self.tap.on_capture(frames, result)
            self._schedule_at(self.now_us + self.latency_us, "fuse", (result, t))
        self._schedule_at(self.now_us + self.vision_us, "capture")
        return True

    def _relocalize(self, t: float, frames) -> None:
        """Global relocalization on these frames (no prior) and, after an in-place turn, on the
        earlier views of the sequence with their odometry poses; a unique verdict sets the pose."""
        if self._relocalizer is None:
            self._relocalizer = Relocalizer(self.robot, self.plane_map, self.localizer)
        rec = self.core.recovery
        if rec.view_index == 0:
            self._views = []
        rel = self.core.recovery_view_pose()
        self._views.append((frames, rel))
        self.relocalization_views.append((t, rel))
        first, more = views_from_latest(self._views)
        res = self._relocalizer.relocalize(first, more_views=more)
        self.relocalizations.append((t, res.verdict))
        if res.verdict == "unique":
            h = res.hypotheses[0]
            self.core.set_pose(t, h.x, h.y, h.phi, np.asarray(h.cov))
        rec.on_verdict(t, res.verdict, [h.to_json() for h in res.hypotheses[:8]], res.reason)
        if rec.wants_move_plan:
            if self._planner is None:
                self._planner = ViewpointPlanner(self.robot, self.plane_map, self._relocalizer.index)
            cfg = self.robot.recovery
            rec.move_planned(t, *plan_recovery_move(self._planner, res.hypotheses, cfg.move_max_distance,
                                                    cfg.move_clearance, rec.moves_left))

    def _kidnap(self, _t: float, payload: object) -> bool:
        self.world.board.pose = tuple(float(v) for v in payload)  # type: ignore[assignment]
        return True

    def _fuse(self, _t: float, payload: object) -> bool:
        result, t_capture = payload
        report = self.core.on_localization(result, t_capture)
        if self.tap is not None:
            self.tap.on_fused(result, t_capture, report)
        return True

    def _trace(self, t: float, _payload: object) -> bool:
        """Sample the true and the fused pose, and the fused pose's NEES."""
        truth = self.world.truth
        if not self.core.initialized:  # no pose yet (relocalizing from nothing): nothing to compare
            self._schedule_at(self.now_us + self.trace_us, "trace")
            return True
        (x, y, phi), P = self.core.pose(t)
        self.truth_trace.append((t, *truth))
        self.est_trace.append((t, x, y, phi))
        e = np.array([x - truth[0], y - truth[1], wrap_angle(phi - truth[2])])
        q = self.core.last_quality
        if q is not None:
            self.quality_trace.append((t, q.state, float(q.horizontal_pl), float(math.hypot(e[0], e[1]))))
        try:
            self.nees.append(float(e @ np.linalg.solve(P, e)))
        except np.linalg.LinAlgError:
            pass
        self._schedule_at(self.now_us + self.trace_us, "trace")
        return True

    def _control(self, t: float, _payload: object) -> bool:
        """One control tick; records the target whose dwell it ends. False once the path is over."""
        link_ok = self.chassis.link_state is LinkState.READY
        self.core.set_chassis_link(link_ok, "" if link_ok else f"chassis link {self.chassis.link_state.value}")
        reconnects = int(self.chassis.stats.get("reconnects", 0) or 0)
        if reconnects != self._reconnects:  # a new session came up between two ticks
            self._reconnects = reconnects
            self.core.note_fault(t, "the motor board reconnected")
        out = self.core.control_step(t)
        if not self.recovery_log or self.recovery_log[-1][1] != self.core.recovery.state:
            self.recovery_log.append((t, self.core.recovery.state))
        sent = out.wheels is not None and self.chassis.send_wheel_speeds(out.wheels)
        self.commands.append((t, out.command.vx, out.command.vy, out.command.wz, bool(sent)))
        state = self.core.trajectory.state
        reached = self.dwell.finished_dwell(self.core.trajectory)
        if reached is not None:
            wp = self.plan.waypoints[reached]
            (x, y, phi), _ = self.core.pose(t)
            self.targets.append(TargetResult(reached, (wp.x, wp.y), self.world.truth, (x, y, phi), t))
        if self.core.finished:
            self.finished, self.reason = True, "path complete"
            return False
        if state in ("aborted", "error"):
            self.reason = f"trajectory {state}: {out.reason}"
            return False
        self._schedule_at(self.now_us + self.control_us, "control")
        return True
