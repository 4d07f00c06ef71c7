"""Pose fusion (see docs/architecture.md, 'EKF'): an EKF on (x, y, phi) in G, built on filterpy.

Model and conventions:

- State ``(x, y, phi)``: the robot frame R in the ground frame G, phi wrapped to [-pi, pi).
- Prediction from wheel odometry. An odometry input at time t is the body twist
  (vx, vy, wz) in R averaged over the interval since the previous input (or since the pose
  was set), with the 3x3 covariance of that mean twist. ``predict_increment`` takes the same
  thing as a body displacement (the wheel-angle differences through the forward kinematics),
  which stays exact across a gap in the samples. The twist is integrated as a constant twist
  (an exact arc, not an Euler step). The process noise is the twist covariance mapped through
  the motion Jacobian plus a floor (a white-noise density per second and slip variances per
  metre travelled and per radian turned) so the filter never becomes overconfident while
  standing still or slipping.
- Optional gyro (``predict_gyro``): samples of the yaw rate in R; an odometry interval that
  contains gyro samples takes their mean rate, combined with the wheels' wz by inverse variance
  (``gyro_mode="combine"``) or in place of it (``"replace"``).
- Updates: each fitted plane is its own measurement ``z = [d_R, psi_R]`` with
  ``h = [n_G . t + d_G, wrap(atan2(n_G) - phi)]`` (``robot.localization.measurements.PlaneMeasurement``),
  behind a chi-square gate on the Mahalanobis distance (2 dof, 99.7 % by default).
  ``update_pose`` fuses an absolute pose (3 dof gate); ``set_pose`` resets, like
  robot_localization's ``set_pose`` service.
- Time: every input carries host monotonic time. A measurement is applied at its capture
  time: the filter keeps a bounded history (``history`` seconds) of its inputs and of the state
  after each one, rewinds to the capture time, applies the update and replays the later inputs
  (robot_localization's ``smooth_lagged_data``). The result depends only on the set of inputs,
  not on their arrival order: events are ordered by (time, kind, camera, plane id) and an
  odometry interval split by a measurement keeps the same total noise. Between the last
  odometry input and a later time the last twist is held for ``hold`` seconds, then the robot
  is assumed still; those states are provisional and are recomputed when odometry arrives.
  Their covariance grows by half the held displacement, since the robot may have stopped at
  once or kept going.
- Gaps: an odometry interval longer than ``max_odom_interval`` (a serial dropout, a host stall
  bridged by cumulative ticks) gives the exact total displacement, but not when it happened:
  the robot may have braked at the start and stood, or rolled on evenly. A fix inside such an
  interval splits it, and each piece's mean is still its share of the displacement, but each
  piece also gets the covariance of that unknown timing, ``(max(f, 1 - f) / 2)^2 g g^T`` plus a
  quarter of it on the diagonal (f the piece's share, g the interval's displacement in G): so the
  fix is gated against where the robot may really have been, and the estimate follows it. An
  interval no fix splits keeps its exact displacement and costs nothing extra.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from robot.base.geometry import arc_coefficients, wrap_angle
from robot.base.stats import chi2_quantile
from robot.config import FilterConfig
from robot.localization.measurements import PlaneMeasurement

Key = Tuple[float, int, str, str, int]

_KIND_ODOM = 0
_KIND_PLANE = 1
_KIND_POSE = 2
_KIND_BASE = -1




@dataclass(frozen=True)
class UpdateResult:
    accepted: bool
    mahalanobis2: float = 0.0  # squared Mahalanobis distance of the innovation (nan if not gated)
    reason: str = ""


# ---------------------------------------------------------------------------------------------
# Pure motion model


def body_increment(twist: np.ndarray, dt: float) -> Tuple[np.ndarray, np.ndarray]:
    """Displacement (dx, dy, dphi) in the start frame after a constant body twist for dt seconds.

    Returns the increment and its Jacobian with respect to the twist (3x3).
    """
    vx, vy, wz = float(twist[0]), float(twist[1]), float(twist[2])
    A, B, dA, dB = arc_coefficients(wz * dt)
    inc = np.array([dt * (A * vx - B * vy), dt * (B * vx + A * vy), wz * dt])
    D = np.array([
        [dt * A, -dt * B, dt * dt * (dA * vx - dB * vy)],
        [dt * B, dt * A, dt * dt * (dB * vx + dA * vy)],
        [0.0, 0.0, dt],
    ])
    return inc, D


class _PlanarEKF(ExtendedKalmanFilter):
    """filterpy's EKF with the exact planar motion: ``u`` is a body-frame increment."""

    def __init__(self):
        super().__init__(dim_x=3, dim_z=2)

    def predict_x(self, u=0):
        phi = float(self.x[2, 0])
        c, s = math.cos(phi), math.sin(phi)
        dx, dy, dphi = float(u[0]), float(u[1]), float(u[2])
        self.x = self.x + np.array([[c * dx - s * dy], [s * dx + c * dy], [dphi]])


def _wrapped_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z - h(x) for filterpy, with the angle row wrapped (the angle is the last row)."""
    r = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    r[-1, 0] = wrap_angle(float(r[-1, 0]))
    return r


# ---------------------------------------------------------------------------------------------
# History records


@dataclass
class _Odom:
    key: Key
    t: float
    twist: np.ndarray  # (3,) mean body twist over the interval ending at t
    Q: np.ndarray  # (3, 3) covariance of that mean twist


@dataclass
class _Fix:
    key: Key
    t: float
    plane: Optional[PlaneMeasurement] = None
    pose: Optional[np.ndarray] = None  # (3,) absolute pose
    pose_cov: Optional[np.ndarray] = None
    gate: bool = True


@dataclass
class _Checkpoint:
    key: Key
    t: float
    x: np.ndarray  # (3,)
    P: np.ndarray  # (3, 3)


def _after_odom(t: float) -> Key:
    """The smallest key after the odometry input at t (and before any fix at t)."""
    return (t, _KIND_ODOM, "", "", 1)


def _spread(phi: float, inc: np.ndarray, scale: float) -> np.ndarray:
    """Covariance of an unknown share (std ``scale``) of the body increment ``inc`` taken at heading
    phi: along the increment in G, plus a quarter of it per axis for a path that was not straight."""
    c, s = math.cos(phi), math.sin(phi)
    g = np.array([c * inc[0] - s * inc[1], s * inc[0] + c * inc[1], inc[2]])
    d2 = float(g[0] * g[0] + g[1] * g[1])
    return (scale * scale) * (np.outer(g, g) + 0.25 * np.diag([d2, d2, float(g[2] * g[2])]))


def _finite(*arrays) -> bool:
    return all(bool(np.isfinite(np.asarray(a, dtype=float)).all()) for a in arrays)


def _is_covariance(C: np.ndarray, n: int) -> bool:
    """Symmetric, finite and positive semi-definite (up to rounding)."""
    C = np.asarray(C, dtype=float)
    if C.shape != (n, n) or not np.isfinite(C).all():
        return False
    scale = max(1e-300, float(np.abs(C).max()))
    if float(np.abs(C - C.T).max()) > 1e-9 * scale:
        return False
    return bool(np.linalg.eigvalsh(C)[0] >= -1e-12 * scale)


class PoseFilter:
    """The fused pose of the robot in G, with lagged-measurement replay.

    Usage: ``set_pose`` once, then ``predict_twist``/``predict_increment`` for each odometry
    sample (strictly increasing time), ``predict_gyro`` for gyro samples, ``update_plane`` for
    each fitted plane (in any order, up to ``history`` seconds late). ``state()`` is the newest
    estimate; ``predicted(t)`` the estimate at time t (the coarse pose for a frame).
    """

    def __init__(self, config: Optional[FilterConfig] = None):
        self.config = config or FilterConfig()
        self._gate2 = chi2_quantile(self.config.gate_probability, 2)
        self._gate3 = chi2_quantile(self.config.gate_probability, 3)
        self._ekf = _PlanarEKF()
        self._base: Optional[_Checkpoint] = None
        self._odom: List[_Odom] = []
        self._odom_keys: List[Key] = []
        self._odom_t: List[float] = []
        self._odom_origin = 0.0  # start of the first kept odometry interval
        self._gyro_t: List[float] = []
        self._gyro: List[Tuple[float, float]] = []  # (wz, variance), parallel to _gyro_t
        self._fixes: List[_Fix] = []
        self._fix_keys: List[Key] = []
        self._results: Dict[Key, UpdateResult] = {}
        self._checkpoints: List[_Checkpoint] = []
        self._dirty: Optional[Key] = None
        self._seq = 0

    # -- public API -------------------------------------------------------------------------

    @property
    def gate_threshold(self) -> float:
        """Squared Mahalanobis distance above which a plane measurement is rejected."""
        return self._gate2

    @property
    def initialized(self) -> bool:
        return self._base is not None

    def set_pose(self, t: float, x: float, y: float, phi: float, cov: np.ndarray) -> None:
        """Reset to a known pose at time t, dropping the history (like robot_localization)."""
        cov = np.asarray(cov, dtype=float)
        if not _finite([t, x, y, phi]) or not _is_covariance(cov, 3):
            raise ValueError("set_pose needs a finite pose and a symmetric positive semi-definite 3x3 covariance")
        key: Key = (float(t), _KIND_BASE, "", "", 0)
        self._base = _Checkpoint(key, float(t), np.array([x, y, float(wrap_angle(phi))]), cov.copy())
        self._odom, self._odom_keys, self._odom_t = [], [], []
        self._odom_origin = float(t)
        self._gyro_t, self._gyro = [], []
        self._fixes, self._fix_keys = [], []
        self._results = {}
        self._checkpoints = []
        self._dirty = None

    def predict_twist(self, t: float, vx: float, vy: float, wz: float, Q_twist: np.ndarray) -> UpdateResult:
        """Odometry: the mean body twist over the interval ending at t, and its covariance."""
        twist = np.array([vx, vy, wz], dtype=float)
        Q = np.asarray(Q_twist, dtype=float)
        if not _finite([t]) or not _finite(twist) or not _is_covariance(Q, 3):
            return UpdateResult(False, math.nan, "odometry rejected: non-finite twist or bad covariance")
        if self._base is None:
            return UpdateResult(False, math.nan, "odometry ignored: the pose is not set")
        t = float(t)
        if t <= self._base.t:
            return UpdateResult(False, math.nan, f"odometry at {t:.3f} s is not after the filter's start {self._base.t:.3f} s")
        if self._odom and t <= self._odom[-1].t:
            return UpdateResult(False, math.nan,
                                f"odometry at {t:.3f} s is not after the previous sample {self._odom[-1].t:.3f} s")
        prev_end = self._odom[-1].t if self._odom else self._odom_origin
        key: Key = (t, _KIND_ODOM, "", "", 0)
        self._odom.append(_Odom(key, t, twist, 0.5 * (Q + Q.T)))
        self._odom_keys.append(key)
        self._odom_t.append(t)
        # Fixes after the previous sample were predicted with the held twist: redo them.
        self._mark_dirty(_after_odom(prev_end))
        self._ensure()
        return UpdateResult(True, 0.0, "")

    def predict_increment(self, t: float, dx: float, dy: float, dphi: float, Q_increment: np.ndarray) -> UpdateResult:
        """Odometry as a body displacement since the previous sample (twist integral, not an arc chord)."""
        if self._base is None:
            return UpdateResult(False, math.nan, "odometry ignored: the pose is not set")
        prev_end = self._odom[-1].t if self._odom else self._odom_origin
        dt = float(t) - prev_end if _finite([t]) else math.nan
        if not dt > 0.0:
            return UpdateResult(False, math.nan, f"odometry at {t} s is not after the previous sample {prev_end:.3f} s")
        Q = np.asarray(Q_increment, dtype=float) / (dt * dt)
        return self.predict_twist(t, dx / dt, dy / dt, dphi / dt, Q)

    def predict_gyro(self, t: float, wz: float, variance: float) -> UpdateResult:
        """A yaw-rate sample (rad/s about R's z axis) and its variance (include the bias)."""
        if not _finite([t, wz, variance]) or variance <= 0.0:
            return UpdateResult(False, math.nan, "gyro rejected: non-finite rate or variance <= 0")
        if self._base is None:
            return UpdateResult(False, math.nan, "gyro ignored: the pose is not set")
        t = float(t)
        if t <= self._base.t:
            return UpdateResult(False, math.nan, f"gyro sample at {t:.3f} s is older than the history")
        i = bisect.bisect_right(self._gyro_t, t)
        self._gyro_t.insert(i, t)
        self._gyro.insert(i, (float(wz), float(variance)))
        j = bisect.bisect_left(self._odom_t, t)
        if j < len(self._odom):  # the interval containing t is already in the history
            start = self._odom_t[j - 1] if j > 0 else self._odom_origin
            self._mark_dirty(_after_odom(start))
        return UpdateResult(True, 0.0, "")

    def update_plane(self, meas: PlaneMeasurement) -> UpdateResult:
        """Fuse one fitted plane at its capture time; returns whether the gate accepted it."""
        return self.update_planes([meas])[0]

    def update_planes(self, measurements: Sequence[PlaneMeasurement]) -> List[UpdateResult]:
        """Fuse the planes of one or more frames with a single replay (cheaper than one by one)."""
        pending: List[Tuple[int, Key, str]] = []
        results: List[Optional[UpdateResult]] = []
        for meas in measurements:
            rejection = self._check_plane(meas)
            if rejection is None:
                key: Key = (float(meas.t_capture), _KIND_PLANE, str(meas.camera), str(meas.plane_id), self._next_seq())
                what = f"plane {meas.plane_id}"
                rejection = self._insert_fix(_Fix(key, float(meas.t_capture), plane=meas), what)
                if rejection is None:
                    pending.append((len(results), key, what))
            results.append(rejection)
        self._ensure()
        for i, key, what in pending:
            results[i] = self._results.get(key, UpdateResult(False, math.nan, f"{what}: dropped from the history"))
        return results

    def _check_plane(self, meas: PlaneMeasurement) -> Optional[UpdateResult]:
        n = np.asarray(meas.n_ground, dtype=float)
        if not _finite([meas.t_capture, meas.d_ground], n, meas.z) or np.shape(meas.z) != (2,) or n.shape != (3,):
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: non-finite or malformed measurement")
        if not _is_covariance(meas.R, 2) or np.linalg.det(np.asarray(meas.R, dtype=float)) <= 0.0:
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: R is not a positive definite 2x2 covariance")
        if math.hypot(n[0], n[1]) < self.config.min_wall_normal:
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: not a wall (normal too close to vertical)")
        return None

    def update_pose(self, t: float, x: float, y: float, phi: float, cov: np.ndarray, gate: bool = True) -> UpdateResult:
        """Fuse an absolute pose fix (e.g. from an operator or a global solve) at time t."""
        cov = np.asarray(cov, dtype=float)
        if not _finite([t, x, y, phi]) or not _is_covariance(cov, 3) or np.linalg.det(cov) <= 0.0:
            return UpdateResult(False, math.nan, "pose fix rejected: non-finite pose or bad covariance")
        key: Key = (float(t), _KIND_POSE, "", "", self._next_seq())
        fix = _Fix(key, float(t), pose=np.array([x, y, phi], dtype=float), pose_cov=cov.copy(), gate=gate)
        rejection = self._insert_fix(fix, "pose fix")
        if rejection is not None:
            return rejection
        self._ensure()
        return self._results.get(key, UpdateResult(False, math.nan, "pose fix: dropped from the history"))

    def state(self) -> Tuple[float, np.ndarray, np.ndarray]:
        """(t, [x, y, phi], P) after the newest input."""
        self._require()
        self._ensure()
        cp = self._checkpoints[-1] if self._checkpoints else self._base
        return cp.t, cp.x.copy(), cp.P.copy()

    def predicted(self, t: float) -> Tuple[float, float, float, np.ndarray]:
        """(x, y, phi, P) at time t, from the inputs up to t, without changing the filter.

        Past the newest input the last twist is held (then zero); before the start of the
        history the oldest kept state is returned.
        """
        self._require()
        self._ensure()
        times = [cp.t for cp in self._checkpoints]
        i = bisect.bisect_right(times, t)
        cp = self._checkpoints[i - 1] if i > 0 else self._base
        x, P = cp.x, cp.P
        if t > cp.t:
            x, P = self._propagate(x, P, cp.t, float(t))
        return float(x[0]), float(x[1]), float(x[2]), P.copy()

    @property
    def history_start(self) -> float:
        """Oldest time a measurement can still be applied at."""
        self._require()
        return self._base.t

    # -- internals --------------------------------------------------------------------------

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _require(self):
        if self._base is None:
            raise RuntimeError("PoseFilter: set_pose() must be called first")

    def _newest_time(self) -> float:
        t = self._base.t
        if self._odom:
            t = max(t, self._odom[-1].t)
        if self._fixes:
            t = max(t, self._fixes[-1].t)
        return t

    def _insert_fix(self, fix: _Fix, what: str) -> Optional[UpdateResult]:
        """Add a fix to the history (replayed by the next ``_ensure``), or say why not."""
        if self._base is None:
            return UpdateResult(False, math.nan, f"{what} ignored: the pose is not set")
        if fix.key <= self._base.key:
            return UpdateResult(False, math.nan,
                                f"{what} at {fix.t:.3f} s is older than the history (starts {self._base.t:.3f} s)")
        ahead = fix.t - self._newest_time()
        if ahead > self.config.max_future:
            return UpdateResult(False, math.nan, f"{what} at {fix.t:.3f} s is {ahead:.2f} s ahead of the newest input")
        i = bisect.bisect_right(self._fix_keys, fix.key)
        self._fixes.insert(i, fix)
        self._fix_keys.insert(i, fix.key)
        self._mark_dirty(fix.key)
        return None

    def _mark_dirty(self, key: Key) -> None:
        if self._dirty is None or key < self._dirty:
            self._dirty = key

    def _ensure(self) -> None:
        """Recompute every state from the first invalid one, then trim the history."""
        if self._dirty is None or self._base is None:
            return
        dirty = self._dirty
        self._dirty = None
        keep = bisect.bisect_left([cp.key for cp in self._checkpoints], dirty)
        del self._checkpoints[keep:]
        start = self._checkpoints[-1] if self._checkpoints else self._base
        i = bisect.bisect_right(self._odom_keys, start.key)
        j = bisect.bisect_right(self._fix_keys, start.key)
        x, P, t = start.x, start.P, start.t
        while i < len(self._odom) or j < len(self._fixes):
            if j >= len(self._fixes) or (i < len(self._odom) and self._odom_keys[i] < self._fix_keys[j]):
                ev_key, ev_t = self._odom_keys[i], self._odom[i].t
                x, P = self._propagate(x, P, t, ev_t)
                i += 1
            else:
                fix = self._fixes[j]
                ev_key, ev_t = fix.key, fix.t
                x, P = self._propagate(x, P, t, ev_t)
                x, P, self._results[fix.key] = self._apply_fix(x, P, fix)
                j += 1
            t = ev_t
            self._checkpoints.append(_Checkpoint(ev_key, t, x, P))
        self._trim()

    def _trim(self) -> None:
        cfg = self.config
        horizon = self._newest_time() - cfg.history
        n = bisect.bisect_left([cp.t for cp in self._checkpoints], horizon)
        excess = len(self._checkpoints) - cfg.max_events
        n = max(n, excess)
        if n <= 0:
            return
        new_base = self._checkpoints[n - 1]
        self._base = _Checkpoint(new_base.key, new_base.t, new_base.x, new_base.P)
        del self._checkpoints[:n]
        # The newest odometry input always stays: it starts the next interval and holds the twist.
        k = min(bisect.bisect_right(self._odom_keys, new_base.key), len(self._odom) - 1)
        if k > 0:
            self._odom_origin = self._odom_t[k - 1]
            del self._odom[:k]
            del self._odom_keys[:k]
            del self._odom_t[:k]
        k = bisect.bisect_right(self._fix_keys, new_base.key)
        for f in self._fixes[:k]:
            self._results.pop(f.key, None)
        del self._fixes[:k]
        del self._fix_keys[:k]
        k = bisect.bisect_right(self._gyro_t, self._odom_origin)
        del self._gyro_t[:k]
        del self._gyro[:k]

    def _interval_twist(self, i: int) -> Tuple[np.ndarray, np.ndarray, float]:
        """Mean twist, its covariance and the interval length of odometry input i, gyro fused in."""
        o = self._odom[i]
        start = self._odom[i - 1].t if i > 0 else self._odom_origin
        twist, Q = o.twist, o.Q
        a = bisect.bisect_right(self._gyro_t, start)
        b = bisect.bisect_right(self._gyro_t, o.t)
        if b > a:
            samples = self._gyro[a:b]
            wz_g = sum(s[0] for s in samples) / len(samples)
            # The mean of n samples is not n times better: bias dominates, so keep the sample variance.
            var_g = sum(s[1] for s in samples) / len(samples)
            var_w = float(Q[2, 2])
            if self.config.gyro_mode == "replace" or var_w <= 0.0:
                w = 0.0
            else:
                w = var_g / (var_w + var_g)  # weight of the wheels' wz
            twist = twist.copy()
            twist[2] = w * twist[2] + (1.0 - w) * wz_g
            Q = Q.copy()
            Q[2, :2] *= w
            Q[:2, 2] *= w
            Q[2, 2] = w * w * var_w + (1.0 - w) ** 2 * var_g
        return twist, Q, o.t - start

    def _propagate(self, x: np.ndarray, P: np.ndarray, t0: float, t1: float) -> Tuple[np.ndarray, np.ndarray]:
        """Predict from t0 to t1 along the odometry schedule (no odometry input strictly inside)."""
        if t1 <= t0:
            return x, P
        i = bisect.bisect_left(self._odom_t, t1)
        if i < len(self._odom):
            twist, Q, dt_int = self._interval_twist(i)
            piece = t1 - t0
            timing = None
            if dt_int > self.config.max_odom_interval and piece < dt_int * (1.0 - 1e-9):
                # A gap split by a fix: where in the gap the motion happened is unknown.
                inc, _ = body_increment(twist, dt_int)
                f = piece / dt_int
                timing = _spread(x[2], inc, 0.5 * max(f, 1.0 - f))
            # The twist error is one draw for the whole interval: a piece of length dt gets the
            # share dt/dt_int of its variance so split intervals add up to the same total.
            return self._predict_segment(x, P, twist, Q, piece, dt_int / piece, timing)
        if not self._odom:
            return self._predict_segment(x, P, np.zeros(3), np.zeros((3, 3)), t1 - t0, 1.0)
        last = len(self._odom) - 1
        twist, Q, _ = self._interval_twist(last)
        hold_end = self._odom[last].t + self.config.hold
        if t0 < hold_end:
            t_mid = min(t1, hold_end)
            inc, _ = body_increment(twist, t_mid - t0)
            # Provisional: the robot may have stopped at once or kept going.
            x, P = self._predict_segment(x, P, twist, Q, t_mid - t0, 1.0, _spread(x[2], inc, 0.5))
            t0 = t_mid
        if t1 > t0:
            x, P = self._predict_segment(x, P, np.zeros(3), np.zeros((3, 3)), t1 - t0, 1.0)
        return x, P

    def _predict_segment(self, x, P, twist, Q_twist, dt: float, q_scale: float, extra: Optional[np.ndarray] = None):
        cfg = self.config
        inc, D = body_increment(twist, dt)
        phi = float(x[2])
        c, s = math.cos(phi), math.sin(phi)
        Rg = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        G = Rg @ D
        dist = math.hypot(inc[0], inc[1])
        turn = abs(inc[2])
        var_pos = cfg.pos_noise_density * dt + cfg.slip_per_metre * dist
        var_phi = cfg.heading_noise_density * dt + cfg.heading_slip_per_rad * turn + cfg.heading_slip_per_metre * dist
        ekf = self._ekf
        ekf.x = x.reshape(3, 1).copy()
        ekf.P = P.copy()
        ekf.F = np.array([[1.0, 0.0, -(s * inc[0] + c * inc[1])], [0.0, 1.0, c * inc[0] - s * inc[1]], [0.0, 0.0, 1.0]])
        ekf.Q = q_scale * (G @ Q_twist @ G.T) + np.diag([var_pos, var_pos, var_phi])
        if extra is not None:
            ekf.Q = ekf.Q + extra
        ekf.predict(u=inc)
        xn = ekf.x.reshape(3).copy()
        xn[2] = wrap_angle(float(xn[2]))
        return xn, 0.5 * (ekf.P + ekf.P.T)

    def _apply_fix(self, x: np.ndarray, P: np.ndarray, fix: _Fix):
        ekf = self._ekf
        if fix.plane is not None:
            meas = fix.plane
            H = meas.jacobian()
            R = np.asarray(meas.R, dtype=float)
            y = meas.residual(x[0], x[1], x[2])
            z = np.asarray(meas.z, dtype=float).reshape(2, 1)

            def hx(s):
                return meas.predict(s[0, 0], s[1, 0], s[2, 0]).reshape(2, 1)

            threshold, what = self._gate2, f"plane {meas.plane_id} ({meas.camera})"
        else:
            H = np.eye(3)
            R = fix.pose_cov
            y = fix.pose - x
            y[2] = wrap_angle(float(y[2]))
            # Unwrap the target angle next to the state so the residual is the short way round.
            z = (x + y).reshape(3, 1)

            def hx(s):
                return s

            threshold, what = (self._gate3 if fix.gate else math.inf), "pose fix"
        S = H @ P @ H.T + R
        try:
            d2 = float(y @ np.linalg.solve(S, y))
        except np.linalg.LinAlgError:
            return x, P, UpdateResult(False, math.nan, f"{what}: singular innovation covariance")
        if not math.isfinite(d2) or d2 > threshold:
            return x, P, UpdateResult(False, d2, f"{what}: gated out (d^2 = {d2:.1f} > {threshold:.1f})")
        ekf.x = x.reshape(3, 1).copy()
        ekf.P = P.copy()
        ekf.update(z, HJacobian=lambda s: H, Hx=hx, R=R, residual=_wrapped_residual)
        xn = ekf.x.reshape(3).copy()
        xn[2] = wrap_angle(float(xn[2]))
        return xn, 0.5 * (ekf.P + ekf.P.T), UpdateResult(True, d2, "")
