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
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.samples import WheelOdometry
from robot.config import RobotConfig
from robot.control.health import HealthSupervisor
from robot.control.kinematics import MecanumKinematics
from robot.control.path_file import PathPlan
from robot.control.trajectory import AxisLimiter, Command, TrajectoryController
from robot.fusion.ekf import PoseFilter
from robot.fusion.quality import LOCALIZED, LOST, QualityMonitor, QualityReport
from robot.localization.localizer import LocalizationResult

IDLE = "idle"
PATH = "path"
TELEOP = "teleop"


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

    def step(self, t: float, target: Sequence[float], scale: float) -> Tuple[float, float, float]:
        dt = 0.02 if self._t is None else min(max(t - self._t, 0.0), self._max_dt)
        self._t = t
        return tuple(lim.step(float(v) * scale, dt) for lim, v in zip(self._lim, target))  # type: ignore[return-value]


class ControllerCore:
    """Fusion + quality + health + path/teleop control of one robot. Single-threaded: the shell
    calls it from one thread (the event loop), never concurrently."""

    def __init__(self, robot: RobotConfig, *, vision: bool = True, t_start: float = 0.0,
                 wheel_speed_noise: float = 0.05):
        self.robot = robot
        self.vision = vision
        self.kinematics = MecanumKinematics.from_config(robot.chassis)
        self.filter = PoseFilter(robot.fusion)
        self.quality = QualityMonitor(robot.quality)
        health_cfg = robot.health if vision else replace(robot.health, vision_required=False)
        self.health = HealthSupervisor(health_cfg, t_start)
        self.wheel_speed_noise = float(wheel_speed_noise)  # rad/s std beyond quantisation (motor ripple)
        self.mode = IDLE
        self.trajectory: Optional[TrajectoryController] = None
        self._teleop = TwistLimiter(robot)
        self._teleop_target = (0.0, 0.0, 0.0)
        self._teleop_t = -math.inf
        self.teleop_deadman = 0.5  # s: an operator twist older than this is zero
        self._t_last_odom = -math.inf
        self._chassis_reason = "chassis link not up yet"
        self._last_quality: Optional[QualityReport] = None
        self.counters: Dict[str, int] = {"odometry": 0, "odometry_rejected": 0, "localizations": 0,
                                         "planes_accepted": 0, "planes_rejected": 0, "ticks": 0,
                                         "ticks_silent": 0}

    # -- pose -------------------------------------------------------------------------------

    def set_pose(self, t: float, x: float, y: float, phi: float, cov: np.ndarray) -> None:
        self.filter.set_pose(t, x, y, phi, cov)
        self.quality.note_fix(t)
        self.health.localization_succeeded(t)
        self._t_last_odom = t

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
        if not self.filter.initialized:
            return False
        var = self.wheel_speed_noise ** 2 + quantisation_variance
        twist = self.kinematics.forward(odo.speeds)
        Q = self.kinematics.forward_covariance(var)
        res = self.filter.predict_twist(odo.t, float(twist[0]), float(twist[1]), float(twist[2]), Q)
        if res.accepted:
            self.counters["odometry"] += 1
            self._t_last_odom = odo.t
        else:
            self.counters["odometry_rejected"] += 1
        return res.accepted

    def on_gyro(self, t: float, wz_robot: float, variance: float) -> bool:
        if not self.filter.initialized:
            return False
        return self.filter.predict_gyro(t, wz_robot, variance).accepted

    def on_localization(self, result: LocalizationResult, t_capture: float, camera: str = "") -> FusionReport:
        """Fuse the planes of one localization (frames captured at ``t_capture``)."""
        report = FusionReport(t_capture, camera, fits=len(result.measurements))
        self.counters["localizations"] += 1
        if not self.vision or not self.filter.initialized or not result.measurements:
            return report
        outcomes = self.filter.update_planes(result.measurements)
        for meas, res in zip(result.measurements, outcomes):
            self.quality.note_update(meas.t_capture, res.accepted)
            if res.accepted:
                report.accepted.append(meas.plane_id)
            else:
                report.rejected.append((meas.plane_id, res.reason))
        self.counters["planes_accepted"] += len(report.accepted)
        self.counters["planes_rejected"] += len(report.rejected)
        if report.accepted:
            self.health.localization_succeeded(t_capture)
        return report

    def set_chassis_link(self, ok: bool, reason: str = "") -> None:
        self.health.chassis_ok = bool(ok)
        self._chassis_reason = reason or ("" if ok else "chassis link down")

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
        return self.mode == PATH and self.trajectory is not None and self.trajectory.finished

    # -- the control tick -------------------------------------------------------------------

    def evaluate_quality(self, t: float) -> QualityReport:
        _, P = self.pose(t) if self.filter.initialized else (None, np.full((3, 3), np.inf))
        self._last_quality = self.quality.evaluate(t, P)
        return self._last_quality

    def speed_scale(self, t: float, quality: QualityReport) -> Tuple[float, str]:
        scale, reason = self.health.speed_scale(t)
        if scale > 0.0 and t - self._t_last_odom > self.health.config.max_command_age:
            return 0.0, f"no wheel odometry for {t - self._t_last_odom:.2f} s: pose is stale"
        if scale > 0.0 and self.vision and self.health.config.vision_required and quality.state == LOST:
            return 0.0, f"localization lost: {quality.reason}"
        return scale, ("" if scale >= 1.0 else reason)

    def control_step(self, t: float) -> ControlOutput:
        self.counters["ticks"] += 1
        if not self.filter.initialized:
            return self._silent(t, "no pose yet")
        quality = self.evaluate_quality(t)
        scale, reason = self.speed_scale(t, quality)
        (x, y, phi), _ = self.pose(t)
        if self.mode == PATH and self.trajectory is not None:
            cmd = self.trajectory.step(t, (x, y, phi), scale)
        elif self.mode == TELEOP:
            target = self._teleop_target if t - self._teleop_t <= self.teleop_deadman else (0.0, 0.0, 0.0)
            vx, vy, wz = self._teleop.step(t, target, scale)
            cmd = Command(vx, vy, wz, t, TELEOP, 0)
        else:
            cmd = Command(0.0, 0.0, 0.0, t, IDLE, 0)
        if not self.health.chassis_ok:
            return self._silent(t, self._chassis_reason or "chassis link down", cmd)
        if not self.health.command_fresh(cmd.t_issued, t):
            return self._silent(t, f"command from {cmd.t_issued:.3f} s is stale at {t:.3f} s", cmd)
        wheels, _ = self.kinematics.limit(self.kinematics.inverse(cmd.vx, cmd.vy, cmd.wz),
                                          self.robot.chassis.max_wheel_speed)
        if not np.isfinite(wheels).all():
            return self._silent(t, "non-finite wheel command refused", cmd)
        return ControlOutput(t, cmd, tuple(float(w) for w in wheels), scale, reason)  # type: ignore[arg-type]

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
        return out
