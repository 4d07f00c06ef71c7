"""From fitted planes to the robot pose (x, y, phi) with covariance (DESIGN.md section 4 step 4).

Two estimators:

* ``paper``: the published method. Heading is the inlier-weighted mean of per-plane angle
  differences; position is the 2x2 weighted least squares of the plane lines
  d_R = n_Gx x + n_Gy y + d_G, weights proportional to inlier counts.
* ``joint`` (default): Gauss-Newton on the pose over every inlier point, weighted by the stereo
  noise model, with a Huber loss. The point-to-plane residual is linear in the homogeneous point,
  so each plane's points enter only through their weighted second-moment matrix M = sum w q q^T
  (q = [p_R, 1]); iterations then cost O(planes), not O(points), and the result is still the
  exact weighted least-squares optimum over all points.

Unobservable directions (one wall, parallel walls) are detected from the information matrix,
kept at the coarse value and given a large variance: never invented.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from robot.geometry import rot_z, wrap_angle
from robot.plane_fit import FitParams, PlaneFit, residual_sigma

HEADING_LENGTH = 1.0  # m: scales phi against x, y when deciding which directions are observable
UNOBSERVED_VARIANCE = 1.0  # m^2 or rad^2 floor for a direction no plane constrains
HUBER_K = 2.0  # residuals beyond this many sigma get linearly, not quadratically, penalised


@dataclass
class ObservedPlane:
    """A fitted plane matched to a map plane, with what both estimators need."""

    plane_id: str
    camera: str
    n_ground: np.ndarray
    d_ground: float
    fit: PlaneFit
    T_robot_camera: np.ndarray
    points_camera: np.ndarray  # (N, 3) inlier points in C
    fit_params: FitParams = field(default_factory=FitParams)
    n_robot: np.ndarray = field(init=False)
    d_robot: float = field(init=False)
    cov_d_psi: np.ndarray = field(init=False)  # 2x2 covariance of (d_R, psi_R)

    def __post_init__(self):
        R, t = self.T_robot_camera[:3, :3], self.T_robot_camera[:3, 3]
        self.n_robot = R @ self.fit.n_camera
        self.d_robot = float(self.fit.d_camera - t @ self.n_robot)
        # Jacobian of (d_R, psi_R) w.r.t. the fit's tangent parameters (theta1, theta2, d_C).
        dn = R @ self.fit.basis.T  # (3, 2): d n_R / d theta
        h2 = self.n_robot[0] ** 2 + self.n_robot[1] ** 2
        dpsi_dn = np.array([-self.n_robot[1], self.n_robot[0], 0.0]) / max(h2, 1e-12)
        J = np.zeros((2, 3))
        J[0, :2] = -t @ dn
        J[0, 2] = 1.0
        J[1, :2] = dpsi_dn @ dn
        self.cov_d_psi = J @ self.fit.cov @ J.T

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
    status: str  # ok | degenerate | no_planes
    unobservable: List[Dict] = field(default_factory=list)


def _direction_label(v: np.ndarray) -> Dict:
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


def _split_observable(H: np.ndarray, unobservable_std: float):
    """Eigen-split the information matrix (in x, y, L*phi units) into observable/unobservable."""
    S = np.diag([1.0, 1.0, HEADING_LENGTH])
    Si = np.linalg.inv(S)
    Hs = Si @ H @ Si
    lam, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    obs = lam > 1.0 / unobservable_std**2
    return S, Si, lam, V, obs


def _covariance(lam, V, obs, Si, coarse_cov: Optional[np.ndarray]) -> np.ndarray:
    Cs = np.zeros((3, 3))
    for j in range(3):
        v = V[:, j]
        if obs[j]:
            Cs += np.outer(v, v) / lam[j]
        else:
            prior = UNOBSERVED_VARIANCE
            if coarse_cov is not None:
                S = np.linalg.inv(Si)
                prior = max(prior, float(v @ (S @ coarse_cov @ S) @ v))
            Cs += np.outer(v, v) * prior
    return Si @ Cs @ Si


def _no_planes(coarse, coarse_cov) -> PoseEstimate:
    cov = np.diag([UNOBSERVED_VARIANCE] * 3) if coarse_cov is None else np.array(coarse_cov, float)
    return PoseEstimate(coarse[0], coarse[1], coarse[2], cov, "no_planes",
                        [_direction_label(np.eye(3)[i]) for i in range(3)])


def solve_paper(planes: Sequence[ObservedPlane], coarse, coarse_cov=None,
                unobservable_std: float = 0.05) -> PoseEstimate:
    """The published estimator: weighted mean heading, then 2x2 weighted LS for position."""
    if not planes:
        return _no_planes(coarse, coarse_cov)
    w = np.array([p.fit.inliers for p in planes], float)
    phis = np.array([p.heading_of_normal_ground - p.psi_robot for p in planes])
    ref = phis[int(np.argmax(w))]
    phi = float(wrap_angle(ref + np.sum(w * wrap_angle(phis - ref)) / w.sum()))
    var_phi = float(np.sum(w**2 * np.array([p.cov_d_psi[1, 1] for p in planes])) / w.sum() ** 2)

    A = np.array([p.n_ground[:2] for p in planes])
    b = np.array([p.d_robot - p.d_ground for p in planes])
    var_b = np.array([p.cov_d_psi[0, 0] for p in planes])
    AtWA = (A * w[:, None]).T @ A
    lam, V = np.linalg.eigh(AtWA)
    # Sandwich covariance: the weights (inlier counts) are not the inverse variances.
    t0 = np.array(coarse[:2], float)
    rhs = (A * w[:, None]).T @ (b - A @ t0)
    delta = np.zeros(2)
    cov_pos = np.zeros((2, 2))
    unobs = []
    meat = (A * (w**2 * var_b)[:, None]).T @ A
    for j in range(2):
        v = V[:, j]
        std = math.sqrt(float(v @ meat @ v)) / lam[j] if lam[j] > 1e-12 * max(lam[-1], 1e-300) else math.inf
        if lam[j] > 1e-9 * w.sum() and std < unobservable_std:
            delta += v * (v @ rhs) / lam[j]
            cov_pos += np.outer(v, v) * std**2
        else:
            prior = UNOBSERVED_VARIANCE if coarse_cov is None else max(UNOBSERVED_VARIANCE, float(v @ np.asarray(coarse_cov)[:2, :2] @ v))
            cov_pos += np.outer(v, v) * prior
            unobs.append(_direction_label(np.array([v[0], v[1], 0.0])))
    cov = np.zeros((3, 3))
    cov[:2, :2] = cov_pos
    cov[2, 2] = var_phi
    t = t0 + delta
    return PoseEstimate(float(t[0]), float(t[1]), phi, cov, "degenerate" if unobs else "ok", unobs)


def _moments(points_robot: np.ndarray, w: np.ndarray) -> np.ndarray:
    q = np.empty((len(points_robot), 4))
    q[:, :3] = points_robot
    q[:, 3] = 1.0
    return (q * w[:, None]).T @ q


def _gauss_newton(planes, moments, x0, unobservable_std, iterations=8):
    x = np.array(x0, float)
    for _ in range(iterations):
        H = np.zeros((3, 3))
        g = np.zeros(3)
        cost = 0.0
        R2 = rot_z(x[2])[:2, :2]
        J90 = np.array([[0.0, -1.0], [1.0, 0.0]])
        for p, M in zip(planes, moments):
            a = p.n_ground[:2]
            c = R2.T @ a
            bvec = R2.T @ J90.T @ a
            u = np.array([c[0], c[1], p.n_ground[2], a @ x[:2] + p.d_ground])
            G = np.zeros((3, 4))
            G[0, 3], G[1, 3] = a
            G[2, :2] = bvec
            GM = G @ M
            H += GM @ G.T
            g += GM @ u
            cost += float(u @ M @ u)
        S, Si, lam, V, obs = _split_observable(H, unobservable_std)
        gs = Si @ g
        step_s = np.zeros(3)
        for j in range(3):
            if obs[j]:
                step_s -= V[:, j] * (V[:, j] @ gs) / lam[j]
        step = Si @ step_s
        x += step
        x[2] = float(wrap_angle(x[2]))
        if np.all(np.abs(step) < [1e-7, 1e-7, 1e-8]):
            break
    return x, H, cost


def solve_joint(planes: Sequence[ObservedPlane], coarse, coarse_cov=None,
                unobservable_std: float = 0.05, start=None) -> PoseEstimate:
    """Weighted, robust Gauss-Newton over all inlier points (see the module docstring)."""
    if not planes:
        return _no_planes(coarse, coarse_cov)
    # Start from the paper estimate: closed form, already close, so GN converges in a few steps.
    x0 = start if start is not None else (lambda e: (e.x, e.y, e.phi))(solve_paper(planes, coarse, coarse_cov, unobservable_std))
    # q_R = T_RC q_C, so the robot-frame moments are T M_C T^T: no per-point work.
    moments = [p.T_robot_camera @ p.fit.moments @ p.T_robot_camera.T for p in planes]
    x, H, cost = _gauss_newton(planes, moments, x0, unobservable_std)
    # One Huber reweighting against the planes the pose predicts (not the per-plane fits).
    T_ground_robot = np.eye(4)
    T_ground_robot[:3, :3] = rot_z(x[2])
    T_ground_robot[:2, 3] = x[:2]
    moments = []
    n_total = 0
    for p in planes:
        T_ground_camera = T_ground_robot @ p.T_robot_camera
        pi_C = np.array([*p.n_ground, p.d_ground]) @ T_ground_camera
        P = p.points_camera
        r = P @ pi_C[:3] + pi_C[3]
        w = 1.0 / np.maximum(residual_sigma(P, p.fit.n_camera, p.fit_params), 1e-4) ** 2
        w *= np.minimum(1.0, HUBER_K / np.maximum(np.abs(r) * np.sqrt(w), 1e-12))
        moments.append(p.T_robot_camera @ _moments(P, w) @ p.T_robot_camera.T)
        n_total += len(P)
    x, H, cost = _gauss_newton(planes, moments, x, unobservable_std)
    chi2_red = cost / max(n_total - 3, 1)
    S, Si, lam, V, obs = _split_observable(H, unobservable_std)
    cov = _covariance(lam, V, obs, Si, coarse_cov)
    obs_cov = np.zeros((3, 3))
    for j in range(3):
        if obs[j]:
            obs_cov += np.outer(V[:, j], V[:, j]) / lam[j]
    cov = cov + Si @ obs_cov @ Si * (max(chi2_red, 1.0) - 1.0)
    unobs = [_direction_label(S @ V[:, j]) for j in range(3) if not obs[j]]
    if unobs:
        # Hold unobservable directions at the coarse value: remove any drift GN put there.
        dx = x - np.array(coarse, float)
        dx[2] = float(wrap_angle(dx[2]))
        dxs = S @ dx
        for j in range(3):
            if not obs[j]:
                dxs -= V[:, j] * (V[:, j] @ dxs)
        x = np.array(coarse, float) + Si @ dxs
        x[2] = float(wrap_angle(x[2]))
    return PoseEstimate(float(x[0]), float(x[1]), float(x[2]), cov, "degenerate" if unobs else "ok", unobs)
