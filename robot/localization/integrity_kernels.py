"""Compiled kernels for the pose solve (robot/localization/integrity.py): the joint covariance of a
stack of observations, the solution of each subset of them, the leave-one-out separation
statistics; and whether they run.

A localization solves a handful of subsets of 2 to 8 planes (the all-in solution and one per
fault hypothesis). In numpy each step of that is a call on (B, 3m, 3m) stacked arrays that
costs more in dispatch (and, between the frames' other work, in cold caches) than in
arithmetic; here each subset is a few loops over its own 3k x 3k block:

* :func:`stack`: ``integrity.Stack``'s G_sys, R_sys, R, W_own and H_i^T W_i;
* :func:`solve`: per subset, the residuals at the linearisation point, the inverse of its
  covariance block (LU with partial pivoting, as LAPACK's gesv that ``np.linalg.inv`` calls),
  the information H^T R^-1 H and its eigen-decomposition (Jacobi rotations), the observed and
  weak directions, the chi-square, the gain A, the pose and its covariance A R A^T;
* :func:`separation`: ``integrity._separation_statistics``' s^T C^+ s.

``integrity.Stack`` and ``integrity._separation_statistics_numpy`` keep the numpy code, the
reference and the fallback. The kernels work on each subset's own rows where numpy works on all
rows with the others decoupled (unit variance, no sensitivity, no residual): the same
quantities, summed in another order, so they agree with numpy to the rounding of their sums
(1e-15 relative, an inverse to its condition number times that; tests/test_integrity_speed_
equivalence.py compares both on random and on rendered stacks). fastmath is off.

Eigenvectors are defined up to sign, and Jacobi's signs are not LAPACK's. Nothing computed from
them depends on the sign, but a subset's unobserved and weak directions are reported
(``Solution.unobservable_directions``, the localizer's ``unobservable``): for a subset with any,
the caller takes the eigenvectors from numpy's ``eigh`` of the same information matrix, so the
reported directions are numpy's, signs included.

Backend: the plane fit's (:func:`robot.localization.fit_kernels.backend`, environment variable
``ROBOT_KERNELS``): these kernels run when it is numba. They compile (or load from numba's
disk cache, ``NUMBA_CACHE_DIR``) at their first use, or at :func:`warm_up`; if compiling fails,
``auto`` falls back to numpy (:func:`backend_note` says why) and ``numba`` raises. numba is
imported only then, never by importing this module. They use no numba linear algebra (which
would load scipy's LAPACK).
"""

from __future__ import annotations

import math
import os
import threading
import time
from typing import Any, Dict, Optional, Tuple

import numpy as np

from robot.base.kernel_cache import compile_kernel_set, jit_table
from robot.localization import fit_kernels

_nb: Dict[str, Any] = {}  # kernel name -> numba dispatcher
_failed = ""  # why the kernels did not compile ("": they did, or were not tried)
_lock = threading.Lock()  # one compilation, whichever thread first solves
_KERNELS = ("_stack_kernel", "_solve_kernel", "_separation_kernel")
_EYE3 = np.eye(3)


def compiled() -> bool:
    """Whether the compiled kernels run (fit_kernels' backend is numba and they compiled)."""
    if fit_kernels.backend() != "numba":
        return False
    if not _nb and not _failed:
        warm_up()
    return bool(_nb)


def backend_note() -> str:
    """One line on whether the integrity kernels run, and why not."""
    if fit_kernels.backend() != "numba":
        return "numpy (the plane fit's backend is numpy)"
    if not _nb and not _failed:
        warm_up()
    return f"numpy ({_failed})" if _failed else f"numba {_nb.get('version', '')}"


def warm_up() -> float:
    """Compile the kernels (or load them from numba's cache) on tiny inputs. Returns the seconds it
    took (0 with the numpy backend). If compiling fails, "auto" falls back to numpy and "numba"
    (ROBOT_KERNELS) raises."""
    global _failed
    if fit_kernels.backend() != "numba":
        return 0.0
    t0 = time.perf_counter()
    with _lock:
        if not (_nb or _failed):
            _failed = compile_kernel_set(_nb, _load, _run_each_kernel, "the integrity kernels",
                                         os.environ.get(fit_kernels.ENV, "auto").strip().lower() == "numba")
    return time.perf_counter() - t0


def _load() -> Dict[str, Any]:
    """numba's dispatchers of the kernels (they compile, or load from the cache, at their first call),
    or the plane fit's backend's kernels compiled ahead of time."""
    return fit_kernels.kernel_table("integrity", jit_kernels)


def jit_kernels() -> Dict[str, Any]:
    """Fresh numba dispatchers of the kernels (also what the ahead-of-time module falls back to
    for an argument type it was not built for)."""
    import numba

    for fn in (_inverse, _eigh3, _rows_of, _wrap):
        numba.extending.register_jitable(fn)
    return jit_table(numba, globals(), _KERNELS)


def _run_each_kernel(kernels: Dict[str, Any]) -> None:
    """Each kernel once on a two-plane stack, with and without a prior, and with an empty subset."""
    H0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    H1 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    R3 = np.eye(3) * 1e-4
    blocks = np.array([(H0, R3, R3, np.eye(3)), (H1, R3, R3, np.eye(3))])
    rows = np.array([(np.full(3, 1e-3), np.zeros(3), np.full(3, 0.01))] * 2)
    y, h0, _, H, _, _, R, _, HtW = stack(blocks, rows, np.ones((2, 3, 7)), np.array([[0, 7], [0, 10]], np.intp), 13,
                                         np.full(7, 0.01), 1e-14, 1e-14, kernels)
    member = np.array([[True, True], [True, False], [False, False]])
    out = solve(R, H, y, h0, np.zeros(3), HtW, member, 0.0025, np.eye(3), kernels)
    solve(R, H, y, h0, np.zeros(3), HtW, member, 0.0025, None, kernels)
    A = out[7]
    separation(A, A[0], np.tile(np.eye(3), (3, 1, 1)), np.array([3, 2, 0], np.intp), np.zeros((3, 3)), R, kernels)


# -- the kernels' callers ---------------------------------------------------------------------------

def stack(blocks: np.ndarray, rows: np.ndarray, G_camera: np.ndarray, cols: np.ndarray, n_par: int,
          cam_std: np.ndarray, floor: float, diagonal_floor: float, kernels: Optional[Dict[str, Any]] = None
          ) -> Tuple[np.ndarray, ...]:
    """``integrity.Stack``'s arrays from its m observations' (H, R_own, R_weight, G_plane) (m, 4, 3, 3),
    (y, h0, plane_std) (m, 3, 3), G_camera (m, 3, 7) and first camera and plane column (m, 2): (y, h0,
    H_blocks, H, G_sys, R_sys, R, W_own, H_i^T W_i side by side (3, 3m)). ``floor``: added to
    R_weight's diagonal before its inverse; ``diagonal_floor``: to R's. LinAlgError where numpy's
    inverse raises it."""
    ok, *out = (kernels or _nb)["_stack_kernel"](blocks, rows, G_camera, cols, int(n_par), cam_std, float(floor),
                                                  float(diagonal_floor))
    if not ok:
        raise np.linalg.LinAlgError("Singular matrix")
    y, h0, H_blocks, rest = out[0], out[1], out[2], out[3:]
    return (y, h0, H_blocks, H_blocks.reshape(len(y), 3)) + tuple(rest)


def solve(R: np.ndarray, H: np.ndarray, y: np.ndarray, h0: np.ndarray, x_lin: np.ndarray, HtW: np.ndarray,
          member: np.ndarray, unobservable_var: float, prior: Optional[np.ndarray],
          kernels: Optional[Dict[str, Any]] = None) -> Tuple[Any, ...]:
    """``integrity.Stack.solve_many``'s algebra for each subset (row b of the (B, m) mask ``member``):
    (info (B, 3, 3), lam (B, 3), V (B, 3, 3), observed (B, 3), weak (B, 3), k_obs (B,), chi2 (B,),
    A (B, 3, 3m), x (B, 3) with its heading wrapped, P (B, 3, 3), how many subsets have an unobserved
    or weak direction). LinAlgError where numpy's inverse raises it."""
    has_prior = prior is not None
    ok, *out = (kernels or _nb)["_solve_kernel"](R, H, y, h0, x_lin, HtW, member, float(unobservable_var),
                                                 prior if has_prior else _EYE3, has_prior)
    if not ok:
        raise np.linalg.LinAlgError("Singular matrix")
    return tuple(out)


def separation(A_subs: np.ndarray, A_all: np.ndarray, V: np.ndarray, k_obs: np.ndarray, sep: np.ndarray,
               R: np.ndarray, kernels: Optional[Dict[str, Any]] = None) -> Tuple[np.ndarray, np.ndarray]:
    """``integrity._separation_statistics`` from the subsets' gains (B, 3, 3m), the all-in gain,
    each subset's observed directions first in V (B, 3, 3) with their count, and the separations."""
    return (kernels or _nb)["_separation_kernel"](A_subs, A_all, V, k_obs, sep, R)


# -- the kernels (plain Python here; _load compiles them) ------------------------------------------
# Elementwise expressions keep the numpy code's operations and their order; sums run over each
# subset's own rows.

def _inverse(M, k, Mi):  # pragma: no cover (compiled)
    """Mi[:k, :k] = M[:k, :k]^-1 by LU with partial pivoting and two triangular solves per
    column of the identity (LAPACK's gesv); False if M is singular. M is overwritten."""
    piv = np.empty(k, np.intp)
    for j in range(k):
        p = j
        big = abs(M[j, j])
        for i in range(j + 1, k):
            if abs(M[i, j]) > big:
                big = abs(M[i, j])
                p = i
        piv[j] = p
        if M[p, j] == 0.0:
            return False
        if p != j:
            for c in range(k):
                t = M[j, c]
                M[j, c] = M[p, c]
                M[p, c] = t
        inv = 1.0 / M[j, j]
        for i in range(j + 1, k):
            f = M[i, j] * inv
            M[i, j] = f
            for c in range(j + 1, k):
                M[i, c] -= f * M[j, c]
    for c in range(k):
        for i in range(k):
            Mi[i, c] = 0.0
        Mi[c, c] = 1.0
    for j in range(k):  # the row swaps, in order
        p = piv[j]
        if p != j:
            for c in range(k):
                t = Mi[j, c]
                Mi[j, c] = Mi[p, c]
                Mi[p, c] = t
    for c in range(k):
        for j in range(k):  # L y = b (unit diagonal)
            x = Mi[j, c]
            if x != 0.0:
                for i in range(j + 1, k):
                    Mi[i, c] -= x * M[i, j]
        for j in range(k - 1, -1, -1):  # U x = y
            Mi[j, c] /= M[j, j]
            x = Mi[j, c]
            if x != 0.0:
                for i in range(j):
                    Mi[i, c] -= x * M[i, j]
    return True


def _eigh3(S, lam, W):  # pragma: no cover (compiled)
    """Eigenvalues (ascending) and eigenvectors (columns of W) of the symmetric 3 x 3 S by cyclic
    Jacobi rotations, to the rounding of S's largest entry."""
    a = S.copy()
    for i in range(3):
        for j in range(3):
            W[i, j] = 1.0 if i == j else 0.0
    for _ in range(64):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off <= 1e-36 * (diag + off):  # (rotations converge quadratically: well below the rounding)
            break
        for p in range(2):
            for q in range(p + 1, 3):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(3):  # a <- a J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(3):  # a <- J^T a (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                a[p, q] = 0.0
                a[q, p] = 0.0
                for k in range(3):
                    wkp, wkq = W[k, p], W[k, q]
                    W[k, p] = c * wkp - s * wkq
                    W[k, q] = s * wkp + c * wkq
    for i in range(3):
        lam[i] = a[i, i]
    for i in range(2):  # ascending, as LAPACK's
        j = i
        for k in range(i + 1, 3):
            if lam[k] < lam[j]:
                j = k
        if j != i:
            t = lam[i]
            lam[i] = lam[j]
            lam[j] = t
            for k in range(3):
                t = W[k, i]
                W[k, i] = W[k, j]
                W[k, j] = t


def _wrap(a):  # pragma: no cover (compiled)
    """geometry.wrap_angle: (a + pi) % 2 pi - pi with numpy's (and Python's) remainder."""
    b = 2.0 * math.pi
    mod = np.fmod(a + math.pi, b)
    if mod != 0.0:
        if (b < 0.0) != (mod < 0.0):
            mod += b
    else:
        mod = math.copysign(0.0, b)
    return mod - math.pi


def _rows_of(member, b, rows):  # pragma: no cover (compiled)
    k = 0
    for j in range(member.shape[1]):
        if member[b, j]:
            for c in range(3):
                rows[k] = 3 * j + c
                k += 1
    return k


def _stack_kernel(blocks, rows3, Gc, cols, n_par, cam_std, floor, dfloor):  # pragma: no cover (compiled)
    m = blocks.shape[0]
    n = 3 * m
    y = np.empty(n)
    h0 = np.empty(n)
    Hb = np.empty((m, 3, 3))
    sig = np.zeros(n_par)
    for i in range(m):  # every camera's std, and the widest claim of each wall's views
        c, p = cols[i, 0], cols[i, 1]
        for j in range(7):
            sig[c + j] = cam_std[j]
        for j in range(3):
            y[3 * i + j] = rows3[i, 0, j]
            h0[3 * i + j] = rows3[i, 1, j]
            v = rows3[i, 2, j]
            if not v <= sig[p + j]:  # np.maximum: NaN wins
                sig[p + j] = v
    G = np.zeros((n, n_par))
    R = np.zeros((n, n))
    R_sys = np.zeros((n, n))
    W = np.empty((m, 3, 3))
    HtW = np.empty((3, n))
    M = np.empty((3, 3))
    Wi = np.empty((3, 3))
    for i in range(m):
        c, p = cols[i, 0], cols[i, 1]
        for a in range(3):
            for j in range(7):
                G[3 * i + a, c + j] = Gc[i, a, j] * sig[c + j]
            for j in range(3):
                G[3 * i + a, p + j] = blocks[i, 3, a, j] * sig[p + j]
                Hb[i, a, j] = blocks[i, 0, a, j]
                M[a, j] = blocks[i, 2, a, j] + (floor if a == j else 0.0)
        if not _inverse(M, 3, Wi):
            return False, y, h0, Hb, G, R_sys, R, W, HtW
        for a in range(3):
            for j in range(3):
                W[i, a, j] = Wi[a, j]
                s = 0.0
                for q in range(3):
                    s += Hb[i, q, a] * Wi[q, j]
                HtW[a, 3 * i + j] = s
    # R_sys = G_sys G_sys^T: two rows share only their camera's columns (first) and their wall's.
    for i in range(n):
        ci, pi = cols[i // 3, 0], cols[i // 3, 1]
        for j in range(n):
            s = 0.0
            if cols[j // 3, 0] == ci:
                for q in range(ci, ci + 7):
                    s += G[i, q] * G[j, q]
            if cols[j // 3, 1] == pi:
                for q in range(pi, pi + 3):
                    s += G[i, q] * G[j, q]
            R_sys[i, j] = s
    for i in range(m):
        for a in range(3):
            for j in range(3):
                R[3 * i + a, 3 * i + j] = blocks[i, 1, a, j]
    for i in range(n):
        for j in range(n):
            R[i, j] += R_sys[i, j]
        R[i, i] += dfloor
    return True, y, h0, Hb, G, R_sys, R, W, HtW


def _solve_kernel(R, H, y, h0, x, HtW, member, unobs_var, prior, has_prior):  # pragma: no cover (compiled)
    B, m = member.shape
    n = 3 * m
    info = np.zeros((B, 3, 3))
    lam = np.zeros((B, 3))
    V = np.zeros((B, 3, 3))
    observed = np.zeros((B, 3), np.bool_)
    weak = np.zeros((B, 3), np.bool_)
    k_obs = np.zeros(B, np.intp)
    chi2 = np.zeros(B)
    A = np.zeros((B, 3, n))
    X = np.zeros((B, 3))
    P = np.zeros((B, 3, 3))
    exposed = 0
    r = np.empty(n)
    for i in range(n):  # Stack.residual
        r[i] = y[i] - (H[i, 0] * x[0] + H[i, 1] * x[1] + H[i, 2] * x[2] + h0[i])
        if i % 3 == 1:
            r[i] = _wrap(r[i])
    rows = np.empty(n, np.intp)
    Rs = np.empty((n, n))
    Ri = np.empty((n, n))
    HtRi = np.empty((3, n))
    As = np.empty((3, n))
    AR = np.empty((3, n))
    N = np.empty((3, 3))
    T = np.empty((3, 3))
    Ti = np.empty((3, 3))
    M = np.empty((3, 3))
    lb = np.empty(3)
    Vb = np.empty((3, 3))
    g = np.empty(3)
    for b in range(B):
        k = _rows_of(member, b, rows)
        # Generalised least squares over the subset's rows: information, H^T R^-1 r, r^T R^-1 r.
        for i in range(k):
            for j in range(k):
                Rs[i, j] = R[rows[i], rows[j]]
        if not _inverse(Rs, k, Ri):
            return False, info, lam, V, observed, weak, k_obs, chi2, A, X, P, exposed
        for a in range(3):
            for j in range(k):
                s = 0.0
                for i in range(k):
                    s += H[rows[i], a] * Ri[i, j]
                HtRi[a, j] = s
        for a in range(3):
            sg = 0.0
            for c in range(3):
                N[a, c] = 0.0
            for j in range(k):
                h = HtRi[a, j]
                sg += h * r[rows[j]]
                for c in range(3):
                    N[a, c] += h * H[rows[j], c]
            g[a] = sg
        for a in range(3):
            for c in range(3):
                info[b, a, c] = 0.5 * (N[a, c] + N[c, a])
        rRr = 0.0
        for i in range(k):
            t = 0.0
            for j in range(k):
                t += Ri[i, j] * r[rows[j]]
            rRr += r[rows[i]] * t
        _eigh3(info[b], lb, Vb)
        for a in range(3):
            lam[b, a] = lb[a]
            for c in range(3):
                V[b, a, c] = Vb[a, c]
        # Observed where the subset knows the direction better than the floor or the prior.
        c2 = rRr
        for i in range(3):
            floor = unobs_var
            if has_prior:
                s = 0.0
                for j in range(3):
                    for q in range(3):
                        s += Vb[j, i] * prior[j, q] * Vb[q, i]
                floor = max(unobs_var, s)
            ob = lb[i] > 1.0 / floor
            observed[b, i] = ob
            weak[b, i] = ob and lb[i] < 1.0 / unobs_var
            if ob:
                k_obs[b] += 1
                w = 0.0
                for a in range(3):
                    w += Vb[a, i] * g[a]
                c2 -= w * w / lb[i]
        chi2[b] = c2
        if k_obs[b] < 3 or weak[b, 0] or weak[b, 1] or weak[b, 2]:
            exposed += 1
        # The estimate's normal matrix in V's basis, unobserved rows and columns replaced by the
        # identity, inverted, then dropped: A = V Ti V^T H^T W over the subset's rows.
        for a in range(3):
            for c in range(3):
                N[a, c] = 0.0
        for j in range(k):
            for a in range(3):
                h = HtW[a, rows[j]]
                for c in range(3):
                    N[a, c] += h * H[rows[j], c]
        for i in range(3):
            for c in range(3):
                s = 0.0
                for a in range(3):
                    s += Vb[a, i] * N[a, c]
                M[i, c] = s
        for i in range(3):
            for j in range(3):
                if observed[b, i] and observed[b, j]:
                    s = 0.0
                    for c in range(3):
                        s += M[i, c] * Vb[c, j]
                    T[i, j] = s
                else:
                    T[i, j] = 1.0 if i == j else 0.0
        if not _inverse(T, 3, Ti):
            return False, info, lam, V, observed, weak, k_obs, chi2, A, X, P, exposed
        for i in range(3):
            for j in range(3):
                if not (observed[b, i] and observed[b, j]):
                    Ti[i, j] = 0.0
        for i in range(3):  # M = V Ti V^T
            for j in range(3):
                s = 0.0
                for a in range(3):
                    s += Vb[i, a] * Ti[a, j]
                T[i, j] = s
        for i in range(3):
            for j in range(3):
                s = 0.0
                for a in range(3):
                    s += T[i, a] * Vb[j, a]
                M[i, j] = s
        for i in range(3):
            d = 0.0
            for j in range(k):
                s = 0.0
                for a in range(3):
                    s += M[i, a] * HtW[a, rows[j]]
                As[i, j] = s
                A[b, i, rows[j]] = s
                d += s * r[rows[j]]
            X[b, i] = x[i] + d
        X[b, 2] = _wrap(X[b, 2])
        for i in range(3):
            for j in range(k):
                s = 0.0
                for q in range(k):
                    s += As[i, q] * R[rows[q], rows[j]]
                AR[i, j] = s
        for i in range(3):
            for j in range(3):
                s = 0.0
                for q in range(k):
                    s += AR[i, q] * As[j, q]
                T[i, j] = s
        for i in range(3):
            for j in range(3):
                P[b, i, j] = 0.5 * (T[i, j] + T[j, i])
    return True, info, lam, V, observed, weak, k_obs, chi2, A, X, P, exposed


def _separation_kernel(A_subs, A_all, V, k_obs, sep, R):  # pragma: no cover (compiled)
    B, _, n = A_subs.shape
    q = np.zeros(B)
    count = np.zeros(B, np.intp)
    T = np.empty((3, n))
    TR = np.empty((3, n))
    C = np.empty((3, 3))
    u = np.empty(3)
    lam = np.empty(3)
    W = np.empty((3, 3))
    for b in range(B):
        k = k_obs[b]
        for i in range(3):  # the separation's gain in the subset's observed directions: V^T (A_sub - A_all)
            for j in range(n):
                s = 0.0
                for a in range(3):
                    s += V[b, a, i] * (A_subs[b, a, j] - A_all[a, j])
                T[i, j] = s
        for i in range(3):
            for j in range(n):
                s = 0.0
                for c in range(n):
                    s += T[i, c] * R[c, j]
                TR[i, j] = s
        for i in range(3):
            for j in range(3):
                s = 0.0
                if i < k and j < k:
                    for c in range(n):
                        s += TR[i, c] * T[j, c]
                C[i, j] = s
        for i in range(3):
            for j in range(i + 1, 3):
                s = 0.5 * (C[i, j] + C[j, i])
                C[i, j] = s
                C[j, i] = s
        for i in range(3):
            s = 0.0
            if i < k:
                for a in range(3):
                    s += V[b, a, i] * sep[b, a]
            u[i] = s
        _eigh3(C, lam, W)
        top = max(max(lam[0], max(lam[1], lam[2])), 1e-30)
        for i in range(3):
            if lam[i] > 1e-9 * top:
                z = 0.0
                for a in range(3):
                    z += W[a, i] * u[a]
                q[b] += z * z / lam[i]
                count[b] += 1
    return q, count
