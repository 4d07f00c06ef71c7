"""From fitted planes to the robot pose (x, y, phi) with covariance (see docs/architecture.md,
'Pose solver', and docs/localization-integrity.md).

Two estimators:

* ``paper``: the published method. Heading is the inlier-weighted mean of per-plane angle
  differences; position is the 2x2 weighted least squares of the plane lines
  d_R = n_Gx x + n_Gy y + d_G, weights proportional to inlier counts. Its covariance is the
  sandwich of its gain around the measurements' full covariance (``paper_gain``).
* ``joint`` (default): generalised least squares over every plane's measurement
  (d_R, psi_R, tilt_R) with the full covariance of pixel noise and the systematic errors the
  planes share (robot/localization/integrity.py). Each plane fit (plane_fit.py) is the
  maximum-likelihood plane of its points with its information matrix; the pose solve runs on
  the planes, O(planes), not on the points.

Unobservable directions (one wall, parallel walls) are detected from the information matrix,
kept at the coarse value and given the coarse pose's variance: never invented.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from robot.base.geometry import wrap_angle
from robot.localization.integrity import UNOBSERVED_VARIANCE
from robot.localization.plane_fit import PlaneFit


@dataclass
class ObservedPlane:
    """A fitted plane matched to a map plane, with what both estimators need."""

    plane_id: str
    camera: str
    n_ground: np.ndarray
    d_ground: float
    fit: PlaneFit
    T_robot_camera: np.ndarray
    n_robot: np.ndarray = field(init=False)
    d_robot: float = field(init=False)
    cov_d_psi: np.ndarray = field(init=False)  # 2x2 covariance of (d_R, psi_R) from the fit alone
    J_fit: np.ndarray = field(init=False)  # (3, 3) d(d_R, psi_R, tilt_R) / d(fit's theta1, theta2, d_C)

    def __post_init__(self):
        R, t = self.T_robot_camera[:3, :3], self.T_robot_camera[:3, 3]
        self.n_robot = R @ self.fit.n_camera
        self.d_robot = float(self.fit.d_camera - t @ self.n_robot)
        # Jacobian of (d_R, psi_R) w.r.t. the fit's tangent parameters (theta1, theta2, d_C).
        dn = R @ self.fit.basis.T  # (3, 2): d n_R / d theta
        h2 = self.n_robot[0] ** 2 + self.n_robot[1] ** 2
        dpsi_dn = np.array([-self.n_robot[1], self.n_robot[0], 0.0]) / max(h2, 1e-12)
        J = np.zeros((3, 3))
        J[0, :2] = -t @ dn
        J[0, 2] = 1.0
        J[1, :2] = dpsi_dn @ dn
        # Elevation of the normal: what the mount's roll and pitch, not the pose, decide.
        J[2, :2] = dn[2] / max(math.sqrt(max(1.0 - self.n_robot[2] ** 2, 0.0)), 1e-6)
        self.J_fit = J
        self.cov_d_psi = J[:2] @ self.fit.cov @ J[:2].T

    @property
    def psi_robot(self) -> float:
        return math.atan2(self.n_robot[1], self.n_robot[0])

    @property
    def heading_of_normal_ground(self) -> float:
        return math.atan2(self.n_ground[1], self.n_ground[0])


@dataclass
class PoseEstimate:
    x: float
    y: float
    phi: float
    cov: np.ndarray
    status: str  # ok | degenerate | inconsistent | no_planes
    unobservable: List[Dict] = field(default_factory=list)


def direction_label(v: np.ndarray) -> Dict:
    v = v / np.linalg.norm(v)
    if abs(v[2]) > 0.9:
        label = "phi"
    else:
        p = v[:2] / np.linalg.norm(v[:2])
        if abs(p[0]) > 0.995:
            label = "x"
        elif abs(p[1]) > 0.995:
            label = "y"
        else:
            label = f"position along ({p[0]:.3f}, {p[1]:.3f})"
    return {"direction": [round(float(c), 6) for c in v], "label": label}


def no_planes(coarse, coarse_cov) -> PoseEstimate:
    cov = np.diag([UNOBSERVED_VARIANCE] * 3) if coarse_cov is None else np.array(coarse_cov, float)
    return PoseEstimate(coarse[0], coarse[1], coarse[2], cov, "no_planes",
                        [direction_label(np.eye(3)[i]) for i in range(3)])


def solve_paper(planes: Sequence[ObservedPlane], coarse, coarse_cov=None, unobservable_std: float = 0.05,
                R: Optional[np.ndarray] = None) -> PoseEstimate:
    """The published estimator: weighted mean heading, then 2x2 weighted LS for position.

    ``R``: the (3m, 3m) covariance of the planes' (d_R, psi_R, tilt_R) measurements with their
    systematic errors (integrity.Stack); the covariance is then the sandwich of the estimator's
    gain around it, otherwise around the fits' own covariances."""
    if not planes:
        return no_planes(coarse, coarse_cov)
    m = len(planes)
    w = np.array([p.fit.inliers for p in planes], float)
    phis = np.array([p.heading_of_normal_ground - p.psi_robot for p in planes])
    ref = phis[int(np.argmax(w))]
    phi = float(wrap_angle(ref + np.sum(w * wrap_angle(phis - ref)) / w.sum()))
    if R is None:
        R = np.zeros((3 * m, 3 * m))
        for i, p in enumerate(planes):
            R[3 * i:3 * i + 2, 3 * i:3 * i + 2] = p.cov_d_psi
    A = np.array([p.n_ground[:2] for p in planes])
    b = np.array([p.d_robot - p.d_ground for p in planes])
    AtWA = (A * w[:, None]).T @ A
    lam, V = np.linalg.eigh(AtWA)
    t0 = np.array(coarse[:2], float)
    rhs = (A * w[:, None]).T @ (b - A @ t0)
    # Gain of (x, y, phi) over the measurement rows (d_R, psi_R, tilt_R) of each plane.
    gain = np.zeros((3, 3 * m))
    gain[2, 1::3] = -w / w.sum()
    delta = np.zeros(2)
    unobs, prior_dirs = [], []
    var_d = np.diag(R)[0::3]
    meat = (A * (w**2 * var_d)[:, None]).T @ A
    for j in range(2):
        v = V[:, j]
        std = math.sqrt(float(v @ meat @ v)) / lam[j] if lam[j] > 1e-12 * max(lam[-1], 1e-300) else math.inf
        if lam[j] > 1e-9 * w.sum() and std < unobservable_std:
            delta += v * (v @ rhs) / lam[j]
            gain[:2, 0::3] += np.outer(v, v @ (A.T * w)) / lam[j]
        else:
            prior_dirs.append(v)
            unobs.append(direction_label(np.array([v[0], v[1], 0.0])))
    cov = gain @ R @ gain.T
    for v in prior_dirs:
        prior = UNOBSERVED_VARIANCE if coarse_cov is None else max(UNOBSERVED_VARIANCE, float(v @ np.asarray(coarse_cov)[:2, :2] @ v))
        cov[:2, :2] += np.outer(v, v) * prior
    t = t0 + delta
    return PoseEstimate(float(t[0]), float(t[1]), phi, cov, "degenerate" if unobs else "ok", unobs)
