"""Batch least squares over all keyframes: calibration parameters and every keyframe pose at once.

Gauss-Newton with Levenberg-Marquardt damping on the model of ``robot.calibration.model``, robust
to outliers (Huber weights on the whitened residuals: a misfitted wall or a slipping wheel costs
linearly, not quadratically). The noise of each group of residuals (per camera: offsets and
angles; odometry: translation and rotation) is estimated from the data (variance components), so
the standard deviations reported are what the residuals support, not what was assumed.

Observability comes from the covariance with the poses marginalised (the Schur complement of the
information matrix): a parameter whose standard deviation stays above its bound, or that is
correlated almost 1 with another, is not observed by the data. Every parameter stays in the solve
with a weak prior, observed or not, so what an unobserved one leaves open shows in the
uncertainty of everything tied to it (``observability``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import wrap_angle
from robot.calibration.model import (
    CAMERA_BLOCK,
    CAMERA_PARAMS,
    DISPARITY_PARAMS,
    ODOMETRY_PARAMS,
    WALL_PARAMS,
    Dataset,
    OdometryArrays,
    ParamLayout,
    PlaneArrays,
    disparity_prior_std,
    odometry_residuals,
    plane_residuals,
    with_walls_as_built,
)
from robot.maps.plane_map import PlaneMap

# What a calibration file holds (robot.config.calibration); the wheels' differences are estimated
# so that they do not bias the rest, but have no place in it.
CALIBRATION_FILE_PARAMS = CAMERA_PARAMS + ("wheel_radius", "lx_plus_ly")
HUBER_K = 3.0  # whitened residuals beyond this many sigma are weighted down
MAX_CORRELATION = 0.99  # |correlation| with another parameter at which neither counts as observed


def default_prior_std(nominal: np.ndarray, layout: ParamLayout, systematic_px: float = 0.0) -> np.ndarray:
    """Weak priors: wide enough not to bias an observed parameter, there to keep the solve well posed.
    The disparity terms get a physical prior instead: ``systematic_px`` RMS over the image."""
    out = np.zeros(len(layout))
    per_cam = {"depth_scale": 0.05, "x": 0.05, "y": 0.05, "z": 0.05, "roll": math.radians(5.0),
               "pitch": math.radians(5.0), "yaw": math.radians(5.0)}
    terms = list(disparity_prior_std(systematic_px))
    for c in layout.cameras:
        out[layout.camera_slice(c)] = [per_cam[p] for p in CAMERA_PARAMS] + terms
    r0, L0 = nominal[layout.odometry_slice][[0, 4]]
    out[layout.odometry_slice] = [0.1 * r0, 0.05 * r0, 0.05 * r0, 0.05 * r0, 0.2 * L0]
    for w in layout.walls:  # the map's default as-built tolerance (robot.maps.plane_map)
        out[layout.wall_slice(w)] = [0.01, 0.01, 0.01]
    return out


def default_bounds(nominal: np.ndarray, layout: ParamLayout) -> np.ndarray:
    """The standard deviation above which a parameter counts as not observed."""
    out = np.zeros(len(layout))
    per_cam = {"depth_scale": 1e-3, "x": 0.002, "y": 0.002, "z": 0.002, "roll": math.radians(0.1),
               "pitch": math.radians(0.1), "yaw": math.radians(0.05)}
    for c in layout.cameras:
        out[layout.camera_slice(c)] = [per_cam[p] for p in CAMERA_PARAMS] + [math.inf] * len(DISPARITY_PARAMS)
    r0, L0 = nominal[layout.odometry_slice][[0, 4]]
    out[layout.odometry_slice] = [1e-3 * r0, 2e-3 * r0, 2e-3 * r0, 2e-3 * r0, 5e-3 * L0]
    for w in layout.walls:
        out[layout.wall_slice(w)] = math.inf
    return out


@dataclass
class NoiseModel:
    """Assumed 1-sigma noise of the odometry residuals before the data rescales them."""

    trans_floor: float = 2e-4  # m per interval
    trans_per_metre: float = 1e-3  # m/sqrt(m) of travel (random slip)
    rot_floor: float = 2e-4  # rad per interval
    rot_per_rad: float = 2e-3  # rad/sqrt(rad) turned
    rot_per_metre: float = 1e-3  # rad/sqrt(m) travelled


@dataclass
class SolveOptions:
    free: Optional[Sequence[str]] = None  # names of the parameters solved for (None: all)
    prior_mean: Optional[np.ndarray] = None  # default: the dataset's nominal vector
    prior_info: Optional[np.ndarray] = None  # (P, P) information of the prior (default: weak, diagonal)
    max_iterations: int = 30
    variance_components: bool = True  # rescale each group's noise from its residuals
    vce_rounds: int = 4
    noise: NoiseModel = field(default_factory=NoiseModel)
    pose_prior_std: Tuple[float, float] = (10.0, math.pi)  # m, rad: keeps a keyframe without data well posed


@dataclass
class Solution:
    layout: ParamLayout
    theta: np.ndarray  # every parameter (held ones at their start value)
    free: List[int]  # indices of the solved parameters
    cov: np.ndarray  # (F, F) covariance of the solved parameters, poses marginalised, prior included
    info_data: np.ndarray  # (F, F) information from the data alone (poses marginalised)
    poses: np.ndarray  # (K, 3)
    iterations: int
    converged: bool
    cost: float
    group_sigma: Dict[str, float]  # factor on each group's assumed noise, from the data
    residual_rms: Dict[str, float]  # whitened RMS per group after the solve
    counts: Dict[str, int]
    cov_random: Optional[np.ndarray] = None  # the part of ``cov`` from the residuals' noise (no systematic terms)

    def std(self) -> np.ndarray:
        """(P,) standard deviation of every parameter; NaN for the held ones."""
        out = np.full(len(self.theta), np.nan)
        out[self.free] = np.sqrt(np.maximum(np.diag(self.cov), 0.0))
        return out

    def correlation(self) -> np.ndarray:
        s = np.sqrt(np.maximum(np.diag(self.cov), 1e-300))
        return self.cov / np.outer(s, s)


class _Normal:
    """Normal equations with a block-tridiagonal pose block: D (K, 3, 3) on the diagonal, B (K-1, 3, 3)
    above it, Hpt (K, 3, F) to the parameters, Htt (F, F), gradients gp (K, 3) and gt (F,)."""

    def __init__(self, D, B, Hpt, Htt, gp, gt):
        self.D, self.B, self.Hpt, self.Htt, self.gp, self.gt = D, B, Hpt, Htt, gp, gt

    def solve_poses(self, rhs: np.ndarray, lam: float) -> np.ndarray:
        """(3K, m) solution of (Hpp + lam diag(Hpp)) X = rhs: a banded Cholesky solve (bandwidth 5)."""
        K = len(self.D)
        D = self.D + lam * self.D * np.eye(3)[None]
        ab = np.zeros((6, 3 * K))
        k = np.arange(K)
        for a in range(3):
            for b in range(a, 3):
                ab[5 + a - b, 3 * k + b] = D[:, a, b]
        if K > 1:
            k = np.arange(K - 1)
            for a in range(3):
                for b in range(3):
                    ab[2 + a - b, 3 * k + 3 + b] = self.B[:, a, b]
        # Imported here: the controller loads this module with the online calibration, which is
        # off by default, and scipy.linalg costs 12 MiB of the Nano's memory.
        from scipy.linalg import cho_solve_banded, cholesky_banded

        cb = cholesky_banded(ab, check_finite=False)
        return cho_solve_banded((cb, False), rhs.reshape(3 * K, -1), check_finite=False)

    def solve_full(self, Htt: np.ndarray, bp: np.ndarray, bt: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """H [xp; xt] = [bp; bt] for (3K, m) and (F, m) right-hand sides (no damping)."""
        K, F = len(self.D), len(Htt)
        Hpt = self.Hpt.reshape(3 * K, F)
        X = self.solve_poses(np.concatenate([bp.reshape(3 * K, -1), Hpt], axis=1), 0.0)
        m = bp.reshape(3 * K, -1).shape[1]
        xb, XH = X[:, :m], X[:, m:]
        xt = np.linalg.solve(Htt - Hpt.T @ XH, bt.reshape(F, -1) - Hpt.T @ xb)
        return xb - XH @ xt, xt

    def step(self, Htt: np.ndarray, gt: np.ndarray, lam: float) -> Tuple[np.ndarray, np.ndarray]:
        """The damped Gauss-Newton step (pose step (K, 3), parameter step (F,)) through the Schur complement."""
        K, F = len(self.D), len(gt)
        Hpt = self.Hpt.reshape(3 * K, F)
        X = self.solve_poses(np.concatenate([self.gp.reshape(3 * K, 1), Hpt], axis=1), lam)
        xg, XH = X[:, 0], X[:, 1:]
        if F:
            A = Htt + lam * np.diag(np.diag(Htt)) - Hpt.T @ XH
            dt = np.linalg.solve(A, -gt + Hpt.T @ xg)
            dp = -xg - XH @ dt
        else:
            dt = np.zeros(0)
            dp = -xg
        return dp.reshape(K, 3), dt


class _Problem:
    """The arrays of one dataset and the normal equations over (poses, free parameters)."""

    def __init__(self, data: Dataset, layout: ParamLayout, options: SolveOptions):
        self.data, self.layout, self.options = data, layout, options
        self.planes = PlaneArrays.build(data, layout)
        self.odo = OdometryArrays.build(data, layout)
        if np.any(self.odo.b != self.odo.a + 1):
            raise ValueError("keyframes must be in time order")
        self.K = len(data.keyframes)
        noise = options.noise
        self.odo_sigma = np.stack([
            np.sqrt(noise.trans_floor ** 2 + noise.trans_per_metre ** 2 * self.odo.travel),
            np.sqrt(noise.trans_floor ** 2 + noise.trans_per_metre ** 2 * self.odo.travel),
            np.sqrt(noise.rot_floor ** 2 + noise.rot_per_rad ** 2 * self.odo.turn
                    + noise.rot_per_metre ** 2 * self.odo.travel)], axis=1) if len(self.odo.a) else np.zeros((0, 3))
        # Residual groups whose noise the data rescales.
        cams = layout.cameras
        self.groups = [f"{c}:offset" for c in cams] + [f"{c}:angle" for c in cams] + ["odometry:translation",
                                                                                     "odometry:rotation"]
        self.scale = {g: 1.0 for g in self.groups}
        self.pose_ref = np.array([k.pose for k in data.keyframes], float).reshape(-1, 3)

    # -- residuals and Jacobians ------------------------------------------------------------------

    def _plane_sigma(self) -> np.ndarray:
        s = self.planes.sigma.copy()
        for ci, c in enumerate(self.layout.cameras):
            m = self.planes.camera == ci
            s[m, 0] *= self.scale[f"{c}:offset"]
            s[m, 1:] *= self.scale[f"{c}:angle"]
        return s

    def _odo_sigma(self) -> np.ndarray:
        s = self.odo_sigma.copy()
        s[:, :2] *= self.scale["odometry:translation"]
        s[:, 2] *= self.scale["odometry:rotation"]
        return s

    def evaluate(self, poses: np.ndarray, theta: np.ndarray, jacobian: bool):
        lay = self.layout
        cams = np.stack([theta[lay.camera_slice(c)] for c in lay.cameras])
        walls = theta[lay.odometry_slice.stop:].reshape(-1, len(WALL_PARAMS)) if lay.walls else None
        rp, Jpl = plane_residuals(self.planes, poses, cams, jacobian, walls)
        rp = rp / self._plane_sigma()
        ro, Jod = odometry_residuals(self.odo, poses, theta[lay.odometry_slice], jacobian)
        ro = ro / self._odo_sigma() if len(ro) else ro
        return rp, Jpl, ro, Jod

    @staticmethod
    def huber(r: np.ndarray) -> np.ndarray:
        a = np.abs(r)
        return np.where(a <= HUBER_K, 1.0, HUBER_K / np.maximum(a, 1e-300))

    @staticmethod
    def huber_cost(r: np.ndarray) -> float:
        a = np.abs(r)
        return float(np.sum(np.where(a <= HUBER_K, 0.5 * a * a, HUBER_K * a - 0.5 * HUBER_K * HUBER_K)))

    def cost(self, poses: np.ndarray, theta: np.ndarray, free: List[int], mean: np.ndarray, info: np.ndarray) -> float:
        rp, _, ro, _ = self.evaluate(poses, theta, False)
        d = theta[free] - mean[free]
        return self.huber_cost(rp) + self.huber_cost(ro) + 0.5 * float(d @ info @ d) + self._pose_prior_cost(poses)

    def _pose_prior_cost(self, poses: np.ndarray) -> float:
        sx, sp = self.options.pose_prior_std
        d = poses - self.pose_ref
        d[:, 2] = wrap_angle(d[:, 2])
        return 0.5 * float(np.sum((d[:, :2] / sx) ** 2) + np.sum((d[:, 2] / sp) ** 2))

    def normal_equations(self, poses: np.ndarray, theta: np.ndarray, free: List[int]) -> _Normal:
        """The robust (IRLS) normal equations over [poses, theta[free]] with the weak pose prior and
        without the parameter prior. Odometry links only keyframes next to each other in time, so the
        pose block is block tridiagonal."""
        lay = self.layout
        K, F = self.K, len(free)
        col = {p: i for i, p in enumerate(free)}
        rp, (Jp, Jc, Jw), ro, Jod = self.evaluate(poses, theta, True)
        sig_p = self._plane_sigma()
        Jp = Jp / sig_p[:, :, None]
        Jc = Jc / sig_p[:, :, None]
        Jw = Jw / sig_p[:, :, None]
        w = np.sqrt(self.huber(rp))
        rp, Jp, Jc, Jw = rp * w, Jp * w[:, :, None], Jc * w[:, :, None], Jw * w[:, :, None]
        # the camera parameter block of each row, mapped to the free columns
        Jt = np.zeros((len(rp), 3, F))
        for ci, c in enumerate(lay.cameras):
            base = lay.camera_slice(c).start
            m = self.planes.camera == ci
            for j in range(len(CAMERA_BLOCK)):
                if base + j in col:
                    Jt[m, :, col[base + j]] = Jc[m, :, j]
        for wi, wall in enumerate(lay.walls):  # the walls as built
            base = lay.wall_slice(wall).start
            m = self.planes.wall == wi
            for j in range(len(WALL_PARAMS)):
                if base + j in col:
                    Jt[m, :, col[base + j]] = Jw[m, :, j]
        kf = self.planes.keyframe
        D = np.zeros((K, 3, 3))
        np.add.at(D, kf, np.einsum("nri,nrj->nij", Jp, Jp))
        Hpt = np.zeros((K, 3, F))
        np.add.at(Hpt, kf, np.einsum("nri,nrj->nij", Jp, Jt))
        gp = np.zeros((K, 3))
        np.add.at(gp, kf, np.einsum("nri,nr->ni", Jp, rp))
        Htt = np.einsum("nri,nrj->ij", Jt, Jt)
        gt = np.einsum("nri,nr->i", Jt, rp)
        B = np.zeros((max(K - 1, 0), 3, 3))  # H[k, k + 1]
        if len(ro):
            Ja, Jb, Jo = Jod
            sig_o = self._odo_sigma()
            Ja, Jb, Jo = Ja / sig_o[:, :, None], Jb / sig_o[:, :, None], Jo / sig_o[:, :, None]
            w = np.sqrt(self.huber(ro))
            ro, Ja, Jb, Jo = ro * w, Ja * w[:, :, None], Jb * w[:, :, None], Jo * w[:, :, None]
            Jto = np.zeros((len(ro), 3, F))
            base = lay.odometry_slice.start
            for j in range(len(ODOMETRY_PARAMS)):
                if base + j in col:
                    Jto[:, :, col[base + j]] = Jo[:, :, j]
            a, b = self.odo.a, self.odo.b
            np.add.at(D, a, np.einsum("nri,nrj->nij", Ja, Ja))
            np.add.at(D, b, np.einsum("nri,nrj->nij", Jb, Jb))
            np.add.at(B, a, np.einsum("nri,nrj->nij", Ja, Jb))
            np.add.at(Hpt, a, np.einsum("nri,nrj->nij", Ja, Jto))
            np.add.at(Hpt, b, np.einsum("nri,nrj->nij", Jb, Jto))
            np.add.at(gp, a, np.einsum("nri,nr->ni", Ja, ro))
            np.add.at(gp, b, np.einsum("nri,nr->ni", Jb, ro))
            Htt += np.einsum("nri,nrj->ij", Jto, Jto)
            gt += np.einsum("nri,nr->i", Jto, ro)
        # the weak pose prior
        sx, sph = self.options.pose_prior_std
        d = poses - self.pose_ref
        d[:, 2] = wrap_angle(d[:, 2])
        D[:, 0, 0] += 1.0 / sx ** 2
        D[:, 1, 1] += 1.0 / sx ** 2
        D[:, 2, 2] += 1.0 / sph ** 2
        gp[:, :2] += d[:, :2] / sx ** 2
        gp[:, 2] += d[:, 2] / sph ** 2
        self.rows = {"plane": (Jp, Jt, rp), "odometry": (Ja, Jb, Jto, ro) if len(ro) else None}
        return _Normal(D, B, Hpt, Htt, gp, gt)

    # -- one solve --------------------------------------------------------------------------------

    def solve(self, theta0: np.ndarray, free: List[int], mean: np.ndarray, info: np.ndarray,
              poses0: np.ndarray) -> Tuple[np.ndarray, np.ndarray, int, bool]:
        theta, poses = theta0.copy(), poses0.copy()
        lam = 1e-4
        cost = self.cost(poses, theta, free, mean, info)
        converged = False
        it = 0
        while it < self.options.max_iterations:
            it += 1
            ne = self.normal_equations(poses, theta, free)
            Htt = ne.Htt + info
            gt = ne.gt + info @ (theta[free] - mean[free])
            accepted = small = False
            for _ in range(12):
                try:
                    dp, dt = ne.step(Htt, gt, lam)
                except (np.linalg.LinAlgError, ValueError):  # not positive definite at this damping
                    lam *= 10.0
                    continue
                p_new = poses + dp
                p_new[:, 2] = wrap_angle(p_new[:, 2])
                t_new = theta.copy()
                t_new[free] += dt
                c_new = self.cost(p_new, t_new, free, mean, info)
                if c_new <= cost:
                    accepted = True
                    small = cost - c_new <= 1e-9 * max(cost, 1.0)
                    poses, theta, cost = p_new, t_new, c_new
                    lam = max(lam / 10.0, 1e-9)
                    break
                lam *= 10.0
            if not accepted or small:
                converged = True
                break
        return theta, poses, it, converged

    def marginal_info(self, poses: np.ndarray, theta: np.ndarray, free: List[int]) -> np.ndarray:
        """(F, F) information about the free parameters from the data, the poses marginalised."""
        if len(free) == 0:
            return np.zeros((0, 0))
        ne = self.normal_equations(poses, theta, free)
        X = ne.solve_poses(ne.Hpt.reshape(len(ne.D) * 3, -1), 0.0)
        S = ne.Htt - ne.Hpt.reshape(len(ne.D) * 3, -1).T @ X
        return 0.5 * (S + S.T)

    def update_scales(self, poses: np.ndarray, theta: np.ndarray, free: List[int], info: np.ndarray) -> float:
        """Rescale each residual group's noise from its robustly weighted residuals and its redundancy
        (the rows' count less their leverage: what the unknowns do not absorb); the largest change.

        The redundancy is exact (from the inverse of the normal matrix) rather than a share of the
        unknowns: the wheel residuals between keyframes are largely absorbed by the poses, the wall
        residuals hardly, and a common share would shrink the wheels' noise without end."""
        ne = self.normal_equations(poses, theta, free)
        K, F = self.K, len(free)
        Hpt = ne.Hpt.reshape(3 * K, F)
        Ainv = ne.solve_poses(np.eye(3 * K), 0.0)  # Hpp^-1
        X = Ainv @ Hpt
        try:
            C = np.linalg.inv(ne.Htt + info - Hpt.T @ X) if F else np.zeros((0, 0))
        except np.linalg.LinAlgError:
            return 1.0
        XC = X @ C
        idx = np.arange(K)
        A_diag = Ainv.reshape(K, 3, K, 3)[idx, :, idx, :] + np.einsum("kif,fg,kjg->kij", X.reshape(K, 3, F), C,
                                                                       X.reshape(K, 3, F))
        Bp = -XC.reshape(K, 3, F)
        Jp, Jt, rp = self.rows["plane"]
        kf = self.planes.keyframe
        lev_p = (np.einsum("nri,nij,nrj->nr", Jp, A_diag[kf], Jp) + 2 * np.einsum("nri,nif,nrf->nr", Jp, Bp[kf], Jt)
                 + np.einsum("nrf,fg,nrg->nr", Jt, C, Jt))
        lev_o = None
        if self.rows["odometry"] is not None:
            Ja, Jb, Jto, ro = self.rows["odometry"]
            a, b = self.odo.a, self.odo.b
            A_ab = Ainv.reshape(K, 3, K, 3)[a, :, b, :] + np.einsum("kif,fg,kjg->kij", X.reshape(K, 3, F)[a], C,
                                                                     X.reshape(K, 3, F)[b])
            lev_o = (np.einsum("nri,nij,nrj->nr", Ja, A_diag[a], Ja) + np.einsum("nri,nij,nrj->nr", Jb, A_diag[b], Jb)
                     + 2 * np.einsum("nri,nij,nrj->nr", Ja, A_ab, Jb)
                     + 2 * np.einsum("nri,nif,nrf->nr", Ja, Bp[a], Jto) + 2 * np.einsum("nri,nif,nrf->nr", Jb, Bp[b], Jto)
                     + np.einsum("nrf,fg,nrg->nr", Jto, C, Jto))
        rp_raw, _, ro_raw, _ = self.evaluate(poses, theta, False)
        groups: Dict[str, Tuple[np.ndarray, np.ndarray]] = {}
        for ci, c in enumerate(self.layout.cameras):
            m = self.planes.camera == ci
            groups[f"{c}:offset"] = (rp_raw[m, 0], lev_p[m, 0])
            groups[f"{c}:angle"] = (rp_raw[m, 1:].reshape(-1), lev_p[m, 1:].reshape(-1))
        if lev_o is not None:
            groups["odometry:translation"] = (ro_raw[:, :2].reshape(-1), lev_o[:, :2].reshape(-1))
            groups["odometry:rotation"] = (ro_raw[:, 2], lev_o[:, 2])
        worst = 1.0
        for g, (r, lev) in groups.items():
            redundancy = float(r.size - np.sum(np.clip(lev, 0.0, 1.0)))
            if r.size < 5 or redundancy < 2.0:
                continue
            ss, _ = _robust_ss(r)
            f = math.sqrt(max(ss / redundancy, 1e-8))
            f = min(max(f, 1e-2), 1e2)
            self.scale[g] *= f
            worst = max(worst, f, 1.0 / f)
        return worst

    def rms(self, poses: np.ndarray, theta: np.ndarray) -> Dict[str, float]:
        rp, _, ro, _ = self.evaluate(poses, theta, False)
        out = {}
        for ci, c in enumerate(self.layout.cameras):
            m = self.planes.camera == ci
            if m.any():
                out[f"{c}:offset"] = float(np.sqrt(np.mean(rp[m, 0] ** 2)))
                out[f"{c}:angle"] = float(np.sqrt(np.mean(rp[m, 1:] ** 2)))
        if len(ro):
            out["odometry:translation"] = float(np.sqrt(np.mean(ro[:, :2] ** 2)))
            out["odometry:rotation"] = float(np.sqrt(np.mean(ro[:, 2] ** 2)))
        return out


def _robust_ss(r: np.ndarray) -> Tuple[float, int]:
    """Sum of squares with each residual capped at the Huber bound (an outlier counts as one at the bound)."""
    return float(np.sum(np.minimum(r * r, HUBER_K * HUBER_K))), int(r.size)


def solve(data: Dataset, options: Optional[SolveOptions] = None, layout: Optional[ParamLayout] = None,
          theta0: Optional[np.ndarray] = None, poses0: Optional[np.ndarray] = None,
          scales: Optional[Dict[str, float]] = None) -> Solution:
    """One robust solve of ``options.free`` (others held at ``theta0``, default the nominal vector)."""
    options = options or SolveOptions()
    layout = layout or ParamLayout(data.cameras)
    prob = _Problem(data, layout, options)
    if scales:
        prob.scale.update({k: v for k, v in scales.items() if k in prob.scale})
    theta = np.array(data.nominal if theta0 is None else theta0, float)
    mean = np.array(data.nominal if options.prior_mean is None else options.prior_mean, float)
    names = layout.names
    free = list(range(len(names))) if options.free is None else sorted(layout.index(n) for n in options.free)
    if options.prior_info is not None:
        info = np.asarray(options.prior_info, float)
        if info.shape == (len(names), len(names)):
            info = info[np.ix_(free, free)]
    else:
        info = np.diag(1.0 / default_prior_std(data.nominal, layout, data.systematic_px)[free] ** 2)
    poses = prob.pose_ref.copy() if poses0 is None else np.array(poses0, float)
    if len(poses) == 0:
        raise ValueError("no keyframes to calibrate from")
    iterations, converged = 0, False
    rounds = options.vce_rounds if options.variance_components else 1
    for _ in range(rounds):
        theta, poses, it, converged = prob.solve(theta, free, mean, info, poses)
        iterations += it
        if not options.variance_components:
            break
        change = prob.update_scales(poses, theta, free, info)
        if change < 1.05:
            break
    if options.variance_components:  # the last solve with the final noise
        theta, poses, it, converged = prob.solve(theta, free, mean, info, poses)
        iterations += it
    I_data = prob.marginal_info(poses, theta, free)
    try:
        cov = np.linalg.inv(I_data + info)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(I_data + info)
    cov_random = 0.5 * (cov + cov.T)
    counts = {"keyframes": prob.K, "plane_observations": len(prob.planes.keyframe), "odometry_intervals": len(prob.odo.a)}
    return Solution(layout, theta, free, 0.5 * (cov + cov.T), I_data, poses, iterations, converged,
                    prob.cost(poses, theta, free, mean, info), dict(prob.scale), prob.rms(poses, theta), counts,
                    cov_random)


# -- observability and the batch routine -----------------------------------------------------------


@dataclass
class ParamReport:
    name: str
    nominal: float
    value: float
    std: float  # NaN when not solved for
    observable: bool
    reason: str  # why not, or ""


@dataclass
class CalibrationResult:
    solution: Solution
    reports: List[ParamReport]
    held: List[str]  # parameters not observed: reported, never written

    def report(self, name: str) -> ParamReport:
        for r in self.reports:
            if r.name == name:
                return r
        raise KeyError(name)

    @property
    def observable(self) -> List[str]:
        return [r.name for r in self.reports if r.observable]


def observability(sol: Solution, bounds: np.ndarray) -> Dict[int, str]:
    """Parameter index -> why it is not observed, for the solved parameters that are not (the
    disparity terms are nuisances and never judged).

    Every parameter stays in the solve with its weak prior, observed or not: holding one at its
    nominal value would make the others look observed through it (a wheel radius held 1 % off
    turns the wheels' distance into a depth scale 1 % off, with a small standard deviation). So
    an unobservable parameter shows as a standard deviation near its prior's, and everything
    correlated with it inherits that. Three tests: the data's information about it is too weak
    even if every other parameter were known; its standard deviation exceeds its bound; it is
    correlated almost 1 with another parameter."""
    names = sol.layout.names
    std = sol.std()
    nuisance = set(sol.layout.nuisance)
    where = {p: i for i, p in enumerate(sol.free)}
    judged = [p for p in sol.free if p not in nuisance]
    corr = sol.correlation()
    diag = np.diag(sol.info_data)
    out: Dict[int, str] = {}
    for p in judged:
        i = where[p]
        if not diag[i] > 0 or 1.0 / math.sqrt(diag[i]) > bounds[p]:
            out[p] = "the data holds too little information about it even with everything else known"
        elif not std[p] <= bounds[p]:
            out[p] = f"std {_fmt(names[p], std[p])} exceeds the bound {_fmt(names[p], bounds[p])}"
        else:
            others = [(abs(corr[i, where[q]]), q) for q in judged if q != p]
            c, q = max(others) if others else (0.0, p)
            if c >= MAX_CORRELATION:
                out[p] = f"correlated {c:.3f} with {names[q]}"
    return out


def _fmt(name: str, v: float) -> str:
    kind = name.rsplit(".", 1)[1]
    if kind in ("roll", "pitch", "yaw"):
        return f"{math.degrees(v):.3g} deg"
    if kind == "depth_scale":
        return f"{v * 100:.3g} %"
    return f"{v * 1000:.3g} mm"


def calibrate(data: Dataset, free: Optional[Sequence[str]] = None, bounds: Optional[np.ndarray] = None,
              options: Optional[SolveOptions] = None, plane_map: Optional[PlaneMap] = None) -> CalibrationResult:
    """Solve every parameter (``free``: a subset; the disparity terms always), then judge each one's
    observability from the result. The reports give for each parameter its estimate and standard
    deviation, and whether the data observed it; only observed ones may be written.

    ``plane_map``: the map the data was taken in. Each wall it holds then has its as-built
    deviation solved beside the calibration, with the plane's tolerance as its prior
    (``with_walls_as_built``), so what the walls' builders left open is not claimed as known.
    Without it the walls are taken as exactly where the data says they are (synthetic data)."""
    options = options or SolveOptions()
    wall_std: Dict[str, np.ndarray] = {}
    if plane_map is not None:
        data, wall_std = with_walls_as_built(data, {p.id: p for p in plane_map.planes})
    layout = ParamLayout(data.cameras, tuple(data.walls))
    if wall_std and options.prior_info is None:
        prior = default_prior_std(data.nominal, layout, data.systematic_px)
        for w, s in wall_std.items():
            prior[layout.wall_slice(w)] = np.maximum(s, 1e-9)
        options = SolveOptions(**{**options.__dict__, "prior_info": np.diag(1.0 / prior ** 2)})
    bounds = default_bounds(data.nominal, layout) if bounds is None else np.asarray(bounds, float)
    trying = list(layout.names) if free is None else sorted(set(free) | {layout.names[i] for i in layout.nuisance})
    sol = solve(data, SolveOptions(**{**options.__dict__, "free": trying}), layout)
    reasons = {layout.names[p]: why for p, why in observability(sol, bounds).items()}
    std = sol.std()
    reports = []
    nuisance = set(layout.nuisance)
    for i, name in enumerate(layout.names):
        if i in nuisance:
            continue
        if i not in sol.free:
            reports.append(ParamReport(name, float(data.nominal[i]), float(data.nominal[i]), math.nan, False,
                                       "not solved for"))
        else:
            reports.append(ParamReport(name, float(data.nominal[i]), float(sol.theta[i]), float(std[i]),
                                       name not in reasons, reasons.get(name, "")))
    return CalibrationResult(sol, reports, sorted(reasons))


# -- checking a calibration against fresh data -----------------------------------------------------


@dataclass
class CheckRow:
    name: str
    current: float
    estimate: float
    std: float
    tolerance: float
    holds: bool


def check_calibration(result: CalibrationResult, tolerances: Optional[np.ndarray] = None,
                      sigmas: float = 3.0) -> Tuple[bool, List[CheckRow]]:
    """Does the calibration the data was taken with (the dataset's nominal values) still hold?

    For every parameter of the calibration file the fresh data observes: it holds while the fresh estimate is within
    ``sigmas`` standard deviations of the current value, or within ``tolerance`` (default: the
    observability bound, the precision a calibration claims) of it. With nothing observed it cannot
    be said to hold."""
    sol = result.solution
    tol = default_bounds(sol.theta, sol.layout) if tolerances is None else np.asarray(tolerances, float)
    rows = []
    for r in result.reports:
        if not r.observable or r.name.rsplit(".", 1)[1] not in CALIBRATION_FILE_PARAMS:
            continue
        diff = abs(r.value - r.nominal)
        t = float(tol[sol.layout.index(r.name)])
        rows.append(CheckRow(r.name, r.nominal, r.value, r.std, t, diff <= max(sigmas * r.std, t)))
    return bool(rows) and all(row.holds for row in rows), rows
