"""Plane fit with the predicted map plane as a prior: which surface in the ROI is the wall, and
its maximum-likelihood plane (docs/localization-integrity.md, docs/architecture.md 'Plane fit').
Pure numpy; its hot parts (the refit, the hypothesis scoring, the behind-the-surface counts,
the covariance and the inlier summary) also run as compiled kernels, fit_kernels (numba, when it
is installed), which agree with the numpy code here: the reference.

Identification does not depend on luck. Every planar surface of the ROI is found in turn
(sequential RANSAC on a fixed subsample: each round draws hypotheses from the points no surface
explains yet, from fixed tables, so the same depth gives the same surfaces). The wall is then
chosen by physics, not by support: it is the *rear-most* surface the prior admits. Clutter
stands in front of a wall and hides part of it; nothing of the wall's own ROI can lie behind
it (openings are holes in the map's polygons, not part of the ROI). So:

* a surface with a real share of the ROI behind it is not the wall, however large it is (a
  panel or a door leaf a few decimetres in front of the wall);
* when the rear-most admissible surface is too small to fit, the wall is dropped, never
  replaced by the surface in front of it;
* when no surface is admissible and most of the ROI's depth lies far behind (or in front of)
  where the prior puts the wall, the fit reports that as evidence against the pose.

The refit is the maximum-likelihood plane under the stereo noise model, not a least-squares
plane through the points. A stereo camera errs in disparity, f_x b / z, by about s pixels
(sigma_z = z^2 s / (f_x b) seen in depth), so inverse depth has the same noise c = s / (f_x b)
at every pixel, and a plane's inverse depth along the pixel ray (x/z, y/z, 1) is linear in the
ray: 1/z = q . ray with q = -n / d. The fit is a linear least-squares problem in q, weighted
only by the depth unit's quantisation (in depth, so it grows as z^2 in inverse depth) and a
Huber loss. Two shortcuts of a point-to-plane fit each bias it by more than its own standard
deviation once a wall is a few metres away or seen obliquely:

* weights from the measured depth: a point that noise pulls towards the camera gets a larger
  weight, which pulls the plane towards the camera by about 4 sigma_z^2 / z;
* a total-least-squares (eigenvector) plane with noise that is not isotropic but along the rays:
  the errors-in-variables term turns an oblique plane's normal.

The inlier band and the weights come from the current plane's predicted depths, never from the
measured ones. The solve is repeated as the band follows the plane: on the identification
subsample, then on every k-th point, then on all points, whose normal equations are the fit's
information matrix. Scatter beyond the noise model (a bowed wall, a second surface too close
to separate, unmodelled structure) is reported as ``excess_var``: the localizer counts it as an
error of the plane that more pixels do not average away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from robot.localization import fit_kernels

# A stage stops after a solve that moved the plane by under five standard deviations
# (step^T H step < 25): the problem is linear, so a solve lands on the optimum for its inlier
# band, and a band that moved that little changes the next solve by hundredths of a standard
# deviation (measured on the localizer benchmark's frames).
CONVERGED = 25.0
STAGE_ITERATIONS = 4
# Fixed hypothesis tables: identification must give the same answer for the same depth, so the
# draws are the same every frame. Columns are fractions of the point pool.
_TABLE_SIZE = 512
_TABLE = np.random.default_rng(20240611).random((3, _TABLE_SIZE))
# Local hypotheses: an anchor and two points this fraction of the ROI's extent to its side and
# below it. Three points of one surface are far likelier near each other than anywhere.
LOCAL_STEP = 0.08
SURFACE_REFINE_STEPS = 1
_RIDGE = np.eye(3) * 1e-12


@dataclass(frozen=True)
class FitParams:
    iterations: int = 60  # hypotheses per identification round (as many local ones when no surface dominates)
    sample: int = 600  # points identification looks at (every k-th ROI point)
    sigma_k: float = 3.0  # inlier band in noise standard deviations, along the ray
    min_threshold: float = 0.004  # m: inlier band floor (depth quantisation, calibration)
    min_inliers: int = 300
    angle_gate: float = math.radians(8.0)
    # The robot's up direction in the camera frame, and a gate on the normal's elevation above
    # the horizontal: heading and position errors turn a plane's predicted normal about this axis
    # only, so its tilt from it is known whatever the coarse pose (None: no such gate).
    up: Optional[Tuple[float, float, float]] = None
    tilt_gate: float = math.radians(8.0)
    # The fitted plane's final tilt must be within 1 deg plus 3 sigma of what the mount, the wall's
    # plumb (``tilt_sigma``) and the matcher's systematic error over the patch's height
    # (``systematic_px``) allow: a board leaning on the wall a few degrees is not the wall.
    tilt_sigma: float = math.radians(0.4)
    systematic_px: float = 0.02
    offset_gate: float = 0.05  # m, half-width of the offsets the prior admits
    noise_fx_b: float = 446.8 * 0.05  # f_x * baseline (pixel m) of the stereo noise model, full-resolution f_x
    noise_subpixel: float = 0.08
    depth_unit: float = 0.0  # m: the frame's depth unit; its rounding adds step^2 / 12 per point and a pattern (below)
    huber_k: float = 2.0  # depth residuals beyond this many sigma are penalised linearly
    # A fit must explain this fraction of its ROI's points. With every hypothesis on the real wall
    # outside the gates (a coarse pose far off), the best one left is a plane across a corner or
    # a strip of some other surface that a few percent of the points happen to lie near; clutter
    # in front of a wall rarely hides three quarters of what the ROI expected of it.
    min_inlier_fraction: float = 0.25
    max_surfaces: int = 4  # identification rounds: surfaces found in one ROI at most
    surface_min_fraction: float = 0.1  # of the subsample: smaller surfaces are not looked for
    # Depth behind a surface by more than this (or 3 sigma_z) counts as behind it, and this share
    # of the ROI behind a surface says it is not the wall. Flying pixels lie between a surface
    # and what is behind it, so they never put depth behind the rear-most surface.
    behind_margin: float = 0.03  # m
    rear_fraction: float = 0.05  # of the identification subsample, among surfaces
    # ... and of a twice denser sample, for the surface finally chosen: a sliver of wall beside
    # a panel, between the image border and the panel's stereo shadow, is a percent or two of a ROI.
    rear_fraction_dense: float = 0.015
    # This share of the ROI far outside the prior's window, and no admissible surface: evidence
    # that the wall is not where the pose says.
    evidence_fraction: float = 0.5


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
    # Where the ROI's depth says the wall is not: "behind" (most of it lies farther than the prior
    # admits), "in_front" (nearer: occluded, or the pose is off), "" (no such evidence).
    evidence: str = ""
    surfaces: int = 0  # planar surfaces identification found in the ROI
    excess_var: float = 0.0  # m^2 along the normal: scatter the noise model does not explain
    centroid: Optional[np.ndarray] = None  # (3,) mean inlier point, camera frame
    z2_mean: float = 0.0  # m^2: mean squared depth of the inliers (systematic disparity error grows as z^2)
    lateral_std: float = 0.0  # m: spread of the inliers along the plane's horizontal direction
    vertical_std: float = 0.0  # m: ... and along its steepest direction


@dataclass
class _Subsample:
    """Every k-th ROI point: what identification looks at. Arrays (3, m) and (m,)."""

    pick: slice
    rx: np.ndarray
    ry: np.ndarray
    z: np.ndarray
    y: np.ndarray  # 1 / z
    rays: np.ndarray  # (3, m): x/z, y/z, 1
    P: np.ndarray  # (3, m) points
    thr: np.ndarray  # inlier band in depth
    sigma: np.ndarray  # depth noise std
    rays32: np.ndarray  # rays, z and thr in float32, for scoring
    z32: np.ndarray
    thr32: np.ndarray


@dataclass
class _Surface:
    n: np.ndarray  # unit normal towards the camera
    d: float
    mask: np.ndarray  # its inliers among the subsample
    refined: bool = True  # False: the best hypothesis as drawn (it held nearly all points)
    admissible: bool = False
    behind: float = 1.0  # share of the subsample behind it
    tags: List[str] = field(default_factory=list)


@dataclass
class _Identification:
    surface: Optional[_Surface]
    reason: str
    evidence: str = ""
    surfaces: int = 0


def depth_sigma(z: np.ndarray, params: FitParams) -> np.ndarray:
    s = z * z * (params.noise_subpixel / params.noise_fx_b)
    if params.depth_unit > 0:
        return np.sqrt(s * s + params.depth_unit**2 / 12.0)
    return s


def clip_unit(v) -> float:
    """``v`` clipped to [-1, 1] as a float, NaN kept (np.clip on a scalar costs ten times more)."""
    v = float(v)
    return -1.0 if v < -1.0 else (1.0 if v > 1.0 else v)


def depth_sigma_scalar(z: float, params: FitParams) -> float:
    """:func:`depth_sigma` of one depth, in floats (the same operations, the same rounding)."""
    s = z * z * (params.noise_subpixel / params.noise_fx_b)
    if params.depth_unit > 0:
        return math.sqrt(s * s + params.depth_unit**2 / 12.0)
    return s


def median(a: np.ndarray) -> float:
    """np.median of a 1-D float array without NaNs (the same values: the middle order statistics
    and their mean), without np.median's generic machinery."""
    n = len(a)
    h = n // 2
    if n % 2:
        return float(np.partition(a, h)[h])
    p = np.partition(a, (h - 1, h))
    return float((p[h - 1] + p[h]) / 2.0)


def cross(a, b) -> np.ndarray:
    """a x b for 3-vectors (written out: np.cross costs more than the math)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / max(math.sqrt(float(v @ v)), 1e-12)


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


def _subsample(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, params: FitParams) -> _Subsample:
    N = len(z)
    k = max(1, -(-N // params.sample))
    pick = slice(k // 2, None, k)  # every k-th point, the same for the same ROI
    sx, sy, sz = rx[pick], ry[pick], z[pick]
    rays = np.empty((3, len(sz)))
    rays[0], rays[1], rays[2] = sx, sy, 1.0
    sigma = depth_sigma(sz, params)
    thr = np.maximum(params.sigma_k * sigma, params.min_threshold)
    return _Subsample(pick, sx, sy, sz, 1.0 / sz, rays, rays * sz, thr, sigma, rays.astype(np.float32),
                      sz.astype(np.float32), thr.astype(np.float32))


def _planes_through(P: np.ndarray, idx: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Planes (H, 3) normals towards the camera and (H,) offsets through the point triplets ``idx``
    (3, H) of ``P`` (3, m); degenerate triplets are left out."""
    a = P[:, idx[0]]
    u = P[:, idx[1]] - a
    v = P[:, idx[2]] - a
    nh = np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])  # (3, H)
    norm = np.sqrt(nh[0] * nh[0] + nh[1] * nh[1] + nh[2] * nh[2])
    good = norm > 1e-9
    nh = nh[:, good] / norm[good]
    dh = -(nh[0] * a[0, good] + nh[1] * a[1, good] + nh[2] * a[2, good])
    sign = np.where(dh < 0, -1.0, 1.0)  # normal towards the camera: d > 0
    return (nh * sign).T, dh * sign


def _global_hypotheses(sub: _Subsample, pool: np.ndarray, count: int) -> Tuple[np.ndarray, np.ndarray]:
    """Planes through triplets drawn anywhere in the pool (from the fixed table)."""
    return _planes_through(sub.P, pool[(_TABLE[:, :count] * len(pool)).astype(np.intp)])


def _local_hypotheses(sub: _Subsample, pool: np.ndarray, count: int) -> Tuple[np.ndarray, np.ndarray]:
    """Planes through an anchor and its neighbours a step to the side and below (ray coordinates),
    the neighbours looked up among up to 128 pool points: when no surface holds most of the pool,
    three points of one surface are far likelier near each other than anywhere."""
    m = len(pool)
    anchors = pool[(_TABLE[0, -count:] * m).astype(np.intp)]
    near = pool[(_TABLE[1, :128] * m).astype(np.intp)] if m > 128 else pool
    px, py = sub.rx[near], sub.ry[near]
    step_x = LOCAL_STEP * max(float(px.max() - px.min()), 1e-6)
    step_y = LOCAL_STEP * max(float(py.max() - py.min()), 1e-6)
    ax, ay = sub.rx[anchors], sub.ry[anchors]
    dx = np.abs(px[None, :] - ax[:, None]) / step_x
    dy = np.abs(py[None, :] - ay[:, None]) / step_y
    right = near[np.argmin(np.abs(px[None, :] - (ax + step_x)[:, None]) / step_x + dy, axis=1)]
    below = near[np.argmin(dx + np.abs(py[None, :] - (ay + step_y)[:, None]) / step_y, axis=1)]
    return _planes_through(sub.P, np.vstack([anchors, right, below]))


def _score(sub: _Subsample, nh: np.ndarray, dh: np.ndarray, cols: Optional[np.ndarray]) -> np.ndarray:
    """Inliers of each hypothesis among the subsample points ``cols`` (None: all): the depth along
    the ray is within the band, |n.p + d| < thr |n.ray| (n.ray < 0 for a plane in front of the
    camera; a ray that misses it has n.ray >= 0 and no inlier). float32: its rounding, 1e-7 of a
    few metres, is far inside any band."""
    if cols is None:
        rays, z, thr = sub.rays32, sub.z32, sub.thr32
    else:
        rays, z, thr = sub.rays32[:, cols], sub.z32[cols], sub.thr32[cols]
    nr = nh.astype(np.float32) @ rays  # (H, m)
    err = nr * z
    err += dh.astype(np.float32)[:, None]
    np.abs(err, out=err)
    nr *= -thr
    return np.count_nonzero(err < nr, axis=1)


def _count_inliers(sub: _Subsample, nh: np.ndarray, dh: np.ndarray, cols: Optional[np.ndarray]) -> np.ndarray:
    """:func:`_score`, compiled when the kernels are."""
    if fit_kernels.backend() == "numba":
        return fit_kernels.score(nh, dh, sub.rays32, sub.z32, sub.thr32, cols)
    return _score(sub, nh, dh, cols)


def _band(sub: _Subsample, q: np.ndarray, params: FitParams) -> np.ndarray:
    """Subsample points within the inlier band of the plane q (as _solve_step draws it)."""
    yp = sub.rx * q[0] + sub.ry * q[1] + q[2]
    c = params.noise_subpixel / params.noise_fx_b
    var = c * c + (yp * yp) ** 2 * (params.depth_unit**2 / 12.0 if params.depth_unit > 0 else 0.0)
    band = (yp * yp * params.min_threshold) ** 2
    r = sub.y - yp
    return (r * r < np.maximum(var * params.sigma_k**2, band)) & (yp > 0)


def _refine_surface(sub: _Subsample, n: np.ndarray, d: float, pool: Optional[np.ndarray],
                    params: FitParams) -> Optional[Tuple[np.ndarray, float, np.ndarray]]:
    """The hypothesis refined on the pool's points within its band (least squares in inverse
    depth, where the stereo noise is the same everywhere: a solve lands on the optimum for its
    band), with its inliers among the whole subsample; None if it degenerates."""
    q = -n / d
    rays, y = (sub.rays, sub.y) if pool is None else (sub.rays[:, pool], sub.y[pool])
    c2 = (params.sigma_k * params.noise_subpixel / params.noise_fx_b) ** 2
    for _ in range(SURFACE_REFINE_STEPS):
        yp = q @ rays
        r = y - yp
        band = yp * yp * params.min_threshold
        m = (r * r < np.maximum(c2, band * band)) & (yp > 0)
        if int(np.count_nonzero(m)) < 3:
            return None
        A = rays[:, m]
        try:
            q = np.linalg.solve(A @ A.T, A @ y[m])
        except np.linalg.LinAlgError:
            return None
    qn = math.sqrt(float(q @ q))
    if not math.isfinite(qn) or qn <= 0:
        return None
    return -q / qn, 1.0 / qn, _band(sub, q, params)


def _find_surfaces(sub: _Subsample, params: FitParams) -> List[_Surface]:
    """Every planar surface of the subsample, largest first: each round takes the best-supported
    plane through the points no earlier surface explains, refines it and sets its inliers aside.
    A surface under ``surface_min_fraction`` of the subsample is not looked for: it could not be
    used as the wall, and what lies behind the wall is counted point by point anyway."""
    m = len(sub.z)
    remaining = np.ones(m, bool)
    min_pts = max(3, int(math.ceil(params.surface_min_fraction * m)))
    out: List[_Surface] = []
    for _ in range(params.max_surfaces):
        pool = np.flatnonzero(remaining)
        if len(pool) < min_pts:
            break
        cols = None if len(pool) == m else pool
        first, first_band = -1, None
        if cols is None and fit_kernels.backend() == "numba":
            # The first round in one call (the band of its best with it): what most walls need.
            nh, dh, score, first, first_band = fit_kernels.first_hypotheses(
                sub.P, _TABLE, params.iterations, sub.rays32, sub.z32, sub.thr32, sub.rx, sub.ry, sub.y, params)
        else:
            nh, dh = _global_hypotheses(sub, pool, params.iterations)
            score = _count_inliers(sub, nh, dh, cols) if len(dh) else np.zeros(0, np.intp)
        if len(dh) == 0 or 2 * int(score.max()) < len(pool):
            # No surface holds most of what is left: add local hypotheses.
            nl, dl = _local_hypotheses(sub, pool, params.iterations)
            nh, dh = np.vstack([nh, nl]), np.concatenate([dh, dl])
            score = np.concatenate([score, _count_inliers(sub, nl, dl, cols)]) if len(dl) else score
        if len(dh) == 0:
            break
        best = int(score.argmax())
        if score[best] < min_pts:
            break
        if not out and score[best] >= m - min_pts:
            # One surface holds nearly everything: the final fit refines it; identification needs
            # it refined only if its admissibility is in doubt (see identify).
            band = first_band if best == first else _band(sub, -nh[best] / dh[best], params)
            out.append(_Surface(nh[best].copy(), float(dh[best]), band, refined=False))
            break
        refined = _refine_surface(sub, nh[best], float(dh[best]), cols, params)
        if refined is None:
            break
        n, d, mask = refined
        if int(np.count_nonzero(mask & remaining)) < min_pts:
            break  # the refinement slid onto points already explained: nothing new here
        out.append(_Surface(n, d, mask))
        remaining &= ~mask
    return out


def _tilt(up: Optional[np.ndarray], n: np.ndarray, n_pred: np.ndarray) -> float:
    if up is None:
        return 0.0
    return abs(math.asin(clip_unit(up @ n)) - math.asin(clip_unit(up @ n_pred)))


def _behind(sub: _Subsample, n: np.ndarray, d: float, pi_pred: np.ndarray, params: FitParams) -> float:
    """Share of the subsample lying behind the plane (n, d) by more than the margin, where the
    prior could still put the wall."""
    return _behind_share(sub.rx, sub.ry, sub.z, 1, n, d, pi_pred, params, params.rear_fraction)


def _behind_share(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, stride: int, n: np.ndarray, d: float,
                  pi_pred: np.ndarray, params: FitParams, matters: float, count: Optional[int] = None) -> float:
    """:func:`_behind_points` of every stride-th point; its first pass compiled when the kernels are
    (the rest, for a share that matters, is rare). ``count``: that first pass's count, where the
    caller has it already (the fit's tail counts it)."""
    if count is None and fit_kernels.backend() == "numba":
        count = fit_kernels.behind_count(rx, ry, z, stride, n, d, params)
    if count is not None:
        m = max(-(-len(z) // stride), 1)
        if count < matters * m:
            return float(count) / m
    return _behind_points(rx[::stride], ry[::stride], z[::stride], n, d, pi_pred, params, matters)


def _behind_points(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, n: np.ndarray, d: float, pi_pred: np.ndarray,
                   params: FitParams, matters: float) -> float:
    """Share of the points behind the plane (n, d); a share under ``matters`` is returned as it is.

    Depth farther than the window the prior admits for the wall is not counted: with the pose
    off, a ROI reaches past the wall's top or end to whatever lies far behind it, which says where
    the wall ends, not that the surface in front is clutter (the window evidence weighs that)."""
    behind = _behind_mask(rx, ry, z, n, d, params)
    m = max(len(z), 1)
    if np.count_nonzero(behind) < matters * m:
        return float(np.count_nonzero(behind)) / m
    P = np.vstack([rx * z, ry * z, z])
    o, W = _window(P, depth_sigma(z, params), pi_pred, params)
    behind &= o <= W
    share = float(np.count_nonzero(behind)) / m
    # What is behind must be surfaces: flying pixels where the wall's own edge meets what lies
    # far behind it (the ROI reaches past its top or end when the pose is off) scatter between
    # the two, and say nothing about the wall. Behind a panel seen at a slant the wall and the
    # next wall at the corner can share what is behind: two surfaces, neither holding half.
    if share >= matters and not (_one_surface(rx[behind], ry[behind], z[behind], params)
                                 or _two_surfaces(rx[behind], ry[behind], z[behind], params)):
        return 0.0
    return share


def _behind_mask(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, n: np.ndarray, d: float, params: FitParams) -> np.ndarray:
    """Points whose ray meets the plane (n, d) in front of the camera and whose depth lies beyond
    it by more than the margin (3 depth sigmas there, at least ``behind_margin``)."""
    nr = n[0] * rx + n[1] * ry + n[2]
    hit = nr < -1e-9  # rays that meet the plane in front of the camera
    z_plane = np.where(hit, -d / np.where(hit, nr, -1.0), 1e3)
    margin = np.maximum(3.0 * depth_sigma(z_plane, params), params.behind_margin)
    return hit & (z > z_plane + margin)


def _thinned_system(rx: np.ndarray, ry: np.ndarray, z: np.ndarray,
                    params: FitParams) -> Tuple[np.ndarray, np.ndarray, float]:
    """The points evenly thinned to about 300 (enough to tell planes from scatter) as a linear
    system in inverse depth: A (3, m) of rays, y = 1/z, and the band's floor c in inverse depth."""
    if len(z) > 300:
        k = -(-len(z) // 300)
        rx, ry, z = rx[::k], ry[::k], z[::k]
    return np.vstack([rx, ry, np.ones(len(z))]), 1.0 / z, params.sigma_k * params.noise_subpixel / params.noise_fx_b


def _in_band(y: np.ndarray, yp: np.ndarray, c: float, params: FitParams) -> np.ndarray:
    """Inverse depths y within the inlier band of the plane's yp (never under min_threshold in depth)."""
    return np.abs(y - yp) < np.maximum(c, yp * yp * params.min_threshold)


def _one_surface(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, params: FitParams) -> bool:
    """Whether a plane holds half of these points or more (least squares in inverse depth,
    trimmed to the inlier band and refitted), rather than their depths scattering."""
    if len(z) < 3:
        return False
    A, y, c = _thinned_system(rx, ry, z, params)
    keep = np.ones(len(y), bool)
    for _ in range(3):
        Ak = A[:, keep]
        try:
            q = np.linalg.solve(Ak @ Ak.T + _RIDGE, Ak @ y[keep])
        except np.linalg.LinAlgError:
            return False
        keep = _in_band(y, q @ A, c, params)
        if int(np.count_nonzero(keep)) < 3:
            return False
    return float(np.count_nonzero(keep)) >= 0.5 * len(y)


TWO_SURFACES_HOLD = 0.7  # of the points: two planes holding this much are surfaces, not scatter
TWO_SURFACES_EACH = 0.2  # ... each of them at least this much
TWO_SURFACES_DRAWS = 48  # three-point planes tried per surface (the hypothesis table's first columns)


def _two_surfaces(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, params: FitParams) -> bool:
    """Whether two planes hold ``TWO_SURFACES_HOLD`` of these points together (each at least
    ``TWO_SURFACES_EACH``): the best of a fixed set of three-point planes, then the best on what it
    leaves. Flying pixels, strung along rays between two depths, fill no two planes."""
    if len(z) < 12:
        return False
    A, y, c = _thinned_system(rx, ry, z, params)
    m = len(y)
    left = np.ones(m, bool)
    held = []
    for _ in range(2):
        idx = np.flatnonzero(left)
        if len(idx) < 3:
            return False
        best = None
        for draw in _TABLE[:, :TWO_SURFACES_DRAWS].T:  # fixed draws: the same answer every frame
            pick = idx[(draw * len(idx)).astype(np.intp)]
            try:
                q = np.linalg.solve(A[:, pick].T, y[pick])
            except np.linalg.LinAlgError:
                continue
            inl = left & _in_band(y, q @ A, c, params)
            if best is None or np.count_nonzero(inl) > np.count_nonzero(best):
                best = inl
        if best is None:
            return False
        held.append(int(np.count_nonzero(best)))
        left &= ~best
    return min(held) >= TWO_SURFACES_EACH * m and sum(held) >= TWO_SURFACES_HOLD * m


def _window(P: np.ndarray, sigma: np.ndarray, pi_pred: np.ndarray, params: FitParams) -> Tuple[np.ndarray, np.ndarray]:
    """Each point's offset behind the predicted plane (m; negative: in front) and the largest
    offset the prior admits for the wall at that point: the offset gate, widened by what the
    normal gates let the plane turn at the point's distance from the camera's foot on it, and the
    depth noise."""
    n, d = pi_pred[:3], float(pi_pred[3])
    o = -(n @ P + d)
    if params.up is not None:
        h = unit(cross(params.up, n))
        v = cross(n, h)
        width = (np.abs(h @ P) * math.tan(min(params.angle_gate, math.radians(80.0)))
                 + np.abs(v @ P) * math.tan(min(params.tilt_gate, math.radians(80.0))))
    else:
        lateral = np.linalg.norm(P - np.outer(n, n @ P), axis=0)
        width = lateral * math.tan(min(params.angle_gate, math.radians(80.0)))
    return o, params.offset_gate + width + np.maximum(3.0 * sigma, params.behind_margin)


def _window_evidence(sub: _Subsample, pi_pred: np.ndarray, params: FitParams) -> Tuple[str, str]:
    """Where the ROI's depth lies relative to the offsets the prior admits for the wall: a point's
    offset from the predicted plane against the gate, widened by what the normal gates let the
    plane turn at the point's distance from the camera's foot on it."""
    o, W = _window(sub.P, sub.sigma, pi_pred, params)
    m = max(len(o), 1)
    behind, front = np.count_nonzero(o > W) / m, np.count_nonzero(o < -W) / m
    if behind >= params.evidence_fraction:
        return "behind", (f"no surface the prior admits: {100 * behind:.0f} % of the ROI's depth lies behind where "
                          "the pose admits the wall (evidence against the pose)")
    if front >= params.evidence_fraction:
        return "in_front", (f"no surface the prior admits: {100 * front:.0f} % of the ROI's depth lies in front of "
                            "where the pose admits the wall (occluded, or evidence against the pose)")
    return "", "no surface within the prior's gates"


def _same_surface(a: _Surface, b: _Surface, sub: _Subsample) -> bool:
    """Two fits of one surface: parallel within 2 deg and within the inlier band of each other."""
    if float(a.n @ b.n) < math.cos(math.radians(2.0)):
        return False
    return abs(a.d - b.d) < 2.0 * median(sub.thr)


def _admissible(s: _Surface, pi_pred: np.ndarray, up: Optional[np.ndarray], params: FitParams) -> bool:
    ang = math.acos(clip_unit(s.n @ pi_pred[:3]))
    return (ang <= params.angle_gate and _tilt(up, s.n, pi_pred[:3]) <= params.tilt_gate
            and abs(s.d - float(pi_pred[3])) <= params.offset_gate)


def identify(sub: _Subsample, pi_pred: np.ndarray, params: FitParams) -> _Identification:
    """Which surface of the ROI is the predicted wall: the rear-most one the prior admits."""
    n_pred, d_pred = pi_pred[:3], float(pi_pred[3])
    up = None if params.up is None else np.asarray(params.up, float)
    surfaces = _find_surfaces(sub, params)
    if len(surfaces) == 1 and not surfaces[0].refined and not _admissible(surfaces[0], pi_pred, up, params):
        refined = _refine_surface(sub, surfaces[0].n, surfaces[0].d, None, params)  # noise at a gate's edge?
        surfaces = [] if refined is None else [_Surface(*refined)]
    for s in surfaces:
        s.admissible = _admissible(s, pi_pred, up, params)
    adm = [s for s in surfaces if s.admissible]
    if len(adm) == 1 and len(surfaces) == 1:
        return _Identification(adm[0], "ok", "", 1)  # nothing else in the ROI: the dense check decides
    for s in adm:
        s.behind = _behind(sub, s.n, s.d, pi_pred, params)
    if not adm:
        # A large surface facing the way the wall does, only at an offset the prior does not admit:
        # the wall is there, not where the pose says.
        m = max(len(sub.z), 1)
        parallel = [s for s in surfaces if math.acos(clip_unit(s.n @ n_pred)) <= params.angle_gate
                    and _tilt(up, s.n, n_pred) <= params.tilt_gate and s.mask.sum() >= params.min_inlier_fraction * m]
        if parallel:
            s = max(parallel, key=lambda t: int(t.mask.sum()))
            where = "behind" if s.d > d_pred else "in_front"
            return _Identification(None, f"a surface parallel to the wall holds {100 * s.mask.sum() / m:.0f} % of the ROI "
                                   f"{1000 * abs(s.d - d_pred):.0f} mm {'behind' if where == 'behind' else 'in front of'} "
                                   f"where the pose puts the wall, beyond the {1000 * params.offset_gate:.0f} mm the "
                                   "prior admits (evidence against the pose)", where, len(surfaces))
        evidence, why = _window_evidence(sub, pi_pred, params)
        return _Identification(None, why, evidence, len(surfaces))
    clear = [s for s in adm if s.behind < params.rear_fraction]
    if not clear:
        s = min(adm, key=lambda t: t.behind)
        evidence, _ = _window_evidence(sub, pi_pred, params)
        return _Identification(None, f"{100 * s.behind:.0f} % of the ROI lies behind the farthest surface the prior "
                               f"admits ({1000 * (s.d - d_pred):+.0f} mm from the prediction): that surface is "
                               "clutter in front of the wall, and the wall is not where the prior admits it",
                               "behind" if evidence == "behind" else "", len(surfaces))
    best = max(clear, key=lambda t: int(t.mask.sum()))
    rivals = [s for s in clear if s is not best and not _same_surface(s, best, sub)]
    if rivals:
        r = rivals[0]
        return _Identification(None, f"ambiguous: two surfaces with nothing behind them could be the wall "
                               f"({1000 * (best.d - d_pred):+.0f} and {1000 * (r.d - d_pred):+.0f} mm from the "
                               "prediction)", "", len(surfaces))
    return _Identification(best, "ok", "", len(surfaces))


def _rear_most_dense(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, n: np.ndarray, d: float, params: FitParams,
                     pi_pred: np.ndarray, behind: int) -> Optional[str]:
    """Why the chosen surface is not the rear-most thing of the ROI on a denser sample (None: it is).
    ``behind``: how many of that sample (every :func:`_dense_stride`-th point) lie behind it by
    more than the margin, before the prior's window (what the fit's tail counted)."""
    b = _behind_share(rx, ry, z, _dense_stride(len(z), params), n, d, pi_pred, params, params.rear_fraction_dense,
                      behind)
    if b < params.rear_fraction_dense:
        return None
    return (f"{100 * b:.1f} % of the ROI lies behind the rear-most surface the prior admits "
            f"({1000 * (d - float(pi_pred[3])):+.0f} mm from the prediction): it is clutter in front of the wall, and too little "
            "of the wall itself is visible to fit")


def _dense_stride(N: int, params: FitParams) -> int:
    """Every k-th ROI point: twice identification's density, for the rear-most check."""
    return max(1, -(-N // (2 * params.sample)))


@dataclass
class _Tail:
    """What the fit computes after identification, whatever its verdict (fit_kernels.fit_tail in
    one compiled call, :func:`_tail` here): the refitted plane, its inliers, how many of the dense
    sample lie behind it, its covariance and information over (theta1, theta2, d) (None: a
    degenerate inlier set), and sums over every k-th inlier."""

    n: np.ndarray
    d: float
    mask: np.ndarray
    count: int
    chi2: float
    behind: int
    basis: np.ndarray
    cov: Optional[np.ndarray]
    info: Optional[np.ndarray]
    k_in: int
    sums: np.ndarray  # sum P (3), sum z^2, sum a, sum a^2, sum b, sum b^2 (a, b: along h and v)
    halves: Optional[Tuple[np.ndarray, ...]]  # _flat_verdict's sums per half, or None


def _tail(rx: np.ndarray, ry: np.ndarray, y: np.ndarray, z: np.ndarray, q: np.ndarray, stride: int, params: FitParams,
          up: Optional[np.ndarray], flat: bool) -> _Tail:
    """The refit of plane q (every ``stride``-th point first, then all), the dense sample's points
    behind it, its covariance with the depth unit's pattern, and the summary of every k-th inlier
    (``flat``: with the half-patch sums of the flatness check). The reference of fit_kernels.fit_tail."""
    N = len(z)
    q, H, mask, chi2, shift = _refit(rx, ry, y, q, stride, params)
    count = int(mask.sum())
    # Written out (not q @ q, BLAS's order): the kernel repeats it to the bit.
    qn = math.sqrt(float(q[0]) * float(q[0]) + float(q[1]) * float(q[1]) + float(q[2]) * float(q[2]))
    n, d = -q / qn, 1.0 / qn
    kb = _dense_stride(N, params)
    behind = int(np.count_nonzero(_behind_mask(rx[::kb], ry[::kb], z[::kb], n, d, params)))
    # Information over (theta1, theta2, d), the normal turned towards e1, e2 and the offset:
    # q = -n / d moves by dq = -(theta1 e1 + theta2 e2) / d + n dd / d^2.
    B = _tangent_basis(n)
    # More scatter than the noise model predicts (calibration, unmodelled noise) widens the
    # covariance; less never narrows it below the model.
    scale = max(chi2 / max(count - 3, 1), 1.0)
    Jq = np.column_stack([-B[0] / d, -B[1] / d, n / (d * d)])
    cov = info = None
    try:
        Hi = np.linalg.inv(H)
        Jqi = np.linalg.inv(Jq)
        cov = Jqi @ Hi @ Jqi.T * scale
        if shift is not None:
            cov += _quantisation_cov(rx, ry, shift[0], shift[1], Hi, Jqi, params)
        info = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        cov = info = None
    # What the inliers look like (every k-th of them): where they are, how deep, how wide.
    h = unit(cross(up, n)) if up is not None else B[0]
    v = cross(n, h)
    sl = slice(None, None, max(1, N // (2 * params.sample)))
    m_s = mask[sl]
    zs = z[sl][m_s]
    P_in = np.vstack([rx[sl][m_s] * zs, ry[sl][m_s] * zs, zs])
    a, b = h @ P_in, v @ P_in
    sums = np.r_[P_in.sum(axis=1), zs @ zs, a.sum(), a @ a, b.sum(), b @ b]
    halves = _half_sums(P_in, a, n, d) if flat else None
    return _Tail(n, d, mask, count, chi2, behind, B, cov, info, P_in.shape[1], sums, halves)


def fit_plane(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, pi_pred: np.ndarray, params: FitParams,
              start: Optional[Tuple[np.ndarray, float]] = None) -> PlaneFit:
    """Identify and fit the map plane predicted as ``pi_pred`` (n towards the camera) in the ROI
    pixels given by their rays (x/z and y/z, (N,) each) and measured depths z (m, (N,), all > 0).

    ``start``: this surface's fit (n, d) from the same frame on an overlapping ROI (the
    localizer's previous pass). It is kept only if it is still the rear-most surface the prior
    admits on the new ROI; otherwise the wall is identified again."""
    N = len(z)
    if N < max(params.min_inliers, 3):
        return PlaneFit(False, f"too few ROI points ({N} < {params.min_inliers})")
    n_pred, d_pred = pi_pred[:3], float(pi_pred[3])
    up = None if params.up is None else np.asarray(params.up, float)
    if start is not None:
        n, d = np.asarray(start[0], float), float(start[1])
        if not (math.acos(clip_unit(n @ n_pred)) <= params.angle_gate
                and _tilt(up, n, n_pred) <= params.tilt_gate and abs(d - d_pred) <= params.offset_gate):
            start = None
    surfaces = 0
    if start is None:
        ident = None
        if fit_kernels.backend() == "numba":
            # Most walls: one surface holds nearly all of the ROI, and the prior admits it.
            one = fit_kernels.one_surface(rx, ry, z, _TABLE, params)
            if one is not None:
                only = _Surface(one[0], one[1], np.zeros(0, bool), refined=False)
                if _admissible(only, pi_pred, up, params):
                    ident = _Identification(only, "ok", "", 1)
        if ident is None:
            ident = identify(_subsample(rx, ry, z, params), pi_pred, params)
        surfaces = ident.surfaces
        if ident.surface is None:
            return PlaneFit(False, ident.reason, evidence=ident.evidence, surfaces=surfaces)
        n, d = ident.surface.n, ident.surface.d
    # Solve on every k-th point, then on all points: each stage starts within a few of its own
    # standard deviations, so its band is nearly final and one or two solves suffice; the full
    # set's last solve gives the information.
    k = N // (4 * params.sample) if start is None else 0
    y = 1.0 / z
    q = -n / d
    flat = start is None  # (a surface kept from the last pass was checked for flatness there, on an overlapping ROI)
    if fit_kernels.backend() == "numba":
        t = fit_kernels.fit_tail(rx, ry, y, z, q, k, params, up, flat)
    else:
        t = _tail(rx, ry, y, z, q, k, params, up, flat)
    n, d, count = t.n, t.d, t.count
    # Nothing of a wall's ROI lies behind it: checked on more points than identification saw, with
    # the plane fitted to all of them.
    why = _rear_most_dense(rx, ry, z, n, d, params, pi_pred, t.behind)
    if why is not None:
        if start is not None:  # the last pass's surface is not the rear-most one here: identify afresh
            return fit_plane(rx, ry, z, pi_pred, params)
        return PlaneFit(False, why, n, d, count, surfaces=surfaces)
    ang = math.acos(clip_unit(n @ n_pred))
    off = d - d_pred
    if count < params.min_inliers:
        return PlaneFit(False, f"too few inliers ({count} < {params.min_inliers}): the wall's visible part is too small",
                        n, d, count, angle_to_prediction=ang, offset_to_prediction=off, surfaces=surfaces)
    if count < params.min_inlier_fraction * N:
        return PlaneFit(False, f"the rear-most plane within the gates explains only {100.0 * count / N:.0f} % of the "
                               "ROI's points: not enough of this wall is visible", n, d, count, angle_to_prediction=ang,
                        offset_to_prediction=off, surfaces=surfaces)
    tilt = _tilt(up, n, n_pred)
    if ang > params.angle_gate or abs(off) > params.offset_gate or tilt > params.tilt_gate:
        return PlaneFit(False, f"fit disagrees with the map: normal {math.degrees(ang):.1f} deg (tilt "
                               f"{math.degrees(tilt):.1f} deg), offset {off * 1000:.0f} mm from prediction", n, d, count,
                        angle_to_prediction=ang, offset_to_prediction=off, surfaces=surfaces)
    if t.cov is None:
        return PlaneFit(False, "degenerate inlier set (all points on a line)", n, d, count)
    chi2_red = t.chi2 / max(count - 3, 1)
    k_in, sums = t.k_in, t.sums
    centroid = sums[:3] / k_in
    z2 = float(sums[3]) / k_in
    sa, saa, sb, sbb = float(sums[4]), float(sums[5]), float(sums[6]), float(sums[7])
    lateral = math.sqrt(max(saa / k_in - (sa / k_in) ** 2, 0.0))
    vertical = math.sqrt(max(sbb / k_in - (sb / k_in) ** 2, 0.0))
    why = None if t.halves is None else _flat_verdict(*t.halves, n, z2, params)
    if why is not None:
        return PlaneFit(False, why, n, d, count, angle_to_prediction=ang, offset_to_prediction=off, surfaces=surfaces)
    if up is not None:
        sd = params.systematic_px / params.noise_fx_b * z2 * abs(float(n[2]))
        allowed = math.radians(1.0) + 3.0 * math.hypot(params.tilt_sigma, sd / max(math.sqrt(3.0) * vertical, 0.1))
        if tilt > allowed:
            return PlaneFit(False, f"the surface is tilted {math.degrees(tilt):.1f} deg from the wall (at most "
                                   f"{math.degrees(allowed):.1f} deg for a wall seen like this): a board or panel "
                                   "leaning in front of it, not the wall", n, d, count, angle_to_prediction=ang,
                            offset_to_prediction=off, surfaces=surfaces)
    # Scatter the noise model does not explain does not average down: if the surface is thicker
    # than the noise, where in that thickness the wall is stays unknown. (chi2_red of a pure noise
    # fit is a little under 1: the band and the Huber loss trim its tails.)
    sig_n = depth_sigma_scalar(math.sqrt(z2), params) * abs(float(n[2]))
    excess = max(chi2_red - 1.1, 0.0) * sig_n * sig_n
    return PlaneFit(True, "ok", n, d, count, t.mask, t.info, t.cov, t.basis, math.sqrt(chi2_red), ang, off, "",
                    surfaces, excess, centroid, z2, lateral, vertical)


FLAT_SLOPE = math.radians(0.5)  # what a built wall's bow may turn one half of a patch against the other


def _half_sums(P_in: np.ndarray, along: np.ndarray, n: np.ndarray, d: float) -> Optional[Tuple[np.ndarray, ...]]:
    """The flatness check's sums per half of the patch along the wall (None under 40 inliers).
    Where another surface meets the wall at a small angle (a door swung back against it, a board
    leaning on it), the inlier band takes both and the fit settles between them: the two halves
    of the patch then slope against the plane in opposite directions (:func:`_flat_verdict`)."""
    k = P_in.shape[1]
    if k < 40:
        return None
    res = n @ P_in + d  # signed distance of each inlier from the plane
    a = along - median(along)  # halves of equal support: a wedge turns them against each other
    side = (a > 0).astype(np.intp)
    # Per half: count and the sums a least-squares slope needs, in one pass each.
    cnt = np.bincount(side, minlength=2).astype(float)
    sa, sr = np.bincount(side, a, 2), np.bincount(side, res, 2)
    saa, sar = np.bincount(side, a * a, 2), np.bincount(side, a * res, 2)
    return cnt, sa, sr, saa, sar


def _flat_verdict(cnt: np.ndarray, sa: np.ndarray, sr: np.ndarray, saa: np.ndarray, sar: np.ndarray, n: np.ndarray,
                  z2: float, params: FitParams) -> Optional[str]:
    """Why the inliers are not one flat surface (None: they are), from :func:`_half_sums`: per
    half (2,) each, the count, and the sums of a, the residual r, a^2 and a r, with a the position
    along the wall from the median. The halves may turn against each other by a built wall's bow
    plus what noise and the matcher's systematic error explain."""
    # In floats: two halves are not worth numpy's per-call cost (the same roundings).
    (c0, c1), (a0, a1), (r0, r1) = cnt.tolist(), sa.tolist(), sr.tolist()
    (aa0, aa1), (ar0, ar1) = saa.tolist(), sar.tolist()
    if min(c0, c1) < 20:
        return None
    var0, var1 = aa0 / c0 - (a0 / c0) * (a0 / c0), aa1 / c1 - (a1 / c1) * (a1 / c1)
    if min(var0, var1) <= 1e-8:
        return None
    slope0, slope1 = (ar0 / c0 - a0 * r0 / (c0 * c0)) / var0, (ar1 / c1 - a1 * r1 / (c1 * c1)) / var1
    sp0, sp1 = math.sqrt(var0), math.sqrt(var1)
    sigma = depth_sigma_scalar(math.sqrt(z2), params) * abs(float(n[2]))
    sys_z = params.systematic_px / params.noise_fx_b * z2 * abs(float(n[2]))
    # Samples are several matcher windows apart: nearly independent (allow 1.5 times their spread).
    noise = math.hypot(1.5 * sigma / (math.sqrt(c0) * sp0), 1.5 * sigma / (math.sqrt(c1) * sp1))
    allowed = FLAT_SLOPE + 3.0 * noise + 2.0 * sys_z / max(min(sp0, sp1), 0.05)
    turn = abs(math.atan(slope0) - math.atan(slope1))
    if turn <= allowed:
        return None
    return (f"not one flat surface: its two halves along the wall turn {math.degrees(turn):.1f} deg against each "
            f"other (at most {math.degrees(allowed):.1f} deg for one wall): another surface meets it at a small angle "
            "(a door swung back, a leaning board)")


def _refit(rx: np.ndarray, ry: np.ndarray, y: np.ndarray, q: np.ndarray, stride: int, params: FitParams):
    """The refit of plane q on points with rays (rx, ry) and inverse depths y: with ``stride`` >= 2
    first on every stride-th point, then on all, each stage a few :func:`_solve_step` until one
    moves the plane by under ``CONVERGED``. Returns the final q and the last solve's (H, inlier
    mask, chi2, shift), the shift arrays when the frame has a depth unit. The reference of
    fit_kernels.fit_tail (with the rest of the tail)."""
    stages = [(rx[::stride], ry[::stride], y[::stride])] if stride >= 2 else []
    stages.append((rx, ry, y))
    for i, (sx, sy, sinv) in enumerate(stages):
        last = i == len(stages) - 1
        for _ in range(STAGE_ITERATIONS):
            step, H, mask, chi2, shift = _solve_step(sx, sy, sinv, q, params, last and params.depth_unit > 0)
            q = q + step
            if step @ H @ step < CONVERGED:
                break
    return q, H, mask, chi2, shift


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
