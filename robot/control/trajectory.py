"""Trajectory controller: drive a holonomic (Mecanum) base through a path file's waypoints.

Model and conventions:

- Input each control tick (``ControlConfig.rate``, 50 Hz): the fused pose (x, y, phi) in G and
  a ``speed_scale`` in [0, 1] from the health supervisor. Output: a body twist (vx, vy, wz) in
  the ROBOT frame (x forward, y left, wz counter-clockwise), SI units.
- Law, per waypoint (stop-and-go, every waypoint is approached to rest): the segment runs from
  the previous waypoint (the pose at start for the first) to the target. Along the segment the
  speed follows a feedforward profile ``min(cruise, sqrt(2 a_b d), k_p d)`` (cruise speed,
  braking distance, then a proportional finish), across it a proportional pull back onto the
  line. Heading: the waypoint's heading, or the last one commanded, with the same profile on
  the wrapped heading error. The G-frame velocity is rotated into R.
- Limits: the target twist goes through a rate-limiter chain per axis (vx, vy, wz), like
  ros2_controllers' SpeedLimiter and Nav2's velocity_smoother: speed, acceleration and jerk
  are bounded, and the acceleration is ramped down ahead of time (discrete braking profile) so
  the speed never overshoots its target. A jump of the pose estimate only changes the target,
  so it can never become a velocity spike; ``speed_scale`` scales the target, so slowing down
  also respects the limits. The translation target's norm is at most ``max_speed``.
- Arrival: within the waypoint's position tolerance and (if it has a heading) its heading
  tolerance and, if ``require_settled``, with the command below the settle speeds. Then the
  robot dwells (holding the target) for the waypoint's ``dwell`` and moves on.
- States: ``following``, ``arrived`` (dwelling), ``paused``, ``done``, ``aborted``, ``error``.
  ``pause()`` brakes to zero within the limits and holds; ``resume()`` continues (also clears
  ``error``); ``abort()`` brakes within the limits and ends. A non-finite pose gives a zero
  command at once and latches ``error`` until ``resume()``: no command is ever NaN.
- After a fault (a host stall, a lost link: the board's watchdog has stopped the wheels) the
  core calls ``reset_motion()``, so the limiters start again from rest and never send the speed
  they had before, and ``hold()`` until the pose is confirmed (shown as ``paused``), then
  ``release()``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

from robot.base.geometry import wrap_angle
from robot.config import ControlConfig
from robot.control.path_file import PathPlan, Waypoint

FOLLOWING = "following"
ARRIVED = "arrived"
PAUSED = "paused"
DONE = "done"
ABORTED = "aborted"
ERROR = "error"




@dataclass(frozen=True)
class Command:
    vx: float  # m/s, robot frame
    vy: float
    wz: float  # rad/s
    t_issued: float  # host monotonic time of the tick that produced it
    state: str
    waypoint: int  # index of the current target (len(waypoints) when done)
    reason: str = ""


class AxisLimiter:
    """Speed, acceleration and jerk limits on one axis, with no overshoot of a steady target.

    Each tick picks the largest acceleration from which the jerk-limited braking staircase
    (a - J dt, a - 2 J dt, ... down to 0) still ends on the target, then moves the acceleration
    towards it by at most ``max_jerk * dt``. The speed therefore settles exactly on the target,
    and a target that drops (a slow-down, a pose jump) is met as fast as the limits allow. The
    staircase takes the next ticks to be as long as this one; when they are shorter (real-time
    ticks jitter), a step that would pass a steady target lands on it instead.
    """

    def __init__(self, max_speed: float, max_accel: float, max_jerk: float):
        self.max_speed, self.max_accel, self.max_jerk = max_speed, max_accel, max_jerk
        self.v = 0.0
        self.a = 0.0
        self._target = math.nan  # the last tick's target (a steady one is never passed)

    def reset(self) -> None:
        self.v = self.a = 0.0
        self._target = math.nan

    def step(self, target: float, dt: float) -> float:
        h = self.max_jerk * dt  # largest change of acceleration in one tick
        target = min(max(target, -self.max_speed), self.max_speed)
        e = target - self.v
        if abs(e) <= 1e-12 and abs(self.a) <= h:
            self.v, self.a = target, 0.0  # landed: stop the rounding-level limit cycle
            return self.v
        E = abs(e)
        # Accelerating at a then braking by h per tick covers dt^2 J n(n+1)/2 + (n+1) dt r with
        # a = n h + r: take the largest n that fits and solve for a.
        n = math.floor((-1.0 + math.sqrt(1.0 + 8.0 * E / (h * dt))) / 2.0)
        reachable = (E / dt + h * n * (n + 1) / 2.0) / (n + 1)
        a_wanted = math.copysign(min(self.max_accel, reachable), e)
        self.a += min(max(a_wanted - self.a, -h), h)
        # The clamp only ever trims rounding: the staircase already keeps |v| <= max_speed.
        v = min(max(self.v + self.a * dt, -self.max_speed), self.max_speed)
        steady = target == self._target
        self._target = target
        if steady and (target - v) * e <= 0.0:
            # The staircase assumes the next ticks as long as this one; a shorter one (real-time
            # ticks jitter by milliseconds) carries the speed past the target, which for a robot
            # braking to a hold means reversing. Land on it instead: a smaller step than the
            # acceleration limit allows, at the end of the staircase where the acceleration left
            # is a few jerk steps. (A target that moves may be crossed: that is tracking it.)
            v, self.a = target, 0.0
        self.v = v
        return self.v


def _clip_norm(x: float, y: float, limit: float) -> Tuple[float, float]:
    n = math.hypot(x, y)
    if n <= limit or n == 0.0:
        return x, y
    return x * limit / n, y * limit / n


def approach_speed(error: float, cruise: float, brake_accel: float, kp: float) -> float:
    """Signed speed towards zero error: cruise, then braking distance, then proportional."""
    d = abs(error)
    return math.copysign(min(cruise, math.sqrt(2.0 * brake_accel * d), kp * d), error)


class TrajectoryController:
    """Follows a :class:`PathPlan`; call :meth:`step` once per control tick."""

    def __init__(self, plan: PathPlan, config: Optional[ControlConfig] = None):
        if not plan.waypoints:
            raise ValueError("a path needs at least one waypoint")
        self.plan = plan
        self.config = cfg = config or ControlConfig()
        self._lim = (AxisLimiter(cfg.max_speed, cfg.max_accel, cfg.max_jerk),
                     AxisLimiter(cfg.max_speed, cfg.max_accel, cfg.max_jerk),
                     AxisLimiter(cfg.max_yaw_rate, cfg.max_yaw_accel, cfg.max_yaw_jerk))
        self._index = 0
        self._state = FOLLOWING
        self._paused = False
        self._held: Optional[str] = None  # why the core holds the robot after a fault
        self._arrived_t = -math.inf  # when the current waypoint was reached
        self._reason = ""
        self._t_last: Optional[float] = None
        self._seg_start: Optional[Tuple[float, float]] = None
        self._heading_goal: Optional[float] = None
        self._dwell_left = 0.0
        self._last: Optional[Command] = None

    # -- operator actions ---------------------------------------------------------------------

    def pause(self) -> None:
        if self._state in (FOLLOWING, ARRIVED):
            self._paused = True

    def resume(self) -> None:
        self._paused = False
        if self._state == ERROR:
            self._state = FOLLOWING if self._index < len(self.plan.waypoints) else DONE
            self._reason = ""

    def abort(self, reason: str = "aborted by operator") -> None:
        if self._state not in (DONE, ABORTED):
            self._state = ABORTED
            self._reason = reason

    def hold(self, reason: str) -> None:
        """Stand still (a zero target) until ``release``, apart from the operator's pause."""
        self._held = reason

    def release(self) -> None:
        self._held = None

    def reset_motion(self) -> None:
        """The wheels were stopped behind the controller's back: start the limiters from rest."""
        for lim in self._lim:
            lim.reset()
        self._t_last = None
        self._last = None

    @property
    def state(self) -> str:
        stopped = self._paused or self._held is not None
        return PAUSED if stopped and self._state in (FOLLOWING, ARRIVED) else self._state

    @property
    def waypoint_index(self) -> int:
        return self._index

    @property
    def finished(self) -> bool:
        """Done or aborted, and the command has come to rest."""
        return self._state in (DONE, ABORTED) and all(lim.v == 0.0 and lim.a == 0.0 for lim in self._lim)

    # -- the control tick -----------------------------------------------------------------------

    def step(self, t: float, pose: Sequence[float], speed_scale: float = 1.0, confirmed: bool = True,
             last_fix: Optional[float] = None) -> Command:
        """One tick. ``confirmed`` False (the views currently disagree with the pose): a waypoint
        may be approached and held, but its dwell does not count. ``last_fix``: capture time of
        the newest accepted camera fix (None without vision): a dwell only ends after a fix taken
        since the arrival, so a waypoint is never declared reached on a pose no view confirmed."""
        cfg = self.config
        if self._t_last is not None and not t > self._t_last and self._last is not None:
            return self._last  # same tick again: nothing new to integrate
        dt = 1.0 / cfg.rate if self._t_last is None else min(t - self._t_last, cfg.max_dt)
        self._t_last = t
        try:
            x, y, phi = (float(v) for v in pose)
        except (TypeError, ValueError):
            x = y = phi = math.nan
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(phi)):
            for lim in self._lim:
                lim.reset()
            self._state, self._reason = ERROR, "pose is not finite: stopped"
            return self._emit(Command(0.0, 0.0, 0.0, t, ERROR, self._index, self._reason))
        if self._state == ERROR:
            return self._emit(Command(0.0, 0.0, 0.0, t, ERROR, self._index, self._reason))
        scale = speed_scale if math.isfinite(speed_scale) else 0.0
        scale = min(max(scale, 0.0), 1.0)

        target = (0.0, 0.0, 0.0)
        stopped = self._paused or self._held is not None
        if self._state in (FOLLOWING, ARRIVED) and not stopped:
            self._advance(t, dt, x, y, phi, confirmed, last_fix)
        if self._state in (FOLLOWING, ARRIVED) and not stopped:
            target = self._target_twist(x, y, phi, scale)
        vx = self._lim[0].step(target[0], dt)
        vy = self._lim[1].step(target[1], dt)
        wz = self._lim[2].step(target[2], dt)
        reason = f"held: {self._held}" if self._held is not None else self._reason
        return self._emit(Command(vx, vy, wz, t, self.state, self._index, reason))

    def _emit(self, cmd: Command) -> Command:
        self._last = cmd
        return cmd

    def _waypoint(self) -> Waypoint:
        return self.plan.waypoints[self._index]

    def _activate(self, x: float, y: float, phi: float) -> None:
        if self._index == 0 or self._seg_start is None:
            self._seg_start = (x, y)
        else:
            prev = self.plan.waypoints[self._index - 1]
            self._seg_start = (prev.x, prev.y)
        if self._heading_goal is None:
            self._heading_goal = phi
        wp = self._waypoint()
        if wp.heading is not None:
            self._heading_goal = wp.heading

    def _advance(self, t: float, dt: float, x: float, y: float, phi: float, confirmed: bool = True,
                 last_fix: Optional[float] = None) -> None:
        """Waypoint bookkeeping: arrival, dwell, next waypoint, done."""
        if self._seg_start is None:
            self._activate(x, y, phi)
        wp = self._waypoint()
        if self._state == FOLLOWING and self._arrived(wp, x, y, phi):
            self._state = ARRIVED
            self._dwell_left = wp.dwell
            self._arrived_t = t
        if self._state == ARRIVED:
            if not confirmed:
                self._dwell_left = wp.dwell  # the dwell starts again once the pose is confirmed
                return
            self._dwell_left -= dt
            if self._dwell_left <= 0.0 and last_fix is not None and last_fix < self._arrived_t:
                return  # dwell over, but no view has confirmed the arrival yet: keep holding
            if self._dwell_left <= 0.0:
                self._index += 1
                if self._index >= len(self.plan.waypoints):
                    self._state = DONE
                    self._reason = "path complete"
                else:
                    self._state = FOLLOWING
                    self._activate(x, y, phi)

    def _arrived(self, wp: Waypoint, x: float, y: float, phi: float) -> bool:
        cfg = self.config
        if math.hypot(wp.x - x, wp.y - y) > wp.tolerance:
            return False
        if wp.heading is not None and abs(wrap_angle(wp.heading - phi)) > wp.heading_tolerance:
            return False
        if cfg.require_settled:
            lx, ly, lw = self._lim
            if math.hypot(lx.v, ly.v) > cfg.settle_speed or abs(lw.v) > cfg.settle_yaw_rate:
                return False
        return True

    def _target_twist(self, x: float, y: float, phi: float, scale: float) -> Tuple[float, float, float]:
        cfg = self.config
        wp = self._waypoint()
        cruise = min(wp.speed, cfg.max_speed) * scale
        brake = cfg.brake_fraction * cfg.max_accel
        ex, ey = wp.x - x, wp.y - y
        sx, sy = self._seg_start
        lx, ly = wp.x - sx, wp.y - sy
        length = math.hypot(lx, ly)
        if length > 1e-6:
            tx, ty = lx / length, ly / length
            along = ex * tx + ey * ty
            cx, cy = ex - along * tx, ey - along * ty  # from the robot to the line
            v_along = approach_speed(along, cruise, brake, cfg.kp_position)
            vcx, vcy = _clip_norm(cfg.kp_cross_track * cx, cfg.kp_cross_track * cy, cruise)
            gx, gy = v_along * tx + vcx, v_along * ty + vcy
        else:
            d = math.hypot(ex, ey)
            speed = abs(approach_speed(d, cruise, brake, cfg.kp_position))
            gx, gy = (ex / d * speed, ey / d * speed) if d > 0.0 else (0.0, 0.0)
        gx, gy = _clip_norm(gx, gy, cruise)
        c, s = math.cos(phi), math.sin(phi)
        vx, vy = c * gx + s * gy, -s * gx + c * gy  # G -> R
        e_phi = wrap_angle(self._heading_goal - phi)
        wz = approach_speed(e_phi, cfg.max_yaw_rate * scale, cfg.brake_fraction * cfg.max_yaw_accel, cfg.kp_heading)
        return vx, vy, wz
