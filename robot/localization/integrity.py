"""Integrity of a localization: an honest covariance, the consistency checks and protection levels
(docs/localization-integrity.md). numpy; the stack, the subsets' solutions and the separation
statistics also run as compiled kernels (integrity_kernels, numba, when the plane fit's backend is
numba), which the numpy code here is the reference for.

Each fitted plane gives a measurement y = (d_R, psi_R, tilt_R) in the robot frame: the offset
of the plane from the robot origin, the heading of its normal and its elevation. For a map plane
(n_G, d_G) at pose (x, y, phi) the model is linear,

    h(x) = (n_Gx x + n_Gy y + d_G,  atan2(n_Gy, n_Gx) - phi,  asin(n_Gz)),

and its errors are of two kinds:

* pixel noise, from the plane fit's own covariance (widened for the matcher's correlation
  between neighbouring pixels), plus per-plane errors no second plane shares: the matcher's
  systematic disparity error (a low-frequency wave and the subpixel non-linearity, growing
  with z^2) and any scatter the noise model does not explain;
* errors shared between planes that more pixels do not average down: each camera's depth scale
  (its offset d_C grows by the scale error times d_C), each camera's mount (position and
  angles, the same for all its planes), and each wall's as-built deviation from the drawing
  (its offset, its direction, its plumb; the same for both cameras seeing it).

The shared errors make the measurements of one frame correlated, so the pose is their
generalised least-squares solution with the full covariance R = R_own + G Sigma G^T (G: each
measurement's sensitivity to each shared error). The tilt row carries no pose information,
but its correlation with the others (through the fit and the mount) is used, and it checks the
mount.

Checks and bounds on top of that:

* consistency: the residual chi-square of the measurements; and leave-one-out, the pose without
  one plane against the pose with all (solution separation). A plane whose removal alone makes
  the rest agree is excluded and named; disagreement that no single exclusion explains makes
  the result inconsistent.
* protection levels: bounds the error exceeds with probability at most ``risk``, under the
  fault-free hypothesis and under each hypothesis "plane j is wrong, and the checks did not
  notice". Under hypothesis j the all-in error is the separation s_j (known) plus the error of
  the solution without j, so PL_j = |s_j| + k sigma_j; the protection level is the largest. In
  directions the planes without j do not observe, that solution is the coarse pose with its
  covariance: a wrong plane there is bounded only by the prior.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import wrap_angle
from robot.base.stats import chi2_quantile
from robot.localization import integrity_kernels

# Which directions are observable is decided in (x, y, phi) with 1 rad counted as 1 m.
UNOBSERVED_VARIANCE = 1.0  # m^2 or rad^2 floor for a direction no plane constrains
CAMERA_PARAMS = 7  # depth scale, mount position (3), mount angles (3)
_EYE3 = np.eye(3)
_FLOOR3 = _EYE3 * 1e-14  # keeps a plane's own covariance invertible where a row is (nearly) exact
_DIAGONAL_FLOOR = 1e-14  # keeps R positive definite when a plane's rows are (nearly) exact
PLANE_PARAMS = 3  # offset along the normal, turn about the vertical, out of plumb


@dataclass(frozen=True)
class ErrorModel:
    """The systematic errors a measurement carries besides pixel noise (LocalizerConfig)."""

    depth_scale_std: float = 0.01
    mount_position_std: float = 0.003  # m per axis
    mount_angle_std: float = math.radians(0.3)  # rad per axis
    disparity_systematic_px: float = 0.02
    noise_correlation_px: float = 1.5

    @classmethod
    def from_config(cls, params) -> ErrorModel:
        return cls(params.depth_scale_std, params.mount_position_std, math.radians(params.mount_angle_std_deg),
                   params.depth_systematic_px, params.noise_correlation_px)

    def correlation_inflation(self, stride_full_px: float) -> float:
        """Variance factor of a fit over samples ``stride_full_px`` apart (full-resolution pixels) when
        the noise is correlated over a Gaussian window of std ``noise_correlation_px``: the effective
        number of independent samples is the area over 4 pi sigma^2, not the sample count."""
        s = max(float(stride_full_px), 1e-6)
        return max(1.0, 4.0 * math.pi * self.noise_correlation_px**2 / (s * s))


@dataclass
class Observation:
    """One fitted plane as a measurement of the pose."""

    plane_id: str
    camera: str
    y: np.ndarray  # (3,) d_R (m), psi_R (rad), tilt_R (rad)
    H: np.ndarray  # (3, 3) dy/d(x, y, phi)
    h0: np.ndarray  # (3,) y = H x + h0 for the map plane
    R_own: np.ndarray  # (3, 3) pixel noise and errors no other measurement shares
    R_weight: np.ndarray  # (3, 3) the part of R_own the estimate weights by (see Stack.solve)
    G_camera: np.ndarray  # (3, 7) sensitivity to the camera's scale, mount position, mount angles
    G_plane: np.ndarray  # (3, 3) sensitivity to the plane's offset, turn and plumb
    plane_std: np.ndarray  # (3,) std of those plane errors

    def predict(self, x: np.ndarray) -> np.ndarray:
        out = self.H @ x + self.h0
        out[1] = float(wrap_angle(out[1]))
        return out


def observation(plane_id: str, camera: str, n_ground: np.ndarray, d_ground: float, n_robot: np.ndarray,
                d_robot: float, d_camera: float, t_robot_camera: np.ndarray, J_fit: np.ndarray, fit_cov: np.ndarray,
                inflation: float, own_extra: np.ndarray, tolerance: float, wall_length: float, height: float,
                lever_ground: np.ndarray, own_unweighted: Optional[np.ndarray] = None) -> Optional[Observation]:
    """The measurement of one fitted plane (see the module docstring), or None for a plane whose
    normal is too close to vertical to have a heading (it says nothing about x, y, phi).

    ``J_fit``: d y / d (fit's theta1, theta2, d_C); ``own_extra``: (3, 3) error of this plane alone
    that its fit shows (scatter beyond the noise model), weighted by like pixel noise;
    ``own_unweighted``: errors of this plane alone that are there whatever the fit shows (the
    matcher's systematic error, the built wall's local shape), in the covariance only;
    ``lever_ground``: robot position minus the fitted patch's centre in G (a turned wall moves its
    offset by the turn times that lever along the wall)."""
    n0, n1, n2 = np.asarray(n_robot, float)[:3].tolist()
    h2 = n0 * n0 + n1 * n1
    g0, g1, g2 = np.asarray(n_ground, float)[:3].tolist()
    gh = math.hypot(g0, g1)
    if h2 < 0.3**2 or gh < 0.3:
        return None
    R_weight = J_fit @ fit_cov @ J_fit.T * inflation + own_extra
    R_own = R_weight if own_unweighted is None else R_weight + own_unweighted
    # Camera: the depth scale stretches d_C; a mount offset dt moves d_R by dt . n; a mount turn
    # dtheta (robot frame) turns the measured normal by n x dtheta, so psi by (n2 n0, n2 n1, -h2) / h2
    # . dtheta and the elevation by (-n1, n0, 0) / sqrt(h2) . dtheta, and moves d_R by (n x t) . dtheta.
    t0, t1, t2 = np.asarray(t_robot_camera, float)[:3].tolist()
    hs = math.sqrt(h2)
    # Plane: built off the drawing by an offset, turned about the vertical through the patch, out of plumb.
    lever_along = (-g1 * float(lever_ground[0]) + g0 * float(lever_ground[1])) / gh
    tol = max(float(tolerance), 0.0)
    # Every small array of the measurement in one buffer (one numpy call, not six).
    buf = np.array([
        d_robot, math.atan2(n1, n0), math.asin(max(-1.0, min(1.0, n2))),  # y
        g0, g1, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0,  # H
        d_ground, math.atan2(g1, g0), math.asin(max(-1.0, min(1.0, g2))),  # h0
        d_camera, n0, n1, n2, n1 * t2 - n2 * t1, n2 * t0 - n0 * t2, n0 * t1 - n1 * t0,  # G_cam
        0.0, 0.0, 0.0, 0.0, n2 * n0 / h2, n2 * n1 / h2, -1.0,
        0.0, 0.0, 0.0, 0.0, -n1 / hs, n0 / hs, 0.0,
        -1.0, lever_along, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0,  # G_pl
        tol, tol / max(wall_length, 1.0), tol / max(height, 1.0)], float)  # plane_std
    y, H, h0 = buf[0:3], buf[3:12].reshape(3, 3), buf[12:15]
    G_cam, G_pl, plane_std = buf[15:36].reshape(3, 7), buf[36:45].reshape(3, 3), buf[45:48]
    return Observation(plane_id, camera, y, H, h0, R_own, R_weight, G_cam, G_pl, plane_std)


@dataclass
class Solution:
    """Generalised least squares over a subset of the observations."""

    members: Tuple[int, ...]
    x: np.ndarray  # (3,) pose; unobservable directions held at the linearisation point (the coarse pose)
    P_obs: np.ndarray  # (3, 3) covariance in the observable directions only
    V_obs: np.ndarray  # (3, k) observable directions, orthonormal in (x, y, phi)
    V_unobs: np.ndarray  # (3, 3 - k)
    chi2: float
    dof: int
    A: Optional[np.ndarray] = None  # (3, 3m) gain over every observation's rows (0 outside the members): dx = A r
    k_obs: int = 0
    V_weak: Optional[np.ndarray] = None  # (3, w) observed directions known no better than unobservable_std
    # Where the compiled kernels solved it, whose eigenvectors' signs are their own: the information
    # matrix and the (ascending) eigenvector indices of V_unobs then V_weak, to report numpy's.
    eig_source: Optional[Tuple[np.ndarray, Tuple[int, ...]]] = field(default=None, repr=False, compare=False)

    @property
    def fully_observed(self) -> bool:
        return self.V_unobs.shape[1] == 0 and (self.V_weak is None or self.V_weak.shape[1] == 0)

    def unobservable_directions(self) -> List[np.ndarray]:
        """Unit directions in (x, y, phi) that the members do not observe, or only weakly (the
        eigenvectors numpy's eigh gives, signs included, whichever backend solved it)."""
        if self.eig_source is not None:
            info, cols = self.eig_source
            W = np.linalg.eigh(info)[1]
            return [W[:, j].copy() for j in cols]
        cols = [self.V_unobs] + ([] if self.V_weak is None else [self.V_weak])
        return [V[:, j].copy() for V in cols for j in range(V.shape[1])]

    def covariance(self, coarse_cov: Optional[np.ndarray], floor: float = UNOBSERVED_VARIANCE) -> np.ndarray:
        """P_obs plus the prior (at least ``floor``) in the unobservable directions. The reported
        covariance keeps the floor (an unobserved direction says so loudly); a protection level
        takes the prior as it is, which is what the caller vouches for."""
        C = self.P_obs.copy()
        for j in range(self.V_unobs.shape[1]):
            v = self.V_unobs[:, j]
            prior = floor
            if coarse_cov is not None:
                prior = max(prior, float(v @ coarse_cov @ v))
            C += np.outer(v, v) * prior
        return C


@dataclass
class Integrity:
    """What the checks found and the protection levels of the reported solution."""

    status: str  # ok | degenerate | inconsistent
    solution: Solution
    cov: np.ndarray
    excluded: List[Tuple[int, str]] = field(default_factory=list)  # (observation index, why)
    reason: str = ""
    horizontal_pl: float = math.inf
    heading_pl: float = math.inf
    chi2: float = 0.0
    dof: int = 0
    systematic_cov: Optional[np.ndarray] = None  # (3, 3): the part of cov from the shared errors
    separation_h: float = 0.0  # m: largest horizontal separation of a leave-one-out solution from the reported one
    separation_heading: float = 0.0  # rad
    # The largest protection level (m, rad) among the hypotheses that only the prior bounds: a
    # wall whose leaving out leaves a direction unobserved, so that the coarse pose decides it
    # (0: the walls bound every hypothesis by themselves). Such a bound is worth what the prior
    # is: nothing new when the prior is the filter's own pose, built on that same wall.
    prior_bound_h: float = 0.0
    prior_bound_heading: float = 0.0
    # Each such hypothesis: (the map walls it takes for wrong, sorted; the unobserved directions
    # in (x, y, phi), unit 3-vectors; its horizontal and heading protection levels). The fusion
    # lifts a bound where walls it fused earlier observe those directions (robot.fusion.quality).
    prior_bounded: List[Tuple[Tuple[str, ...], List[List[float]], float, float]] = field(default_factory=list)


_NO_COLUMNS = np.zeros((3, 0))
_NO_COLUMNS.setflags(write=False)
_COLUMNS: Dict[bytes, Tuple[object, object, object, int, Tuple[int, ...]]] = {}


def _columns(observed: bytes, weak: bytes) -> Tuple[object, object, object, int, Tuple[int, ...]]:
    """For 3-column masks of observed and weak eigenvectors: how to take the observed, the other
    and the weak columns (... : all, None: none, a slice where they are contiguous: a view, else
    an index), the observed count, and the indices of the others then the weak ones."""
    key = observed + weak
    cols = _COLUMNS.get(key)
    if cols is None:
        def index(idx: List[int]) -> object:
            if not idx:
                return None
            if idx == list(range(idx[0], idx[-1] + 1)):
                return slice(idx[0], idx[-1] + 1)
            return np.array(idx, np.intp)
        on = [i for i in range(3) if observed[i]]
        off = [i for i in range(3) if not observed[i]]
        wk = [i for i in range(3) if weak[i]]
        cols = _COLUMNS[key] = (... if len(on) == 3 else index(on), index(off), index(wk), len(on), tuple(off + wk))
    return cols


class Stack:
    """Observations of one localization with their joint covariance."""

    def __init__(self, obs: Sequence[Observation], model: ErrorModel):
        self.obs = list(obs)
        m = len(self.obs)
        n = 3 * m
        cams = sorted({o.camera for o in self.obs})
        planes = sorted({o.plane_id for o in self.obs})
        cam_col = {c: CAMERA_PARAMS * i for i, c in enumerate(cams)}
        plane_col = {p: CAMERA_PARAMS * len(cams) + PLANE_PARAMS * i for i, p in enumerate(planes)}
        n_par = CAMERA_PARAMS * len(cams) + PLANE_PARAMS * len(planes)
        cam_std = np.array([model.depth_scale_std] + [model.mount_position_std] * 3 + [model.mount_angle_std] * 3)
        self._eye: Optional[np.ndarray] = None  # the numpy solve's identity for rows outside a subset
        self._residual_at: Tuple[bytes, np.ndarray] = (b"", np.zeros(0))
        if not m:
            self.y, self.H, self.h0 = np.zeros(0), np.zeros((0, 3)), np.zeros(0)
            self.H_blocks, self.W_own = np.zeros((0, 3, 3)), np.zeros((0, 3, 3))
            self.G_sys, self.R_sys, self.R = np.zeros((0, n_par)), np.zeros((0, 0)), np.zeros((0, 0))
            self._HtW = np.zeros((3, 0))
            return
        if integrity_kernels.compiled():
            # Each observation's arrays in three stacks (the numpy calls, not the arithmetic, cost here).
            (self.y, self.h0, self.H_blocks, self.H, self.G_sys, self.R_sys, self.R, self.W_own,
             self._HtW) = integrity_kernels.stack(
                np.array([(o.H, o.R_own, o.R_weight, o.G_plane) for o in self.obs], float),
                np.array([(o.y, o.h0, o.plane_std) for o in self.obs], float),
                np.array([o.G_camera for o in self.obs], float),
                np.array([(cam_col[o.camera], plane_col[o.plane_id]) for o in self.obs], np.intp), n_par, cam_std,
                float(_FLOOR3[0, 0]), _DIAGONAL_FLOOR)
            return
        self.y = np.concatenate([o.y for o in self.obs])
        self.H_blocks = np.array([o.H for o in self.obs])
        self.H = self.H_blocks.reshape(n, 3)
        self.h0 = np.concatenate([o.h0 for o in self.obs])
        G = np.zeros((n, n_par))
        sig = np.zeros(n_par)
        R = np.zeros((n, n))
        for i, o in enumerate(self.obs):
            r = slice(3 * i, 3 * i + 3)
            R[r, r] = o.R_own
            c, p = cam_col[o.camera], plane_col[o.plane_id]
            G[r, c:c + CAMERA_PARAMS] = o.G_camera
            G[r, p:p + PLANE_PARAMS] = o.G_plane
            sig[c:c + CAMERA_PARAMS] = cam_std
            sig[p:p + PLANE_PARAMS] = np.maximum(sig[p:p + PLANE_PARAMS], o.plane_std)
        self.W_own = np.linalg.inv(np.array([o.R_weight for o in self.obs]) + _FLOOR3)
        self.G_sys = G * sig
        self.R_sys = self.G_sys @ self.G_sys.T
        self.R = R + self.R_sys
        self.R.flat[::n + 1] += _DIAGONAL_FLOOR
        # Each plane's weighted sensitivity H_i^T W_i side by side (3, 3m), for every solve.
        self._HtW = (self.H_blocks.transpose(0, 2, 1) @ self.W_own).transpose(1, 0, 2).reshape(3, n)

    def __len__(self) -> int:
        return len(self.obs)

    def rows(self, members: Sequence[int]) -> np.ndarray:
        return (3 * np.asarray(members, dtype=np.intp)[:, None] + np.arange(3)).ravel()

    def residual(self, x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        r = self.y[rows] - (self.H[rows] @ x + self.h0[rows])
        psi = rows % 3 == 1
        r[psi] = np.remainder(r[psi] + math.pi, 2 * math.pi) - math.pi
        return r

    def _residual_all(self, x: np.ndarray) -> np.ndarray:
        """Every row's residual at ``x`` (the checks solve every subset at the same coarse pose)."""
        key = x.tobytes()
        if self._residual_at[0] != key:
            r = self.y - (self.H @ x + self.h0)
            r[1::3] = np.remainder(r[1::3] + math.pi, 2 * math.pi) - math.pi
            self._residual_at = (key, r)
        return self._residual_at[1]

    def solve(self, members: Sequence[int], x_lin: np.ndarray, unobservable_std: float,
              prior_cov: Optional[np.ndarray] = None) -> Solution:
        """The pose from the observations ``members`` (see :meth:`solve_many`)."""
        return self.solve_many([members], x_lin, unobservable_std, prior_cov)[0]

    def solve_many(self, subsets: Sequence[Sequence[int]], x_lin: np.ndarray, unobservable_std: float,
                   prior_cov: Optional[np.ndarray] = None) -> List[Solution]:
        """The pose from each subset of the observations, linearised at ``x_lin`` (exact: the model
        is linear), all subsets solved together as stacked arrays.

        A direction is estimated when the subset knows it better than ``unobservable_std`` or than
        the prior ``prior_cov`` does (a far wall seen through an uncalibrated depth scale is still
        better than a coarse guess); otherwise it stays at ``x_lin``. An estimated direction known
        no better than ``unobservable_std`` is reported as weak.

        Which directions are observed, and the residual chi-square, come from the full covariance
        (generalised least squares). The estimate itself weights each plane by its own errors
        (pixel noise and the systematic terms no other plane shares): that is the best weighting
        once the shared errors are calibrated away, and it does not trade a precise wall for an
        imprecise one because both share a camera's scale. Its covariance is the sandwich of its
        gain around the full covariance, so it is honest whatever the weights."""
        x_lin = np.asarray(x_lin, float)
        B, m = len(subsets), len(self.obs)
        if B == 0:
            return []
        flat = bytearray(B * m)
        for b, sub in enumerate(subsets):
            for j in sub:
                if not 0 <= j < m:
                    raise IndexError(f"observation {j} of {m}")
                flat[b * m + j] = 1
        member = np.frombuffer(flat, np.bool_).reshape(B, m)
        prior = None if prior_cov is None else np.asarray(prior_cov, float)
        compiled = integrity_kernels.compiled()
        if compiled:
            info, _, V, obs, weak, _, chi2, A, X, P, _ = integrity_kernels.solve(
                self.R, self.H, self.y, self.h0, x_lin, self._HtW, member, unobservable_std**2,
                None if prior is None else np.ascontiguousarray(prior))
        else:
            _, V, obs, weak, chi2, A, dx, P = self._solve_subsets(member, self._residual_all(x_lin), unobservable_std,
                                                                  prior)
            X = x_lin + dx
            for b in range(B):
                X[b, 2] = wrap_angle(X[b, 2])
        observed, weakly, chi2s = obs.tobytes(), weak.tobytes(), chi2.tolist()
        out = []
        for b, (sub, x, Pb, Vb, Ab) in enumerate(zip(subsets, X, P, V, A)):
            on, off, wk, k, reported = _columns(observed[3 * b:3 * b + 3], weakly[3 * b:3 * b + 3])
            out.append(Solution(tuple(sub), x, Pb, Vb if on is ... else _NO_COLUMNS if on is None else Vb[:, on],
                                _NO_COLUMNS if off is None else Vb[:, off], max(chi2s[b], 0.0), 3 * len(sub) - k, Ab, k,
                                _NO_COLUMNS if wk is None else Vb[:, wk],
                                (info[b], reported) if compiled and reported else None))
        return out

    def _solve_subsets(self, member: np.ndarray, r_all: np.ndarray, unobservable_std: float,
                       prior: Optional[np.ndarray]) -> Tuple[np.ndarray, ...]:
        """solve_many's algebra on (B, m) membership masks: (lam, V, observed, weak, chi2, A, dx, P),
        the reference the compiled kernel (integrity_kernels) follows."""
        # Every subset over all rows: a row outside it is decoupled (unit variance, no
        # correlation), has no sensitivity to the pose and no residual, so it counts for nothing.
        on = np.repeat(member, 3, axis=1)  # (B, 3m)
        if self._eye is None:
            self._eye = np.eye(len(self.R))
        Ri = np.linalg.inv(np.where(on[:, :, None] & on[:, None, :], self.R, self._eye))
        H = self.H * on[:, :, None]  # (B, 3m, 3)
        r = r_all * on
        HtRi = H.transpose(0, 2, 1) @ Ri
        info = HtRi @ H
        lam, V = np.linalg.eigh(0.5 * (info + info.transpose(0, 2, 1)))
        Vt = V.transpose(0, 2, 1)
        floor = unobservable_std**2
        if prior is not None:
            floor = np.maximum(floor, np.einsum("bji,jk,bki->bi", V, prior, V))
        obs = lam > 1.0 / floor  # (B, 3): estimated
        weak = obs & (lam < 1.0 / unobservable_std**2)
        # Generalised least squares only for the chi-square of the residuals.
        w = (Vt @ (HtRi @ r[:, :, None]))[:, :, 0]
        chi2 = np.einsum("bi,bij,bj->b", r, Ri, r) - np.sum(np.where(obs, w * w / np.where(obs, lam, 1.0), 0.0), axis=1)
        # The estimate, restricted to the observed directions (exactly: unobserved rows and
        # columns of the normal matrix in V's basis replaced by the identity, then dropped).
        HtW = self._HtW * on[:, None, :]  # (B, 3, 3m): 0 outside the subset
        keep = obs[:, :, None] & obs[:, None, :]
        Ti = np.linalg.inv(np.where(keep, Vt @ (HtW @ H) @ V, _EYE3)) * keep
        A = V @ Ti @ Vt @ HtW  # gain over all rows (0 outside the subset): dx = A r
        dx = (A @ r[:, :, None])[:, :, 0]
        P = A @ self.R @ A.transpose(0, 2, 1)
        return lam, V, obs, weak, chi2, A, dx, 0.5 * (P + P.transpose(0, 2, 1))


@functools.lru_cache(maxsize=256)
def normal_quantile(p: float) -> float:
    """z with P(Z > z) = p for a standard normal Z."""
    lo, hi = 0.0, 40.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if 0.5 * math.erfc(mid / math.sqrt(2.0)) > p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _separation_statistics(stack: Stack, sol_all: Solution, subs: Sequence[Solution]) -> Tuple[np.ndarray, np.ndarray]:
    """(s^T C^-1 s, dof) for each subset's solution: its separation s from the all-in one, in the
    directions the subset observes, against the separation's covariance C. Both solutions are
    linear in the residuals, s = (A_sub E - A_all) r, so C = (A_sub E - A_all) R (A_sub E - A_all)^T
    (whatever the weights: the all-in solution need not be efficient)."""
    B = len(subs)
    if B == 0:
        return np.zeros(0), np.zeros(0, np.intp)
    A = np.array([sub.A for sub in subs])  # (B, 3, 3m)
    V = np.zeros((B, 3, 3))  # each subset's observed directions first
    k_obs = [sub.k_obs for sub in subs]
    for b, sub in enumerate(subs):
        V[b, :, :k_obs[b]] = sub.V_obs
    sep = np.array([sub.x for sub in subs]) - sol_all.x  # (B, 3)
    for b in range(B):
        sep[b, 2] = float(wrap_angle(sep[b, 2]))
    if integrity_kernels.compiled():
        return integrity_kernels.separation(A, sol_all.A, V, np.array(k_obs, np.intp), sep, stack.R)
    return _separation_statistics_numpy(stack.R, A, sol_all.A, V, np.array(k_obs), sep)


def _separation_statistics_numpy(R: np.ndarray, A: np.ndarray, A_all: np.ndarray, V: np.ndarray, k_obs: np.ndarray,
                                 sep: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`_separation_statistics` on stacked arrays, the reference integrity_kernels follows."""
    keep = np.arange(3) < k_obs[:, None]  # (B, 3)
    Vt = V.transpose(0, 2, 1)
    T = Vt @ (A - A_all)  # (B, 3, 3m): the separation in each subset's observed directions
    C = np.where(keep[:, :, None] & keep[:, None, :], T @ R @ T.transpose(0, 2, 1), 0.0)
    u = (Vt @ sep[:, :, None])[:, :, 0] * keep
    lam, W = np.linalg.eigh(0.5 * (C + C.transpose(0, 2, 1)))
    ok = lam > 1e-9 * np.maximum(lam.max(axis=1, keepdims=True), 1e-30)
    z = (W.transpose(0, 2, 1) @ u[:, :, None])[:, :, 0]
    q = np.sum(np.where(ok, z * z / np.where(ok, lam, 1.0), 0.0), axis=1)
    return q, ok.sum(axis=1)


class Checker:
    """Consistency checks, exclusion and protection levels over a :class:`Stack`."""

    def __init__(self, stack: Stack, coarse: Sequence[float], coarse_cov: np.ndarray, unobservable_std: float,
                 false_alarm: float, risk: float):
        self.stack = stack
        self.coarse = np.asarray(coarse, float)
        self.coarse_cov = np.asarray(coarse_cov, float)
        self.unobservable_std = unobservable_std
        self.false_alarm = false_alarm
        self.risk = risk
        self._cache: Dict[Tuple[int, ...], Solution] = {}
        self._faults: Dict[Tuple[int, ...], List[Tuple[int, ...]]] = {}

    def solve(self, members: Sequence[int]) -> Solution:
        key = tuple(members)
        sol = self._cache.get(key)
        if sol is None:
            sol = self._cache[key] = self.stack.solve(key, self.coarse, self.unobservable_std, self.coarse_cov)
        return sol

    def faults(self, members: Sequence[int]) -> List[Tuple[int, ...]]:
        """The single faults the checks consider among ``members``: one observation is wrong (a
        surface taken for the wall it is not), or one map wall is (built off the drawing: every
        observation of it is off together)."""
        key = tuple(members)
        out = self._faults.get(key)
        if out is None:
            by_plane: Dict[str, List[int]] = {}
            for j in key:
                by_plane.setdefault(self.stack.obs[j].plane_id, []).append(j)
            out = self._faults[key] = [(j,) for j in key] + [tuple(g) for g in by_plane.values() if len(g) > 1]
        return list(out)

    def without(self, members: Sequence[int], faults: Sequence[Tuple[int, ...]]) -> List[Solution]:
        """The solution without each fault's observations (solved together with the members' own, cached)."""
        members = tuple(members)
        keys = [tuple([i for i in members if i not in f]) for f in faults]
        cache = self._cache
        missing = list(dict.fromkeys([k for k in [members] + keys if k not in cache]))
        if missing:
            for k, sol in zip(missing, self.stack.solve_many(missing, self.coarse, self.unobservable_std, self.coarse_cov)):
                cache[k] = sol
        return [cache[k] for k in keys]

    def agree_as_a_whole(self, sol: Solution) -> bool:
        """The residual chi-square test alone."""
        return sol.dof <= 0 or sol.chi2 <= chi2_quantile(1.0 - self.false_alarm, sol.dof)

    def _name(self, fault: Tuple[int, ...]) -> str:
        obs = [self.stack.obs[j] for j in fault]
        if len(obs) == 1:
            return f"{obs[0].plane_id} ({obs[0].camera})"
        return f"{obs[0].plane_id} (all its views)"

    def disagreement(self, members: Sequence[int]) -> Optional[str]:
        """Why the members do not agree with each other within their covariance (None: they do):
        the residual chi-square, or one fault's leave-out separation."""
        faults = self.faults(members) if len(members) > 1 else []
        subs = self.without(members, faults)
        sol = self.solve(members)
        if sol.dof > 0 and sol.chi2 > chi2_quantile(1.0 - self.false_alarm, sol.dof):
            return f"chi-square {sol.chi2:.1f} over {sol.dof} degrees of freedom"
        if not faults:
            return None
        p_each = self.false_alarm / len(faults)
        q, k = _separation_statistics(self.stack, sol, subs)
        for f, qf, kf in zip(faults, q, k):
            if kf and qf > chi2_quantile(1.0 - p_each, int(kf)):
                return f"without {self._name(f)} the pose moves by {math.sqrt(qf):.1f} sigma"
        return None

    def check(self, max_exclusions: int = 2) -> Integrity:
        """Exclude single faults while exactly one exclusion restores agreement; then bound."""
        members = list(range(len(self.stack)))
        excluded: List[Tuple[int, str]] = []
        rounds = 0
        reason = self.disagreement(members)
        while reason is not None:
            fixes = []
            if rounds < max_exclusions and len(members) > 1:
                for f in self.faults(members):
                    rest = [i for i in members if i not in f]
                    if self.solve(rest).dof > 0 and self.disagreement(rest) is None:
                        fixes.append(f)
            # A wall seen twice that explains it as a whole explains it also view by view: the
            # fault is the wall (or one of its views), keep the smallest set that restores agreement.
            fixes = [f for f in fixes if not any(set(g) < set(f) for g in fixes)] if len(fixes) > 1 else fixes
            if len(fixes) != 1:
                names = ", ".join(self._name(f) for f in fixes)
                why = (f"the planes disagree ({reason}) and no single plane explains it" if not fixes else
                       f"the planes disagree ({reason}) and leaving out any one of {names} explains it")
                sol = self.solve(members)
                return Integrity("inconsistent", sol, self.coarse_cov.copy(), excluded, why, math.inf, math.inf,
                                 sol.chi2, sol.dof)
            f = fixes[0]
            what = "it breaks" if len(f) == 1 else "the map's wall, in every view of it, breaks"
            excluded += [(j, f"left out: {what} the agreement of the others ({reason})") for j in f]
            members = [i for i in members if i not in f]
            rounds += 1
            reason = self.disagreement(members)
        sol = self.solve(members)
        cov = sol.covariance(self.coarse_cov)
        status = "ok" if sol.fully_observed else "degenerate"
        hpl, vpl, sep_h, sep_v, prior_h, prior_v, bounded = self.protection(members, sol, cov)
        sys_cov = sol.A @ self.stack.R_sys @ sol.A.T if members else None
        return Integrity(status, sol, cov, excluded, "", hpl, vpl, sol.chi2, sol.dof, sys_cov, sep_h, sep_v, prior_h,
                         prior_v, bounded)

    def protection(self, members: Sequence[int], sol: Solution, cov: np.ndarray) -> Tuple[
            float, float, float, float, float, float, List[Tuple[Tuple[str, ...], List[List[float]], float, float]]]:
        """(horizontal, heading) protection levels of ``sol`` at ``self.risk``: the largest bound
        over the fault-free hypothesis and each single-fault hypothesis (:meth:`faults`); the
        largest separations (horizontal, heading) of those hypotheses; the largest bounds
        (horizontal, heading) among the hypotheses whose solution leaves a direction to the prior
        (0 where there is none); and those hypotheses (:attr:`Integrity.prior_bounded`)."""
        k2 = math.sqrt(-2.0 * math.log(self.risk))  # P(|e| > k sqrt(lambda_max)) <= exp(-k^2 / 2) in 2-D
        k1 = normal_quantile(self.risk / 2.0)
        faults = self.faults(members)
        hyps = [sol] + self.without(members, faults)
        obs = self.stack.obs
        # A handful of hypotheses: plain floats, each operation as numpy's elementwise one.
        sep = (sol.x - np.array([h.x for h in hyps])).tolist()
        for s in sep[1:]:
            s[2] = wrap_angle(s[2])
        sep_h = np.hypot([s[0] for s in sep], [s[1] for s in sep]).tolist()
        hpl, vpl = [], []
        prior_h = prior_v = 0.0
        bounded = []
        for i, (h, s, sh) in enumerate(zip(hyps, sep, sep_h)):
            (c00, c01, _), (c10, c11, _), (_, _, c22) = _prior_covariance(h, self.coarse_cov)
            a, b, c = c00, 0.5 * (c01 + c10), c11
            # Largest eigenvalue of the 2x2 position block, in closed form.
            lam = 0.5 * (a + c) + math.sqrt(0.25 * ((a - c) * (a - c)) + b * b)
            hpl.append(sh + k2 * math.sqrt(max(lam, 0.0)))
            vpl.append(abs(s[2]) + k1 * math.sqrt(max(c22, 0.0)))
            if h.V_unobs.shape[1]:
                prior_h, prior_v = max(prior_h, hpl[-1]), max(prior_v, vpl[-1])
                walls = tuple(sorted({obs[j].plane_id for j in faults[i - 1]})) if i else ()
                bounded.append((walls, [_signed(u) for u in h.V_unobs.T.tolist()], hpl[-1], vpl[-1]))
        return (_largest(hpl), _largest(vpl), _largest(sep_h), _largest([abs(s[2]) for s in sep]), prior_h, prior_v,
                bounded)


def _signed(u: List[float]) -> List[float]:
    """A direction with its sign fixed (its largest component positive): a basis of unobserved
    directions is defined up to sign, which says nothing."""
    big = max(u, key=abs)
    return [-v for v in u] if big < 0 else list(u)


def _prior_covariance(sol: Solution, coarse_cov: np.ndarray) -> List[List[float]]:
    """``sol.covariance(coarse_cov, 0.0)`` as nested lists."""
    C = sol.P_obs.tolist()
    for j in range(sol.V_unobs.shape[1]):
        v = sol.V_unobs[:, j]
        prior = max(0.0, float(v @ coarse_cov @ v))
        vs = v.tolist()
        for r in range(3):
            for c in range(3):
                C[r][c] += vs[r] * vs[c] * prior
    return C


def _largest(values: List[float]) -> float:
    """max as numpy's: NaN if any is NaN."""
    top = max(values)
    return math.nan if any(v != v for v in values) else float(top)


def protection_multipliers(risk: float) -> Tuple[float, float]:
    """(k horizontal, k heading): bound = k sigma at probability ``risk`` (2-D radial, 1-D two-sided)."""
    return math.sqrt(-2.0 * math.log(risk)), normal_quantile(risk / 2.0)
