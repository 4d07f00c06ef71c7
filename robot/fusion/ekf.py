"""Pose fusion (see docs/architecture.md, 'EKF'): an EKF on (x, y, phi) in G (filterpy's equations, written out).

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
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import arc_coefficients, wrap_angle
from robot.base.stats import chi2_quantile
from robot.config import FilterConfig
from robot.localization.measurements import PlaneMeasurement

Key = Tuple[float, int, str, str, int]

_KIND_ODOM = 0
_KIND_PLANE = 1
_KIND_POSE = 2
_KIND_BASE = -1
TRIM_BATCH = 32  # expired history states dropped together (see PoseFilter._trim)

# The filter runs at the odometry rate and replays its history for every lagged fix, so the
# per-step work is plain floats on cached, state-independent parts: the EKF's predict and update
# are filterpy's equations (tests/test_ekf.py holds them against filterpy's ExtendedKalmanFilter)
# written out for three states, without filterpy's per-call numpy work and without the 46 MiB of
# scipy modules importing it loads (docs/cpu-budget.md). A motion is (i0, i1, i2, m00, m01, m02, m11, m12, m22, var_pos,
# var_phi): the body increment of one constant-twist segment, q_scale * D Q_twist D^T (its
# twist noise in the start frame, symmetric) and the floor variances.
Motion = Tuple[float, float, float, float, float, float, float, float, float, float, float]
# An extra process noise (the unknown timing of a gap, a held twist): (e00, e01, e02, e11, e12, e22) in G.
Extra = Tuple[float, float, float, float, float, float]


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


def _motion(vx: float, vy: float, wz: float, Q: Sequence[Sequence[float]], dt: float, q_scale: float,
            cfg: FilterConfig) -> Motion:
    """The state-independent part of one prediction segment (``body_increment`` and D Q D^T, in floats)."""
    A, B, dA, dB = arc_coefficients(wz * dt)
    i0, i1, i2 = dt * (A * vx - B * vy), dt * (B * vx + A * vy), wz * dt
    d00, d01, d02 = dt * A, -dt * B, dt * dt * (dA * vx - dB * vy)
    d10, d11, d12 = dt * B, dt * A, dt * dt * (dB * vx + dA * vy)
    (q00, q01, q02), (q10, q11, q12), (q20, q21, q22) = Q
    r00, r01, r02 = d00 * q00 + d01 * q10 + d02 * q20, d00 * q01 + d01 * q11 + d02 * q21, d00 * q02 + d01 * q12 + d02 * q22
    r10, r11, r12 = d10 * q00 + d11 * q10 + d12 * q20, d10 * q01 + d11 * q11 + d12 * q21, d10 * q02 + d11 * q12 + d12 * q22
    dist = math.hypot(i0, i1)
    turn = abs(i2)
    var_pos = cfg.pos_noise_density * dt + cfg.slip_per_metre * dist
    var_phi = cfg.heading_noise_density * dt + cfg.heading_slip_per_rad * turn + cfg.heading_slip_per_metre * dist
    return (i0, i1, i2,
            q_scale * (r00 * d00 + r01 * d01 + r02 * d02), q_scale * (r00 * d10 + r01 * d11 + r02 * d12),
            q_scale * (r02 * dt), q_scale * (r10 * d10 + r11 * d11 + r12 * d12), q_scale * (r12 * dt),
            q_scale * (q22 * dt * dt), var_pos, var_phi)


_ZERO_Q = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

# Inside the history a state is a tuple (x, y, phi) and a covariance the tuple of its upper
# triangle (p00, p01, p02, p11, p12, p22): symmetric by construction, and a replay step builds no
# numpy arrays (each costs a microsecond or two, several per step on the Nano's Python 3.8).
# Arrays are made only at the public API (``state``, ``predicted``).
State = Tuple[float, float, float]
Cov6 = Tuple[float, float, float, float, float, float]


def _cov6(C: np.ndarray) -> Cov6:
    """The upper triangle of a (checked, symmetric up to rounding) 3x3 covariance, symmetrised."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(C, dtype=float).tolist()
    return (a, 0.5 * (b + d), 0.5 * (c + g), e, 0.5 * (f + h), i)


def _cov33(P: Cov6) -> np.ndarray:
    p00, p01, p02, p11, p12, p22 = P
    return np.array([[p00, p01, p02], [p01, p11, p12], [p02, p12, p22]])


def _joseph(P: Sequence[Sequence[float]], A: Sequence[Sequence[float]], K: Sequence[Sequence[float]],
            R: Sequence[Sequence[float]]) -> Cov6:
    """A P A^T + K R K^T (the Joseph form of the update, A = I - K H), symmetrised, for a 3-state
    filter and an m-dimensional measurement, in floats (the pose fix's; a wall has its own below)."""
    AP = [[A[i][0] * P[0][j] + A[i][1] * P[1][j] + A[i][2] * P[2][j] for j in range(3)] for i in range(3)]
    m = len(R)
    KR = [[sum(K[i][k] * R[k][j] for k in range(m)) for j in range(m)] for i in range(3)]
    out = [[0.0] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i, 3):
            v = (AP[i][0] * A[j][0] + AP[i][1] * A[j][1] + AP[i][2] * A[j][2]
                 + sum(KR[i][k] * K[j][k] for k in range(m)))
            w = (AP[j][0] * A[i][0] + AP[j][1] * A[i][1] + AP[j][2] * A[i][2]
                 + sum(KR[j][k] * K[i][k] for k in range(m)))
            out[i][j] = out[j][i] = 0.5 * (v + w)
    return (out[0][0], out[0][1], out[0][2], out[1][1], out[1][2], out[2][2])


# ---------------------------------------------------------------------------------------------
# History records


@dataclass
class _Odom:
    key: Key
    t: float
    twist: Tuple[float, float, float]  # mean body twist over the interval ending at t
    Q: Tuple[Tuple[float, float, float], ...]  # its covariance (3x3 rows, symmetric)
    # Caches, dropped when a gyro sample lands in the interval: (vx, vy, wz, Q rows, length) with
    # the gyro fused in, and the motion of each piece (t0, t1) of the interval a replay used.
    interval: Optional[Tuple[float, float, float, Tuple[Tuple[float, ...], ...], float]] = None
    pieces: Dict[Tuple[float, float], Motion] = field(default_factory=dict)


@dataclass
class _Fix:
    key: Key
    t: float
    plane: Optional[PlaneMeasurement] = None
    pose: Optional[np.ndarray] = None  # (3,) absolute pose
    pose_cov: Optional[np.ndarray] = None
    gate: bool = True
    # A plane's model, taken once when it is inserted (it is replayed many times):
    # (n0, n1, d_G, atan2(n_G), z0, z1, R (2x2) entries, label); H = [[n0, n1, 0], [0, 0, -1]].
    model: Optional[tuple] = None


@dataclass
class _Checkpoint:
    key: Key
    t: float
    x: State
    P: Cov6


def _after_odom(t: float) -> Key:
    """The smallest key after the odometry input at t (and before any fix at t)."""
    return (t, _KIND_ODOM, "", "", 1)


def _spread(phi: float, i0: float, i1: float, i2: float, scale: float) -> Extra:
    """Covariance of an unknown share (std ``scale``) of the body increment ``inc`` taken at heading
    phi: along the increment in G, plus a quarter of it per axis for a path that was not straight."""
    c, s = math.cos(phi), math.sin(phi)
    g0, g1, g2 = c * i0 - s * i1, s * i0 + c * i1, i2
    d2 = g0 * g0 + g1 * g1
    k = scale * scale
    return (k * (g0 * g0 + 0.25 * d2), k * (g0 * g1), k * (g0 * g2), k * (g1 * g1 + 0.25 * d2), k * (g1 * g2),
            k * (g2 * g2 + 0.25 * (g2 * g2)))


def _finite(*arrays) -> bool:
    return all(bool(np.isfinite(np.asarray(a, dtype=float)).all()) for a in arrays)


def _all_finite(*values: float) -> bool:
    for v in values:
        if not math.isfinite(v):
            return False
    return True


def _is_covariance(C: np.ndarray, n: int) -> bool:
    """Symmetric, finite and positive semi-definite (up to rounding)."""
    C = np.asarray(C, dtype=float)
    if C.shape != (n, n) or not np.isfinite(C).all():
        return False
    scale = max(1e-300, float(np.abs(C).max()))
    if float(np.abs(C - C.T).max()) > 1e-9 * scale:
        return False
    return bool(np.linalg.eigvalsh(C)[0] >= -1e-12 * scale)


def _float_rows3(C: object) -> Optional[Tuple[Tuple[float, float, float], ...]]:
    """``C`` itself when it is a tuple of three tuples of three floats (what the odometry feed
    passes a hundred times a second), else None (the caller goes through numpy)."""
    if type(C) is not tuple or len(C) != 3:  # exactly a tuple, not a subclass
        return None
    for row in C:
        if type(row) is not tuple or len(row) != 3:
            return None
        for v in row:
            if type(v) is not float:  # a numpy scalar or a string takes numpy's path
                return None
    return C  # type: ignore[return-value]


def _is_covariance3(rows: Sequence[Sequence[float]], C: Optional[np.ndarray] = None) -> bool:
    """``_is_covariance(C, 3)`` without LAPACK for the usual (diagonally dominant) case; ``rows``
    is ``C.tolist()`` (``C`` itself is only needed, and built if not given, when that fails)."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    if not _all_finite(a, b, c, d, e, f, g, h, i):
        return False
    scale = max(1e-300, abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
    if max(abs(b - d), abs(c - g), abs(f - h)) > 1e-9 * scale:
        return False
    # Gershgorin on the lower triangle (what eigvalsh reads): every eigenvalue is at least this.
    if min(a - abs(d) - abs(g), e - abs(d) - abs(h), i - abs(g) - abs(h)) >= 0.0:
        return True
    return _is_covariance(np.array(rows, dtype=float) if C is None else C, 3)


def _is_definite2(R: np.ndarray) -> bool:
    """``_is_covariance(R, 2)`` and ``det(R) > 0``, in closed form when clearly so."""
    if R.shape != (2, 2):
        return False
    (a, b), (c, d) = R.tolist()
    if not _all_finite(a, b, c, d):
        return False
    scale = max(1e-300, abs(a), abs(b), abs(c), abs(d))
    if abs(b - c) > 1e-9 * scale:
        return False
    # Smallest eigenvalue of the lower triangle's matrix; a clear margin makes the determinant
    # positive whatever rounding the general routines would add.
    half = 0.5 * (a - d)
    lam = 0.5 * (a + d) - math.sqrt(half * half + c * c)
    if lam >= 1e-6 * scale:
        return True
    return _is_covariance(R, 2) and np.linalg.det(R) > 0.0


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
        # The state after each input, as parallel lists (bisected by key and by time, never scanned).
        self._cp_keys: List[Key] = []
        self._cp_t: List[float] = []
        self._cp_x: List[State] = []
        self._cp_P: List[Cov6] = []
        self._dirty: Optional[Key] = None
        self._seq = 0
        # predicted(t) for the last t asked, until the next input: the control tick and the frame
        # pipeline ask for the same instant more than once.
        self._memo: Optional[Tuple[float, float, float, float, Cov6]] = None

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
        self._base = _Checkpoint(key, float(t), (float(x), float(y), float(wrap_angle(phi))), _cov6(cov))
        self._odom, self._odom_keys, self._odom_t = [], [], []
        self._odom_origin = float(t)
        self._gyro_t, self._gyro = [], []
        self._fixes, self._fix_keys = [], []
        self._results = {}
        self._cp_keys, self._cp_t, self._cp_x, self._cp_P = [], [], [], []
        self._dirty = None
        self._memo = None

    def predict_twist(self, t: float, vx: float, vy: float, wz: float, Q_twist: np.ndarray) -> UpdateResult:
        """Odometry: the mean body twist over the interval ending at t, and its covariance (a 3x3
        array, or a tuple of three tuples of three floats as ``OdometryFeed`` makes them)."""
        self._memo = None
        rows = _float_rows3(Q_twist)
        if rows is None:
            Q = np.asarray(Q_twist, dtype=float)
            rows = Q.tolist() if Q.shape == (3, 3) else None
        try:
            t, vx, vy, wz = float(t), float(vx), float(vy), float(wz)
        except (TypeError, ValueError):
            t = math.nan
        if not _all_finite(t, vx, vy, wz) or rows is None or not _is_covariance3(rows):
            return UpdateResult(False, math.nan, "odometry rejected: non-finite twist or bad covariance")
        if self._base is None:
            return UpdateResult(False, math.nan, "odometry ignored: the pose is not set")
        if t <= self._base.t:
            return UpdateResult(False, math.nan, f"odometry at {t:.3f} s is not after the filter's start {self._base.t:.3f} s")
        if self._odom and t <= self._odom[-1].t:
            return UpdateResult(False, math.nan,
                                f"odometry at {t:.3f} s is not after the previous sample {self._odom[-1].t:.3f} s")
        prev_end = self._odom[-1].t if self._odom else self._odom_origin
        key: Key = (t, _KIND_ODOM, "", "", 0)
        # Symmetrised as stored; an exactly symmetric Q (the usual) is its own symmetric part.
        (q00, q01, q02), (q10, q11, q12), (q20, q21, q22) = rows
        a, b, c = 0.5 * (q01 + q10), 0.5 * (q02 + q20), 0.5 * (q12 + q21)
        self._odom.append(_Odom(key, t, (vx, vy, wz), ((q00, a, b), (a, q11, c), (b, c, q22))))
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
        self._memo = None
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
            o = self._odom[j]
            o.interval = None
            o.pieces.clear()
            start = self._odom_t[j - 1] if j > 0 else self._odom_origin
            self._mark_dirty(_after_odom(start))
        return UpdateResult(True, 0.0, "")

    def update_plane(self, meas: PlaneMeasurement) -> UpdateResult:
        """Fuse one fitted plane at its capture time; returns whether the gate accepted it."""
        return self.update_planes([meas])[0]

    def update_planes(self, measurements: Sequence[PlaneMeasurement]) -> List[UpdateResult]:
        """Fuse the planes of one or more frames with a single replay (cheaper than one by one)."""
        self._memo = None
        pending: List[Tuple[int, Key, str]] = []
        results: List[Optional[UpdateResult]] = []
        for meas in measurements:
            model = self._plane_model(meas)
            if isinstance(model, UpdateResult):
                rejection: Optional[UpdateResult] = model
            else:
                key: Key = (float(meas.t_capture), _KIND_PLANE, str(meas.camera), str(meas.plane_id), self._next_seq())
                what = f"plane {meas.plane_id}"
                rejection = self._insert_fix(_Fix(key, float(meas.t_capture), plane=meas, model=model), what)
                if rejection is None:
                    pending.append((len(results), key, what))
            results.append(rejection)
        self._ensure()
        for i, key, what in pending:
            results[i] = self._results.get(key, UpdateResult(False, math.nan, f"{what}: dropped from the history"))
        return results  # type: ignore[return-value]

    def _plane_model(self, meas: PlaneMeasurement):
        """The checked plane's model for ``_apply_plane``, or the UpdateResult that rejects it."""
        n = np.asarray(meas.n_ground, dtype=float)
        z = np.asarray(meas.z, dtype=float)
        ok = n.shape == (3,) and z.shape == (2,)
        if ok:
            n0, n1, n2 = n.tolist()
            z0, z1 = z.tolist()
            try:
                t, d = float(meas.t_capture), float(meas.d_ground)
            except (TypeError, ValueError):
                t = d = math.nan
            ok = _all_finite(t, d, n0, n1, n2, z0, z1)
        if not ok:
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: non-finite or malformed measurement")
        R = np.asarray(meas.R, dtype=float)  # only read: no copy
        if not _is_definite2(R):
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: R is not a positive definite 2x2 covariance")
        if math.hypot(n0, n1) < self.config.min_wall_normal:
            return UpdateResult(False, math.nan, f"plane {meas.plane_id}: not a wall (normal too close to vertical)")
        (r00, r01), (r10, r11) = R.tolist()
        return (n0, n1, d, math.atan2(n1, n0), z0, z1, r00, r01, r10, r11, f"plane {meas.plane_id} ({meas.camera})")

    def update_pose(self, t: float, x: float, y: float, phi: float, cov: np.ndarray, gate: bool = True) -> UpdateResult:
        """Fuse an absolute pose fix (e.g. from an operator or a global solve) at time t."""
        self._memo = None
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
        if self._cp_keys:
            return self._cp_t[-1], np.array(self._cp_x[-1]), _cov33(self._cp_P[-1])
        return self._base.t, np.array(self._base.x), _cov33(self._base.P)

    def predicted(self, t: float) -> Tuple[float, float, float, np.ndarray]:
        """(x, y, phi, P) at time t, from the inputs up to t, without changing the filter.

        Past the newest input the last twist is held (then zero); before the start of the
        history the oldest kept state is returned.
        """
        self._require()
        self._ensure()
        memo = self._memo
        if memo is not None and memo[0] == t:
            return memo[1], memo[2], memo[3], _cov33(memo[4])
        i = bisect.bisect_right(self._cp_t, t)
        if i > 0:
            t0, x, P = self._cp_t[i - 1], self._cp_x[i - 1], self._cp_P[i - 1]
        else:
            t0, x, P = self._base.t, self._base.x, self._base.P
        if t > t0:
            x, P = self._propagate(x, P, t0, float(t))
        self._memo = (t, x[0], x[1], x[2], P)
        return x[0], x[1], x[2], _cov33(P)

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
        self._memo = None
        cp_keys, cp_t, cp_x, cp_P = self._cp_keys, self._cp_t, self._cp_x, self._cp_P
        keep = bisect.bisect_left(cp_keys, dirty)
        del cp_keys[keep:], cp_t[keep:], cp_x[keep:], cp_P[keep:]
        if keep:
            start_key, t, x, P = cp_keys[-1], cp_t[-1], cp_x[-1], cp_P[-1]
        else:
            b = self._base
            start_key, t, x, P = b.key, b.t, b.x, b.P
        odom, odom_keys, fixes, fix_keys = self._odom, self._odom_keys, self._fixes, self._fix_keys
        i = bisect.bisect_right(odom_keys, start_key)
        j = bisect.bisect_right(fix_keys, start_key)
        n_odom, n_fix = len(odom), len(fixes)
        while i < n_odom or j < n_fix:
            if j >= n_fix or (i < n_odom and odom_keys[i] < fix_keys[j]):
                ev_key, ev_t = odom_keys[i], odom[i].t
                if ev_t > t:
                    x, P = self._propagate_in(i, x, P, t, ev_t)
                i += 1
            else:
                fix = fixes[j]
                ev_key, ev_t = fix_keys[j], fix.t
                if ev_t > t:
                    x, P = self._propagate(x, P, t, ev_t)
                if fix.model is not None:
                    x, P, self._results[ev_key] = self._apply_plane(x, P, fix.model)
                else:
                    x, P, self._results[ev_key] = self._apply_fix(x, P, fix)
                j += 1
            t = ev_t
            cp_keys.append(ev_key)
            cp_t.append(t)
            cp_x.append(x)
            cp_P.append(P)
        self._trim()

    def _trim(self) -> None:
        cfg = self.config
        horizon = self._newest_time() - cfg.history
        n = bisect.bisect_left(self._cp_t, horizon)
        excess = len(self._cp_t) - cfg.max_events
        # Expired states go TRIM_BATCH at a time: every input would otherwise shift the front of
        # five lists of hundreds of entries by one. The history then reaches at most that many
        # events further back than ``history`` (measurements there are still applied exactly).
        if n < TRIM_BATCH and excess <= 0:
            return
        n = max(n, excess)
        self._base = _Checkpoint(self._cp_keys[n - 1], self._cp_t[n - 1], self._cp_x[n - 1], self._cp_P[n - 1])
        del self._cp_keys[:n], self._cp_t[:n], self._cp_x[:n], self._cp_P[:n]
        new_key = self._base.key
        # The newest odometry input always stays: it starts the next interval and holds the twist.
        k = min(bisect.bisect_right(self._odom_keys, new_key), len(self._odom) - 1)
        if k > 0:
            self._odom_origin = self._odom_t[k - 1]
            del self._odom[:k]
            del self._odom_keys[:k]
            del self._odom_t[:k]
        k = bisect.bisect_right(self._fix_keys, new_key)
        for key in self._fix_keys[:k]:
            self._results.pop(key, None)
        del self._fixes[:k]
        del self._fix_keys[:k]
        k = bisect.bisect_right(self._gyro_t, self._odom_origin)
        del self._gyro_t[:k]
        del self._gyro[:k]

    def _interval(self, i: int):
        """(vx, vy, wz, Q rows, interval length) of odometry input i, gyro fused in (cached)."""
        o = self._odom[i]
        if o.interval is not None:
            return o.interval
        start = self._odom_t[i - 1] if i > 0 else self._odom_origin
        vx, vy, wz = o.twist
        a = bisect.bisect_right(self._gyro_t, start)
        b = bisect.bisect_right(self._gyro_t, o.t)
        if b <= a:  # no gyro sample in the interval (the usual case): the wheels' twist as it came
            o.interval = (vx, vy, wz, o.Q, o.t - start)
            return o.interval
        Q = [list(r) for r in o.Q]
        samples = self._gyro[a:b]
        wz_g = sum(s[0] for s in samples) / len(samples)
        # The mean of n samples is not n times better: bias dominates, so keep the sample variance.
        var_g = sum(s[1] for s in samples) / len(samples)
        var_w = Q[2][2]
        if self.config.gyro_mode == "replace" or var_w <= 0.0:
            w = 0.0
        else:
            w = var_g / (var_w + var_g)  # weight of the wheels' wz
        wz = w * wz + (1.0 - w) * wz_g
        Q[2][0] *= w
        Q[2][1] *= w
        Q[0][2] *= w
        Q[1][2] *= w
        Q[2][2] = w * w * var_w + (1.0 - w) ** 2 * var_g
        o.interval = (vx, vy, wz, tuple(tuple(r) for r in Q), o.t - start)
        return o.interval

    def _propagate(self, x: State, P: Cov6, t0: float, t1: float) -> Tuple[State, Cov6]:
        """Predict from t0 to t1 along the odometry schedule (no odometry input strictly inside)."""
        if t1 <= t0:
            return x, P
        i = bisect.bisect_left(self._odom_t, t1)
        if i < len(self._odom):
            return self._propagate_in(i, x, P, t0, t1)
        cfg = self.config
        if not self._odom:
            return self._predict(x, P, _motion(0.0, 0.0, 0.0, _ZERO_Q, t1 - t0, 1.0, cfg))
        last = len(self._odom) - 1
        vx, vy, wz, Q, _ = self._interval(last)
        hold_end = self._odom[last].t + cfg.hold
        if t0 < hold_end:
            t_mid = min(t1, hold_end)
            mo = _motion(vx, vy, wz, Q, t_mid - t0, 1.0, cfg)
            # Provisional: the robot may have stopped at once or kept going.
            x, P = self._predict(x, P, mo, _spread(x[2], mo[0], mo[1], mo[2], 0.5))
            t0 = t_mid
        if t1 > t0:
            x, P = self._predict(x, P, _motion(0.0, 0.0, 0.0, _ZERO_Q, t1 - t0, 1.0, cfg))
        return x, P

    def _propagate_in(self, i: int, x: State, P: Cov6, t0: float, t1: float) -> Tuple[State, Cov6]:
        """Predict from t0 to t1 inside odometry interval i (t0 < t1 <= its end)."""
        o = self._odom[i]
        piece_key = (t0, t1)
        mo = o.pieces.get(piece_key)
        vx, vy, wz, Q, dt_int = self._interval(i)
        piece = t1 - t0
        if mo is None:
            # The twist error is one draw for the whole interval: a piece of length dt gets the
            # share dt/dt_int of its variance so split intervals add up to the same total.
            mo = _motion(vx, vy, wz, Q, piece, dt_int / piece, self.config)
            o.pieces[piece_key] = mo
        if dt_int > self.config.max_odom_interval and piece < dt_int * (1.0 - 1e-9):
            # A gap split by a fix: where in the gap the motion happened is unknown.
            A, B, _, _ = arc_coefficients(wz * dt_int)
            f = piece / dt_int
            extra = _spread(x[2], dt_int * (A * vx - B * vy), dt_int * (B * vx + A * vy), wz * dt_int,
                            0.5 * max(f, 1.0 - f))
            return self._predict(x, P, mo, extra)
        return self._predict(x, P, mo)

    def _predict(self, x: State, P: Cov6, mo: Motion, extra: Optional[Extra] = None) -> Tuple[State, Cov6]:
        """One filterpy prediction of motion ``mo`` from (x, P); F and Q built from floats."""
        i0, i1, i2, a, b, e, d, f, g, var_pos, var_phi = mo
        px, py, phi = x
        c, s = math.cos(phi), math.sin(phi)
        # Q = Rg (D Q_twist D^T) Rg^T + floor: the start-frame noise turned into G.
        n00, n01, n10, n11 = c * a - s * b, c * b - s * d, s * a + c * b, s * b + c * d
        q00 = n00 * c - n01 * s + var_pos
        q01 = n00 * s + n01 * c
        q11 = n10 * s + n11 * c + var_pos
        q02 = c * e - s * f
        q12 = s * e + c * f
        q22 = g + var_phi
        if extra is not None:
            q00, q01, q02 = q00 + extra[0], q01 + extra[1], q02 + extra[2]
            q11, q12, q22 = q11 + extra[3], q12 + extra[4], q22 + extra[5]
        gx, gy = c * i0 - s * i1, s * i0 + c * i1
        # x' = x + (gx, gy, i2); P' = F P F^T + Q with F = [[1, 0, -gy], [0, 1, gx], [0, 0, 1]].
        p00, p01, p02, p11, p12, p22 = P
        a00, a01, a02 = p00 - gy * p02, p01 - gy * p12, p02 - gy * p22  # rows of F P
        a10, a11, a12 = p01 + gx * p02, p11 + gx * p12, p12 + gx * p22
        # (F P F^T)[0][1] and [1][0] are equal up to rounding: their mean keeps P' symmetric.
        m01 = q01 + 0.5 * ((a01 + gx * a02) + (a10 - gy * a12))
        return ((px + gx, py + gy, wrap_angle(phi + i2)),
                (a00 - gy * a02 + q00, m01, a02 + q02, a11 + gx * a12 + q11, a12 + q12, p22 + q22))

    def _apply_plane(self, x: State, P: Cov6, model: tuple) -> Tuple[State, Cov6, UpdateResult]:
        n0, n1, dg, ang, z0, z1, r00, r01, r10, r11, what = model
        px, py, phi = x
        y0 = z0 - (n0 * px + n1 * py + dg)
        y1 = wrap_angle(z1 - wrap_angle(ang - phi))
        p00, p01, p02, p11, p12, p22 = P
        # P H^T with H = [[n0, n1, 0], [0, 0, -1]]: columns (u0, u1, u2) and (-p02, -p12, -p22).
        u0, u1, u2 = p00 * n0 + p01 * n1, p01 * n0 + p11 * n1, p02 * n0 + p12 * n1
        # S = H P H^T + R
        s00 = n0 * u0 + n1 * u1 + r00
        s01 = r01 - u2
        s10 = r10 - u2
        s11 = p22 + r11
        det = s00 * s11 - s01 * s10
        if det == 0.0 or not math.isfinite(det):
            return x, P, UpdateResult(False, math.nan, f"{what}: singular innovation covariance")
        d2 = (y0 * (s11 * y0 - s01 * y1) + y1 * (s00 * y1 - s10 * y0)) / det
        threshold = self._gate2
        if not math.isfinite(d2) or d2 > threshold:
            return x, P, UpdateResult(False, d2, f"{what}: gated out (d^2 = {d2:.1f} > {threshold:.1f})")

        # K = P H^T S^-1, x' = x + K y, P' = (I - K H) P (I - K H)^T + K R K^T (filterpy's update).
        si00, si01, si10, si11 = s11 / det, -s01 / det, -s10 / det, s00 / det
        k00, k01 = u0 * si00 - p02 * si10, u0 * si01 - p02 * si11
        k10, k11 = u1 * si00 - p12 * si10, u1 * si01 - p12 * si11
        k20, k21 = u2 * si00 - p22 * si10, u2 * si01 - p22 * si11
        xn = (px + k00 * y0 + k01 * y1, py + k10 * y0 + k11 * y1, wrap_angle(phi + k20 * y0 + k21 * y1))
        # Rows of A = I - K H.
        a00, a01, a02 = 1.0 - k00 * n0, -k00 * n1, k01
        a10, a11, a12 = -k10 * n0, 1.0 - k10 * n1, k11
        a20, a21, a22 = -k20 * n0, -k20 * n1, 1.0 + k21
        # Rows of A P (P symmetric).
        b00, b01, b02 = a00 * p00 + a01 * p01 + a02 * p02, a00 * p01 + a01 * p11 + a02 * p12, a00 * p02 + a01 * p12 + a02 * p22
        b10, b11, b12 = a10 * p00 + a11 * p01 + a12 * p02, a10 * p01 + a11 * p11 + a12 * p12, a10 * p02 + a11 * p12 + a12 * p22
        b20, b21, b22 = a20 * p00 + a21 * p01 + a22 * p02, a20 * p01 + a21 * p11 + a22 * p12, a20 * p02 + a21 * p12 + a22 * p22
        # K R K^T with R's symmetric part (what the symmetrised Joseph form keeps of it).
        rs = 0.5 * (r01 + r10)
        c00, c01 = k00 * r00 + k01 * rs, k00 * rs + k01 * r11
        c10, c11 = k10 * r00 + k11 * rs, k10 * rs + k11 * r11
        c20, c21 = k20 * r00 + k21 * rs, k20 * rs + k21 * r11
        return xn, (b00 * a00 + b01 * a01 + b02 * a02 + c00 * k00 + c01 * k01,
                    0.5 * (b00 * a10 + b01 * a11 + b02 * a12 + b10 * a00 + b11 * a01 + b12 * a02) + c00 * k10 + c01 * k11,
                    0.5 * (b00 * a20 + b01 * a21 + b02 * a22 + b20 * a00 + b21 * a01 + b22 * a02) + c00 * k20 + c01 * k21,
                    b10 * a10 + b11 * a11 + b12 * a12 + c10 * k10 + c11 * k11,
                    0.5 * (b10 * a20 + b11 * a21 + b12 * a22 + b20 * a10 + b21 * a11 + b22 * a12) + c10 * k20 + c11 * k21,
                    b20 * a20 + b21 * a21 + b22 * a22 + c20 * k20 + c21 * k21), UpdateResult(True, d2, "")

    def _apply_fix(self, x: State, P6: Cov6, fix: _Fix) -> Tuple[State, Cov6, UpdateResult]:
        """An absolute pose fix (rare: an operator, a global solve); H = I, in numpy."""
        xv = np.array(x)
        P = _cov33(P6)
        R = fix.pose_cov
        y = fix.pose - xv
        y[2] = wrap_angle(float(y[2]))  # the short way round
        threshold, what = (self._gate3 if fix.gate else math.inf), "pose fix"
        S = P + R
        try:
            d2 = float(y @ np.linalg.solve(S, y))
            K = P @ np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return x, P6, UpdateResult(False, math.nan, f"{what}: singular innovation covariance")
        if not math.isfinite(d2) or d2 > threshold:
            return x, P6, UpdateResult(False, d2, f"{what}: gated out (d^2 = {d2:.1f} > {threshold:.1f})")
        x0, x1, x2 = (xv + K @ y).tolist()
        return (x0, x1, wrap_angle(x2)), _joseph(P.tolist(), (np.eye(3) - K).tolist(), K.tolist(), R.tolist()), \
            UpdateResult(True, d2, "")
