"""RANSAC plane fit with the predicted map plane as a prior (DESIGN.md section 4 step 3). Pure numpy.

Hypotheses whose normal or offset disagree with the prediction beyond the gates are never
scored, which removes the paper's wrong-plane identifications. Among the hypotheses that pass,
the map plane is taken to be the *rear-most* well-supported one: clutter can stand in front of
a wall and occlude it, but nothing in view stands behind it. A weighted least-squares refit on
all inliers (weights from the stereo noise model) gives the plane and its covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class FitParams:
    iterations: int = 60
    sample: int = 600
    sigma_k: float = 3.0  # inlier band in noise standard deviations
    min_threshold: float = 0.004  # m: inlier band floor (depth quantisation, calibration)
    min_inliers: int = 300
    angle_gate: float = math.radians(8.0)
    offset_gate: float = 0.05  # m
    rear_support: float = 0.3  # a rear plane needs this fraction of the best plane's support
    noise_fx_b: float = 446.8 * 0.05  # f_x * baseline (pixel m) of the stereo noise model
    noise_subpixel: float = 0.08


@dataclass
class PlaneFit:
    ok: bool
    reason: str
    n_camera: Optional[np.ndarray] = None  # unit normal, towards the camera
    d_camera: float = 0.0
    inliers: int = 0
    inlier_mask: Optional[np.ndarray] = None
    moments: Optional[np.ndarray] = None  # 4x4 sum w q q^T of the inliers, q = [p_C, 1]
    cov: Optional[np.ndarray] = None  # 3x3 of (theta1, theta2, d) in the tangent basis (e1, e2)
    basis: Optional[np.ndarray] = None  # (2, 3) e1, e2 orthogonal to n
    rms: float = 0.0
    angle_to_prediction: float = 0.0
    offset_to_prediction: float = 0.0


def depth_sigma(z: np.ndarray, params: FitParams) -> np.ndarray:
    return z * z * (params.noise_subpixel / params.noise_fx_b)


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


def residual_sigma(points: np.ndarray, n: np.ndarray, params: FitParams) -> np.ndarray:
    """Point-to-plane noise: depth noise along each pixel ray, projected on the plane normal."""
    z = points[:, 2]
    ray_dot = np.abs(points @ n) / np.maximum(z, 1e-6)  # |n . (x/z, y/z, 1)|
    return np.maximum(depth_sigma(z, params) * ray_dot, 1e-4)


def fit_plane(points: np.ndarray, pi_pred: np.ndarray, params: FitParams,
              rng: np.random.Generator) -> PlaneFit:
    """Fit the map plane predicted as ``pi_pred`` (n towards the camera) to (N, 3) ROI points."""
    N = len(points)
    if N < max(params.min_inliers, 3):
        return PlaneFit(False, f"too few ROI points ({N} < {params.min_inliers})")
    n_pred, d_pred = pi_pred[:3], float(pi_pred[3])
    m = min(params.sample, N)
    sub = points[rng.choice(N, m, replace=False)] if m < N else points
    thr_sub = np.maximum(params.sigma_k * depth_sigma(sub[:, 2], params), params.min_threshold)

    # All hypotheses at once: three sample points each.
    idx = rng.integers(0, m, size=(params.iterations, 3))
    a, b, c = sub[idx[:, 0]], sub[idx[:, 1]], sub[idx[:, 2]]
    nh = np.cross(b - a, c - a)
    norm = np.linalg.norm(nh, axis=1)
    good = norm > 1e-9
    nh[good] /= norm[good, None]
    dh = -np.einsum("ij,ij->i", nh, a)
    flip = dh < 0
    nh[flip] *= -1
    dh[flip] *= -1
    cos_gate = math.cos(params.angle_gate)
    good &= (nh @ n_pred) >= cos_gate
    good &= np.abs(dh - d_pred) <= params.offset_gate
    if not good.any():
        return PlaneFit(False, "no RANSAC hypothesis within the prediction gates")
    nh, dh = nh[good], dh[good]
    inl = np.abs(sub @ nh.T + dh) < thr_sub[:, None]  # (m, H)
    score = inl.sum(axis=0)
    best = int(score.argmax())
    # Rear-most rule: a parallel, farther plane with real support is the wall; the best one is clutter.
    parallel = (nh @ nh[best]) >= math.cos(math.radians(3.0))
    farther = dh > dh[best] + 2 * params.min_threshold + 2 * float(np.median(thr_sub))
    rear = parallel & farther & (score >= params.rear_support * score[best])
    if rear.any():
        cand = np.flatnonzero(rear)
        best = int(cand[np.argmax(dh[cand])])
    n, d = nh[best], float(dh[best])

    # Refit on all points: weighted LS on the hypothesis' inliers via the moment matrix, then
    # the refined plane's inliers (one refit is enough: a 3-point hypothesis is already within
    # the inlier band, so the refit moves the plane by a fraction of it).
    thr = np.maximum(params.sigma_k * depth_sigma(points[:, 2], params), params.min_threshold)
    mask = np.abs(points @ n + d) < thr
    if mask.sum() >= 3:
        n, d = plane_from_moments(weighted_moments(points[mask], n, params))
        mask = np.abs(points @ n + d) < thr
    count = int(mask.sum())
    ang = math.acos(float(np.clip(n @ n_pred, -1.0, 1.0)))
    off = d - d_pred
    if count < params.min_inliers:
        return PlaneFit(False, f"too few inliers ({count} < {params.min_inliers})", n, d, count,
                        angle_to_prediction=ang, offset_to_prediction=off)
    if ang > params.angle_gate or abs(off) > params.offset_gate:
        return PlaneFit(False, f"fit disagrees with the map: normal {math.degrees(ang):.1f} deg, "
                               f"offset {off * 1000:.0f} mm from prediction", n, d, count,
                        angle_to_prediction=ang, offset_to_prediction=off)
    M = weighted_moments(points[mask], n, params)
    nh = np.array([*n, d])
    chi2_red = float(nh @ M @ nh) / max(count - 3, 1)
    basis = _tangent_basis(n)
    E = np.zeros((3, 4))
    E[0, :3], E[1, :3], E[2, 3] = basis[0], basis[1], 1.0
    cov = np.linalg.inv(E @ M @ E.T) * max(chi2_red, 1.0)
    rms = math.sqrt(max(float(nh @ M @ nh), 0.0) / max(M[3, 3], 1e-300)) if M[3, 3] > 0 else 0.0
    return PlaneFit(True, "ok", n, d, count, mask, M, cov, basis, rms, ang, off)


def weighted_moments(points: np.ndarray, n: np.ndarray, params: FitParams) -> np.ndarray:
    """M = sum_k w_k q_k q_k^T with q = [p, 1] and w = 1 / sigma_r^2 (stereo noise along the ray,
    projected on the normal). Everything downstream (refit, covariance, pose) needs only M."""
    q = np.empty((len(points), 4))
    q[:, :3] = points
    q[:, 3] = 1.0
    w = 1.0 / np.maximum(residual_sigma(points, n, params), 1e-4) ** 2
    return (q * w[:, None]).T @ q


def plane_from_moments(M: np.ndarray):
    """Weighted total-least-squares plane from a moment matrix: (n towards the origin, d)."""
    sw = M[3, 3]
    c = M[:3, 3] / sw
    S = M[:3, :3] - sw * np.outer(c, c)
    _, vecs = np.linalg.eigh(S)
    n = vecs[:, 0]
    d = -float(n @ c)
    if d < 0:  # the camera (origin) is on the observable side
        n, d = -n, -d
    return n, d
