"""The robot's decisions, with explicit time and no I/O: fusion, quality, health and the command.

Every input carries its own timestamp (host monotonic seconds, or simulated seconds: the core
cannot tell and does not care). The asyncio app (``robot.app.controller``) and the simulated-clock runner
(``robot.sim.runner``) are two shells around this one core, so the code that decides what the
wheels do is the same on the robot, in real-time simulation, faster than real time, and in
replay.

Data flow per input:

- wheel odometry -> EKF prediction (mean twist through the forward kinematics, its covariance
  from the encoder quantisation; the filter adds slip noise per metre);
- a localization result -> each fitted plane is an EKF update at the frame's capture time
  (lagged replay), gated; the gate decisions feed the quality monitor and the health supervisor;
- a control tick -> the speed scale from health and quality, the trajectory controller (path)
  or the teleop limiter, the inverse kinematics, and a command that is only ever produced from
  fresh inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import RobotError
from robot.base.geometry import compose_se2, integrate_twist, invert_se2
from robot.base.samples import WheelOdometry
from robot.config import RobotConfig
from robot.control.health import HealthSupervisor
from robot.control.kinematics import MecanumKinematics, limit_floats
from robot.control.odometry import OdometryFeed
from robot.control.path_file import PathPlan
from robot.control.protective_stop import CLEAR, DISABLED, ProtectiveStop, SafetyDecision
from robot.control.recovery import RecoverySupervisor
from robot.control.trajectory import AxisLimiter, Command, TrajectoryController, approach_speed
from robot.fusion.calibration_filter import CalibrationFilter
from robot.fusion.ekf import PoseFilter
from robot.fusion.quality import LOCALIZED, LOST, FusedProtection, QualityMonitor, QualityReport
from robot.localization.localizer import LocalizationResult
from robot.maps.plane_map import PlaneMap

STILL_SPEED = 0.005  # m/s: slower than this the robot counts as standing still
STILL_TURN = 0.01  # rad/s
IDLE = "idle"
PATH = "path"
TELEOP = "teleop"
TURN = "recovery_turn"  # Command.state of the relocalization's in-place turn
MOVE = "recovery_move"  # Command.state of the relocalization's straight move
MOVE_DONE_TOL = 0.005  # m short of the move's end that counts as there (by wheel odometry)
MOVE_KP = 1.0  # 1/s: the move's approach to its end, below the braking curve
TURN_DONE_TOL = math.radians(2.0)  # rad short of the next view's heading that counts as there (odometry gives the exact angle)
TURN_KP = 2.0  # 1/s: the turn's approach to its heading, below the braking curve


class CommandRefused(RobotError):
    """An operator or fleet request that the robot's present state does not allow, with the reason."""


@dataclass(frozen=True)
class ControlOutput:
    """What one control tick decided. ``wheels`` is None when nothing may be sent."""

    t: float
    command: Command  # body twist (robot frame) after limits and health scaling
    wheels: Optional[Tuple[float, float, float, float]]  # rad/s FL, FR, RL, RR; None = send nothing
    speed_scale: float
    reason: str  # why the scale is below 1 or nothing is sent ("" when all is well)


@dataclass
class FusionReport:
    t_capture: float
    camera: str
    accepted: List[str] = field(default_factory=list)  # plane ids the gate took
    rejected: List[Tuple[str, str]] = field(default_factory=list)  # (plane id, reason)
    fits: int = 0  # planes the localizer fitted (before the gate)


class TwistLimiter:
    """Teleop: the operator's target twist through the same speed/accel/jerk limits as paths."""

    def __init__(self, robot: RobotConfig):
        c = robot.control
        self._lim = (AxisLimiter(c.max_speed, c.max_accel, c.max_jerk),
                     AxisLimiter(c.max_speed, c.max_accel, c.max_jerk),
                     AxisLimiter(c.max_yaw_rate, c.max_yaw_accel, c.max_yaw_jerk))
        self._max_dt = c.max_dt
        self._t: Optional[float] = None

    def reset(self) -> None:
        """Start again from rest (the wheels were stopped behind the limiter's back)."""
        for lim in self._lim:
            lim.reset()
        self._t = None

    def step(self, t: float, target: Sequence[float], scale: float) -> Tuple[float, float, float]:
        dt = 0.02 if self._t is None else min(max(t - self._t, 0.0), self._max_dt)
        self._t = t
        return tuple(lim.step(float(v) * scale, dt) for lim, v in zip(self._lim, target))  # type: ignore[return-value]


class ControllerCore:
    """Fusion + quality + health + path/teleop control of one robot. Single-threaded: the shell
    calls it from one thread (the event loop), never concurrently."""

    def __init__(self, robot: RobotConfig, *, vision: bool = True, t_start: float = 0.0,
                 wheel_speed_noise: float = 0.05, plane_map: Optional[PlaneMap] = None,
                 calibration: Optional[CalibrationFilter] = None):
        self.robot = robot
        # Online calibration (optional): corrects each plane measurement with the estimated depth
        # scale and mount before the filter sees it, and learns from what the filter accepted.
        self.calibration = calibration
        # The protective stop: scans come from the localization worker (update_scan), the limit is
        # applied here, on every tick, before the command is turned into wheel speeds.
        self.safety = ProtectiveStop(robot.safety, robot, plane_map)
        self.last_safety: Optional[SafetyDecision] = None
        self._safety_scale = 1.0
        # When lost or kidnapped: hold still until a relocalization is confirmed.
        self.recovery = RecoverySupervisor(robot.recovery)
        self._last_fix = -math.inf  # capture time of the newest accepted camera fix
        self._odom_speed = 0.0  # m/s and rad/s of the newest wheel odometry
        self._odom_turn = 0.0
        # The in-place turn of a relocalization: the odometry pose since the sequence's first view
        # (view 0's robot frame), its unwrapped heading, and the turn's own rate limiter.
        self._turn_rel: Tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._turn_yaw = 0.0
        c = robot.control
        self._turn_lim = AxisLimiter(min(robot.recovery.turn_rate, c.max_yaw_rate), c.max_yaw_accel, c.max_yaw_jerk)
        self._turn_t: Optional[float] = None
        self._turn_t0 = -math.inf  # when the present turn began: only a fault since then stops it
        # The relocalization's move (a turn to face the way, then straight ahead): its own limiters
        # (speed along the move, yaw rate), the odometry pose (view 0's frame) where it started,
        # and its direction in the robot frame.
        self._move_lim = AxisLimiter(min(robot.recovery.move_speed, c.max_speed), c.max_accel, c.max_jerk)
        self._move_yaw_lim = AxisLimiter(min(robot.recovery.turn_rate, c.max_yaw_rate), c.max_yaw_accel, c.max_yaw_jerk)
        self._move_t: Optional[float] = None
        self._move_t0 = -math.inf  # when the present move began: only a fault since then stops it
        self._move_start: Optional[Tuple[float, float, float]] = None
        self._move_serial = 0  # recovery.move_serial of the move _move_start belongs to
        self._move_yaw0 = 0.0  # unwrapped odometry heading where it started
        self._move_facing = False  # the turn to face the way is done
        self._move_dir = (1.0, 0.0)
        self._t_odom_seen = -math.inf  # newest wheel odometry, pose or not (the turn needs it fresh)
        self.vision = vision
        self.kinematics = MecanumKinematics.from_config(robot.chassis)
        self.filter = PoseFilter(robot.fusion)
        self.quality = QualityMonitor(robot.quality)
        health_cfg = robot.health if vision else replace(robot.health, vision_required=False)
        self.health = HealthSupervisor(health_cfg, t_start)
        self.wheel_speed_noise = float(wheel_speed_noise)  # rad/s std beyond quantisation (motor ripple)
        self._odometry = OdometryFeed(self.kinematics, robot.chassis, self.wheel_speed_noise)
        self.mode = IDLE
        self.trajectory: Optional[TrajectoryController] = None
        self._teleop = TwistLimiter(robot)
        self._teleop_target = (0.0, 0.0, 0.0)
        self._teleop_t = -math.inf
        self.teleop_deadman = 0.5  # s: an operator twist older than this is zero
        self._t_last_odom = -math.inf
        self._chassis_reason = "chassis link not up yet"
        self._last_quality: Optional[QualityReport] = None
        # What the last accepted localization adds to the fused pose's protection levels.
        self._protection: Optional[FusedProtection] = None
        self._fused_walls: Dict[str, Tuple[float, float]] = {}  # map wall -> ground normal (x, y), accepted since
        # Operator entry points (go, extend, pause, speed limit): plans waiting for the current one
        # to end, a pause that also holds plans started later, a limit at or below control.max_speed.
        self._queued: List[PathPlan] = []
        self._paused = False
        self._speed_limit = robot.control.max_speed
        self.counters: Dict[str, int] = {"odometry": 0, "odometry_rejected": 0, "localizations": 0,
                                         "planes_accepted": 0, "planes_rejected": 0, "ticks": 0,
                                         "ticks_silent": 0}

    # -- pose -------------------------------------------------------------------------------

    def set_pose(self, t: float, x: float, y: float, phi: float, cov: np.ndarray,
                 hidden_walls: Sequence[Mapping] = ()) -> None:
        """A pose given to the robot (a person, the pose store, a relocalization). ``hidden_walls``:
        a relocalization's walls that a panel may hide ({"plane", "up_to_m", "direction"}): its pose
        may then be that much farther from the wall, and the fused protection levels stay over
        that until walls other than it observe the direction (FusedProtection)."""
        self.filter.set_pose(t, x, y, phi, cov)
        self.quality.note_fix(t)
        # The pose set comes with its own covariance, and with what it could not exclude.
        self._protection = FusedProtection.from_hidden_walls(hidden_walls, cov) if hidden_walls else None
        self._fused_walls = {}
        self.health.localization_succeeded(t)
        self._t_last_odom = t
        self._odometry.reset()

    @property
    def initialized(self) -> bool:
        return self.filter.initialized

    def pose(self, t: float) -> Tuple[Tuple[float, float, float], np.ndarray]:
        """The fused pose at time t (the held last twist beyond the newest odometry)."""
        x, y, phi, P = self.filter.predicted(t)
        return (x, y, phi), P

    def coarse_pose(self, t_capture: float) -> Tuple[Tuple[float, float, float], np.ndarray]:
        """Coarse pose and covariance for a frame captured at ``t_capture`` (its ROI prediction)."""
        return self.pose(t_capture)

    # -- inputs -----------------------------------------------------------------------------

    def on_odometry(self, odo: WheelOdometry, quantisation_variance: float = 0.0) -> bool:
        if self.calibration is not None:
            self.calibration.add_odometry(odo)
        if self.vision and (self.recovery.in_sequence or not self.filter.initialized):
            self._turn_odometry(odo)
        if not self.filter.initialized:
            return False
        # A sample spans its own interval; a gap before it (the encoders restarted) gets an input
        # of its own whose covariance covers the unseen motion, and holds the robot.
        steps, gap = self._odometry.steps(odo, quantisation_variance, self._t_last_odom)
        for t, twist, Q in steps:
            res = self.filter.predict_twist(t, float(twist[0]), float(twist[1]), float(twist[2]), Q)
            self._odom_speed = math.hypot(float(twist[0]), float(twist[1]))
            self._odom_turn = float(twist[2])
        if gap is not None and res.accepted:
            self.counters["odometry_gaps"] = self.counters.get("odometry_gaps", 0) + 1
            self.health.note_fault(odo.t, gap)
            self._restart_from_rest()
        if res.accepted:
            self.counters["odometry"] += 1
            self._t_last_odom = odo.t
        else:
            self.counters["odometry_rejected"] += 1
        return res.accepted

    def _turn_odometry(self, odo: WheelOdometry) -> None:
        """Wheel odometry without the filter: the relative pose between the views of a relocalization
        (the filter's pose is missing or wrong then), and whether the robot stands still."""
        dt = float(odo.dt)
        self._t_odom_seen = max(self._t_odom_seen, float(odo.t))
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            return
        vx, vy, wz = (float(v) for v in self.kinematics.forward(odo.speeds))
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            return
        if not self.filter.initialized:  # else on_odometry sets them from the filter's inputs
            self._odom_speed, self._odom_turn = math.hypot(vx, vy), wz
        if self.recovery.in_sequence:
            self._turn_rel = integrate_twist(*self._turn_rel, vx, vy, wz, dt)
            self._turn_yaw += wz * dt  # unwrapped: the turn's goal may pass +-pi

    def recovery_view_pose(self) -> Tuple[float, float, float]:
        """The robot's pose now in the robot frame of the first view of this relocalization (odometry)."""
        return self._turn_rel

    def on_gyro(self, t: float, wz_robot: float, variance: float) -> bool:
        if not self.filter.initialized:
            return False
        return self.filter.predict_gyro(t, wz_robot, variance).accepted

    def on_localization(self, result: LocalizationResult, t_capture: float, camera: str = "") -> FusionReport:
        """Fuse the planes of one localization (frames captured at ``t_capture``)."""
        return self.on_localizations([(result, t_capture, camera)])[0]

    def on_localizations(self, items: Sequence[Tuple[LocalizationResult, float, str]]) -> List[FusionReport]:
        """Fuse several localizations (each ``(result, t_capture, camera)``: the frames of every
        camera taken together) in one filter update, so the history after the earliest of them is
        replayed once, not once per camera. Each measurement keeps its own capture time."""
        reports = [FusionReport(t, camera, fits=len(result.measurements)) for result, t, camera in items]
        self.counters["localizations"] += len(items)
        if not self.vision or not self.filter.initialized:
            return reports
        corrected = [result if self.calibration is None or not result.measurements else self.calibration.correct(result)
                     for result, _, _ in items]
        measurements = [m for result in corrected for m in result.measurements]
        outcomes = iter(self.filter.update_planes(measurements) if measurements else [])
        for (raw, t_capture, _), result, report in zip(items, corrected, reports):
            if not result.measurements:
                self._note_recovery(result, t_capture, 0)
                continue
            for meas in result.measurements:
                res = next(outcomes)
                self.quality.note_update(meas.t_capture, res.accepted)
                if res.accepted:
                    report.accepted.append(meas.plane_id)
                else:
                    report.rejected.append((meas.plane_id, res.reason))
            self.counters["planes_accepted"] += len(report.accepted)
            self.counters["planes_rejected"] += len(report.rejected)
            if report.accepted:
                self.health.localization_succeeded(t_capture)
                accepted = set(report.accepted)
                for meas in result.measurements:
                    if meas.plane_id in accepted:
                        self._fused_walls[meas.plane_id] = (float(meas.n_ground[0]), float(meas.n_ground[1]))
                self._protection = FusedProtection.from_localization(raw, self._protection, self._fused_walls)
                self._last_fix = max(self._last_fix, t_capture)
                self.health.note_accepted(t_capture, len(report.accepted))
            self._note_recovery(result, t_capture, len(report.accepted))
            if self.calibration is not None and report.accepted:
                self.calibration.add_localization(raw, t_capture, report.accepted, self.pose(t_capture)[0])
        return reports

    @property
    def walls_explain_obstacles(self) -> bool:
        """Whether the protective stop may take depth points on mapped walls (at the filter's pose)
        for those walls. Not while the recovery holds the robot: the pose is missing or in doubt
        then, and at a wrong pose a person could stand where a wall is expected (the in-place turn
        and the move see every point as an obstacle)."""
        return not (self.vision and self.recovery.holding)

    def relocalization_due(self, t: float) -> bool:
        """Whether the shell should relocalize now: asked for by the recovery supervisor, and the
        robot has braked to a standstill (frames of a moving robot would describe a blur of poses)."""
        if abs(self._odom_speed) > STILL_SPEED or abs(self._odom_turn) > STILL_TURN:
            return False
        if not self.recovery.wants_relocalization(t):
            return False
        if self.recovery.view_index == 0:  # a new sequence: its first view is the origin
            self._turn_rel, self._turn_yaw = (0.0, 0.0, 0.0), 0.0
        return True

    def _note_recovery(self, result: LocalizationResult, t_capture: float, accepted: int) -> None:
        """Tell the recovery supervisor how this view agreed with the pose. Predicted walls with a
        large region of interest and no fit at all disagree as much as fits the gate rejects. Walls
        that contradict one another (an inconsistent result the depth did not decide) say
        nothing about the pose: a panel in front of one wall does that to a robot that is where it
        thinks (measured in the cluttered FZK house, where it stopped the tour for nothing)."""
        fitted = len(result.measurements)
        if result.status == "inconsistent" and not (result.integrity or {}).get("depth_against_pose"):
            fitted = 0
        elif fitted == 0:
            big = sum(1 for r in result.planes if getattr(r, "roi_points", 0) >= self.robot.localizer.min_inliers)
            fitted = big if big >= 1 else 0
        self.recovery.on_fusion(t_capture, fitted, accepted)

    def set_chassis_link(self, ok: bool, reason: str = "") -> None:
        self.health.note_link(ok, reason)  # a change is a fault: the robot is held until confirmed
        self._chassis_reason = reason or ("" if ok else "chassis link down")

    def note_fault(self, t: float, reason: str) -> None:
        """A fault the shell saw (the board reconnected, the loop missed its deadlines): the robot
        comes back stopped, its limiters start from rest, and the mission waits for a confirmed pose."""
        self.health.note_fault(t, reason)
        self._restart_from_rest()

    def _restart_from_rest(self) -> None:
        self.counters["faults"] = self.counters.get("faults", 0) + 1
        if self.trajectory is not None:
            self.trajectory.reset_motion()
        self._teleop.reset()

    def _fault_hold(self, t: float, P: np.ndarray, scale: float, reason: str) -> Tuple[float, str]:
        """While held after a fault: speed scale 0 and the path held, until the pose is confirmed."""
        if not self.health.holding:
            return scale, reason
        if self.mode != PATH:  # an operator drives by hand: the limiters already start from rest
            self.health.clear_fault()
            return scale, reason
        P_xy = np.asarray(P, dtype=float)[:2, :2]
        pos_std = math.sqrt(max(0.0, float(np.linalg.eigvalsh(P_xy)[-1]))) if np.isfinite(P_xy).all() else math.inf
        released, why = self.health.release(t, pos_std, self._t_last_odom)
        if released:
            if self.trajectory is not None:
                self.trajectory.release()
            return scale, reason
        if self.trajectory is not None:
            self.trajectory.hold(why)
        return 0.0, why

    # -- missions ---------------------------------------------------------------------------

    def follow(self, plan: PathPlan) -> None:
        self.trajectory = TrajectoryController(plan, self.robot.control)
        self.mode = PATH

    def teleoperate(self) -> None:
        self.mode = TELEOP
        self.trajectory = None

    def set_teleop_twist(self, t: float, vx: float, vy: float, wz: float) -> None:
        vals = (float(vx), float(vy), float(wz))
        if not all(math.isfinite(v) for v in vals):
            vals = (0.0, 0.0, 0.0)
        self._teleop_target = vals
        self._teleop_t = t

    @property
    def finished(self) -> bool:
        return self.mode == PATH and self.trajectory is not None and self.trajectory.finished and not self._queued

    # -- operator entry points (control socket, fleet link) ---------------------------------

    @property
    def mission_active(self) -> bool:
        """A path is being driven, braked or waited for (paused counts as active)."""
        return self.mode == PATH and (bool(self._queued) or (self.trajectory is not None and not self.trajectory.finished))

    @property
    def paused(self) -> bool:
        return self._paused

    def go(self, plan: PathPlan, replace: bool = False) -> None:
        """Start a new mission. While one runs: CommandRefused, or with ``replace`` brake it to rest
        within the limits (never a jump in speed) and start ``plan`` from there."""
        if self.mode == TELEOP:
            raise CommandRefused("the robot is teleoperated: it takes no missions")
        if self.mission_active:
            if not replace:
                raise CommandRefused(f"a mission is running ({self.trajectory.state}, waypoint "
                                     f"{self.trajectory.waypoint_index + 1} of {len(self.trajectory.plan.waypoints)}): "
                                     "abort it first or replace it")
            self.trajectory.abort("replaced by a new mission")
            self._queued = [plan]
            return
        self._start(plan)

    def extend(self, plan: PathPlan) -> None:
        """Drive ``plan`` once the current plan has ended (at once when none runs)."""
        if self.mode == TELEOP:
            raise CommandRefused("the robot is teleoperated: it takes no missions")
        if self.mission_active:
            self._queued.append(plan)
        else:
            self._start(plan)

    def abort(self, reason: str = "aborted by operator") -> bool:
        """Brake within the limits and end the mission; False when there was none."""
        self._queued.clear()
        if self.trajectory is None or self.trajectory.finished:
            return False
        self.trajectory.abort(reason)
        return True

    def pause(self) -> None:
        """Brake to rest within the limits and hold, from the next tick on, also plans started while
        paused (applied after the tick's step: a trajectory has its first segment only then)."""
        self._paused = True

    def resume(self) -> None:
        self._paused = False
        self.health.acknowledge()  # with resume_after_fault: command, a fault hold waits for this
        if self.trajectory is not None:
            self.trajectory.resume()

    @property
    def speed_limit(self) -> float:
        return self._speed_limit

    def set_speed_limit(self, speed: Optional[float]) -> float:
        """Lower the cruise speed limit at run time (None: back to control.max_speed); the new limit."""
        cap = self.robot.control.max_speed
        if speed is None:
            self._speed_limit = cap
            return cap
        v = float(speed)
        if not (math.isfinite(v) and v > 0.0):
            raise CommandRefused(f"a speed limit must be a finite number above 0 m/s, got {v}")
        if v > cap:
            raise CommandRefused(f"a speed limit of {v:g} m/s is above the configured control.max_speed ({cap:g} m/s)")
        self._speed_limit = v
        return v

    def _start(self, plan: PathPlan) -> None:
        self.follow(plan)

    def _limit_scale(self) -> float:
        """The speed scale that keeps the cruise speed at or below the run-time limit (it goes through
        the trajectory's limiters like any slow-down, so lowering it never jerks the robot)."""
        cap = self.robot.control.max_speed
        if self._speed_limit >= cap:
            return 1.0
        cruise = cap
        if self.mode == PATH and self.trajectory is not None and self.trajectory.waypoint_index < len(self.trajectory.plan.waypoints):
            cruise = min(self.trajectory.plan.waypoints[self.trajectory.waypoint_index].speed, cap)
        return min(1.0, self._speed_limit / cruise)

    # -- the control tick -------------------------------------------------------------------

    @property
    def last_quality(self) -> Optional[QualityReport]:
        """The quality report of the last control tick (or status), None before the first."""
        return self._last_quality

    def evaluate_quality(self, t: float) -> QualityReport:
        _, P = self.pose(t) if self.filter.initialized else (None, np.full((3, 3), np.inf))
        return self._evaluate_quality(t, P)

    def _evaluate_quality(self, t: float, P: np.ndarray) -> QualityReport:
        self._last_quality = self.quality.evaluate(t, P, self._protection)
        return self._last_quality

    def speed_scale(self, t: float, quality: QualityReport) -> Tuple[float, str]:
        scale, reason = self.health.speed_scale(t)
        if scale > 0.0 and t - self._t_last_odom > self.health.config.max_command_age:
            return 0.0, f"no wheel odometry for {t - self._t_last_odom:.2f} s: pose is stale"
        if scale > 0.0 and self.vision and self.health.config.vision_required and quality.state == LOST:
            return 0.0, f"localization lost: {quality.reason}"
        if self.vision and self.health.config.vision_required and quality.protection_exceeded \
                and scale > self.health.config.slow_scale:
            # The pose cannot be vouched for to the alert limits: drive as slowly as when degraded.
            return self.health.config.slow_scale, f"localization degraded: {quality.reason}"
        return scale, ("" if scale >= 1.0 else reason)

    def control_step(self, t: float) -> ControlOutput:
        self.counters["ticks"] += 1
        if self.health.note_tick(t, 1.0 / self.robot.control.rate) is not None:
            self._restart_from_rest()  # a stall or a link change: the board has stopped the wheels
        if not self.filter.initialized:
            turn = self._recovery_motion(t) if self.vision else None
            return turn if turn is not None else self._silent(t, "no pose yet")
        # One pose for the quality and the command: the filter's memo gave the same twice.
        (x, y, phi), P = self.pose(t)
        quality = self._evaluate_quality(t, P)
        scale, reason = self.speed_scale(t, quality)
        if self.vision:  # without vision there is nothing to relocalize with (odometry-only runs)
            self.recovery.on_quality(t, quality.state)
        if self.vision and self.recovery.holding:  # brake within the limits and hold until confirmed
            scale, reason = 0.0, f"{self.recovery.state}: {self.recovery.reason}"
        scale, reason = self._fault_hold(t, P, scale, reason)
        if self._queued and self.trajectory is not None and self.trajectory.finished:
            self._start(self._queued.pop(0))
        if self.mode == PATH and self.trajectory is not None:
            # The protective stop's last limit also slows the plan, so that it decelerates
            # smoothly instead of being cut every tick.
            confirmed = not (self.vision and self.recovery.doubting)
            last_fix = self._last_fix if self.vision else None
            cmd = self.trajectory.step(t, (x, y, phi), min(scale, self._safety_scale) * self._limit_scale(), confirmed,
                                       last_fix)
            if self._paused:
                self.trajectory.pause()
        elif self.mode == TELEOP:
            target = self._teleop_target if t - self._teleop_t <= self.teleop_deadman else (0.0, 0.0, 0.0)
            vx, vy, wz = self._teleop.step(t, target, scale * self._limit_scale())
            cmd = Command(vx, vy, wz, t, TELEOP, 0)
        else:
            cmd = Command(0.0, 0.0, 0.0, t, IDLE, 0)
        turn = self._recovery_motion(t) if self.vision else None
        if turn is not None:  # the path or teleop is held (scale 0); the turn's or move's command replaces theirs
            return turn
        # (While the recovery holds, the scans come without a pose: the stop sees them as taken.)
        cmd, reason = self._protective_stop(t, cmd, (x, y, phi) if self.walls_explain_obstacles else None, reason)
        if not self.health.chassis_ok:
            return self._silent(t, self._chassis_reason or "chassis link down", cmd)
        if not self.health.command_fresh(cmd.t_issued, t):
            return self._silent(t, f"command from {cmd.t_issued:.3f} s is stale at {t:.3f} s", cmd)
        wheels = self._wheels(cmd.vx, cmd.vy, cmd.wz)
        if wheels is None:
            return self._silent(t, "non-finite wheel command refused", cmd)
        return ControlOutput(t, cmd, wheels, scale, reason)

    def _wheels(self, vx: float, vy: float, wz: float) -> Optional[Tuple[float, float, float, float]]:
        """The wheel speeds of a twist scaled into the limit (``limit_floats``, what
        ``MecanumKinematics.limit`` computes), or None when they are not finite."""
        w = self.kinematics.inverse(vx, vy, wz).tolist()
        isfinite = math.isfinite
        if not (isfinite(w[0]) and isfinite(w[1]) and isfinite(w[2]) and isfinite(w[3])):
            return None
        return limit_floats(w, self.robot.chassis.max_wheel_speed)[0]  # type: ignore[return-value]

    def _turn_blocker(self, t: float, since: float) -> str:
        """Why the recovery's turn or move that began at ``since`` may not go on now ("" when it may).

        A fault noted before it began does not stop it: the fault stopped the motion it happened
        in, and the health hold that follows waits for a confirmed pose, which only the
        relocalization this motion serves can give. The motion starts from rest and needs the
        link and fresh odometry like any other."""
        if self.health.holding and self.health.t_fault >= since:
            return f"fault: {self.health.fault}"
        if not self.health.chassis_ok:
            return self._chassis_reason or "chassis link down"
        if t - self._t_odom_seen > self.health.config.max_command_age:
            return f"no wheel odometry for {t - self._t_odom_seen:.2f} s"
        if self.mode == TELEOP:
            return "the robot is teleoperated: it does not move by itself"
        return ""

    def _stop_if_blocked(self, t: float, since: float, stop, *limiters: AxisLimiter) -> None:
        """End the recovery's turn or move (``stop``) when it may not go on (``_turn_blocker``);
        where the board has stopped the wheels itself there is nothing to brake: the limiters
        start from rest."""
        why = self._turn_blocker(t, since)
        if why:
            stop(t, why)
            if self.health.holding or not self.health.chassis_ok:
                for lim in limiters:
                    lim.reset()

    def _recovery_motion(self, t: float) -> Optional[ControlOutput]:
        """The relocalization's in-place turn or move (at most one of them runs)."""
        move = self._recovery_move(t)
        return move if move is not None else self._recovery_turn(t)

    def _recovery_move(self, t: float) -> Optional[ControlOutput]:
        """The relocalization's move while the supervisor asks for it, and its braking to still
        after it; None when neither.

        ``recovery.move_goal`` (dx, dy, dphi) from where the move started, by wheel odometry: first
        a turn on the spot to face the way (dphi), then straight ahead, so that the front camera
        and the protective stop see where the robot goes; within the robot's limits, at
        ``recovery.move_speed``. Anything that limits or stops it (something in the way, no fresh
        depth, a fault, the link, stale odometry, teleop) ends the move for good: the supervisor
        keeps the last verdict."""
        rec = self.recovery
        lim, yaw_lim = self._move_lim, self._move_yaw_lim
        if not rec.moving and lim.v == 0.0 and lim.a == 0.0 and yaw_lim.v == 0.0 and yaw_lim.a == 0.0:
            self._move_t, self._move_start, self._move_facing = None, None, False
            return None
        c = self.robot.control
        dt = 1.0 / c.rate if self._move_t is None else min(max(t - self._move_t, 0.0), c.max_dt)
        self._move_t = t
        if rec.moving and (self._move_start is None or self._move_serial != rec.move_serial):
            # A new move: from where the robot stands now (the one before may have ended, been
            # relocalized and replanned before a tick saw the robot still and forgot it).
            self._move_start, self._move_yaw0, self._move_facing = self._turn_rel, self._turn_yaw, False
            self._move_serial, self._move_dir, self._move_t0 = rec.move_serial, (1.0, 0.0), t
        if rec.moving:
            self._stop_if_blocked(t, self._move_t0, rec.move_stopped, lim, yaw_lim)
        wz_target, v_target, dist = 0.0, 0.0, math.inf
        if rec.moving and self._move_start is not None:
            gx, gy, gphi = rec.move_goal
            if not self._move_facing:
                yaw_left = self._move_yaw0 + gphi - self._turn_yaw
                if abs(yaw_left) <= TURN_DONE_TOL:
                    self._move_facing = True
                else:
                    wz_target = approach_speed(yaw_left, yaw_lim.max_speed, 0.5 * c.max_yaw_accel, TURN_KP)
            if self._move_facing:
                goal = compose_se2(self._move_start, (gx, gy, gphi))
                rx, ry, _ = compose_se2(invert_se2(self._turn_rel), goal)
                dist = math.hypot(rx, ry)
                if dist > 1e-9:
                    self._move_dir = (rx / dist, ry / dist)
                if yaw_lim.v == 0.0 and yaw_lim.a == 0.0:  # the turn has braked: straight ahead now
                    v_target = approach_speed(dist, lim.max_speed, 0.5 * c.max_accel, MOVE_KP)
        wz = yaw_lim.step(wz_target, dt)
        v = lim.step(v_target, dt)
        ux, uy = self._move_dir
        cmd = Command(v * ux, v * uy, wz, t, MOVE, 0)
        # Every depth point is an obstacle here: the pose is missing or in doubt (walls_explain_obstacles).
        limited, reason = self._protective_stop(t, cmd, None, "")
        if limited.vx != cmd.vx or limited.vy != cmd.vy or limited.wz != cmd.wz:
            if rec.moving:
                rec.move_stopped(t, reason or "the protective stop")
            lim.reset()  # the stop cut the motion at once: the limiters start from rest again
            yaw_lim.reset()
            cmd = limited
        elif rec.moving and self._move_facing and dist <= MOVE_DONE_TOL:
            rec.move_done(t)  # brakes from here (the target drops to zero); relocalizes once still
        reason = f"{rec.state}: {rec.reason}" + (f"; {reason}" if reason else "")
        if not self.health.chassis_ok:
            return self._silent(t, self._chassis_reason or "chassis link down", cmd)
        wheels = self._wheels(cmd.vx, cmd.vy, cmd.wz)
        if wheels is None:
            return self._silent(t, "non-finite wheel command refused", cmd)
        return ControlOutput(t, cmd, wheels, 0.0, reason)

    def _recovery_turn(self, t: float) -> Optional[ControlOutput]:
        """The relocalization's in-place turn while the supervisor asks for it, and its braking to
        still after it; None when neither (the normal command stands).

        A pure rotation (vx = vy = 0) towards the next view's heading by wheel odometry, through the
        robot's yaw limits and the protective stop. Anything that stops it (an obstacle inside the
        turning circle, no fresh depth, a fault, the link, stale odometry) ends the turn for good:
        the supervisor keeps the last verdict."""
        rec = self.recovery
        lim = self._turn_lim
        if not rec.turning and lim.v == 0.0 and lim.a == 0.0:
            self._turn_t = None
            return None
        c = self.robot.control
        if self._turn_t is None:
            self._turn_t0 = t
        dt = 1.0 / c.rate if self._turn_t is None else min(max(t - self._turn_t, 0.0), c.max_dt)
        self._turn_t = t
        if rec.turning:
            self._stop_if_blocked(t, self._turn_t0, rec.turn_stopped, lim)
        remaining = rec.turn_goal - self._turn_yaw
        if rec.turning:
            target = approach_speed(remaining, lim.max_speed, 0.5 * c.max_yaw_accel, TURN_KP)
        else:
            target = 0.0
        wz = lim.step(target, dt)
        cmd = Command(0.0, 0.0, wz, t, TURN, 0)
        # Every depth point is an obstacle here: the pose is missing or in doubt (walls_explain_obstacles).
        limited, reason = self._protective_stop(t, cmd, None, "")
        if limited.wz != wz or limited.vx != 0.0 or limited.vy != 0.0:
            if rec.turning:
                rec.turn_stopped(t, reason or "the protective stop")
            lim.reset()  # the stop cut the rotation at once: the limiter starts from rest again
            cmd = replace(limited, vx=0.0, vy=0.0)
        elif rec.turning and abs(remaining) <= TURN_DONE_TOL:
            rec.turn_done(t)  # brakes from here (the target drops to zero); relocalizes once still
        reason = f"{rec.state}: {rec.reason}" + (f"; {reason}" if reason else "")
        if not self.health.chassis_ok:
            return self._silent(t, self._chassis_reason or "chassis link down", cmd)
        wheels = self._wheels(0.0, 0.0, cmd.wz)
        if wheels is None:
            return self._silent(t, "non-finite wheel command refused", cmd)
        return ControlOutput(t, cmd, wheels, 0.0, reason)

    def _protective_stop(self, t: float, cmd: Command, pose, reason: str) -> Tuple[Command, str]:
        """The command limited by the obstacle picture (stop, slow-down and blind zones)."""
        d = self.safety.limit(t, (cmd.vx, cmd.vy, cmd.wz), pose)
        self.last_safety = d
        max_speed = self.robot.control.max_speed
        self._safety_scale = 1.0 if d.speed_limit == float("inf") else min(1.0, d.speed_limit / max_speed)
        if d.zone in (CLEAR, DISABLED):
            return cmd, reason
        why = f"protective {d.zone}: {d.reason}"
        reason = f"{reason}; {why}" if reason else why
        if d.twist == (cmd.vx, cmd.vy, cmd.wz):  # already within what the zone allows (slowed last tick)
            return cmd, reason
        self.counters["safety_limited"] = self.counters.get("safety_limited", 0) + 1
        self.counters[f"safety_{d.zone}"] = self.counters.get(f"safety_{d.zone}", 0) + 1
        return replace(cmd, vx=d.twist[0], vy=d.twist[1], wz=d.twist[2]), reason

    def _silent(self, t: float, reason: str, cmd: Optional[Command] = None) -> ControlOutput:
        self.counters["ticks_silent"] += 1
        return ControlOutput(t, cmd or Command(0.0, 0.0, 0.0, t, self.mode, 0, reason), None, 0.0, reason)

    # -- reporting --------------------------------------------------------------------------

    def status(self, t: float) -> Dict[str, object]:
        """A JSON-able summary for STATUS= lines, the teleop display and the recorder."""
        out: Dict[str, object] = {"t": t, "mode": self.mode}
        if self.filter.initialized:
            (x, y, phi), P = self.pose(t)
            q = self._last_quality or self.evaluate_quality(t)
            out.update({"x": x, "y": y, "phi": phi, "cov": np.asarray(P).tolist(), "quality": q.state,
                        "reason": q.reason, "pos_std": q.pos_std})
        else:
            out.update({"quality": LOST, "reason": "no pose yet"})
        if self.trajectory is not None:
            out.update({"path_state": self.trajectory.state, "waypoint": self.trajectory.waypoint_index,
                        "waypoints": len(self.trajectory.plan.waypoints)})
        out["localized"] = out.get("quality") == LOCALIZED
        out["recovery"] = self.recovery.to_json()
        if self.calibration is not None:
            out["calibration"] = self.calibration.status()
        out["fault"] = self.health.fault
        if self.last_safety is not None:
            s = self.last_safety
            out["safety"] = {"zone": s.zone, "reason": s.reason,
                             "free_distance": None if s.free_distance == float("inf") else s.free_distance,
                             "speed_limit": None if s.speed_limit == float("inf") else s.speed_limit}
        return out
