"""Mecanum kinematics: body twist <-> wheel speeds, and exact planar integration. Pure numpy.

Conventions (docs/architecture.md, 'Frames and units'): robot frame x forward, y left, z up; twist (vx, vy, wz) in
the robot frame (m/s, m/s, rad/s, wz counter-clockwise seen from above). Wheel order FL, FR,
RL, RR; a positive wheel speed turns the wheel so that it rolls the robot forward (+x).

Rollers: the roller touching the floor has its axis along (1, -1)/sqrt(2) on FL and RR and
along (1, 1)/sqrt(2) on FR and RL. Seen from above through the chassis, the top rollers then
form an "X" (equivalently, the floor contacts form an "O"): the usual mounting. Bench check:
driving left (vy > 0) turns FL and RR backwards and FR and RL forwards; turning
counter-clockwise (wz > 0) turns the left wheels backwards and the right wheels forwards.

With L = lx + ly (half wheelbase + half track) and r the wheel radius, rolling without slip:

    w_FL = (vx - vy - L wz) / r        w_FR = (vx + vy + L wz) / r
    w_RL = (vx + vy - L wz) / r        w_RR = (vx - vy + L wz) / r

Four wheels over-determine three twist components; ``forward`` is the least-squares inverse
(exact when the wheels agree) and ``slip_residual`` is the part no rigid motion explains.
"""

from __future__ import annotations

from typing import Sequence, Tuple, Union

import numpy as np

from robot.config import ChassisConfig

ArrayLike = Union[Sequence[float], np.ndarray]


class MecanumKinematics:
    """Wheel speeds (rad/s) <-> robot twist for one chassis geometry."""

    def __init__(self, wheel_radius: float, half_wheelbase: float, half_track: float):
        if wheel_radius <= 0 or half_wheelbase < 0 or half_track < 0 or half_wheelbase + half_track <= 0:
            raise ValueError(f"bad Mecanum geometry: r={wheel_radius}, lx={half_wheelbase}, ly={half_track}")
        self.r = float(wheel_radius)
        self.L = float(half_wheelbase + half_track)
        r, L = self.r, self.L
        # inverse: wheels = J @ twist
        self.J = np.array([[1.0, -1.0, -L], [1.0, 1.0, L], [1.0, 1.0, -L], [1.0, -1.0, L]]) / r
        # forward: twist = F @ wheels, F = pinv(J); the columns of J are orthogonal so this is exact
        self.F = (r / 4.0) * np.array([[1.0, 1.0, 1.0, 1.0], [-1.0, 1.0, 1.0, -1.0],
                                       [-1.0 / L, 1.0 / L, -1.0 / L, 1.0 / L]])
        # unit vector orthogonal to J's columns: rigid rolling always has w_FL + w_FR = w_RL + w_RR
        self.n_slip = np.array([1.0, 1.0, -1.0, -1.0]) / 2.0
        # F's rows are orthogonal, so equal independent wheel noise s2 gives s2 F F^T, a diagonal.
        self._FFt = self.F @ self.F.T
        self._FFt_rows = tuple(tuple(row) for row in self._FFt.tolist())

    @classmethod
    def from_config(cls, config: ChassisConfig) -> MecanumKinematics:
        return cls(config.wheel_radius, config.half_wheelbase, config.half_track)

    def inverse(self, vx: float, vy: float, wz: float) -> np.ndarray:
        """Wheel speeds (4,) in rad/s, FL, FR, RL, RR, for the twist (vx, vy, wz)."""
        return self.J @ np.array([vx, vy, wz], dtype=float)

    def forward(self, wheels: ArrayLike) -> np.ndarray:
        """Twist (vx, vy, wz) of wheel speeds (..., 4) in rad/s: least squares over the 4 wheels."""
        if _one_sample(wheels):
            return np.array(self.forward_floats(wheels))
        return np.asarray(wheels, dtype=float) @ self.F.T

    def forward_floats(self, wheels: ArrayLike) -> Tuple[float, float, float]:
        """``forward`` of one sample as a tuple of floats (what the odometry feed hands the filter)."""
        if _one_sample(wheels):
            # One odometry sample, a hundred times a second on the event loop: floats cost a
            # fraction of numpy's per-call overhead (and no array for the filter to take apart).
            w0, w1, w2, w3 = float(wheels[0]), float(wheels[1]), float(wheels[2]), float(wheels[3])
            q = 0.25 * self.r
            return q * (w0 + w1 + w2 + w3), q * (w1 + w2 - w0 - w3), q * (w1 + w3 - w0 - w2) / self.L
        vx, vy, wz = self.forward(wheels).tolist()
        return vx, vy, wz

    def slip_residual(self, wheels: ArrayLike) -> np.ndarray:
        """rad/s of wheel speed no rigid motion explains: (w_FL + w_FR - w_RL - w_RR) / 2.

        Zero when all four wheels roll without slip; the odometry can use it to flag slip.
        """
        return np.asarray(wheels, dtype=float) @ self.n_slip

    def forward_covariance(self, wheel_variance: Union[float, ArrayLike]) -> np.ndarray:
        """3x3 covariance of (vx, vy, wz) from wheel speed noise, F Sigma_w F^T.

        ``wheel_variance``: one variance (rad/s)^2 for all wheels, four per-wheel variances, or a
        full 4x4 covariance. Equal independent noise s2 gives diag(r^2 s2/4, r^2 s2/4, r^2 s2/(4 L^2)).
        """
        if isinstance(wheel_variance, float):
            return self._FFt * wheel_variance
        v = np.asarray(wheel_variance, dtype=float)
        if v.ndim == 0:
            cov_w = np.eye(4) * float(v)
        elif v.shape == (4,):
            cov_w = np.diag(v)
        elif v.shape == (4, 4):
            cov_w = v
        else:
            raise ValueError(f"wheel variance must be a scalar, 4 values or 4x4, got shape {v.shape}")
        return self.F @ cov_w @ self.F.T

    def forward_covariance_rows(self, wheel_variance: float) -> Tuple[Tuple[float, float, float], ...]:
        """``forward_covariance`` of one variance for all wheels, as rows of floats: the same
        products (F F^T times the variance, entry by entry) without a numpy array per sample."""
        v = float(wheel_variance)
        return tuple((a * v, b * v, c * v) for a, b, c in self._FFt_rows)

    def limit(self, wheels: ArrayLike, max_speed: float) -> Tuple[np.ndarray, float]:
        """Scale all four wheels by one factor so none exceeds max_speed: keeps the direction of motion.

        Returns (wheels, scale) with scale in (0, 1]. Clamping wheels one by one would instead bend
        the path of a Mecanum robot. The arithmetic is ``limit_floats``'s (one rule for the array
        API and the control tick, which calls that directly).
        """
        w = np.asarray(wheels, dtype=float)
        scaled, scale = limit_floats(w.ravel().tolist(), max_speed)
        return np.array(scaled, dtype=float).reshape(w.shape), scale


def limit_floats(wheels: Sequence[float], max_speed: float) -> Tuple[Tuple[float, ...], float]:
    """``MecanumKinematics.limit`` on plain floats: (wheels scaled by one factor, the factor).

    The control tick limits one command fifty times a second, where numpy's per-call overhead
    was most of the cost. The peak is taken as ``np.max(np.abs(w))`` takes it, a NaN anywhere
    included, so non-finite input gives what the array version always gave.
    """
    peak = 0.0
    for v in wheels:
        a = abs(v)
        if a > peak or a != a:  # (a != a: NaN, which wins as in numpy's max)
            peak = a
    if peak <= max_speed or peak == 0.0:
        return tuple(wheels), 1.0
    scale = max_speed / peak
    return tuple(v * scale for v in wheels), scale


def make_kinematics(config: ChassisConfig) -> MecanumKinematics:
    return MecanumKinematics.from_config(config)


def _one_sample(wheels: ArrayLike) -> bool:
    """A tuple of four wheel speeds (one sample), not a stack of them."""
    return isinstance(wheels, tuple) and len(wheels) == 4 and not isinstance(wheels[0], (tuple, list, np.ndarray))
