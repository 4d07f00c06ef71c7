"""From fitted planes to the robot pose (x, y, phi) with covariance (DESIGN.md section 4 step 4).

Two estimators:

* ``paper``: the published method. Heading is the inlier-weighted mean of per-plane angle
  differences; position is the 2x2 weighted least squares of the plane lines
  d_R = n_Gx x + n_Gy y + d_G, weights proportional to inlier counts.
* ``joint`` (default): Gauss-Newton on the pose over every inlier point, weighted by the stereo
  noise model, with a robust loss. Each plane fit (robot/plane_fit.py) is the maximum-likelihood
  plane of its points with their information matrix over (two normal angles, offset); to second
  order the points' cost is that quadratic form around the fitted plane, so the pose solve runs
  on the planes (O(planes) per iteration, not O(points)) and is still the optimum over all
  points. The points' robust loss (Huber on depth residuals) lives in the fit; here a second
  Huber loss on each plane's Mahalanobis residual keeps one plane that disagrees with the
  others (a wall built off the model, a wrong identification) from dragging the pose.

The covariance is the inverse information, widened by the planes' disagreement with each other
when it exceeds what their own covariances explain (reduced chi-square > 1).

Unobservable directions (one wall, parallel walls) are detected from the information matrix,
kept at the coarse value and given a large variance: never invented.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from robot.base.geometry import wrap_angle
from robot.localization.plane_fit import PlaneFit

HEADING_LENGTH = 1.0  # m: scales phi against x, y when deciding which directions are observable
UNOBSERVED_VARIANCE = 1.0  # m^2 or rad^2 floor for a direction no plane constrains
PLANE_HUBER_K = 3.0  # a plane's Mahalanobis residual beyond this many sigma is penalised linearly


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


_S = np.diag([1.0, 1.0, HEADING_LENGTH])
_SI = np.linalg.inv(_S)


def _split_observable(H: np.ndarray, unobservable_std: float):
    """Eigen-split the information matrix (in x, y, L*phi units) into observable/unobservable."""
    Hs = _SI @ H @ _SI
    lam, V = np.linalg.eigh(0.5 * (Hs + Hs.T))
    obs = lam > 1.0 / unobservable_std**2
    return _S, _SI, lam, V, obs


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


class _PlaneStack:
    """The planes' data as arrays, for Gauss-Newton vectorised over planes.

    Each map plane moved into its camera at pose (x, y, phi) is pi_C = T_RC^T T_GR^T pi_G:
    n_R = Rz(phi)^T n_G = cos(phi) a + sin(phi) b + e with a = (n_Gx, n_Gy, 0),
    b = (n_Gy, -n_Gx, 0), e = (0, 0, n_Gz); d_R = n_G . (x, y, 0) + d_G; n_C = R_RC^T n_R and
    d_C = n_R . t_RC + d_R. Its difference from the fit in the fit's tangent coordinates,
    (e1 . n_C, e2 . n_C, d_C - d_fit) (e_i is orthogonal to the fitted normal), is therefore
    cos(phi) Kc + sin(phi) Ks + K0 + (0, 0, n_Gxy . (x, y)) with per-plane constants."""

    def __init__(self, planes: Sequence[ObservedPlane]):
        P = len(planes)
        R = np.array([p.T_robot_camera[:3, :3] for p in planes])
        t = np.array([p.T_robot_camera[:3, 3] for p in planes])
        nG = np.array([p.n_ground for p in planes], float)
        BR = np.einsum("pkj,pij->pki", np.array([p.fit.basis for p in planes]), R)  # e_i . R^T v = (R e_i) . v
        a = np.column_stack([nG[:, 0], nG[:, 1], np.zeros(P)])
        b = np.column_stack([nG[:, 1], -nG[:, 0], np.zeros(P)])
        e = np.column_stack([np.zeros(P), np.zeros(P), nG[:, 2]])
        self.Kc, self.Ks, self.K0 = (np.empty((P, 3)) for _ in range(3))
        for K, v in ((self.Kc, a), (self.Ks, b), (self.K0, e)):
            K[:, :2] = np.einsum("pki,pi->pk", BR, v)
            K[:, 2] = np.einsum("pi,pi->p", v, t)
        self.K0[:, 2] += np.array([p.d_ground - p.fit.d_camera for p in planes])
        self.nxy = nG[:, :2]
        self.info = np.array([p.fit.info for p in planes])  # (P, 3, 3)

    def residuals(self, x: np.ndarray):
        """(P, 3) residuals at pose ``x`` and their (P, 3, 3) Jacobian over (x, y, phi)."""
        c, s = math.cos(x[2]), math.sin(x[2])
        r = c * self.Kc + s * self.Ks + self.K0
        r[:, 2] += self.nxy @ x[:2]
        J = np.zeros((len(r), 3, 3))
        J[:, 2, :2] = self.nxy
        J[:, :, 2] = c * self.Ks - s * self.Kc
        return r, J


def _normal_equations(st: _PlaneStack, x: np.ndarray, W: np.ndarray):
    r, J = st.residuals(x)
    JtW = np.matmul(J.transpose(0, 2, 1), W)
    return np.matmul(JtW, J).sum(axis=0), np.matmul(JtW, r[:, :, None]).sum(axis=0)[:, 0], r


def _gauss_newton(st: _PlaneStack, x0, weights: np.ndarray, unobservable_std: float, iterations: int = 10):
    """Minimise sum_j w_j r_j^T I_j r_j over the pose; steps only along observable directions.
    Linear in position, so a few steps converge from any heading within tens of degrees."""
    x = np.array(x0, float)
    W = st.info * weights[:, None, None]
    Vo = None
    for _ in range(iterations):
        H, g, _ = _normal_equations(st, x, W)
        if Vo is None:  # which directions are observable does not change between the steps
            _, Si, lam, V, obs = _split_observable(H, unobservable_std)
            Vo = Si @ V[:, obs]  # observable directions in (x, y, phi)
        # Newton step restricted to the observable subspace.
        step = -Vo @ np.linalg.solve(Vo.T @ H @ Vo, Vo.T @ g)
        x += step
        x[2] = float(wrap_angle(x[2]))
        if abs(step[0]) < 1e-8 and abs(step[1]) < 1e-8 and abs(step[2]) < 1e-9:
            break
    H, _, r = _normal_equations(st, x, W)
    m2 = np.einsum("pk,pkl,pl->p", r, st.info, r)  # each plane's squared Mahalanobis residual
    return x, H, m2


def solve_joint(planes: Sequence[ObservedPlane], coarse, coarse_cov=None,
                unobservable_std: float = 0.05, start=None) -> PoseEstimate:
    """Robust Gauss-Newton over all planes' fits (see the module docstring)."""
    if not planes:
        return _no_planes(coarse, coarse_cov)
    st = _PlaneStack(planes)
    weights = np.ones(len(planes))
    x, H, m2 = _gauss_newton(st, coarse if start is None else start, weights, unobservable_std)
    # Huber on each plane's Mahalanobis residual (IRLS): a plane far from what the others agree
    # on loses weight instead of moving the pose.
    for _ in range(3):
        new = np.minimum(1.0, PLANE_HUBER_K / np.sqrt(np.maximum(m2, 1e-12)))
        if float(np.max(np.abs(new - weights))) < 1e-3:
            break
        weights = new
        x, H, m2 = _gauss_newton(st, x, weights, unobservable_std)
    S, Si, lam, V, obs = _split_observable(H, unobservable_std)
    cov = _covariance(lam, V, obs, Si, coarse_cov)
    dof = 3 * len(planes) - int(obs.sum())
    chi2_red = float(np.sum(weights * m2)) / max(dof, 1)
    if chi2_red > 1.0:
        Vo = V[:, obs]
        cov = cov + Si @ (Vo / lam[obs]) @ Vo.T @ Si * (chi2_red - 1.0)
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
