"""RANSAC plane fit with the predicted map plane as a prior (DESIGN.md section 4 step 3). Pure numpy.

Hypotheses whose normal or offset disagree with the prediction beyond the gates are never
scored, which removes the paper's wrong-plane identifications. Among the hypotheses that pass,
the map plane is taken to be the *rear-most* well-supported one: clutter can stand in front of
a wall and occlude it, but nothing in view stands behind it.

The refit is the maximum-likelihood plane under the stereo noise model, not a least-squares
plane through the points. A stereo camera errs in disparity, f_x b / z, by about s pixels
(DESIGN.md section 6: sigma_z = z^2 s / (f_x b) is that error seen in depth), so inverse depth
has the same noise c = s / (f_x b) at every pixel, and a plane's inverse depth along the pixel
ray (x/z, y/z, 1) is linear in the ray: 1/z = q . ray with q = -n / d. The fit is a linear
least-squares problem in q, weighted only by the depth unit's quantisation (in depth, so it
grows as z^2 in inverse depth) and a Huber loss. Two shortcuts of a point-to-plane fit each
bias it by more than its own standard deviation once a wall is a few metres away or seen
obliquely (scripts/bench_buildings.py reports the resulting NEES):

* weights from the measured depth: a point that noise pulls towards the camera gets a larger
  weight, which pulls the plane towards the camera by about 4 sigma_z^2 / z;
* a total-least-squares (eigenvector) plane with noise that is not isotropic but along the rays:
  the errors-in-variables term turns an oblique plane's normal.

The inlier band and the weights come from the current plane's predicted depths, never from the
measured ones. The solve is repeated as the band follows the plane: on the RANSAC subsample,
then on every k-th point, then on all points, whose normal equations are the fit's
information matrix, all the pose solver needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

# A stage stops after a solve that moved the plane by under five standard deviations
# (step^T H step < 25): the problem is linear, so a solve lands on the optimum for its inlier
# band, and a band that moved that little changes the next solve by hundredths of a standard
# deviation (measured on the localizer benchmark's frames).
CONVERGED = 25.0
STAGE_ITERATIONS = 4


@dataclass(frozen=True)
class FitParams:
    iterations: int = 60
    sample: int = 600
    sigma_k: float = 3.0  # inlier band in noise standard deviations, along the ray
    min_threshold: float = 0.004  # m: inlier band floor (depth quantisation, calibration)
    min_inliers: int = 300
    angle_gate: float = math.radians(8.0)
    # The robot's up direction in the camera frame, and a gate on the normal's elevation above
    # the horizontal: heading and position errors turn a plane's predicted normal about this axis
    # only, so its tilt from it is known whatever the coarse pose (None: no such gate).
    up: Optional[Tuple[float, float, float]] = None
    tilt_gate: float = math.radians(8.0)
    offset_gate: float = 0.05  # m
    rear_support: float = 0.3  # a rear plane needs this fraction of the best plane's support
    noise_fx_b: float = 446.8 * 0.05  # f_x * baseline (pixel m) of the stereo noise model, full-resolution f_x
    noise_subpixel: float = 0.08
    depth_unit: float = 0.0  # m: the frame's depth unit; its rounding adds step^2 / 12 per point and a pattern (below)
    huber_k: float = 2.0  # depth residuals beyond this many sigma are penalised linearly
    # A fit must explain this fraction of its ROI's points. With every hypothesis on the real wall
    # outside the gates (a coarse pose far off), the best one left is a plane across a corner or
    # a strip of some other surface that a few percent of the points happen to lie near; clutter
    # in front of a wall rarely hides three quarters of what the ROI expected of it.
    min_inlier_fraction: float = 0.25


@dataclass
class PlaneFit:
    ok: bool
    reason: str
    n_camera: Optional[np.ndarray] = None  # unit normal, towards the camera
    d_camera: float = 0.0
    inliers: int = 0
    inlier_mask: Optional[np.ndarray] = None
    info: Optional[np.ndarray] = None  # 3x3 information of (theta1, theta2, d) in the tangent basis
    cov: Optional[np.ndarray] = None  # its inverse: the covariance of (theta1, theta2, d)
    basis: Optional[np.ndarray] = None  # (2, 3) e1, e2 orthogonal to n
    rms: float = 0.0  # weighted rms of the depth residuals, in noise standard deviations
    angle_to_prediction: float = 0.0
    offset_to_prediction: float = 0.0


def depth_sigma(z: np.ndarray, params: FitParams) -> np.ndarray:
    s = z * z * (params.noise_subpixel / params.noise_fx_b)
    if params.depth_unit > 0:
        return np.sqrt(s * s + params.depth_unit**2 / 12.0)
    return s


def _tangent_basis(n: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal e1, e2 with e1 x e2 = n (written out: np.cross costs more than the math)."""
    x, y, z = float(n[0]), float(n[1]), float(n[2])
    if abs(x) < 0.9:  # e1 = n x (1, 0, 0)
        e1 = (0.0, z, -y)
    else:  # e1 = n x (0, 1, 0)
        e1 = (-z, 0.0, x)
    k = 1.0 / math.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    a, b, c = e1[0] * k, e1[1] * k, e1[2] * k
    return np.array([[a, b, c], [y * c - z * b, z * a - x * c, x * b - y * a]])


def _ransac(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, pi_pred: np.ndarray, params: FitParams,
            rng: np.random.Generator) -> Tuple[Optional[np.ndarray], Optional[float], slice]:
    """The rear-most well-supported hypothesis within the gates: (n, d, the subsample), n None if none.

    Arrays are laid out (3, m) and (hypotheses, m) so that every operation runs along contiguous
    rows: numpy is several times slower on short second axes."""
    N = len(z)
    n_pred, d_pred = pi_pred[:3], float(pi_pred[3])
    # Every k-th ROI point from a random start: spread over the ROI like a random draw, at no cost.
    k = max(1, -(-N // params.sample))
    pick = slice(int(rng.integers(k)), None, k)
    z_s = z[pick]
    m = len(z_s)
    rays = np.empty((3, m))
    rays[0] = rx[pick]
    rays[1] = ry[pick]
    rays[2] = 1.0
    P = rays * z_s
    thr_sub = np.maximum(params.sigma_k * depth_sigma(z_s, params), params.min_threshold)

    # All hypotheses at once: three sample points each.
    idx = rng.integers(0, m, size=(3, params.iterations))
    a = P[:, idx[0]]
    u = P[:, idx[1]] - a
    v = P[:, idx[2]] - a
    nh = np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])  # (3, H)
    norm = np.sqrt(nh[0] * nh[0] + nh[1] * nh[1] + nh[2] * nh[2])
    good = norm > 1e-9
    nh /= np.where(good, norm, 1.0)
    dh = -(nh[0] * a[0] + nh[1] * a[1] + nh[2] * a[2])
    sign = np.where(dh < 0, -1.0, 1.0)  # normal towards the camera: d > 0
    nh *= sign
    dh *= sign
    good &= n_pred @ nh >= math.cos(params.angle_gate)
    if params.up is not None:
        up = np.asarray(params.up)
        good &= np.abs(np.arcsin(np.clip(up @ nh, -1.0, 1.0)) - math.asin(float(np.clip(up @ n_pred, -1.0, 1.0)))) \
            <= params.tilt_gate
    good &= np.abs(dh - d_pred) <= params.offset_gate
    if not good.any():
        return None, None, pick
    nh, dh = nh[:, good].T, dh[good]  # (H, 3), (H,)
    # Inlier when the depth along the ray is within the band: |n.p + d| < thr |n.ray|, where
    # n.p = z n.ray and n.ray < 0 for a plane in front of the camera (a ray that misses it has
    # n.ray >= 0 and no inlier). Scored in float32 (half the memory traffic): its rounding,
    # 1e-7 of a few metres, is far inside any band.
    nr = nh.astype(np.float32) @ rays.astype(np.float32)  # (H, m)
    err = nr * z_s.astype(np.float32)
    err += dh.astype(np.float32)[:, None]
    np.abs(err, out=err)
    nr *= -thr_sub.astype(np.float32)
    score = np.count_nonzero(err < nr, axis=1)
    best = int(score.argmax())
    # Rear-most rule: a parallel, farther plane with real support is the wall; the best one is clutter.
    parallel = (nh @ nh[best]) >= math.cos(math.radians(3.0))
    farther = dh > dh[best] + 2 * params.min_threshold + 2 * float(np.partition(thr_sub, m // 2)[m // 2])
    rear = parallel & farther & (score >= params.rear_support * score[best])
    if rear.any():
        cand = np.flatnonzero(rear)
        best = int(cand[np.argmax(dh[cand])])
    return nh[best].copy(), float(dh[best]), pick


def _solve_step(rx: np.ndarray, ry: np.ndarray, y: np.ndarray, q: np.ndarray, params: FitParams,
                with_shift: bool = False):
    """One weighted least-squares update of the plane q (inverse depth 1/z = q . (x/z, y/z, 1))
    on points with rays (rx, ry) and measured inverse depths y, with the inlier band, the
    quantisation weights and the Huber weights taken at the current plane.

    Returns (step, information H = sum w r r^T, inlier mask, weighted residual sum of squares,
    and with ``with_shift`` the arrays (w yp^2, yp), else None: a depth error e at a point moves
    the normal equations' right side by -w yp^2 e r).

    Written on 1-D arrays: numpy is several times slower on (N, 3) arrays broadcast along their
    short axis, and H's entries are dot products."""
    yp = rx * q[0]
    yp += ry * q[1]
    yp += q[2]  # predicted inverse depth; <= 0 where the ray misses the plane
    res = y - yp
    r2 = res * res
    c = params.noise_subpixel / params.noise_fx_b
    yp2 = yp * yp
    if params.depth_unit > 0:  # quantisation in depth: Delta^2 / 12 in z is that times yp^4 in 1/z
        var = yp2 * yp2
        var *= params.depth_unit**2 / 12.0
        var += c * c
    else:
        var = np.full(len(y), c * c)
    # The band: sigma_k sigmas, and never under min_threshold in depth (min_threshold yp^2 in 1/z).
    band = yp2 * params.min_threshold
    band *= band
    mask = r2 < np.maximum(var * params.sigma_k**2, band)
    mask &= yp > 0
    w = mask / var
    far = r2 > var * params.huber_k**2
    far &= mask
    if far.any():  # Huber: weight times k / |u| beyond k sigma
        w[far] *= params.huber_k * np.sqrt(var[far] / r2[far])
    a, b = w * rx, w * ry
    axy = float(a @ ry)
    ax1, ay1 = float(a.sum()), float(b.sum())
    H = np.array([[float(a @ rx), axy, ax1], [axy, float(b @ ry), ay1], [ax1, ay1, float(w.sum())]])
    t = w * res
    g = np.array([float(t @ rx), float(t @ ry), float(t.sum())])
    chi2 = float(t @ res)
    shift = (w * yp2, yp) if with_shift else None
    try:
        step = np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        step = np.zeros(3)
    return step, H, mask, chi2, shift


def fit_plane(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, pi_pred: np.ndarray, params: FitParams,
              rng: np.random.Generator, start: Optional[Tuple[np.ndarray, float]] = None) -> PlaneFit:
    """Fit the map plane predicted as ``pi_pred`` (n towards the camera) to ROI pixels given by
    their rays (x/z and y/z, (N,) each) and measured depths z (m, (N,), all > 0).

    ``start``: this surface's fit (n, d) from the same frame on an overlapping ROI (the
    localizer's previous pass): RANSAC and the coarse stages are skipped, the plane is refined on
    the new ROI's points."""
    N = len(z)
    if N < max(params.min_inliers, 3):
        return PlaneFit(False, f"too few ROI points ({N} < {params.min_inliers})")
    y = 1.0 / z
    stages = []
    if start is None:
        n, d, pick = _ransac(rx, ry, z, pi_pred, params, rng)
        if n is None:
            return PlaneFit(False, "no RANSAC hypothesis within the prediction gates")
        # Solve on the RANSAC subsample, then on every k-th point, then on all points: each stage
        # starts within a few of its own standard deviations, so its band is nearly final and one
        # or two solves suffice; the full set's last solve gives the information.
        if pick.step > 1:
            stages.append((rx[pick], ry[pick], y[pick]))
        k = N // (4 * params.sample)
        if k >= 2:
            stages.append((rx[::k], ry[::k], y[::k]))
    else:
        n, d = np.asarray(start[0], float), float(start[1])
    stages.append((rx, ry, y))
    q = -n / d
    for i, (sx, sy, sinv) in enumerate(stages):
        last = i == len(stages) - 1
        for _ in range(STAGE_ITERATIONS):
            step, H, mask, chi2, shift = _solve_step(sx, sy, sinv, q, params, last and params.depth_unit > 0)
            q = q + step
            if step @ H @ step < CONVERGED:
                break
    count = int(mask.sum())
    qn = math.sqrt(float(q @ q))
    n, d = -q / qn, 1.0 / qn
    n_pred, d_pred = pi_pred[:3], float(pi_pred[3])
    ang = math.acos(float(np.clip(n @ n_pred, -1.0, 1.0)))
    off = d - d_pred
    if count < params.min_inliers:
        return PlaneFit(False, f"too few inliers ({count} < {params.min_inliers})", n, d, count,
                        angle_to_prediction=ang, offset_to_prediction=off)
    if count < params.min_inlier_fraction * N:
        return PlaneFit(False, f"the best plane within the gates explains only {100.0 * count / N:.0f} % of the ROI's "
                               "points: not this wall", n, d, count, angle_to_prediction=ang, offset_to_prediction=off)
    tilt = 0.0
    if params.up is not None:
        up = np.asarray(params.up)
        tilt = abs(math.asin(float(np.clip(up @ n, -1.0, 1.0))) - math.asin(float(np.clip(up @ n_pred, -1.0, 1.0))))
    if ang > params.angle_gate or abs(off) > params.offset_gate or tilt > params.tilt_gate:
        return PlaneFit(False, f"fit disagrees with the map: normal {math.degrees(ang):.1f} deg (tilt "
                               f"{math.degrees(tilt):.1f} deg), offset {off * 1000:.0f} mm from prediction", n, d, count,
                        angle_to_prediction=ang, offset_to_prediction=off)
    # Information over (theta1, theta2, d), the normal turned towards e1, e2 and the offset:
    # q = -n / d moves by dq = -(theta1 e1 + theta2 e2) / d + n dd / d^2.
    B = _tangent_basis(n)
    Jq = np.column_stack([-B[0] / d, -B[1] / d, n / (d * d)])
    # More scatter than the noise model predicts (calibration, unmodelled noise) widens the
    # covariance; less never narrows it below the model.
    chi2_red = chi2 / max(count - 3, 1)
    try:
        Hi = np.linalg.inv(H)
        Jqi = np.linalg.inv(Jq)
    except np.linalg.LinAlgError:
        return PlaneFit(False, "degenerate inlier set (all points on a line)", n, d, count)
    cov = Jqi @ Hi @ Jqi.T * max(chi2_red, 1.0)
    if shift is not None:
        cov += _quantisation_cov(rx, ry, shift[0], shift[1], Hi, Jqi, params)
    info = np.linalg.inv(cov)
    return PlaneFit(True, "ok", n, d, count, mask, info, cov, B, math.sqrt(chi2_red), ang, off)


def _quantisation_cov(rx: np.ndarray, ry: np.ndarray, u: np.ndarray, yp: np.ndarray, Hi: np.ndarray,
                      Jqi: np.ndarray, params: FitParams) -> np.ndarray:
    """Covariance the depth unit's rounding adds to a fit, over (theta1, theta2, d).

    Rounding errors average out like independent noise only where the stereo noise dithers them:
    with Gaussian noise sigma, depth z comes out off by (Delta / pi) exp(-2 pi^2 sigma^2 / Delta^2)
    sin(2 pi z / Delta) on average (plus harmonics that are negligible wherever this matters): the
    same error for every pixel at the same depth. Within about half a metre (sigma_z under half a
    depth unit of 1 mm) that pattern does not average out over a fit. Its phase depends on where
    the wall is to a fraction of a millimetre (and on rounding versus truncation), so it is
    treated as unknown: a random phase, whose covariance follows from the fit's sensitivity to
    the sine and cosine patterns at the fitted depths. ``u`` = w yp^2 and ``yp`` are the last
    solve's weights and predicted inverse depths, ``Hi`` its inverse normal matrix, ``Jqi`` maps
    inverse-depth coefficients to (theta1, theta2, d)."""
    delta = params.depth_unit
    c = params.noise_subpixel / params.noise_fx_b
    # Only points whose pattern is damped less than exp(-8) (sigma_z under 0.64 units: nearer than
    # 0.4 m for 1 mm units at 848x480) carry one worth counting; the others are left out of the sums.
    z_cut = math.sqrt(0.64 * delta / c)
    near = np.flatnonzero(yp > 1.0 / z_cut)
    if len(near) == 0:
        return np.zeros((3, 3))
    zp = 1.0 / yp[near]
    sig = zp * zp * (c * math.pi / delta)
    amp = np.exp(-2.0 * sig * sig) * (delta / math.pi) * u[near]
    # float32: several times faster for these arguments (thousands of radians), and its 1e-7
    # relative rounding is far below what the pattern's shape needs.
    phase = (zp * (2.0 * math.pi / delta)).astype(np.float32)
    rxn, ryn = rx[near], ry[near]
    cov = np.zeros((3, 3))
    for pattern in (np.sin(phase), np.cos(phase)):
        pattern = amp * pattern
        v = Jqi @ (Hi @ np.array([float(pattern @ rxn), float(pattern @ ryn), float(pattern.sum())]))
        cov += np.outer(v, v)
    return cov / 2.0
