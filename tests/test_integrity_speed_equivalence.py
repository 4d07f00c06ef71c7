"""The pose solve and integrity checks (robot/localization/integrity.py), rewritten for speed, give
the results of the code they replace: that code is kept here as the reference (copied plainly,
numpy only), and both backends (numpy, and numba's kernels in integrity_kernels.py) are compared
with it on random stacks of measurements (every subset solved, and the whole check with
exclusions) and on the localizer's results for rendered frames with clutter, tracking and cold.

Agreement: to 1e-9 relative (the kernels sum in another order than numpy's stacked products) on
poses, covariances, gains, chi-squares and protection levels; identical statuses, exclusions,
reasons, observed-direction counts and reported unobservable directions (signs included)."""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import pytest

from drivers.sim.building import free_space_poses
from drivers.sim.clutter import as_built, leaning_boards, parallel_panel
from drivers.sim.render import Box, DepthNoise, SimScene, render_depth_frame
from robot.base.geometry import wrap_angle
from robot.base.stats import chi2_quantile
from robot.config import load_robot_config
from robot.localization import fit_kernels as fk
from robot.localization import integrity as integ
from robot.localization import integrity_kernels as ik
from robot.localization import localizer as loc_mod
from robot.localization.integrity import ErrorModel, Integrity, Observation, Solution
from robot.localization.localizer import Localizer, coarse_covariance
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")
P = ROBOT.localizer
MODEL = ErrorModel.from_config(P)
RTOL = 1e-9
BACKENDS = ["numpy", "numba"]


# -- the reference: the numpy code before the rewrite -------------------------------------------

_EYE3 = np.eye(3)
_FLOOR3 = _EYE3 * 1e-14


class RefStack:
    """integrity.Stack as it was."""

    def __init__(self, obs: Sequence[Observation], model: ErrorModel):
        self.obs = list(obs)
        m = len(self.obs)
        self.y = np.concatenate([o.y for o in self.obs]) if m else np.zeros(0)
        self.H = np.vstack([o.H for o in self.obs]) if m else np.zeros((0, 3))
        self.h0 = np.concatenate([o.h0 for o in self.obs]) if m else np.zeros(0)
        cams = sorted({o.camera for o in self.obs})
        planes = sorted({o.plane_id for o in self.obs})
        cam_col = {c: integ.CAMERA_PARAMS * i for i, c in enumerate(cams)}
        plane_col = {p: integ.CAMERA_PARAMS * len(cams) + integ.PLANE_PARAMS * i for i, p in enumerate(planes)}
        n_par = integ.CAMERA_PARAMS * len(cams) + integ.PLANE_PARAMS * len(planes)
        G = np.zeros((3 * m, n_par))
        sig = np.zeros(n_par)
        cam_std = np.array([model.depth_scale_std] + [model.mount_position_std] * 3 + [model.mount_angle_std] * 3)
        R = np.zeros((3 * m, 3 * m))
        for i, o in enumerate(self.obs):
            r = slice(3 * i, 3 * i + 3)
            R[r, r] = o.R_own
            c, p = cam_col[o.camera], plane_col[o.plane_id]
            G[r, c:c + integ.CAMERA_PARAMS] = o.G_camera
            G[r, p:p + integ.PLANE_PARAMS] = o.G_plane
            sig[c:c + integ.CAMERA_PARAMS] = cam_std
            sig[p:p + integ.PLANE_PARAMS] = np.maximum(sig[p:p + integ.PLANE_PARAMS], o.plane_std)
        self.H_blocks = np.array([o.H for o in self.obs]) if m else np.zeros((0, 3, 3))
        self.W_own = np.linalg.inv(np.array([o.R_weight for o in self.obs]) + _FLOOR3) if m else np.zeros((0, 3, 3))
        self.G_sys = G * sig
        self.R_sys = self.G_sys @ self.G_sys.T
        self.R = R + self.R_sys
        self.R[np.diag_indices_from(self.R)] += 1e-14

    def __len__(self) -> int:
        return len(self.obs)

    def rows(self, members: Sequence[int]) -> np.ndarray:
        return (3 * np.asarray(members, dtype=np.intp)[:, None] + np.arange(3)).ravel()

    def residual(self, x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        r = self.y[rows] - (self.H[rows] @ x + self.h0[rows])
        psi = rows % 3 == 1
        r[psi] = np.remainder(r[psi] + math.pi, 2 * math.pi) - math.pi
        return r

    def solve(self, members, x_lin, unobservable_std, prior_cov=None) -> Solution:
        return self.solve_many([members], x_lin, unobservable_std, prior_cov)[0]

    def solve_many(self, subsets, x_lin, unobservable_std, prior_cov=None) -> List[Solution]:
        x_lin = np.asarray(x_lin, float)
        B, m = len(subsets), len(self.obs)
        if B == 0:
            return []
        member = np.zeros((B, m), bool)
        for b, sub in enumerate(subsets):
            member[b, list(sub)] = True
        on = np.repeat(member, 3, axis=1)
        both = on[:, :, None] & on[:, None, :]
        Rm = np.where(both, self.R, 0.0) + np.eye(3 * m) * (~on)[:, None, :]
        Ri = np.linalg.inv(Rm)
        H = self.H[None] * on[:, :, None]
        r = self.residual(x_lin, np.arange(3 * m))[None] * on
        HtRi = H.transpose(0, 2, 1) @ Ri
        info = HtRi @ H
        lam, V = np.linalg.eigh(0.5 * (info + info.transpose(0, 2, 1)))
        floor = unobservable_std**2
        if prior_cov is not None:
            floor = np.maximum(floor, np.einsum("bji,jk,bki->bi", V, np.asarray(prior_cov, float), V))
        obs = lam > 1.0 / floor
        weak = obs & (lam < 1.0 / unobservable_std**2)
        w = (V.transpose(0, 2, 1) @ (HtRi @ r[:, :, None]))[:, :, 0]
        chi2 = np.einsum("bi,bij,bj->b", r, Ri, r) - np.sum(np.where(obs, w * w / np.where(obs, lam, 1.0), 0.0), axis=1)
        HtW = (self.H_blocks[None].transpose(0, 1, 3, 2) @ (self.W_own[None] * member[:, :, None, None]))
        HtW = HtW.transpose(0, 2, 1, 3).reshape(B, 3, 3 * m)
        T = V.transpose(0, 2, 1) @ (HtW @ H) @ V
        keep = obs[:, :, None] & obs[:, None, :]
        Ti = np.linalg.inv(np.where(keep, T, 0.0) + _EYE3 * (~obs)[:, None, :]) * keep
        A = V @ Ti @ V.transpose(0, 2, 1) @ HtW
        dx = (A @ r[:, :, None])[:, :, 0]
        P_ = A @ self.R @ A.transpose(0, 2, 1)
        out = []
        for b in range(B):
            x = x_lin + dx[b]
            x[2] = float(wrap_angle(x[2]))
            k = int(obs[b].sum())
            out.append(Solution(tuple(subsets[b]), x, 0.5 * (P_[b] + P_[b].T), V[b][:, obs[b]], V[b][:, ~obs[b]],
                                float(max(chi2[b], 0.0)), int(3 * len(subsets[b]) - k), A[b], k, V[b][:, weak[b]]))
        return out


def _ref_separation_statistics(stack, sol_all, subs):
    B = len(subs)
    if B == 0:
        return np.zeros(0), np.zeros(0, np.intp)
    D = np.array([sub.A for sub in subs]) - sol_all.A[None]
    V = np.zeros((B, 3, 3))
    keep = np.zeros((B, 3), bool)
    for b, sub in enumerate(subs):
        V[b][:, :sub.k_obs] = sub.V_obs
        keep[b, :sub.k_obs] = True
    T = V.transpose(0, 2, 1) @ D
    C = T @ stack.R @ T.transpose(0, 2, 1)
    both = keep[:, :, None] & keep[:, None, :]
    C = np.where(both, C, 0.0)
    sep = np.array([_ref_separation(sub.x - sol_all.x) for sub in subs])
    u = (V.transpose(0, 2, 1) @ sep[:, :, None])[:, :, 0] * keep
    lam, W = np.linalg.eigh(0.5 * (C + C.transpose(0, 2, 1)))
    ok = lam > 1e-9 * np.maximum(lam.max(axis=1, keepdims=True), 1e-30)
    z = (W.transpose(0, 2, 1) @ u[:, :, None])[:, :, 0]
    q = np.sum(np.where(ok, z * z / np.where(ok, lam, 1.0), 0.0), axis=1)
    return q, ok.sum(axis=1)


def _ref_separation(dx):
    out = np.asarray(dx, float).copy()
    out[2] = float(wrap_angle(out[2]))
    return out


class RefChecker:
    """integrity.Checker as it was."""

    def __init__(self, stack, coarse, coarse_cov, unobservable_std, false_alarm, risk):
        self.stack = stack
        self.coarse = np.asarray(coarse, float)
        self.coarse_cov = np.asarray(coarse_cov, float)
        self.unobservable_std = unobservable_std
        self.false_alarm = false_alarm
        self.risk = risk
        self._cache: Dict[Tuple[int, ...], Solution] = {}

    def solve(self, members):
        key = tuple(members)
        sol = self._cache.get(key)
        if sol is None:
            sol = self._cache[key] = self.stack.solve(key, self.coarse, self.unobservable_std, self.coarse_cov)
        return sol

    def faults(self, members):
        out = [(j,) for j in members]
        by_plane: Dict[str, List[int]] = {}
        for j in members:
            by_plane.setdefault(self.stack.obs[j].plane_id, []).append(j)
        return out + [tuple(g) for g in by_plane.values() if len(g) > 1]

    def without(self, members, faults):
        keys = [tuple(i for i in members if i not in f) for f in faults]
        missing = list(dict.fromkeys(k for k in [tuple(members)] + keys if k not in self._cache))
        if missing:
            for k, sol in zip(missing, self.stack.solve_many(missing, self.coarse, self.unobservable_std, self.coarse_cov)):
                self._cache[k] = sol
        return [self._cache[k] for k in keys]

    def agree_as_a_whole(self, sol):
        return sol.dof <= 0 or sol.chi2 <= chi2_quantile(1.0 - self.false_alarm, sol.dof)

    def _name(self, fault):
        obs = [self.stack.obs[j] for j in fault]
        if len(obs) == 1:
            return f"{obs[0].plane_id} ({obs[0].camera})"
        return f"{obs[0].plane_id} (all its views)"

    def disagreement(self, members):
        faults = self.faults(members) if len(members) > 1 else []
        subs = self.without(members, faults)
        sol = self.solve(members)
        if sol.dof > 0 and sol.chi2 > chi2_quantile(1.0 - self.false_alarm, sol.dof):
            return f"chi-square {sol.chi2:.1f} over {sol.dof} degrees of freedom"
        if not faults:
            return None
        p_each = self.false_alarm / len(faults)
        q, k = _ref_separation_statistics(self.stack, sol, subs)
        for f, qf, kf in zip(faults, q, k):
            if kf and qf > chi2_quantile(1.0 - p_each, int(kf)):
                return f"without {self._name(f)} the pose moves by {math.sqrt(qf):.1f} sigma"
        return None

    def check(self, max_exclusions: int = 2) -> Integrity:
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

    def protection(self, members, sol, cov):
        k2 = math.sqrt(-2.0 * math.log(self.risk))
        k1 = integ.normal_quantile(self.risk / 2.0)
        faults = self.faults(members)
        subs = self.without(members, faults)
        sep = np.array([np.zeros(3)] + [_ref_separation(sol.x - sub.x) for sub in subs])
        C = np.array([sol.covariance(self.coarse_cov, 0.0)] + [sub.covariance(self.coarse_cov, 0.0) for sub in subs])
        a, b, c = C[:, 0, 0], 0.5 * (C[:, 0, 1] + C[:, 1, 0]), C[:, 1, 1]
        lam = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
        hpl = np.hypot(sep[:, 0], sep[:, 1]) + k2 * np.sqrt(np.maximum(lam, 0.0))
        vpl = np.abs(sep[:, 2]) + k1 * np.sqrt(np.maximum(C[:, 2, 2], 0.0))
        hyps = [sol] + list(subs)
        walls = [()] + [tuple(sorted({self.stack.obs[j].plane_id for j in f})) for f in faults]
        leans = np.array([h.V_unobs.shape[1] > 0 for h in hyps])
        bounded = [(w, [list(u) if u[np.argmax(np.abs(u))] > 0 else list(-u) for u in h.V_unobs.T], float(hpl[i]),
                    float(vpl[i]))
                   for i, (h, w) in enumerate(zip(hyps, walls)) if leans[i]]
        return (float(hpl.max()), float(vpl.max()), float(np.hypot(sep[:, 0], sep[:, 1]).max()),
                float(np.abs(sep[:, 2]).max()), float(hpl[leans].max(initial=0.0)), float(vpl[leans].max(initial=0.0)),
                bounded)


# -- comparisons ------------------------------------------------------------------------------------

@pytest.fixture(params=BACKENDS)
def backend(request, monkeypatch):
    """The backend under test (conftest puts the plane fit's back afterwards)."""
    if request.param == "numba":
        pytest.importorskip("numba", reason="the compiled kernels need numba (pip install -e '.[perf]')")
    assert fk.set_backend(request.param) == request.param
    assert ik.compiled() == (request.param == "numba"), ik.backend_note()
    return request.param


def close(a, b, what: str, scale: Optional[float] = None) -> None:
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, (what, a.shape, b.shape)
    finite = np.isfinite(b)
    assert np.array_equal(np.isfinite(a), finite) and np.array_equal(a[~finite], b[~finite]), what
    if not finite.any():
        return
    s = float(np.max(np.abs(b[finite]))) if scale is None else scale
    err = float(np.max(np.abs(a[finite] - b[finite])))
    assert err <= RTOL * max(s, 1e-300), (what, err, s)


def same_solution(a: Solution, b: Solution, what: str) -> None:
    """``a`` (the code under test) against ``b`` (the reference)."""
    assert (a.members, a.dof, a.k_obs, a.fully_observed) == (b.members, b.dof, b.k_obs, b.fully_observed), what
    assert (a.V_obs.shape, a.V_unobs.shape, a.V_weak.shape) == (b.V_obs.shape, b.V_unobs.shape, b.V_weak.shape), what
    close(a.x, b.x, what + " x", 1.0)
    close(a.P_obs, b.P_obs, what + " P")
    close(a.chi2, b.chi2, what + " chi2", max(1.0, b.chi2))
    close(a.A, b.A, what + " A")
    for name in ("V_obs", "V_unobs", "V_weak"):  # the directions, whatever their signs
        Va, Vb = getattr(a, name), getattr(b, name)
        close(Va @ Va.T, Vb @ Vb.T, f"{what} {name}", 1.0)
    ua, ub = a.unobservable_directions(), b.unobservable_directions()  # reported: signs too
    assert len(ua) == len(ub), what
    if ua:
        close(np.array(ua), np.array(ub), what + " reported directions", 1.0)
    for cov in (None, np.diag([0.04, 0.09, 0.01])):
        close(a.covariance(cov), b.covariance(cov), what + " covariance")


def same_integrity(a: Integrity, b: Integrity, what: str) -> None:
    assert (a.status, a.excluded, a.reason, a.dof) == (b.status, b.excluded, b.reason, b.dof), what
    same_solution(a.solution, b.solution, what + " solution")
    close(a.cov, b.cov, what + " cov")
    for name in ("horizontal_pl", "heading_pl", "chi2", "separation_h", "separation_heading", "prior_bound_h",
                 "prior_bound_heading"):
        close(getattr(a, name), getattr(b, name), f"{what} {name}", max(abs(getattr(b, name)), 1e-6))
    assert (a.systematic_cov is None) == (b.systematic_cov is None), what
    if b.systematic_cov is not None:
        close(a.systematic_cov, b.systematic_cov, what + " systematic_cov")


# -- random stacks --------------------------------------------------------------------------------------

CAMERA_MOUNTS = {"front": np.array([0.15, 0.0, 0.2]), "left": np.array([0.0, 0.12, 0.2])}


def random_case(rng: np.random.Generator):
    """Observations of 1 to 8 walls around a pose (some seen by both cameras, some parallel, one
    possibly off by centimetres), a coarse pose and its covariance."""
    truth = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-math.pi, math.pi)])
    n_walls = int(rng.integers(1, 6))
    parallel = rng.random() < 0.25  # every wall along one direction: position along it unobserved
    base = rng.uniform(-math.pi, math.pi)
    obs: List[Observation] = []
    for w in range(n_walls):
        a = base + (math.pi * int(rng.integers(2)) if parallel else rng.uniform(-math.pi, math.pi))
        n_g = np.array([math.cos(a), math.sin(a), rng.normal(0, 0.003)])
        dist = rng.uniform(0.4, 6.0)
        d_g = -float(n_g[:2] @ truth[:2]) + dist
        for cam in rng.permutation(list(CAMERA_MOUNTS))[:int(rng.integers(1, 3))]:
            if len(obs) >= 8:
                break
            psi = a - truth[2] + rng.normal(0, 0.002)
            n_r = np.array([math.cos(psi), math.sin(psi), rng.normal(0, 0.003)])
            n_r /= np.linalg.norm(n_r)
            d_r = dist + rng.normal(0, 0.002)
            J = np.eye(3) + rng.normal(0, 0.3, (3, 3))
            L_ = rng.normal(0, 1, (3, 3)) * np.array([1e-3, 1e-3, 3e-3])
            fit_cov = L_ @ L_.T + np.diag([1e-8, 1e-8, 1e-7])
            extra = np.diag(rng.uniform(0, 1e-6, 3))
            unweighted = np.diag(rng.uniform(0, 4e-6, 3)) if rng.random() < 0.7 else None
            o = integ.observation(f"w{w}", str(cam), n_g, d_g, n_r, d_r, dist + rng.uniform(0.0, 0.3), CAMERA_MOUNTS[cam], J,
                            fit_cov, float(rng.uniform(1.0, 6.0)), extra, float(rng.uniform(0.0, 0.02)),
                            float(rng.uniform(0.5, 8.0)), 2.5, rng.uniform(-2, 2, 2), unweighted)
            if o is not None:
                obs.append(o)
    if obs and len(obs) > 1 and rng.random() < 0.4:  # a surface taken for the wall, or a wall off the drawing
        j = int(rng.integers(len(obs)))
        obs[j] = dataclasses.replace(obs[j], y=obs[j].y + np.array([rng.choice([-1, 1]) * rng.uniform(0.01, 0.15),
                                                                      rng.normal(0, 0.01), 0.0]))
    std_xy, std_phi = (0.02, math.radians(1.0)) if rng.random() < 0.5 else (0.1, math.radians(10.0))
    coarse = truth + rng.normal(0, 1, 3) * (std_xy, std_xy, std_phi)
    return obs, tuple(coarse), coarse_covariance(std_xy, std_phi)


def all_subsets(m: int) -> List[Tuple[int, ...]]:
    return [tuple(j for j in range(m) if mask >> j & 1) for mask in range(1 << m)]


def test_random_stacks_solve_and_check_as_the_reference(backend):
    rng = np.random.default_rng(20240607)
    statuses = set()
    excluded = 0
    for case in range(150):
        obs, coarse, cov = random_case(rng)
        if not obs:
            continue
        what = f"{backend} case {case}"
        new, ref = integ.Stack(obs, MODEL), RefStack(obs, MODEL)
        close(new.R, ref.R, what + " R")
        close(new.R_sys, ref.R_sys, what + " R_sys")
        close(new.G_sys, ref.G_sys, what + " G_sys")
        subsets = all_subsets(len(obs)) if len(obs) <= 6 else [tuple(range(len(obs)))] + [
            tuple(j for j in range(len(obs)) if j != k) for k in range(len(obs))]
        for prior in (cov, None):
            for a, b in zip(new.solve_many(subsets, coarse, P.unobservable_std, prior),
                            ref.solve_many(subsets, coarse, P.unobservable_std, prior)):
                same_solution(a, b, f"{what} subset {b.members}")
        args = (coarse, cov, P.unobservable_std, P.false_alarm, P.integrity_risk)
        a, b = integ.Checker(new, *args).check(), RefChecker(ref, *args).check()
        same_integrity(a, b, what)
        statuses.add(b.status)
        excluded += bool(b.excluded)
    # The sample covers what the checks can conclude.
    assert statuses == {"ok", "degenerate", "inconsistent"} and excluded >= 3, (statuses, excluded)


def test_an_empty_stack_and_no_subsets(backend):
    stack = integ.Stack([], MODEL)
    assert stack.R.shape == (0, 0) and stack.solve_many([], (0.0, 0.0, 0.0), 0.05) == []
    obs, coarse, cov = random_case(np.random.default_rng(3))
    new, ref = integ.Stack(obs, MODEL), RefStack(obs, MODEL)
    assert new.solve_many([], coarse, 0.05, cov) == []
    same_solution(new.solve((), coarse, 0.05, cov), ref.solve((), coarse, 0.05, cov), "empty subset")


# -- the localizer on rendered frames -----------------------------------------------------------------

def scenes():
    """(map, frames, [(coarse, cov), ...]) with panels, boards, boxes, walls as built, depth scale errors."""
    arena = load_plane_map("config/maps/paper_arena.yaml")
    fzk = load_plane_map("config/maps/fzk_haus_ground.yaml")
    rng = np.random.default_rng(11)
    out = []
    spots = [(arena, (0.5, 0.5, 0.3)), (arena, (0.35, 0.7, 2.6)), (arena, (0.2, 0.9, -0.8)), (arena, (0.9, 0.3, 2.4)),
             (fzk, None), (fzk, None)]
    for k, (pm, truth) in enumerate(spots):
        if truth is None:
            truth = free_space_poses(pm, 1, rng, clearance=0.5, z=0.15)[0]
        walls = [p for p in pm.planes if abs(p.pi[2]) < 0.5]
        wall = walls[int(rng.integers(len(walls)))]
        clutter = [parallel_panel(wall, float(rng.uniform(0.05, 0.3)), float(rng.uniform(0.3, 0.8)), rng),
                   Box(truth[0] + 0.8, truth[1] + 0.3, 0.2, 0.2, 0.2, 0.3)]
        if k % 2:
            clutter.append(leaning_boards(walls[int(rng.integers(len(walls)))], 0.6, rng, count=2, width=0.5))
        noise = DepthNoise.realistic(scale_error={"front": 0.004, "left": -0.006}, unit_seed=k)
        scene = SimScene(pm, clutter, walls=as_built(pm, rng))
        frames = [render_depth_frame(ROBOT, scene, c.name, truth, rng=rng, noise=noise, frame_number=k)
                  for c in ROBOT.cameras]
        off = rng.normal(0, 1, 3) * (0.01, 0.01, math.radians(0.5))
        tracking = ((truth[0] + off[0], truth[1] + off[1], truth[2] + off[2]), coarse_covariance(0.02, math.radians(1.0)))
        cold = ((truth[0] + 0.07, truth[1] - 0.07, truth[2] + math.radians(10.0)), None)
        out.append((pm, frames, [tracking, cold]))
    return out


@pytest.fixture(scope="module")
def rendered():
    return scenes()


def summary(res) -> Dict:
    return {"status": res.status, "pose": np.array(res.pose), "cov": np.array(res.cov), "hpl": res.horizontal_pl,
            "vpl": res.heading_pl, "passes": res.passes, "integrity": res.integrity, "unobservable": res.unobservable,
            "planes": [p.to_json() for p in res.planes],
            "sys": None if res.systematic_cov is None else np.array(res.systematic_cov),
            "measurements": [(m.plane_id, m.camera, np.array(m.R)) for m in res.measurements]}


def same_tree(a, b, path: str) -> None:
    if isinstance(b, dict):
        assert set(a) == set(b), path
        for k in b:
            same_tree(a[k], b[k], f"{path}.{k}")
    elif isinstance(b, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            same_tree(x, y, f"{path}[{i}]")
    elif isinstance(b, np.ndarray):
        close(a, b, path)
    elif isinstance(b, float):
        close(a, b, path, max(abs(b), 1e-6) if math.isfinite(b) else None)
    else:
        assert a == b, (path, a, b)


def test_the_localizer_gives_the_reference_results_on_rendered_frames(backend, rendered, monkeypatch):
    statuses = []
    for k, (pm, frames, runs) in enumerate(rendered):
        loc = Localizer(ROBOT, pm)
        for i, (coarse, cov) in enumerate(runs):
            for n in (1, 2):
                with monkeypatch.context() as m:
                    m.setattr(loc_mod, "Stack", RefStack)
                    m.setattr(loc_mod, "Checker", RefChecker)
                    ref = loc.localize(frames[:n], coarse, cov)
                new = loc.localize(frames[:n], coarse, cov)
                same_tree(summary(new), summary(ref), f"{backend} scene {k} run {i} frames {n}")
                statuses.append(ref.status)
        paper = loc.localize(frames, *runs[0], method="paper")
        with monkeypatch.context() as m:
            m.setattr(loc_mod, "Stack", RefStack)
            m.setattr(loc_mod, "Checker", RefChecker)
            same_tree(summary(paper), summary(loc.localize(frames, *runs[0], method="paper")), f"{backend} paper {k}")
    assert len(set(statuses)) >= 2, statuses
