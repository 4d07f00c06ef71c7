"""The plane fit's compiled kernels (robot/localization/fit_kernels.py) agree with its numpy code,
the reference: kernel by kernel on random inputs, fit_plane on synthetic ROIs, and the whole
localizer on rendered frames; and the backend choice (ROBOT_KERNELS) behaves."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from drivers.sim.clutter import leaning_boards, parallel_panel
from drivers.sim.render import Box, SimScene, render_depth_frame
from robot.config import load_robot_config
from robot.localization import fit_kernels as fk
from robot.localization import plane_fit as pf
from robot.localization.localizer import Localizer, coarse_covariance
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
NEEDS_NUMBA = "the compiled kernels need numba (pip install -e '.[perf]')"


@pytest.fixture
def numba_backend():
    pytest.importorskip("numba", reason=NEEDS_NUMBA)
    assert fk.set_backend("numba") == "numba"


def rel_err(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = float(np.max(np.abs(b))) if b.size else 0.0
    return float(np.max(np.abs(a - b))) / scale if scale > 0 else float(np.max(np.abs(a - b), initial=0.0))


# -- random inputs -----------------------------------------------------------------------------------

def wall_points(rng, n, d=None, normal=None, spread=(0.55, 0.4)):
    """Rays (rx, ry) of n pixels and the true plane q = -normal / d in inverse depth."""
    normal = pf.unit(normal if normal is not None else [rng.normal(0, 0.3), rng.normal(0, 0.2), -1.0])
    d = rng.uniform(0.4, 4.0) if d is None else d
    rx, ry = rng.uniform(-spread[0], spread[0], n), rng.uniform(-spread[1], spread[1], n)
    return rx, ry, -normal / d


def noisy_inverse_depth(rng, rx, ry, q, params, outliers=0.1, heavy=True):
    """Measured inverse depths of the plane q: stereo noise (``heavy``: with heavy tails), a share
    of points far off the plane (outside the band; ``heavy``: also behind it), quantised to the
    depth unit. The Huber loss acts on either noise."""
    c = params.noise_subpixel / params.noise_fx_b
    y = rx * q[0] + ry * q[1] + q[2] + c * (rng.standard_t(3, len(rx)) if heavy else rng.normal(0, 1, len(rx)))
    off = rng.random(len(rx)) < outliers
    y[off] *= rng.choice([0.7, 1.3] if heavy else [1.3], int(off.sum())) * rng.uniform(0.9, 1.1, int(off.sum()))
    y = np.maximum(y, 0.05)
    if params.depth_unit > 0:
        z = np.maximum(np.round(1.0 / y / params.depth_unit), 1.0) * params.depth_unit
        y = 1.0 / z
    return y


# The depth unit's pattern in a covariance sums float32 sines of thousands of radians, libm's in
# the kernel and numpy's own in the reference: 1-ulp differences, and the random phases cancel,
# so that term agrees to about 1e-5 and a covariance holding it to 1e-6 (everything else to 1e-9).
PATTERN_TOL = 1e-6


def assert_same_tail(got, ref, cov_tol=1e-9):
    assert rel_err(got.n, ref.n) < 1e-12 and abs(got.d - ref.d) <= 1e-12 * ref.d
    assert got.mask.dtype == bool and np.array_equal(got.mask, ref.mask) and got.count == ref.count
    assert abs(got.chi2 - ref.chi2) <= 1e-9 * abs(ref.chi2)
    assert got.behind == ref.behind and got.k_in == ref.k_in
    assert rel_err(got.basis, ref.basis) < 1e-12
    assert (got.cov is None) == (ref.cov is None) and (got.info is None) == (ref.info is None)
    if ref.cov is not None:
        assert rel_err(got.cov, ref.cov) < cov_tol and rel_err(got.info, ref.info) < cov_tol * np.linalg.cond(ref.cov)
    assert rel_err(got.sums, ref.sums) < 1e-9
    assert (got.halves is None) == (ref.halves is None)
    if ref.halves is not None:
        for a, b in zip(got.halves, ref.halves):
            assert rel_err(a, b) < 1e-9


@pytest.mark.parametrize("seed", range(40))
def test_fit_tail_kernel_equals_the_numpy_tail(numba_backend, seed):
    """The fit after identification in one call (refit stages, the dense rear check's count, the
    covariance with the depth unit's pattern and its inverse, the inlier summary) against
    plane_fit._tail: the same inliers and counts; plane, covariance and sums to the rounding of
    their sums (the pattern's float32 sines: libm's against numpy's)."""
    rng = np.random.default_rng(seed)
    depth_unit = (0.0, 0.001, 0.004)[seed % 3]
    params = pf.FitParams(depth_unit=depth_unit, min_threshold=(0.004, 0.0133)[seed % 2])
    n = int(rng.choice([400, 1500, 2500, 6000, 12000]))
    # Near walls too: within half a metre the depth unit's pattern is in the covariance.
    rx, ry, q_true = wall_points(rng, n, d=rng.uniform(0.3, 4.0))
    y = noisy_inverse_depth(rng, rx, ry, q_true, params, outliers=rng.uniform(0.0, 0.4))
    z = 1.0 / y
    q0 = q_true * (1.0 + rng.normal(0, 0.01, 3))  # where identification leaves it: off by many sigma
    up = np.array([0.0, -1.0, 0.0]) if seed % 2 else None
    for stride in (0, n // (4 * params.sample)):
        for flat in (True, False):
            ref = pf._tail(rx, ry, y, z, q0, stride, params, up, flat)
            got = fk.fit_tail(rx, ry, y, z, q0, stride, params, up, flat)
            assert_same_tail(got, ref, PATTERN_TOL if depth_unit > 0 else 1e-9)
    # The cases the kernel must cover: Huber weights and points outside the band.
    q_ref = -ref.n / ref.d
    c = params.noise_subpixel / params.noise_fx_b
    res = np.abs(y - (rx * q_ref[0] + ry * q_ref[1] + q_ref[2]))
    assert np.any(ref.mask & (res > params.huber_k * c)) and not ref.mask.all()


def test_fit_tail_covers_the_depth_units_pattern_and_what_lies_behind(numba_backend, monkeypatch):
    """A near wall (its depth unit's pattern counts) with a far surface seen through a hole:
    both paths count the same points behind, and the pattern's term is there in both."""
    rng = np.random.default_rng(11)
    params = pf.FitParams(depth_unit=0.001)
    rx, ry, q = wall_points(rng, 12000, d=0.25, normal=[0.1, 0.0, -1.0])
    qq = np.tile(q, (len(rx), 1))
    qq[(np.abs(rx) < 0.15) & (ry > 0)] = q * 0.25 / 0.8  # through a hole, 0.55 m behind
    y = noisy_inverse_depth(rng, rx, ry, qq.T, params, outliers=0.0, heavy=False)
    z = 1.0 / y
    ref = pf._tail(rx, ry, y, z, q, 0, params, None, True)
    got = fk.fit_tail(rx, ry, y, z, q, 0, params, None, True)
    assert_same_tail(got, ref, PATTERN_TOL)
    assert ref.behind > 0
    with monkeypatch.context() as m:
        m.setattr(pf, "_quantisation_cov", lambda *args: np.zeros((3, 3)))
        without = pf._tail(rx, ry, y, z, q, 0, params, None, True)
    # The pattern's term is a real part of this covariance, so the comparison above tested it.
    assert np.max(np.abs(np.diag(ref.cov) - np.diag(without.cov)) / np.diag(ref.cov)) > 0.01


def test_fit_tail_with_no_inliers_takes_no_step(numba_backend):
    """All points outside the band: numpy's solve of the zero system raises, the loop takes no
    step, and the covariance of no inliers is none (a degenerate set) on both paths."""
    rng = np.random.default_rng(3)
    params = pf.FitParams(depth_unit=0.001)
    rx, ry, q = wall_points(rng, 800, d=2.0)
    y = noisy_inverse_depth(rng, rx, ry, q, params, outliers=0.0)
    q_far = q * 0.5  # the plane twice as far: nothing within its band
    for up in (None, np.array([0.0, -1.0, 0.0])):
        ref = pf._tail(rx, ry, y, 1.0 / y, q_far, 0, params, up, True)
        got = fk.fit_tail(rx, ry, y, 1.0 / y, q_far, 0, params, up, True)
        assert not ref.mask.any() and not got.mask.any() and got.count == ref.count == 0
        qn = math.sqrt(float(q_far @ q_far))
        assert rel_err(got.n, -q_far / qn) < 1e-15 and rel_err(ref.n, -q_far / qn) < 1e-15
        assert got.cov is None and ref.cov is None and got.chi2 == ref.chi2 == 0.0
        assert got.k_in == ref.k_in == 0 and got.halves is None and ref.halves is None


def two_surfaces(rng, n, params):
    """A wall and a panel 0.15 m in front of it over part of the patch, with noise and outliers."""
    rx, ry, q = wall_points(rng, n, d=rng.uniform(0.8, 3.0))
    panel = rx < rng.uniform(-0.3, 0.2)
    q_panel = q * (1.0 / q[2]) / (1.0 / q[2] - 0.15)
    qq = np.where(panel[:, None], q_panel, q)
    y = noisy_inverse_depth(rng, rx, ry, np.array([qq[:, 0], qq[:, 1], qq[:, 2]]), params, outliers=0.05)
    return rx, ry, 1.0 / y, q


@pytest.mark.parametrize("seed", range(12))
def test_score_kernel_counts_exactly_what_numpy_counts(numba_backend, seed):
    rng = np.random.default_rng(100 + seed)
    params = pf.FitParams(depth_unit=0.001 if seed % 2 else 0.0)
    rx, ry, z, _ = two_surfaces(rng, 3000, params)
    sub = pf._subsample(rx, ry, z, params)
    m = len(sub.z)
    pool = np.flatnonzero(rng.random(m) < 0.6)
    nh, dh = pf._global_hypotheses(sub, np.arange(m), params.iterations)
    nl, dl = pf._local_hypotheses(sub, pool, params.iterations)
    # Hypotheses that put one point each exactly on its band edge (in exact arithmetic): whether it
    # counts is decided by float32 rounding alone, which the kernel must reproduce.
    j = rng.choice(m, 60, replace=False)
    ne = np.tile(nh[:1], (60, 1))
    nr = ne[:, 0] * sub.rx[j] + ne[:, 1] * sub.ry[j] + ne[:, 2]
    de = -nr * sub.z[j] + sub.thr[j] * np.abs(nr) * rng.choice([-1.0, 1.0], 60)
    for hn, hd in ((nh, dh), (nl, dl), (ne, de)):
        for cols in (None, pool):
            ref = pf._score(sub, hn, hd, cols)
            got = fk.score(hn, hd, sub.rays32, sub.z32, sub.thr32, cols)
            assert np.array_equal(got, ref)
            assert got.dtype == ref.dtype


def test_score_kernel_for_a_blas_without_fused_products(numba_backend):
    """Where numpy's float32 product rounds each product and sum (no FMA), the kernel counts as an
    elementwise numpy score with those roundings does."""
    rng = np.random.default_rng(7)
    params = pf.FitParams(depth_unit=0.001)
    rx, ry, z, _ = two_surfaces(rng, 3000, params)
    sub = pf._subsample(rx, ry, z, params)
    nh, dh = pf._global_hypotheses(sub, np.arange(len(sub.z)), params.iterations)
    n32, d32 = nh.astype(np.float32), dh.astype(np.float32)
    nr = (n32[:, 0:1] * sub.rays32[0] + n32[:, 1:2] * sub.rays32[1]) + n32[:, 2:3] * sub.rays32[2]
    ref = np.count_nonzero(np.abs(nr * sub.z32 + d32[:, None]) < nr * -sub.thr32, axis=1)
    got = fk._nb["_score_kernel"](np.ascontiguousarray(n32), d32, sub.rays32, sub.z32, sub.thr32, fk._NO_COLS, True, False)
    assert np.array_equal(got, ref)


@pytest.mark.parametrize("seed", range(12))
def test_the_first_round_kernel_is_the_numpy_first_round(numba_backend, seed):
    """Identification's first round in one call: the planes through the table's triplets, their
    counts and the best's inlier band, exactly as _global_hypotheses, _score and _band give them;
    on two surfaces and one, with and without a depth unit, and with repeated points (degenerate
    triplets, left out as numpy leaves them out)."""
    rng = np.random.default_rng(300 + seed)
    params = pf.FitParams(depth_unit=0.001 if seed % 2 else 0.0)
    if seed % 3 == 0:
        rx, ry, z, _ = two_surfaces(rng, 3000, params)
    else:
        rx, ry, q = wall_points(rng, 3000)
        z = 1.0 / noisy_inverse_depth(rng, rx, ry, q, params, outliers=0.02 * (seed % 3))
    if seed % 4 == 1:  # a few points repeated: some triplets span no plane
        rx[1::7], ry[1::7], z[1::7] = rx[0::7][:len(rx[1::7])], ry[0::7][:len(rx[1::7])], z[0::7][:len(rx[1::7])]
    sub = pf._subsample(rx, ry, z, params)
    m = len(sub.z)
    nh, dh = pf._global_hypotheses(sub, np.arange(m), params.iterations)
    score = pf._score(sub, nh, dh, None)
    got_n, got_d, got_score, best, band = fk.first_hypotheses(sub.P, pf._TABLE, params.iterations, sub.rays32,
                                                              sub.z32, sub.thr32, sub.rx, sub.ry, sub.y, params)
    assert np.array_equal(got_n, nh) and np.array_equal(got_d, dh) and np.array_equal(got_score, score)
    assert best == int(score.argmax())
    assert np.array_equal(band, pf._band(sub, -nh[best] / dh[best], params))


def test_one_surface_kernel_is_the_search_when_one_surface_holds_the_roi(numba_backend, monkeypatch):
    """The kernel's shortcut (subsample, first round, and its best when it holds all but the
    smallest surface looked for) gives a surface exactly when the numpy search stops at one
    unrefined surface, and the same one to the bit; on single walls, walls with outliers, two
    surfaces and tiny ROIs."""
    rng = np.random.default_rng(17)
    kinds = []
    for k in range(40):
        params = pf.FitParams(depth_unit=0.001 if k % 2 else 0.0)
        n_pts = int(rng.choice([5, 40, 700, 3000, 9000]))
        if k % 4 == 0:
            rx, ry, z, _ = two_surfaces(rng, max(n_pts, 100), params)
        else:
            rx, ry, q = wall_points(rng, n_pts)
            z = 1.0 / noisy_inverse_depth(rng, rx, ry, q, params, outliers=(0.0, 0.03, 0.3)[k % 3], heavy=k % 3 == 2)
        got = fk.one_surface(rx, ry, z, pf._TABLE, params)
        with monkeypatch.context() as m:
            m.setattr(fk, "backend", lambda: "numpy")
            ref = pf._find_surfaces(pf._subsample(rx, ry, z, params), params)
        simple = len(ref) == 1 and not ref[0].refined
        assert (got is not None) == simple
        if simple:
            assert np.array_equal(got[0], ref[0].n) and got[1] == ref[0].d
        kinds.append(simple)
    assert any(kinds) and not all(kinds)


def test_identification_takes_the_same_surfaces_with_the_first_round_compiled(numba_backend, monkeypatch):
    """_find_surfaces with the compiled first round and with the numpy one: the same surfaces,
    masks and all, on one surface, on two, and on clutter in front of a wall."""
    rng = np.random.default_rng(5)
    for k in range(9):
        params = pf.FitParams(depth_unit=0.001)
        if k % 3 == 0:
            rx, ry, z, _ = two_surfaces(rng, 3000, params)
        else:
            rx, ry, q = wall_points(rng, 3000)
            z = 1.0 / noisy_inverse_depth(rng, rx, ry, q, params, outliers=0.15 * (k % 3))
        sub = pf._subsample(rx, ry, z, params)
        got = pf._find_surfaces(sub, params)
        with monkeypatch.context() as m:
            m.setattr(fk, "backend", lambda: "numpy")
            ref = pf._find_surfaces(sub, params)
        assert len(got) == len(ref) > 0
        for a, b in zip(got, ref):
            assert np.array_equal(a.n, b.n) and a.d == b.d and np.array_equal(a.mask, b.mask) and a.refined == b.refined


@pytest.mark.parametrize("seed", range(10))
def test_behind_count_equals_numpy(numba_backend, seed):
    rng = np.random.default_rng(200 + seed)
    params = pf.FitParams(depth_unit=0.001 if seed % 2 else 0.0)
    rx, ry, z, q = two_surfaces(rng, 4000, params)
    qn = math.sqrt(float(q @ q))
    pi_pred = np.r_[-q / qn, 1.0 / qn]
    panel_q = np.array([q[0], q[1], q[2] * 1.1])  # a plane in front of the wall: the wall is behind it
    for qq in (q, panel_q, q * 0.8):
        nn = math.sqrt(float(qq @ qq))
        n, d = -qq / nn, 1.0 / nn
        for stride in (1, 3):
            for matters in (0.015, 0.05, 1.0):
                fk.set_backend("numpy")
                ref = pf._behind_share(rx, ry, z, stride, n, d, pi_pred, params, matters)
                fk.set_backend("numba")
                got = pf._behind_share(rx, ry, z, stride, n, d, pi_pred, params, matters)
                assert got == ref
                assert ref == pf._behind_points(rx[::stride], ry[::stride], z[::stride], n, d, pi_pred, params, matters)


def gather_reference(depth, rows, cols, stride, scale, zmin, zmax, ray_cols, ray_rows):
    """The gather as plainly as numpy says it: 2-D index, metres, range limits, rays."""
    z = depth[rows * stride, cols * stride].astype(np.float64) * scale
    ok = (z > zmin) & (z < zmax)
    return z[ok], ray_cols[cols[ok]], ray_rows[rows[ok]], len(rows)


@pytest.mark.parametrize("seed", range(8))
def test_gather_kernel_equals_numpy(numba_backend, seed):
    """Depths, rays and ROI size bit for bit: holes (0), depths beyond either range limit, every
    stride, and an image that is not contiguous (a view), which takes the numpy path."""
    rng = np.random.default_rng(300 + seed)
    stride = 1 + seed % 4
    h, w = 480, 848
    depth = rng.integers(0, 12000, size=(h, w)).astype(np.uint16)
    depth[rng.random((h, w)) < 0.1] = 0
    gh, gw = (h + stride - 1) // stride, (w + stride - 1) // stride
    ray_cols, ray_rows = rng.normal(0, 0.5, gw), rng.normal(0, 0.4, gh)
    n = int(rng.integers(0, 5000))
    rows = rng.integers(0, gh, n).astype(np.int32)
    cols = rng.integers(0, gw, n).astype(np.int32)
    scale = float(rng.choice([0.001, 0.000998, 0.0001]))
    ref = gather_reference(depth, rows, cols, stride, scale, 0.2, 10.0, ray_cols, ray_rows)
    for backend in ("numba", "numpy"):
        fk.set_backend(backend)
        got = fk.gather_roi(depth, rows, cols, stride, scale, 0.2, 10.0, ray_cols, ray_rows)
        assert got[3] == ref[3]
        for a, b in zip(got[:3], ref[:3]):
            assert a.dtype == np.float64 and np.array_equal(a, b)
    padded = np.zeros((h, w + 8), np.uint16)
    padded[:, :w] = depth
    view = padded[:, :w]
    assert not view.flags.c_contiguous
    fk.set_backend("numba")
    got = fk.gather_roi(view, rows, cols, stride, scale, 0.2, 10.0, ray_cols, ray_rows)
    assert all(np.array_equal(a, b) for a, b in zip(got[:3], ref[:3])) and got[3] == ref[3]


def test_a_degenerate_inlier_set_has_no_covariance_on_either_path(numba_backend):
    """Every point on one image row of a wall (a line): no plane, and no covariance, on both paths."""
    params = pf.FitParams(depth_unit=0.001)
    rx = np.linspace(-0.5, 0.5, 900)
    ry = np.zeros(900)
    q = np.array([0.0, 0.0, 0.5])
    y = rx * q[0] + ry * q[1] + q[2]
    for path in (pf._tail, fk.fit_tail):
        t = path(rx, ry, y, 1.0 / y, q, 0, params, None, True)
        assert t.count == 900 and t.cov is None and t.info is None


# -- fit_plane on synthetic ROIs -------------------------------------------------------------------

def synthetic_roi(seed, kind):
    """A wall patch seen by a camera whose up is -y, with what the fit must sort out: clutter in
    front ("panel"), a board meeting it at a small angle ("wedge"), a hole to a surface behind
    ("behind") or nothing ("plain")."""
    rng = np.random.default_rng(seed)
    params = pf.FitParams(depth_unit=0.001, up=(0.0, -1.0, 0.0), min_threshold=0.0133, offset_gate=0.06)
    n_true = pf.unit([rng.normal(0, 0.3), rng.normal(0, 0.02), -1.0])
    d = rng.uniform(0.8, 3.0)
    rx, ry, q = wall_points(rng, int(rng.integers(2000, 9000)), d=d, normal=n_true)
    qq = np.tile(q, (len(rx), 1))
    if kind == "panel":  # 0.1 m in front, over a third of the patch
        qq[rx < -0.2] = q * d / (d - 0.1)
    elif kind == "wedge":  # turned 4 deg about the patch's vertical centre line
        c, s = math.cos(math.radians(4)), math.sin(math.radians(4))
        n2 = np.array([c * n_true[0] - s * n_true[2], n_true[1], s * n_true[0] + c * n_true[2]])
        qq[rx > 0] = -n2 / d
    elif kind == "behind":  # a far surface through a hole
        qq[(np.abs(rx) < 0.1) & (ry > 0)] = q * d / (d + 0.5)
    y = noisy_inverse_depth(rng, rx, ry, qq.T, params, outliers=0.03, heavy=False)
    n_pred = pf.unit(n_true + rng.normal(0, 0.01, 3))
    pi_pred = np.r_[n_pred, d + rng.normal(0, 0.01)]
    return rx, ry, 1.0 / y, pi_pred, params


def assert_same_fit(a, b):
    assert (a.ok, a.reason, a.inliers, a.surfaces, a.evidence) == (b.ok, b.reason, b.inliers, b.surfaces, b.evidence)
    for name in ("n_camera", "d_camera", "info", "cov", "basis", "rms", "angle_to_prediction", "offset_to_prediction",
                 "excess_var", "centroid", "z2_mean", "lateral_std", "vertical_std"):
        va, vb = getattr(a, name), getattr(b, name)
        assert (va is None) == (vb is None), name
        if va is not None:
            tol = PATTERN_TOL * (np.linalg.cond(vb) if name == "info" else 1.0) if name in ("cov", "info") else 1e-9
            assert rel_err(va, vb) < tol or abs(float(np.max(np.abs(np.subtract(va, vb))))) < 1e-12, name
    assert (a.inlier_mask is None) == (b.inlier_mask is None)
    if a.inlier_mask is not None:
        assert np.array_equal(a.inlier_mask, b.inlier_mask)


def test_fit_plane_is_the_same_with_either_backend(numba_backend):
    reasons = set()
    for seed in range(24):
        for kind in ("plain", "panel", "wedge", "behind"):
            rx, ry, z, pi_pred, params = synthetic_roi(seed, kind)
            fits = {}
            for name in ("numpy", "numba"):
                fk.set_backend(name)
                fits[name] = pf.fit_plane(rx, ry, z, pi_pred, params)
            assert_same_fit(fits["numba"], fits["numpy"])
            reasons.add(fits["numpy"].reason.split(":")[0].split("(")[0].strip())
            if fits["numpy"].ok:  # the next pass: the fit as the start on the same ROI
                start = (fits["numpy"].n_camera, fits["numpy"].d_camera)
                again = {}
                for name in ("numpy", "numba"):
                    fk.set_backend(name)
                    again[name] = pf.fit_plane(rx, ry, z, pi_pred, params, start)
                assert_same_fit(again["numba"], again["numpy"])
    # The scenes reach the fit's verdicts, not only its good fits.
    assert "ok" in reasons and "not one flat surface" in reasons, reasons
    assert any("behind" in r for r in reasons), reasons


# -- the localizer on rendered frames ----------------------------------------------------------------

def rendered(scene, pose, seed):
    rng = np.random.default_rng(seed)
    return [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, frame_number=seed) for c in ROBOT.cameras]


def localize_both(frames, coarse, cov):
    out = {}
    for name in ("numpy", "numba"):
        fk.set_backend(name)
        out[name] = Localizer(ROBOT, ARENA).localize(frames, coarse, cov)
    return out["numpy"], out["numba"]


TRACKING = ((0.007, -0.007, 0.008), coarse_covariance(0.02, math.radians(1.0)))
COLD = ((0.07, -0.07, math.radians(10.0)), None)
FACING_WEST = (0.5, 0.5, math.pi)


def scene(name):
    """(scene, true poses): the arena, and clutter in front of wall_west as the front camera sees it."""
    west = ARENA["wall_west"]
    if name == "empty":
        return SimScene(ARENA), [(0.5, 0.5, 0.3), (0.35, 0.7, 2.6), (0.2, 0.9, -0.8)]
    clutter = {"panel": lambda: [parallel_panel(west, 0.15, 1.0, None, region=(0.0, 0.9))],
               "boards": lambda: [leaning_boards(west, 0.9, np.random.default_rng(5))],
               "box": lambda: [Box(-0.10, 0.5, 0.1, 0.5, 0.24)]}[name]()
    return SimScene(ARENA, clutter), [FACING_WEST]


@pytest.mark.parametrize("name", ["empty", "panel", "boards", "box"])
def test_localizer_gives_the_same_result_with_either_backend(numba_backend, name):
    scene_, poses = scene(name)
    for i, truth in enumerate(poses):
        frames = rendered(scene_, truth, seed=41 + i)
        for off, cov in (TRACKING, COLD):
            coarse = (truth[0] + off[0], truth[1] + off[1], truth[2] + off[2])
            a, b = localize_both(frames, coarse, cov)
            assert b.status == a.status
            assert abs(b.x - a.x) < 1e-9 and abs(b.y - a.y) < 1e-9 and abs(b.phi - a.phi) < 1e-9
            assert rel_err(b.cov, a.cov) < 1e-7
            assert [(p.id, p.camera, p.inliers, p.used, p.reason, p.roi_points) for p in b.planes] == \
                   [(p.id, p.camera, p.inliers, p.used, p.reason, p.roi_points) for p in a.planes]
            for pa, pb in zip(a.planes, b.planes):
                if pa.normal is not None:
                    assert np.allclose(pb.normal, pa.normal, atol=2e-6) and abs(pb.d - pa.d) <= 2e-6
            assert b.passes == a.passes


# -- the backend choice -----------------------------------------------------------------------------

def test_numpy_backend_forced_runs_the_numpy_code(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a compiled kernel ran with the numpy backend")

    for name in ("fit_tail", "score", "behind_count", "first_hypotheses", "outlines", "views", "zbuffer"):
        monkeypatch.setattr(fk, name, refuse)
    assert fk.set_backend("numpy") == "numpy" and fk.backend() == "numpy"
    assert fk.warm_up() == 0.0
    truth = FACING_WEST
    frames = rendered(SimScene(ARENA, [Box(-0.10, 0.5, 0.1, 0.5, 0.24)]), truth, seed=3)
    res = Localizer(ROBOT, ARENA).localize(frames, (truth[0] + 0.05, truth[1] - 0.05, truth[2] + 0.1))
    assert any(p.used for p in res.planes)
    assert math.hypot(res.x - truth[0], res.y - truth[1]) < 0.005


def test_environment_chooses_the_backend(monkeypatch):
    monkeypatch.setenv(fk.ENV, "numpy")
    assert fk.set_backend(None) == "numpy"
    monkeypatch.setenv(fk.ENV, "fortran")
    with pytest.raises(RuntimeError, match="ROBOT_KERNELS 'fortran'"):
        fk.set_backend(None)
    monkeypatch.delenv(fk.ENV)
    assert fk.set_backend(None) in ("numba", "numpy")  # auto


def test_numba_asked_for_but_missing_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba now raises ImportError
    monkeypatch.setenv("ROBOT_KERNEL_DIR", str(tmp_path))  # and no kernels built ahead of time there
    monkeypatch.setenv(fk.ENV, "numba")
    with pytest.raises(RuntimeError) as err:
        fk.set_backend(None)
    message = str(err.value)
    assert "\n" not in message and "numba does not import" in message and "ROBOT_KERNELS" in message
    # auto falls back to numpy, and says why
    monkeypatch.setenv(fk.ENV, "auto")
    assert fk.set_backend(None) == "numpy"
    assert "numba does not import" in fk.backend_note()
    assert fk.warm_up() == 0.0


def test_warm_up_compiles_every_kernel(numba_backend):
    seconds = fk.warm_up()
    assert seconds >= 0.0
    assert all(fk._nb[name].signatures for name in fk._KERNELS)


def test_kernels_that_do_not_compile_fall_back_to_numpy_only_under_auto(numba_backend, monkeypatch, tmp_path):
    monkeypatch.setenv("ROBOT_KERNEL_DIR", str(tmp_path))  # auto would take kernels built ahead of time there
    def broken(*args):
        raise RuntimeError("no LLVM here\nsecond line")

    monkeypatch.setitem(fk._nb, "_tail_kernel", broken)
    monkeypatch.setattr(fk, "_warmed", False)  # (a process whose kernels have not run yet)
    with pytest.raises(RuntimeError, match="no LLVM"):
        fk.warm_up()  # numba was asked for
    assert fk.backend() == "numba"
    assert fk.set_backend("auto") == "numba"
    fk.warm_up()
    assert fk.backend() == "numpy"
    assert "did not compile" in fk.backend_note() and "\n" not in fk.backend_note()


def test_the_app_loads_the_kernels_before_its_first_frame_and_stops_if_they_were_demanded_and_fail(monkeypatch):
    """Start-up compiles (or loads) the kernels off the loop before any frame; when ROBOT_KERNELS=numba
    was asked for and they cannot be had, the controller does not start (one reason, exit 1)."""
    import asyncio

    from robot.app.controller import AppOptions
    from robot.config import load_robot_config
    from robot.maps.plane_map import load_plane_map
    from robot.sim.realtime import RealtimeSimSettings, sim_rig

    robot = load_robot_config("config/robot.yaml")
    arena = load_plane_map("config/maps/paper_arena.yaml")
    calls = []

    def failing_warm_up():
        calls.append("warm_up")
        raise RuntimeError("ROBOT_KERNELS=numba but numba is not installed (pip install '.[perf]')")

    monkeypatch.setattr(fk, "warm_up", failing_warm_up)
    opts = AppOptions(install_signal_handlers=False, stop_when_done=False)
    with sim_rig(robot, arena, (0.4, 0.6, 0.0), RealtimeSimSettings(fps=8, decimation=4), opts) as rig:
        rc = asyncio.run(asyncio.wait_for(rig.app.run(), 60.0))
    assert rc == 1 and calls == ["warm_up"]
    assert rig.app.exit_reason.startswith("plane-fit kernels: RuntimeError: ROBOT_KERNELS=numba")
    assert rig.app.stats.localizations == 0
