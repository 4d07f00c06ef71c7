"""Compiled kernels for the plane fit's hot loops (and the relocalizer's pixel scoring), and the
choice between them and numpy.

The plane fit (:mod:`robot.localization.plane_fit`) spends its time in many small numpy calls on
a few thousand points or on 3 x 3 matrices: the per-call overhead, not the arithmetic, is their
cost. Here each of those parts is one numba-compiled function:

* the fit after identification, whatever its verdict, in one call (:func:`fit_tail`,
  ``plane_fit._tail``): every stage and iteration of the weighted least squares in inverse depth
  (``plane_fit._refit`` over ``_solve_step``), the denser sample's points behind the plane (the
  rear-most check), the covariance from the normal equations (three 3 x 3 inverses and products)
  with the depth unit's pattern (``plane_fit._quantisation_cov``), its inverse, and the inlier
  summary (centroid, depth, spread) with the flatness check's half-patch sums. One call instead
  of six, and no numpy temporaries between them: a wall's fit crossed from Python to compiled
  code and back at every step;
* the hypothesis scoring of identification (``plane_fit._score``), and identification's first
  round in one call: the planes through the fixed table's point triplets, their scores, and the
  inlier band of the best (``plane_fit._global_hypotheses``, ``_score`` and ``_band``);
* the share of points behind a surface (the first pass of ``plane_fit._behind_points``), for
  identification's surfaces;
* the gather of a wall's ROI: its pixels' depths in metres, those within the range limits and
  their rays (``gather_roi``; its numpy code is the localizer's, kept here beside it);
* the ROI prediction's geometry (:func:`outlines`): the polygons that cross a frustum plane
  clipped against the planes they cross (Sutherland-Hodgman, as ``visibility.clip_vertex_list``),
  every kept vertex projected to full-resolution and fixed-point grid pixels, and per plane its
  nearest depth and grid box (``roi._clip_to_frustum``, ``_project`` and ``_plane_outlines``). The
  fill that follows stays OpenCV's: its rasterization rules decide which pixels an outline
  takes, and the ROIs, and every relocalization verdict built on the same labels, were measured
  with them. On a floor of alike rooms, where a camera sees a dozen polygons that all cross the
  frustum's top, this loop was a tenth of a relocalization's CPU;
* the relocalizer's wall finder, the inliers of each line through a pair of floor-plan points
  (:func:`best_line`, ``relocalize._best_line``);
* the relocalizer's per-pixel work of a score (:func:`score_pixels`, ``relocalize._pixels``): the
  label image's edges, the unscored returns seen through a predicted wall, and each scored
  pixel's predicted depth, residual and the neighbouring wall it may be taken on instead; the
  log-likelihoods after it stay numpy's (its exp and log are not libm's on every machine).

The numpy code in ``plane_fit`` stays the reference and the fallback. The kernels repeat its
arithmetic operation for operation, so they agree with it to the rounding of its sums and
matrix products (1e-15 relative, a 3 x 3 inverse to its condition number times that), a mask
differs only for a point exactly on a band edge, and counts are the same. One term does not
follow to that precision: the depth unit's pattern in a fit's covariance takes float32 sines and
cosines, libm's in a kernel and numpy's own vectorised ones in numpy, which differ in their last
bit (1e-7 of that term, under 1e-8 of a covariance). Otherwise:

* fastmath is off: elementwise expressions round exactly as numpy's (no reassociation, no
  contraction into fused multiply-adds);
* scoring is float32 like numpy's, and its one matrix product (BLAS sgemm, which on most machines
  chains fused multiply-adds) is rounded as the BLAS in use rounds it: a probe at load time
  tells a fused chain from separate products and sums (:func:`backend_note` says which, and if
  neither reproduces it exactly);
* 3 x 3 systems are solved by LU with partial pivoting, as LAPACK's gesv does, and a singular one
  is reported where numpy raises LinAlgError.

The kernels release the GIL (``nogil``), so the localization thread runs beside the event loop.

Backend: the environment variable ``ROBOT_KERNELS``, read at the first :func:`backend` call:
``auto`` (the default: the kernels compiled ahead of time if ``robotctl kernels build`` made them
for this source, else numba if it imports, else numpy), ``aot`` (ahead of time only: a
RuntimeError if they are not built), ``numba`` (the JIT: a RuntimeError if numba is missing) or
``numpy``. numba is imported only for the JIT, never by importing this module, and never with the
kernels compiled ahead of time (:mod:`robot.base.aot_kernels`); :func:`backend` says "numba" for
both, the same compiled code.

Compiled code is cached on disk (``cache=True``) where ``NUMBA_CACHE_DIR`` says; numba reads that
variable when it is imported, so it must be set before the first :func:`backend` or
:func:`warm_up` call. The service sets it to its state directory (the installed package's folder
may not be writable), and calls :func:`warm_up` at start-up: that compiles the kernels the first
time (about 40 s of CPU on the development machine with either numba: BENCHMARKS.md, "The
localizer, step by step", gives each run's figure; expect 5 to 8 times that on the Nano, which
is why the install builds them ahead of time) and loads them from the cache afterwards (0.2 s,
plus 0.2 s to import numba).
"""

from __future__ import annotations

import math
import os
import time
from typing import TYPE_CHECKING, Any, Callable, Dict, Optional, Tuple

import numpy as np

from robot.base import aot_kernels
from robot.base.kernel_cache import cache_lock, jit_table

if TYPE_CHECKING:  # plane_fit imports this module
    from robot.localization.plane_fit import FitParams, _Tail

ENV = "ROBOT_KERNELS"
BACKENDS = ("auto", "aot", "numba", "numpy")

_backend: Optional[str] = None  # "numba" or "numpy" once resolved
_requested = "auto"  # what was asked for: only "auto" falls back to numpy when compiling fails
_note = ""  # how the backend was chosen, for the start-up log
_nb: Dict[str, Any] = {}  # kernel name -> numba dispatcher (or its ahead-of-time build)
_aot: Optional[Dict[str, Dict[str, Any]]] = None  # the ahead-of-time kernels of every module, when in use
_compiled = False  # whether every kernel was compiled (or loaded from the cache), under the cache lock
# Whether every kernel has run once in this process, under the lock: after that nothing of ours
# writes numba's cache, and a later warm-up (each app start in a process) must not wait on the
# lock while another process holds it for minutes (``robotctl kernels build``).
_warmed = False
_fused = True  # whether numpy's float32 matrix product chains fused multiply-adds (probed)
_probe_exact = True  # ... and whether the kernel then rounds exactly as it does
_NO_COLS = np.zeros(0, np.intp)
_NO_UP = np.zeros(3)


def backend() -> str:
    """The backend in use, "numba" or "numpy" (resolved from ``ROBOT_KERNELS`` on first use)."""
    if _backend is None:
        set_backend(None)
    return _backend  # type: ignore[return-value]


def backend_note() -> str:
    """One line on how the backend was chosen (why numpy, when numba was not available)."""
    backend()
    return _note


def set_backend(name: Optional[str]) -> str:
    """Choose the backend: "auto", "aot", "numba" or "numpy" (None: from ``ROBOT_KERNELS``, default
    auto). Returns the one in use ("numba" for the kernels compiled ahead of time too). Raises
    RuntimeError for an unknown name, for "numba" without numba, or for "aot" without a module
    built for this source."""
    global _backend, _note, _requested, _aot, _compiled, _warmed
    source = "argument"
    if name is None:
        name, source = os.environ.get(ENV, "auto").strip().lower() or "auto", ENV
    if name not in BACKENDS:
        raise RuntimeError(f"{source} {name!r}: the plane fit's kernel backend must be one of {', '.join(BACKENDS)}")
    if name == "numpy":
        _backend, _note, _requested = "numpy", f"numpy ({source} says numpy)", name
        return _backend
    if name in ("auto", "aot") and _use_aot():
        _backend, _requested = "numba", name
        _note = f"numba {_nb['version']} (numpy's float32 matrix product {'fused' if _fused else 'unfused'})"
        return _backend
    if name == "aot":
        raise RuntimeError(f"{source} asks for the kernels compiled ahead of time, but {aot_kernels.why_not()}")
    if _aot is not None:  # the JIT asked for after the ahead-of-time kernels (robotctl kernels build)
        _aot = None
        _nb.clear()
        _compiled = _warmed = False
    try:
        _load()
    except ImportError as e:
        why = (str(e).splitlines() or [type(e).__name__])[0]
        if name == "numba":
            raise RuntimeError(f"{source} asks for the plane fit's numba kernels, but numba does not import ({why}): "
                               "install the perf extra (pip install -e '.[perf]') or set ROBOT_KERNELS=numpy") from None
        _backend, _note, _requested = "numpy", f"numpy (numba does not import: {why})", name
        return _backend
    try:
        _compile_once()
    except Exception as e:
        if name == "numba":
            raise
        _backend, _requested = "numpy", name
        _note = f"numpy (the numba kernels did not compile: {type(e).__name__}: {e})".split("\n")[0]
        return _backend
    _backend, _requested = "numba", name
    _note = (f"numba {_nb['version']} (numpy's float32 matrix product {'fused' if _fused else 'unfused'}"
             + ("" if _probe_exact else ", not reproduced exactly: a point at a band edge may count differently") + ")")
    return _backend


_KERNELS = ("_tail_kernel", "_one_surface_kernel", "_score_kernel", "_behind_kernel", "_gather_kernel",
            "_hypotheses_kernel", "_outline_kernel", "_views_kernel", "_zbuffer_kernel", "_hidden_kernel",
            "_shrink_kernel", "_best_line_kernel")
_NUMPY_ERRORS = ("_pixels_kernel",)  # kernels compiled with numpy's floating-point error model


def _use_aot() -> bool:
    """Take the kernels compiled ahead of time when they are built for this source."""
    global _aot, _fused, _compiled, _warmed
    table = aot_kernels.load()
    if table is None or "fit" not in table:
        return False
    aot_kernels.set_fallbacks(table["fit"], jit_kernels)
    _nb.clear()
    _nb.update(table["fit"])
    _aot = table
    _fused = _probe_fused()
    _compiled = True
    _warmed = False  # (their first run may compile a fallback: warm_up runs them under the lock)
    return True


def kernel_table(tag: str, jit_kernels: Callable[[], Dict[str, Any]]) -> Dict[str, Any]:
    """The kernels of module ``tag`` ("integrity", "scan"): built ahead of time when the backend
    uses them (a type not built goes to ``jit_kernels``), else ``jit_kernels()``, numba's."""
    backend()
    table = None if _aot is None else _aot.get(tag)
    if table is None:
        return jit_kernels()
    aot_kernels.set_fallbacks(table, jit_kernels)
    return dict(table)


def _load() -> None:
    """Import numba and wrap the kernels (:func:`_compile_once` compiles them)."""
    global _fused
    import numba  # noqa: F401 (each time: a test may hide it)

    if _nb:
        return
    _fused = _probe_fused()
    _nb.update(jit_kernels())


def jit_kernels() -> Dict[str, Any]:
    """Fresh numba dispatchers of the kernels (also what the ahead-of-time module falls back to
    for an argument type it was not built for)."""
    import numba

    # Called from the kernels, they stay plain Python here.
    for fn in (_solve3, _count_inliers, _clip, _wall_depth, _score_std, _refit, _behind, _plane_cov, _summary, _basis,
               _quantisation_cov, _hypotheses, _outlines_of):
        numba.extending.register_jitable(fn)
    table = jit_table(numba, globals(), _KERNELS)
    # Where a predicted plane is seen edge-on its depth is a division by zero: inf, as numpy's.
    table.update(jit_table(numba, globals(), _NUMPY_ERRORS, error_model="numpy"))
    return table


def _compile_once() -> None:
    """Compile every kernel, or load it from numba's cache, before the backend says numba: with
    the cache lock held, so that no other process of ours writes the cache meanwhile (see
    :mod:`robot.base.kernel_cache`), and before any thread can call a kernel and compile it
    without the lock."""
    global _compiled, _warmed
    if _compiled:
        return
    with cache_lock():
        _run_each_kernel()
    _compiled = _warmed = True


def warm_up() -> float:
    """Resolve the backend and, with numba, compile the kernels or load them from numba's cache
    (the first :func:`backend` call does that), then run each once on tiny inputs of the types the
    fit passes. Returns the seconds it took (0 with the numpy backend). If compiling fails, "auto"
    falls back to numpy (:func:`backend_note` says why) and "numba" raises."""
    global _backend, _note, _warmed
    t0 = time.perf_counter()
    if backend() != "numba":
        return 0.0
    if _warmed:  # (the first backend() call compiled them, or an earlier warm-up ran them)
        return time.perf_counter() - t0
    try:
        with cache_lock():
            _run_each_kernel()
        _warmed = True
    except Exception as e:
        if _requested == "numba":
            raise
        _backend, _note = "numpy", f"numpy (the numba kernels did not compile: {type(e).__name__}: {e})".split("\n")[0]
    return time.perf_counter() - t0


def _run_each_kernel() -> None:
    rng = np.random.default_rng(0)
    n = 64
    rx, ry = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.4, 0.4, n)
    q = np.array([0.01, -0.02, 0.5])
    y = rx * q[0] + ry * q[1] + q[2] + rng.normal(0.0, 1e-3, n)
    z = 1.0 / y
    from robot.localization.plane_fit import _TABLE, FitParams

    params = FitParams(depth_unit=0.001)
    for stride, up, flat in ((2, None, True), (0, np.array([0.0, -1.0, 0.0]), False)):
        fit_tail(rx, ry, y, z, q, stride, params, up, flat)
    rays = np.ones((3, n), np.float32)
    rays[0], rays[1] = rx, ry
    nh = np.array([[0.0, 0.0, -1.0], [0.1, 0.0, -1.0]], np.float32)
    _nb["_score_kernel"](nh, np.array([2.0, 2.1], np.float32), rays, z.astype(np.float32), np.full(n, 0.01, np.float32),
                         _NO_COLS, True, _fused)
    P = rays.astype(np.float64) * z
    table = np.random.default_rng(1).random((3, 16))
    _nb["_hypotheses_kernel"](P, table, 8, rays, z.astype(np.float32), np.full(n, 0.01, np.float32), _fused, rx, ry, y,
                              1e-6, 1e-7, 9.0, 0.004)
    one_surface(rx, ry, z, _TABLE, params)
    _nb["_behind_kernel"](rx, ry, z, 1, np.array([0.0, 0.0, -1.0]), 2.0, 1e-3, 1e-7, True, 0.03)
    depth = np.full((4, 4), 1500, np.uint16)
    idx = np.arange(3, dtype=np.int32)  # the ROI's rows and columns come as int32 (cv2.findNonZero)
    _nb["_gather_kernel"](depth.ravel(), idx, idx, 4, 1, 0.001, 0.2, 10.0, np.zeros(4), np.zeros(4))
    best_line(np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.01]]), np.array([[0, 1], [1, 2]], np.int64), np.full(3, 0.02))
    label = np.array([[0, 0, -1], [0, 1, 1]], np.int32)
    zz = np.full((2, 3), 2.0)
    ok = np.ones((2, 3), np.bool_)
    grid3 = np.linspace(-0.5, 0.5, 3)
    for free in (None, ~ok):
        score_pixels(label, np.array([[0.0, 0.0, -1.0, 2.0], [0.1, 0.0, -1.0, 2.1]]), zz, ok, free, grid3, grid3[:2],
                     (0.01, 0.005, 0.03, 0.02), True)
    # A square in front of a camera that crosses one frustum plane.
    P = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [1.0, 1.0, 2.0], [-1.0, 1.0, 2.0]])
    one = np.ones(1, np.int64)
    outlines(P, one * 0, one * 2, one * 0, one * 4, one * 0, np.array([[0.0, 0.0, 1.0, -0.01], [1.0, 0.0, 0.0, 0.5]]),
             np.array([100.0, 100.0]), np.array([50.0, 50.0]), 4.0, 0.01, 4, 25, 25, 6.0)
    buf = np.zeros((3, 4))
    zbuffer(np.ones((3, 4), np.uint8), buf, np.full((3, 4), -1, np.int32), np.linspace(-0.5, 0.5, 4),
            np.linspace(-0.3, 0.3, 3), 0.1, 0.2, 0.5, 0, (0, 3, 0, 4), True)
    hidden(buf, (0, 3, 0, 4), 0.5)
    for radius in (0, 1):
        shrink(np.array([[0, 0, -1], [0, 1, 1]], np.int32), np.array([[0, 0, 1, 1], [1, 1, 2, 1]]), np.array([radius, 0]), 0)
    # The same square as a one-plane map (a wall 2 m ahead, facing the camera), seen from the origin.
    frustum = np.array([[0.0, 0.0, 1.0, -0.01], [1.0, 0.0, 0.0, 0.5]])
    cells = (-1.0, -1.0, 2.0, 1, 1, np.array([0, 1], np.int64), np.zeros(1, np.int64))
    views(np.eye(4), np.zeros((8, 3)), np.vstack([frustum, [[0.0, 0.0, -1.0, 6.0]]]), cells,
          np.array([[0.0, 0.0, 2.0, 1.0, 1.0, 0.0]]), np.zeros(1, np.int64), np.array([[0.0, 0.0, -1.0, 2.0]]),
          np.array([0, 1], np.int64), P, np.array([0, 4], np.int64), frustum, np.array([100.0, 100.0]),
          np.array([50.0, 50.0]), 4.0, 0.01, 4, 25, 25, 6.0, 1e-6, 1e-9)


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float64)


# -- the kernels' callers: plain arguments in, plane_fit's values out ------------------------------

def fit_tail(rx: np.ndarray, ry: np.ndarray, y: np.ndarray, z: np.ndarray, q: np.ndarray, stride: int,
             params: FitParams, up: Optional[np.ndarray], flat: bool) -> _Tail:
    """``plane_fit._tail`` in one call: the refit of plane q (inverse depth 1/z = q . (x/z, y/z, 1))
    on points with rays (rx, ry), measured inverse depths y and depths z (with ``stride`` >= 2 first
    on every stride-th point), the dense sample's points behind it, its covariance and information
    over (theta1, theta2, d) with the depth unit's pattern, and the inlier summary (``flat``: with
    the flatness check's sums per half). ``up``: the robot's up in the camera frame, or None."""
    from robot.localization.plane_fit import CONVERGED, STAGE_ITERATIONS, _dense_stride, _Tail

    N = len(z)
    c = params.noise_subpixel / params.noise_fx_b
    delta = float(params.depth_unit)
    quantised = delta > 0
    # Constants computed in Python as plane_fit computes them: the same doubles.
    n, d, mask, count, chi2, behind, B, cov_ok, cov, info_ok, info, k_in, sums, hs = _nb["_tail_kernel"](
        _f64(rx), _f64(ry), _f64(y), _f64(z), _f64(q), int(stride), c * c, delta**2 / 12.0, quantised,
        params.sigma_k**2, float(params.min_threshold), float(params.huber_k), params.huber_k**2, CONVERGED,
        STAGE_ITERATIONS, _dense_stride(N, params), c, float(params.behind_margin), max(1, N // (2 * params.sample)),
        _NO_UP if up is None else _f64(up), up is not None, bool(flat), delta,
        math.sqrt(0.64 * delta / c) if quantised else 1.0)
    k_in = int(k_in)
    return _Tail(n, float(d), mask, int(count), float(chi2), int(behind), B, cov if cov_ok else None,
                 info if cov_ok and info_ok else None, k_in, sums,
                 (hs[0], hs[1], hs[2], hs[3], hs[4]) if flat and k_in >= 40 else None)


def score(nh: np.ndarray, dh: np.ndarray, rays32: np.ndarray, z32: np.ndarray, thr32: np.ndarray,
          cols: Optional[np.ndarray]) -> np.ndarray:
    """``plane_fit._score``: inliers of each hypothesis (normals nh (H, 3), offsets dh (H,))
    among the points ``cols`` (None: all) of float32 rays (3, m), depths and bands."""
    all_cols = cols is None
    f32 = np.float32
    return _nb["_score_kernel"](np.ascontiguousarray(nh, f32), np.ascontiguousarray(dh, f32), np.ascontiguousarray(rays32, f32),
                                np.ascontiguousarray(z32, f32), np.ascontiguousarray(thr32, f32),
                                _NO_COLS if all_cols else np.ascontiguousarray(cols, np.intp), all_cols, _fused)


def first_hypotheses(P: np.ndarray, table: np.ndarray, count: int, rays32: np.ndarray, z32: np.ndarray,
                     thr32: np.ndarray, rx: np.ndarray, ry: np.ndarray, y: np.ndarray, params: FitParams
                     ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, int, Optional[np.ndarray]]:
    """Identification's first round over all m subsample points (points P (3, m), their rays,
    depths and bands in float32, rays rx, ry and inverse depths y): the planes through the point
    triplets ``table[:, :count] * m`` (``plane_fit._global_hypotheses``; degenerate triplets left
    out), their inlier counts (``plane_fit._score``), the first best, and its inlier band
    (``plane_fit._band``; None without hypotheses)."""
    c = params.noise_subpixel / params.noise_fx_b
    nh, dh, score, best, band = _nb["_hypotheses_kernel"](
        _f64(P), table, int(count), np.ascontiguousarray(rays32, np.float32), np.ascontiguousarray(z32, np.float32),
        np.ascontiguousarray(thr32, np.float32), _fused, _f64(rx), _f64(ry), _f64(y), c * c,
        params.depth_unit**2 / 12.0 if params.depth_unit > 0 else 0.0, params.sigma_k**2, float(params.min_threshold))
    return nh, dh, score, int(best), (band if best >= 0 else None)


def one_surface(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, table: np.ndarray, params: FitParams
                ) -> Optional[Tuple[np.ndarray, float]]:
    """The surface identification finds when one surface holds nearly everything: the subsample
    (``plane_fit._subsample``), the first round (:func:`first_hypotheses`), and its best when
    ``plane_fit._find_surfaces`` would stop there with that one surface, unrefined: (n, d), else
    None (the ROI needs the whole search)."""
    c = params.noise_subpixel / params.noise_fx_b
    quantised = params.depth_unit > 0
    found, n, d = _nb["_one_surface_kernel"](
        _f64(rx), _f64(ry), _f64(z), max(1, -(-len(z) // params.sample)), c, params.depth_unit**2 / 12.0, quantised,
        float(params.sigma_k), float(params.min_threshold), table, int(params.iterations), _fused, c * c,
        params.depth_unit**2 / 12.0 if quantised else 0.0, params.sigma_k**2, float(params.surface_min_fraction))
    return (n, float(d)) if found else None


def behind_count(rx: np.ndarray, ry: np.ndarray, z: np.ndarray, stride: int, n: np.ndarray, d: float,
                 params: FitParams) -> int:
    """How many of every stride-th point (from the first) lie behind the plane (n, d) by more
    than the margin: ``behind`` in ``plane_fit._behind_points`` before the prior's window."""
    return int(_nb["_behind_kernel"](_f64(rx), _f64(ry), _f64(z), int(stride), _f64(n), float(d),
                                     params.noise_subpixel / params.noise_fx_b, params.depth_unit**2 / 12.0,
                                     params.depth_unit > 0, float(params.behind_margin)))


def gather_roi(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, stride: int, depth_scale: float,
               min_range: float, max_range: float, ray_cols: np.ndarray, ray_rows: np.ndarray
               ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The depth (m) of grid pixels (rows, cols) of a uint16 depth image sampled every ``stride``
    pixels, kept where min_range < z < max_range, and the kept pixels' rays: (z, rx, ry, the
    number of ROI pixels). Compiled when the backend is numba, else numpy (the reference)."""
    w = depth.shape[1]
    if backend() == "numba" and depth.flags.c_contiguous:
        z, rx, ry = _nb["_gather_kernel"](depth.ravel(), rows, cols, stride * w, stride, float(depth_scale),
                                          float(min_range), float(max_range), ray_cols, ray_rows)
        return z, rx, ry, len(rows)
    # One flat gather costs two thirds of a 2-D fancy index (the same pixels).
    if depth.flags.c_contiguous:
        z = depth.ravel().take(rows * (stride * w) + cols * stride) * depth_scale
    else:
        z = depth[rows * stride, cols * stride] * depth_scale
    n_roi = len(z)
    ok = (z > min_range) & (z < max_range)
    if np.count_nonzero(ok) < n_roi:
        z, rows, cols = z[ok], rows[ok], cols[ok]
    return z, ray_cols.take(cols), ray_rows.take(rows), n_roi


def outlines(P_camera: np.ndarray, every: np.ndarray, some: np.ndarray, first: np.ndarray, counts: np.ndarray,
             plane_of: np.ndarray, frustum: np.ndarray, f_px: np.ndarray, c_px: np.ndarray, fixed_scale: float,
             near: float, stride: int, grid_h: int, grid_w: int, max_range: float) -> Tuple[np.ndarray, ...]:
    """``roi._clip_to_frustum``, ``roi._project`` and ``roi._plane_outlines`` in one pass over the
    stacked polygons (vertices ``P_camera`` (N, 3), polygon k's rows ``first[k]`` on for
    ``counts[k]``, on map plane ``plane_of[k]``; ``every`` and ``some``: the AND and the OR of its
    vertices' outside-bits over the (F, 4) ``frustum``). Returns (px (M, 2) full-resolution pixels,
    fixed (M, 2) int32 fixed-point grid pixels, seg (n + 1,) the rows of each kept polygon,
    planes (p,) the map plane of each plane kept, its kept polygons (p, 2) (first, one past the
    last), z_near (p,), boxes (p, 4) (c0, r0, c1, r1)): the planes whose nearest visible depth
    is under ``max_range``, in stacking order."""
    return _nb["_outline_kernel"](P_camera, every, some, first, counts, plane_of, frustum,
                                  float(f_px[0]), float(f_px[1]), float(c_px[0]), float(c_px[1]), float(fixed_scale),
                                  float(near), int(stride), int(grid_h), int(grid_w), float(max_range))


def views(T_ground_camera: np.ndarray, corners: np.ndarray, cull: np.ndarray, cells: Tuple, box6: np.ndarray,
          poly_plane: np.ndarray, planes: np.ndarray, plane_first: np.ndarray, vertices: np.ndarray,
          vertex_first: np.ndarray, frustum: np.ndarray, f_px: np.ndarray, c_px: np.ndarray, fixed_scale: float,
          near: float, stride: int, grid_h: int, grid_w: int, max_range: float, back_eps: float,
          cull_eps: float) -> Tuple[np.ndarray, ...]:
    """``PlaneIndex.in_view`` and ``roi.predict_plane_views``' geometry in one call (see
    ``roi.predict_views``): the view's bounding ``corners`` (8, 3) and ``cull`` planes (6, 4) in the
    camera frame, the polygon grid ``cells`` (origin x, origin y, cell, ni, nj, offsets, ids), the
    packed map (polygon boxes, plane of each polygon, planes, first polygon of each plane, the
    vertices and first vertex of each polygon). Returns (facing planes, their planes in C, and
    :func:`outlines`' seven arrays)."""
    T = _f64(T_ground_camera)
    R_T = np.ascontiguousarray(T[:3, :3].T)
    t_C = -T[:3, :3].T @ T[:3, 3]  # as roi._stack_in_camera computes it
    ox, oy, cell, ni, nj, offsets, ids = cells
    return _nb["_views_kernel"](T, corners, cull, float(ox), float(oy), float(cell), int(ni), int(nj), offsets, ids,
                                box6, poly_plane, planes, plane_first, vertices, vertex_first, R_T, t_C, frustum,
                                float(f_px[0]), float(f_px[1]), float(c_px[0]), float(c_px[1]), float(fixed_scale),
                                float(near), int(stride), int(grid_h), int(grid_w), float(max_range), float(back_eps),
                                float(cull_eps))


def zbuffer(mask: np.ndarray, ibuf: np.ndarray, label: np.ndarray, cols: np.ndarray, rows: np.ndarray, a: float,
            b: float, c: float, k: int, box: Tuple[int, int, int, int], write: bool) -> None:
    """``roi._zbuffer``: a plane's pixels into the label image and the inverse-depth buffer, in place
    (``box``: r0, r1, c0, c1, the ends excluded)."""
    r0, r1, c0, c1 = box
    _nb["_zbuffer_kernel"](mask, ibuf, label, cols, rows, float(a), float(b), float(c), int(k), int(r0), int(r1),
                           int(c0), int(c1), bool(write))


def hidden(ibuf: np.ndarray, box: Tuple[int, int, int, int], top: float) -> bool:
    """``roi._hidden``: whether the buffer holds at least ``top`` everywhere on ``box`` (r0, r1, c0,
    c1, the ends excluded), looking no further than the first pixel that does not."""
    r0, r1, c0, c1 = box
    return bool(_nb["_hidden_kernel"](ibuf, int(r0), int(r1), int(c0), int(c1), float(top)))


def shrink(label: np.ndarray, boxes: np.ndarray, radii: np.ndarray, pad: int
           ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``roi.shrink_rois``' pixel work for every view of a label image in one call: view k (its
    label) owns the pixels labelled k in its grid box ``boxes[k]`` (c0, r0, c1, r1, inclusive);
    its pixel count is taken on the inner grid (``pad`` pixels in from every edge), and its ROI
    is what a rectangular erosion of radius ``radii[k]`` (grid pixels; zero beyond the box, as
    ``cv2.erode`` with a constant border of 0) leaves there, row by row, in inner-grid
    coordinates. Returns (rows, cols, offsets (n + 1), pixels (n)): view k's ROI is
    ``rows[offsets[k]:offsets[k + 1]]`` and the same of ``cols`` (int32, as cv2.findNonZero)."""
    return _nb["_shrink_kernel"](np.ascontiguousarray(label, np.int32), np.ascontiguousarray(boxes, np.int64),
                                 np.ascontiguousarray(radii, np.int64), int(pad))


def best_line(pts: np.ndarray, pairs: np.ndarray, tol: np.ndarray) -> Tuple[int, Optional[np.ndarray]]:
    """``relocalize._best_line``: (the count, the inlier mask) of the best line, or (-1, None)."""
    best, mask = _nb["_best_line_kernel"](_f64(pts), np.ascontiguousarray(pairs, np.int64), _f64(tol))
    return (int(best), mask) if best >= 0 else (-1, None)


def score_pixels(label: np.ndarray, table: np.ndarray, z: np.ndarray, valid: np.ndarray, free: Optional[np.ndarray],
                 cols: np.ndarray, rows: np.ndarray, sigma_terms: Tuple[float, float, float, float],
                 coarse: bool) -> Tuple[int, Optional[Tuple[np.ndarray, ...]]]:
    """``relocalize._pixels``: (the unscored returns seen through a predicted wall, the scored
    pixels' arrays or None). ``sigma_terms``: (a, b, c, d) of the depth std a + b z^2, plus
    c + d z with ``coarse`` (relocalize.DEPTH_SIGMA)."""
    has_free = free is not None
    out = _nb["_pixels_kernel"](np.ascontiguousarray(label, np.int32), np.ascontiguousarray(table, np.float64),
                                _f64(z), np.ascontiguousarray(valid, np.bool_),
                                np.ascontiguousarray(free if has_free else valid, np.bool_), has_free, _f64(cols),
                                _f64(rows), np.array(sigma_terms, np.float64), bool(coarse))
    n_free, px = int(out[0]), out[1:]
    return n_free, (px if len(px[0]) else None)


def _probe_fused() -> bool:
    """Whether numpy's float32 (H, 3) @ (3, m) rounds as a chain of fused multiply-adds (OpenBLAS's
    kernels for CPUs with FMA) or as separate products and sums, on shapes like the scoring's.
    Sets ``_probe_exact``: whether either reproduces it exactly."""
    global _probe_exact
    rng = np.random.default_rng(7)
    nh = rng.normal(size=(60, 3)).astype(np.float32)
    rays = np.ones((3, 600), np.float32)
    rays[0], rays[1] = rng.uniform(-0.6, 0.6, 600), rng.uniform(-0.4, 0.4, 600)
    nr = nh @ rays
    a0, a1, a2 = nh[:, 0:1], nh[:, 1:2], nh[:, 2:3]
    split = (a0 * rays[0] + a1 * rays[1]) + a2 * rays[2]
    # A float32 fma is exact in float64 before its one rounding (products of 24-bit mantissas).
    f = (a1.astype(np.float64) * rays[1] + a0 * rays[0]).astype(np.float32)
    fused = (a2.astype(np.float64) * rays[2] + f).astype(np.float32)
    off_fused, off_split = int(np.count_nonzero(nr != fused)), int(np.count_nonzero(nr != split))
    _probe_exact = min(off_fused, off_split) == 0
    return off_fused <= off_split


# -- the kernels (plain Python here; _load compiles them) ------------------------------------------
# Every elementwise expression keeps the numpy code's operations and their order, so that its
# roundings are the same; only sums run in a different order.

def _solve3(A, B, X):  # pragma: no cover (compiled)
    """X = A^-1 B for A (3, 3) and B (3, m) by LU with partial pivoting (LAPACK's gesv); False
    (X undefined) if A is singular."""
    L = A.copy()
    X[:, :] = B
    m = B.shape[1]
    for j in range(3):
        p = j
        big = abs(L[j, j])
        for r in range(j + 1, 3):
            if abs(L[r, j]) > big:
                big = abs(L[r, j])
                p = r
        if L[p, j] == 0.0:
            return False
        if p != j:
            for c in range(3):
                t = L[j, c]
                L[j, c] = L[p, c]
                L[p, c] = t
            for c in range(m):
                t = X[j, c]
                X[j, c] = X[p, c]
                X[p, c] = t
        inv = 1.0 / L[j, j]
        for r in range(j + 1, 3):
            f = L[r, j] * inv
            L[r, j] = f
            for c in range(j + 1, 3):
                L[r, c] -= f * L[j, c]
    for c in range(m):  # the triangular solves, column by column as LAPACK's go
        X[1, c] -= X[0, c] * L[1, 0]
        X[2, c] -= X[0, c] * L[2, 0]
        X[2, c] -= X[1, c] * L[2, 1]
        X[2, c] /= L[2, 2]
        X[1, c] -= X[2, c] * L[1, 2]
        X[0, c] -= X[2, c] * L[0, 2]
        X[1, c] /= L[1, 1]
        X[0, c] -= X[1, c] * L[0, 1]
        X[0, c] /= L[0, 0]
    return True


def _refit(rx, ry, y, q_in, stride, c2, qvar, quantised, sk2, min_thr, hk, hk2, converged, iterations,
           with_shift):  # pragma: no cover (compiled)
    """plane_fit._refit over _solve_step, written out per point (see there for the model)."""
    n = rx.shape[0]
    q0, q1, q2 = q_in[0], q_in[1], q_in[2]
    mask = np.zeros(n, np.bool_)
    m_shift = n if with_shift else 0
    u_out = np.zeros(m_shift)
    yp_out = np.zeros(m_shift)
    H = np.zeros((3, 3))
    g = np.zeros((3, 1))
    step = np.zeros((3, 1))
    chi2 = 0.0
    stages = 2 if stride >= 2 else 1
    for stage in range(stages):
        last = stage == stages - 1
        k = 1 if last else stride
        shift = last and with_shift
        for _ in range(iterations):
            hxx = 0.0
            hxy = 0.0
            hx1 = 0.0
            hyy = 0.0
            hy1 = 0.0
            h11 = 0.0
            gx = 0.0
            gy = 0.0
            g1 = 0.0
            chi2 = 0.0
            for i in range(0, n, k):
                xi = rx[i]
                yi = ry[i]
                yp = xi * q0
                yp += yi * q1
                yp += q2
                res = y[i] - yp
                r2 = res * res
                yp2 = yp * yp
                if quantised:
                    var = yp2 * yp2
                    var *= qvar
                    var += c2
                else:
                    var = c2
                band = yp2 * min_thr
                band *= band
                lim = var * sk2
                if band > lim:
                    lim = band
                inside = r2 < lim and yp > 0
                if last:
                    mask[i] = inside
                if shift:
                    yp_out[i] = yp
                    u_out[i] = 0.0
                if not inside:
                    continue
                w = 1.0 / var
                if r2 > var * hk2:  # Huber
                    w *= hk * math.sqrt(var / r2)
                if shift:
                    u_out[i] = w * yp2
                a = w * xi
                b = w * yi
                t = w * res
                hxx += a * xi
                hxy += a * yi
                hx1 += a
                hyy += b * yi
                hy1 += b
                h11 += w
                gx += t * xi
                gy += t * yi
                g1 += t
                chi2 += t * res
            H[0, 0] = hxx
            H[0, 1] = hxy
            H[0, 2] = hx1
            H[1, 0] = hxy
            H[1, 1] = hyy
            H[1, 2] = hy1
            H[2, 0] = hx1
            H[2, 1] = hy1
            H[2, 2] = h11
            g[0, 0] = gx
            g[1, 0] = gy
            g[2, 0] = g1
            if _solve3(H, g, step):
                s0, s1, s2 = step[0, 0], step[1, 0], step[2, 0]
            else:  # numpy's LinAlgError: no step
                s0, s1, s2 = 0.0, 0.0, 0.0
            q0 = q0 + s0
            q1 = q1 + s1
            q2 = q2 + s2
            # step @ H @ step as numpy evaluates it: (step @ H) @ step
            v0 = s0 * H[0, 0] + s1 * H[1, 0] + s2 * H[2, 0]
            v1 = s0 * H[0, 1] + s1 * H[1, 1] + s2 * H[2, 1]
            v2 = s0 * H[0, 2] + s1 * H[1, 2] + s2 * H[2, 2]
            if v0 * s0 + v1 * s1 + v2 * s2 < converged:
                break
    q_out = np.empty(3)
    q_out[0] = q0
    q_out[1] = q1
    q_out[2] = q2
    return q_out, H, mask, chi2, u_out, yp_out


def _score_kernel(nh, dh, rays, z, thr, cols, all_cols, fused):  # pragma: no cover (compiled)
    """plane_fit._score per hypothesis and point, in float32: |n.ray z + d| < -thr n.ray, with
    n.ray rounded as numpy's matrix product rounds it (``fused``: a chain of fused multiply-adds,
    emulated in float64, where products of float32 values are exact)."""
    out = np.zeros(nh.shape[0], np.intp)
    _count_inliers(nh, dh, rays, z, thr, cols, all_cols, fused, out)
    return out


def _count_inliers(nh, dh, rays, z, thr, cols, all_cols, fused, out):  # pragma: no cover (compiled)
    """_score_kernel's counts into ``out`` (float32 nh (H, 3) and dh (H,))."""
    nhyp = nh.shape[0]
    m = z.shape[0] if all_cols else cols.shape[0]
    for h in range(nhyp):
        a0 = nh[h, 0]
        a1 = nh[h, 1]
        a2 = nh[h, 2]
        d = dh[h]
        count = 0
        for jj in range(m):
            j = jj if all_cols else cols[jj]
            r0 = rays[0, j]
            r1 = rays[1, j]
            r2 = rays[2, j]
            if fused:
                nr = np.float32(np.float64(a1) * np.float64(r1) + np.float64(a0 * r0))
                nr = np.float32(np.float64(a2) * np.float64(r2) + np.float64(nr))
            else:
                nr = (a0 * r0 + a1 * r1) + a2 * r2
            err = abs(nr * z[j] + d)
            if err < nr * -thr[j]:
                count += 1
        out[h] = count


def _hypotheses(P, table, count, rays, z, thr, fused, rx, ry, y, c2, qvar, sk2, min_thr):  # pragma: no cover (compiled)
    """plane_fit._global_hypotheses over all m points, _score of each and _band of the first best."""
    m = P.shape[1]
    nh = np.empty((count, 3))
    dh = np.empty(count)
    k = 0
    for h in range(count):
        i0 = np.intp(table[0, h] * m)
        i1 = np.intp(table[1, h] * m)
        i2 = np.intp(table[2, h] * m)
        a0, a1, a2 = P[0, i0], P[1, i0], P[2, i0]
        u0, u1, u2 = P[0, i1] - a0, P[1, i1] - a1, P[2, i1] - a2
        v0, v1, v2 = P[0, i2] - a0, P[1, i2] - a1, P[2, i2] - a2
        n0 = u1 * v2 - u2 * v1
        n1 = u2 * v0 - u0 * v2
        n2 = u0 * v1 - u1 * v0
        norm = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if not norm > 1e-9:
            continue  # a degenerate triplet
        n0 /= norm
        n1 /= norm
        n2 /= norm
        d = -(n0 * a0 + n1 * a1 + n2 * a2)
        sign = -1.0 if d < 0 else 1.0  # normal towards the camera: d > 0
        nh[k, 0], nh[k, 1], nh[k, 2] = n0 * sign, n1 * sign, n2 * sign
        dh[k] = d * sign
        k += 1
    nh = nh[:k]
    dh = dh[:k]
    nh32 = np.empty((k, 3), np.float32)
    dh32 = np.empty(k, np.float32)
    for h in range(k):
        nh32[h, 0], nh32[h, 1], nh32[h, 2] = np.float32(nh[h, 0]), np.float32(nh[h, 1]), np.float32(nh[h, 2])
        dh32[h] = np.float32(dh[h])
    score = np.zeros(k, np.intp)
    _count_inliers(nh32, dh32, rays, z, thr, np.zeros(0, np.intp), True, fused, score)
    band = np.zeros(m, np.bool_)
    best = -1
    top = -1
    for h in range(k):
        if score[h] > top:
            top = score[h]
            best = h
    if best >= 0:
        q0, q1, q2 = -nh[best, 0] / dh[best], -nh[best, 1] / dh[best], -nh[best, 2] / dh[best]
        for j in range(m):
            yp = rx[j] * q0 + ry[j] * q1 + q2
            t = yp * yp
            var = c2 + t * t * qvar
            b = t * min_thr
            b = b * b
            r = y[j] - yp
            lim = var * sk2
            if b > lim:
                lim = b
            band[j] = r * r < lim and yp > 0
    return nh, dh, score, best, band


def _hypotheses_kernel(P, table, count, rays, z, thr, fused, rx, ry, y, c2, qvar, sk2, min_thr):  # pragma: no cover (compiled)
    """_hypotheses as a kernel of its own (the first round on a subsample already made)."""
    return _hypotheses(P, table, count, rays, z, thr, fused, rx, ry, y, c2, qvar, sk2, min_thr)


def _one_surface_kernel(rx, ry, z, k, c, unit_var, quantised, sigma_k, min_thr, table, count, fused, c2, qvar, sk2,
                        min_fraction):  # pragma: no cover (compiled)
    """plane_fit._subsample, then _find_surfaces' first round and its verdict when the best
    hypothesis holds all but min_pts of the subsample (see one_surface)."""
    N = z.shape[0]
    first = k // 2
    m = 0 if N <= first else (N - 1 - first) // k + 1
    P = np.empty((3, m))
    rays = np.empty((3, m), np.float32)
    z32 = np.empty(m, np.float32)
    thr32 = np.empty(m, np.float32)
    sx = np.empty(m)
    sy = np.empty(m)
    sinv = np.empty(m)
    for j in range(m):
        i = first + j * k
        x, yy, zz = rx[i], ry[i], z[i]
        sx[j], sy[j], sinv[j] = x, yy, 1.0 / zz
        P[0, j], P[1, j], P[2, j] = x * zz, yy * zz, 1.0 * zz
        rays[0, j], rays[1, j], rays[2, j] = np.float32(x), np.float32(yy), np.float32(1.0)
        z32[j] = np.float32(zz)
        s = zz * zz * c
        if quantised:
            s = np.sqrt(s * s + unit_var)
        t = sigma_k * s
        if min_thr > t:
            t = min_thr
        thr32[j] = np.float32(t)
    n = np.zeros(3)
    min_pts = max(3, int(math.ceil(min_fraction * m)))
    if m < min_pts:
        return False, n, 0.0
    nh, dh, score, best, _ = _hypotheses(P, table, count, rays, z32, thr32, fused, sx, sy, sinv, c2, qvar, sk2, min_thr)
    if best < 0 or 2 * score[best] < m or score[best] < min_pts or score[best] < m - min_pts:
        return False, n, 0.0
    n[0], n[1], n[2] = nh[best, 0], nh[best, 1], nh[best, 2]
    return True, n, dh[best]


def _behind(rx, ry, z, stride, n, d, c, qvar, quantised, margin_min):  # pragma: no cover (compiled)
    """plane_fit._behind_points' count before the window: rays that meet the plane in front of
    the camera with depth beyond it by more than max(3 depth_sigma(z_plane), margin_min)."""
    n0, n1, n2 = n[0], n[1], n[2]
    count = 0
    for i in range(0, z.shape[0], stride):
        nr = n0 * rx[i] + n1 * ry[i] + n2
        if not nr < -1e-9:
            continue
        zp = -d / nr
        s = zp * zp * c
        if quantised:
            s = math.sqrt(s * s + qvar)
        margin = 3.0 * s
        if margin_min > margin:
            margin = margin_min
        if z[i] > zp + margin:
            count += 1
    return count


def _behind_kernel(rx, ry, z, stride, n, d, c, qvar, quantised, margin_min):  # pragma: no cover (compiled)
    """_behind as a kernel of its own (identification's rear check)."""
    return _behind(rx, ry, z, stride, n, d, c, qvar, quantised, margin_min)


def _plane_cov(H, B, n, d, scale):  # pragma: no cover (compiled)
    """fit_plane's (Hi, Jqi, Jqi @ Hi @ Jqi.T * scale); ok False where numpy raises LinAlgError."""
    eye = np.eye(3)
    Hi = np.zeros((3, 3))
    Jqi = np.zeros((3, 3))
    cov = np.zeros((3, 3))
    Jq = np.empty((3, 3))
    dd = d * d
    for r in range(3):
        Jq[r, 0] = -B[0, r] / d
        Jq[r, 1] = -B[1, r] / d
        Jq[r, 2] = n[r] / dd
    if not (_solve3(H, eye, Hi) and _solve3(Jq, eye, Jqi)):
        return False, Hi, Jqi, cov
    M = np.zeros((3, 3))
    for r in range(3):
        for c in range(3):
            M[r, c] = Jqi[r, 0] * Hi[0, c] + Jqi[r, 1] * Hi[1, c] + Jqi[r, 2] * Hi[2, c]
    for r in range(3):
        for c in range(3):
            cov[r, c] = (M[r, 0] * Jqi[c, 0] + M[r, 1] * Jqi[c, 1] + M[r, 2] * Jqi[c, 2]) * scale
    return True, Hi, Jqi, cov


def _summary(rx, ry, z, mask, stride, h, v, n, d, halves):  # pragma: no cover (compiled)
    """Sums over the inliers among every stride-th point, P = z (rx, ry, 1), a = h . P, b = v . P:
    (their number k, [sum P (3), sum z^2, sum a, sum a^2, sum b, sum b^2], and with ``halves``
    and k >= 40 plane_fit._half_sums' (count, sum a', sum r, sum a'^2, sum a' r) per half,
    a' = a - median(a) and r = n . P + d)."""
    h0, h1, h2 = h[0], h[1], h[2]
    v0, v1, v2 = v[0], v[1], v[2]
    n0, n1, n2 = n[0], n[1], n[2]
    m = (z.shape[0] + stride - 1) // stride
    along = np.empty(m)
    res = np.empty(m)
    sums = np.zeros(8)
    k = 0
    for i in range(0, z.shape[0], stride):
        if not mask[i]:
            continue
        zi = z[i]
        px = rx[i] * zi
        py = ry[i] * zi
        a = h0 * px + h1 * py + h2 * zi
        b = v0 * px + v1 * py + v2 * zi
        sums[0] += px
        sums[1] += py
        sums[2] += zi
        sums[3] += zi * zi
        sums[4] += a
        sums[5] += a * a
        sums[6] += b
        sums[7] += b * b
        along[k] = a
        res[k] = (n0 * px + n1 * py + n2 * zi) + d
        k += 1
    hs = np.zeros((5, 2))  # count, sum a', sum r, sum a'^2, sum a' r per half, as np.bincount sums them
    if halves and k >= 40:
        med = np.median(along[:k])
        for j in range(k):
            a = along[j] - med
            side = 1 if a > 0 else 0
            hs[0, side] += 1.0
            hs[1, side] += a
            hs[2, side] += res[j]
            hs[3, side] += a * a
            hs[4, side] += a * res[j]
    return k, sums, hs


def _basis(n):  # pragma: no cover (compiled)
    """plane_fit._tangent_basis: (2, 3) orthonormal e1, e2 with e1 x e2 = n."""
    x, y, z = n[0], n[1], n[2]
    if abs(x) < 0.9:  # e1 = n x (1, 0, 0)
        e0, e1, e2 = 0.0, z, -y
    else:  # e1 = n x (0, 1, 0)
        e0, e1, e2 = -z, 0.0, x
    k = 1.0 / math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    a, b, c = e0 * k, e1 * k, e2 * k
    B = np.empty((2, 3))
    B[0, 0], B[0, 1], B[0, 2] = a, b, c
    B[1, 0], B[1, 1], B[1, 2] = y * c - z * b, z * a - x * c, x * b - y * a
    return B


def _quantisation_cov(rx, ry, u, yp, Hi, Jqi, delta, c, z_cut):  # pragma: no cover (compiled)
    """plane_fit._quantisation_cov. Its float32 sine and cosine are libm's here and numpy's own
    there, and its exp may be too: the two agree to the float32 rounding of the pattern (1e-7 of
    this term), not to the bit."""
    lim = 1.0 / z_cut
    k_sig = c * math.pi / delta
    k_amp = delta / math.pi
    k_phase = 2.0 * math.pi / delta
    s0 = s1 = s2 = c0 = c1 = c2 = 0.0
    for i in range(yp.shape[0]):
        if not yp[i] > lim:
            continue
        zp = 1.0 / yp[i]
        sig = zp * zp * k_sig
        amp = math.exp(-2.0 * sig * sig) * k_amp * u[i]
        phase = np.float32(zp * k_phase)
        ps = amp * np.float64(np.sin(phase))
        pc = amp * np.float64(np.cos(phase))
        s0 += ps * rx[i]
        s1 += ps * ry[i]
        s2 += ps
        c0 += pc * rx[i]
        c1 += pc * ry[i]
        c2 += pc
    cov = np.zeros((3, 3))
    for g0, g1, g2 in ((s0, s1, s2), (c0, c1, c2)):
        w0 = Hi[0, 0] * g0 + Hi[0, 1] * g1 + Hi[0, 2] * g2
        w1 = Hi[1, 0] * g0 + Hi[1, 1] * g1 + Hi[1, 2] * g2
        w2 = Hi[2, 0] * g0 + Hi[2, 1] * g1 + Hi[2, 2] * g2
        v = np.empty(3)
        for r in range(3):
            v[r] = Jqi[r, 0] * w0 + Jqi[r, 1] * w1 + Jqi[r, 2] * w2
        for r in range(3):
            for cc in range(3):
                cov[r, cc] += v[r] * v[cc]
    return cov / 2.0


def _tail_kernel(rx, ry, y, z, q_in, stride, c2, qvar, quantised, sk2, min_thr, hk, hk2, converged, iterations,
                 dense, c, margin_min, summary_stride, up, has_up, flat, delta, z_cut):  # pragma: no cover (compiled)
    """plane_fit._tail: refit, behind count, covariance and information, inlier summary."""
    q, H, mask, chi2, u, yp = _refit(rx, ry, y, q_in, stride, c2, qvar, quantised, sk2, min_thr, hk, hk2, converged,
                                     iterations, quantised)
    count = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            count += 1
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    n = np.empty(3)
    n[0], n[1], n[2] = -q[0] / qn, -q[1] / qn, -q[2] / qn
    d = 1.0 / qn
    behind = _behind(rx, ry, z, dense, n, d, c, qvar, quantised, margin_min)
    B = _basis(n)
    red = chi2 / max(count - 3, 1)
    scale = red if red > 1.0 else 1.0
    cov_ok, Hi, Jqi, cov = _plane_cov(H, B, n, d, scale)
    info = np.zeros((3, 3))
    info_ok = False
    if cov_ok:
        if quantised:
            cov += _quantisation_cov(rx, ry, u, yp, Hi, Jqi, delta, c, z_cut)
        info_ok = _solve3(cov, np.eye(3), info)
    h = np.empty(3)
    if has_up:  # unit(up x n)
        h[0] = up[1] * n[2] - up[2] * n[1]
        h[1] = up[2] * n[0] - up[0] * n[2]
        h[2] = up[0] * n[1] - up[1] * n[0]
        hn = math.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])
        if hn < 1e-12:
            hn = 1e-12
        h /= hn
    else:
        h[0], h[1], h[2] = B[0, 0], B[0, 1], B[0, 2]
    v = np.empty(3)  # n x h
    v[0] = n[1] * h[2] - n[2] * h[1]
    v[1] = n[2] * h[0] - n[0] * h[2]
    v[2] = n[0] * h[1] - n[1] * h[0]
    k_in, sums, hs = _summary(rx, ry, z, mask, summary_stride, h, v, n, d, flat)
    return n, d, mask, count, chi2, behind, B, cov_ok, cov, info_ok, info, k_in, sums, hs


def _gather_kernel(flat, rows, cols, row_step, stride, scale, zmin, zmax, ray_cols, ray_rows):  # pragma: no cover (compiled)
    """gather_roi's numpy code in one pass (uint16 times a double rounds as numpy's does)."""
    n = rows.shape[0]
    z = np.empty(n)
    rx = np.empty(n)
    ry = np.empty(n)
    k = 0
    for i in range(n):
        r = rows[i]
        c = cols[i]
        v = flat[r * row_step + c * stride] * scale
        if v > zmin and v < zmax:
            z[k] = v
            rx[k] = ray_cols[c]
            ry[k] = ray_rows[r]
            k += 1
    return z[:k], rx[:k], ry[:k]


def _clip(buf, n, planes, bits, out):  # pragma: no cover (compiled)
    """visibility.clip_vertex_list of the polygon buf[:n] (rows x, y, z) against the planes whose
    bit is set in ``bits``, in their order: the number of vertices left (0: fewer than 3), the
    polygon in buf[:count]. ``out`` is scratch of buf's size."""
    for j in range(planes.shape[0]):
        if not (bits >> j) & 1:
            continue
        a, b, c, d = planes[j, 0], planes[j, 1], planes[j, 2], planes[j, 3]
        s = np.empty(n)
        top = -math.inf
        for i in range(n):
            s[i] = a * buf[i, 0] + b * buf[i, 1] + c * buf[i, 2] + d
            if s[i] > top or i == 0:
                top = s[i]
        if top < 0:
            return 0
        m = 0
        for i in range(n):
            k = i + 1 if i + 1 < n else 0
            si, sk = s[i], s[k]
            if si >= 0:
                out[m, 0], out[m, 1], out[m, 2] = buf[i, 0], buf[i, 1], buf[i, 2]
                m += 1
            if (si >= 0) != (sk >= 0):
                t = si / (si - sk)
                out[m, 0] = buf[i, 0] + t * (buf[k, 0] - buf[i, 0])
                out[m, 1] = buf[i, 1] + t * (buf[k, 1] - buf[i, 1])
                out[m, 2] = buf[i, 2] + t * (buf[k, 2] - buf[i, 2])
                m += 1
        for i in range(m):
            buf[i, 0], buf[i, 1], buf[i, 2] = out[i, 0], out[i, 1], out[i, 2]
        n = m
    return n if n >= 3 else 0


def _outline_kernel(P, every, some, first, counts, plane_of, frustum, fx, fy, cx, cy, fixed_scale, near, stride,
                    grid_h, grid_w, max_range):  # pragma: no cover (compiled)
    return _outlines_of(P, every, some, first, counts, plane_of, frustum, fx, fy, cx, cy, fixed_scale, near, stride,
                        grid_h, grid_w, max_range)


def _views_kernel(T, corners, cull, origin_x, origin_y, cell, ni, nj, offsets, ids, box6, poly_plane, planes,
                  plane_first, vertices, vertex_first, R_T, t_C, frustum, fx, fy, cx, cy, fixed_scale, near, stride,
                  grid_h, grid_w, max_range, back_eps, cull_eps):  # pragma: no cover (compiled)
    """PlaneIndex.in_view, then roi._facing_camera, _stack_in_camera, _outside_bits and the outlines
    (_outlines_of), in one call. The visibility cull is conservative, as in_view's: it leaves a
    polygon out only when its box lies outside a bounding plane of the view by more than
    ``cull_eps``, which no rounding of these sums reaches, and the grid query's box is padded by a
    micrometre: so it keeps the planes in_view keeps (at most a plane more that the facing test or
    the clip drops), and the views are the same. From the facing test on, every product is
    numpy's, operation for operation (the einsums' orders, measured: tests/test_roi_speed_equivalence.py)."""
    # -- in_view: the grid cells under the range-truncated frustum's footprint
    x_lo = math.inf
    y_lo = math.inf
    x_hi = -math.inf
    y_hi = -math.inf
    for i in range(corners.shape[0]):
        x = corners[i, 0] * T[0, 0] + corners[i, 1] * T[0, 1] + corners[i, 2] * T[0, 2] + T[0, 3]
        y = corners[i, 0] * T[1, 0] + corners[i, 1] * T[1, 1] + corners[i, 2] * T[1, 2] + T[1, 3]
        x_lo = min(x_lo, x)
        x_hi = max(x_hi, x)
        y_lo = min(y_lo, y)
        y_hi = max(y_hi, y)
    pad = 1e-6
    i0 = math.floor((x_lo - pad - origin_x) / cell)
    j0 = math.floor((y_lo - pad - origin_y) / cell)
    i1 = math.floor((x_hi + pad - origin_x) / cell)
    j1 = math.floor((y_hi + pad - origin_y) / cell)
    n_map = planes.shape[0]
    seen = np.zeros(n_map, np.bool_)
    if not (i1 < 0 or j1 < 0 or i0 >= ni or j0 >= nj):
        i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1, ni - 1), min(j1, nj - 1)
        # The view's bounding planes in G: n_G = n_C R^T, d_G = d_C - n_G . t
        nc = cull.shape[0]
        nn = np.empty((nc, 6))
        dg = np.empty(nc)
        for k in range(nc):
            for j in range(3):
                nn[k, j] = cull[k, 0] * T[j, 0] + cull[k, 1] * T[j, 1] + cull[k, 2] * T[j, 2]
                nn[k, 3 + j] = abs(nn[k, j])
            dg[k] = cull[k, 3] - (nn[k, 0] * T[0, 3] + nn[k, 1] * T[1, 3] + nn[k, 2] * T[2, 3])
        for i in range(i0, i1 + 1):
            for q in range(offsets[i * nj + j0], offsets[i * nj + j1 + 1]):
                c = ids[q]
                if seen[poly_plane[c]]:
                    continue
                inside = True
                for k in range(nc):
                    r = dg[k]
                    for j in range(6):
                        r += box6[c, j] * nn[k, j]
                    if r < -cull_eps:
                        inside = False
                        break
                if inside:
                    seen[poly_plane[c]] = True
    # The back-face test of in_view (with its rounding room), then _facing_camera's:
    # pi_C = pi_G T_GC, the camera on the observable side when pi_C's last entry is positive.
    n_front = 0
    facing = np.empty(n_map, np.int64)
    for p in range(n_map):
        if not seen[p]:
            continue
        if planes[p, 0] * T[0, 3] + planes[p, 1] * T[1, 3] + planes[p, 2] * T[2, 3] + planes[p, 3] <= back_eps - cull_eps:
            continue
        if ((planes[p, 0] * T[0, 3] + planes[p, 1] * T[1, 3]) + planes[p, 2] * T[2, 3]) + planes[p, 3] * T[3, 3] \
                > back_eps:
            facing[n_front] = p
            n_front += 1
    facing = facing[:n_front]
    pi_camera = np.empty((n_front, 4))
    n_polys = 0
    n_rows = 0
    for f in range(n_front):
        p = facing[f]
        for k in range(4):
            pi_camera[f, k] = ((planes[p, 0] * T[0, k] + planes[p, 1] * T[1, k]) + planes[p, 2] * T[2, k]) \
                + planes[p, 3] * T[3, k]
        n_polys += plane_first[p + 1] - plane_first[p]
        n_rows += vertex_first[plane_first[p + 1]] - vertex_first[plane_first[p]]
    # _stack_in_camera: the facing planes' polygons, plane after plane, their vertices in C;
    # _outside_bits: bit j of a vertex's word when it is outside frustum plane j.
    P = np.empty((n_rows, 3))
    first = np.empty(n_polys, np.int64)
    counts = np.empty(n_polys, np.int64)
    plane_of = np.empty(n_polys, np.int64)
    every = np.empty(n_polys, np.int64)
    some = np.empty(n_polys, np.int64)
    n_f = frustum.shape[0]
    k = 0
    row = 0
    for f in range(n_front):
        p = facing[f]
        for c in range(plane_first[p], plane_first[p + 1]):
            first[k] = row
            counts[k] = vertex_first[c + 1] - vertex_first[c]
            plane_of[k] = p
            w_and = -1
            w_or = 0
            for v in range(vertex_first[c], vertex_first[c + 1]):
                for j in range(3):
                    P[row, j] = ((vertices[v, 0] * R_T[j, 0] + vertices[v, 1] * R_T[j, 1]) + vertices[v, 2] * R_T[j, 2]) \
                        + t_C[j]
                word = 0
                for j in range(n_f):
                    if (P[row, 0] * frustum[j, 0] + P[row, 2] * frustum[j, 2]) + P[row, 1] * frustum[j, 1] < -frustum[j, 3]:
                        word |= 1 << j
                w_and &= word
                w_or |= word
                row += 1
            every[k] = w_and
            some[k] = w_or
            k += 1
    px, fixed, seg, kept, plane_polys, z_near, boxes = _outlines_of(
        P, every, some, first, counts, plane_of, frustum, fx, fy, cx, cy, fixed_scale, near, stride, grid_h, grid_w,
        max_range)
    return facing, pi_camera, px, fixed, seg, kept, plane_polys, z_near, boxes


def _outlines_of(P, every, some, first, counts, plane_of, frustum, fx, fy, cx, cy, fixed_scale, near, stride,
                 grid_h, grid_w, max_range):  # pragma: no cover (compiled)
    n_polys = first.shape[0]
    n_planes = frustum.shape[0]
    # Room for every vertex: a clip against one plane at most doubles a polygon's vertices.
    cap = 0
    for k in range(n_polys):
        if every[k] == 0:
            cap += counts[k] << min(n_planes, 8) if some[k] != 0 else counts[k]
    Q = np.empty((max(cap, 1), 3))
    seg = np.empty(n_polys + 1, np.int64)
    kept_plane = np.empty(n_polys, np.int64)
    n_kept = 0
    rows = 0
    for k in range(n_polys):
        if every[k] != 0:
            continue  # every vertex outside one frustum plane
        a, cnt = first[k], counts[k]
        if some[k] == 0:
            for i in range(cnt):
                Q[rows + i, 0], Q[rows + i, 1], Q[rows + i, 2] = P[a + i, 0], P[a + i, 1], P[a + i, 2]
            got = cnt
        else:
            size = cnt << min(n_planes, 8)
            buf = np.empty((size, 3))
            out = np.empty((size, 3))
            for i in range(cnt):
                buf[i, 0], buf[i, 1], buf[i, 2] = P[a + i, 0], P[a + i, 1], P[a + i, 2]
            got = _clip(buf, cnt, frustum, some[k], out)
            if got == 0:
                continue
            for i in range(got):
                Q[rows + i, 0], Q[rows + i, 1], Q[rows + i, 2] = buf[i, 0], buf[i, 1], buf[i, 2]
        seg[n_kept] = rows
        kept_plane[n_kept] = plane_of[k]
        n_kept += 1
        rows += got
    seg[n_kept] = rows
    # Full-resolution pixels (depth floored at the near plane, as np.maximum: NaN stays NaN) and
    # the fixed-point grid pixels fillPoly takes.
    px = np.empty((rows, 2))
    fixed = np.empty((rows, 2), np.int32)
    for i in range(rows):
        z = Q[i, 2]
        m = z if (z != z or z >= near) else near
        u = Q[i, 0] / m
        u *= fx
        u += cx
        v = Q[i, 1] / m
        v *= fy
        v += cy
        px[i, 0] = u
        px[i, 1] = v
        fixed[i, 0] = np.int32(np.rint(u * fixed_scale))
        fixed[i, 1] = np.int32(np.rint(v * fixed_scale))
    # Per plane: nearest depth and the box around its outlines (kept polygons come by plane).
    planes = np.empty(n_kept, np.int64)
    plane_polys = np.empty((n_kept, 2), np.int64)  # first and one past the last kept polygon
    z_near = np.empty(n_kept)
    boxes = np.empty((n_kept, 4), np.int64)
    n_out = 0
    i = 0
    while i < n_kept:
        idx = kept_plane[i]
        start = i
        zn = math.inf
        u0 = math.inf
        v0 = math.inf
        u1 = -math.inf
        v1 = -math.inf
        while i < n_kept and kept_plane[i] == idx:
            for r in range(seg[i], seg[i + 1]):
                z = Q[r, 2]
                if z < zn:
                    zn = z
                if px[r, 0] < u0:
                    u0 = px[r, 0]
                if px[r, 1] < v0:
                    v0 = px[r, 1]
                if px[r, 0] > u1:
                    u1 = px[r, 0]
                if px[r, 1] > v1:
                    v1 = px[r, 1]
            i += 1
        if zn < max_range:
            planes[n_out] = idx
            plane_polys[n_out, 0] = start
            plane_polys[n_out, 1] = i
            z_near[n_out] = zn
            boxes[n_out, 0] = max(math.floor(u0 / stride), 0)
            boxes[n_out, 1] = max(math.floor(v0 / stride), 0)
            boxes[n_out, 2] = min(math.ceil(u1 / stride), grid_w - 1)
            boxes[n_out, 3] = min(math.ceil(v1 / stride), grid_h - 1)
            n_out += 1
    return px, fixed, seg[:n_kept + 1], planes[:n_out], plane_polys[:n_out], z_near[:n_out], boxes[:n_out]


def _zbuffer_kernel(mask, ibuf, label, cols, rows, a, b, c, k, r0, r1, c0, c1, write):  # pragma: no cover (compiled)
    """roi._zbuffer's numpy code pixel by pixel: on rows r0:r1, columns c0:c1, a pixel inside the
    plane's polygons (``mask``) that it sees nearer than ``ibuf`` (inverse depth, float64) takes
    label ``k``, and its inverse depth goes into ``ibuf`` when ``write``."""
    for r in range(r0, r1):
        by = b * rows[r]
        for col in range(c0, c1):
            if mask[r, col] == 0:
                continue
            inv = (a * cols[col] + by) + c
            if inv > ibuf[r, col]:
                label[r, col] = k
                if write:
                    ibuf[r, col] = inv


def _hidden_kernel(ibuf, r0, r1, c0, c1, top):  # pragma: no cover (compiled)
    """top <= ibuf[r0:r1, c0:c1].min(), stopping at the first pixel below ``top``."""
    for r in range(r0, r1):
        for col in range(c0, c1):
            if ibuf[r, col] < top:
                return False
    return True


def _shrink_kernel(label, boxes, radii, pad):  # pragma: no cover (compiled)
    """shrink's work (see :func:`shrink`): per view, count its pixels on the inner grid, then keep
    those whose whole (2 r + 1)^2 window lies in its box and is its own. The window test runs as
    two passes of run lengths: along each row, how many of its own pixels end at a column; then,
    of the pixels whose row window is whole, how many end at a row down each column."""
    H, W = label.shape
    n = boxes.shape[0]
    cap = 0
    for k in range(n):
        i0, j0 = max(boxes[k, 1], pad), max(boxes[k, 0], pad)
        i1, j1 = min(boxes[k, 3], H - 1 - pad), min(boxes[k, 2], W - 1 - pad)
        if i1 >= i0 and j1 >= j0:
            cap += (i1 - i0 + 1) * (j1 - j0 + 1)
    rows = np.empty(cap, np.int32)
    cols = np.empty(cap, np.int32)
    offsets = np.zeros(n + 1, np.int64)
    pixels = np.zeros(n, np.int64)
    pos = 0
    for k in range(n):
        offsets[k] = pos
        c0, r0, c1, r1 = boxes[k, 0], boxes[k, 1], boxes[k, 2], boxes[k, 3]
        i0, j0, i1, j1 = max(r0, pad), max(c0, pad), min(r1, H - 1 - pad), min(c1, W - 1 - pad)
        if i1 < i0 or j1 < j0:
            continue
        rad = radii[k]
        if rad <= 0:
            for r in range(i0, i1 + 1):
                for c in range(j0, j1 + 1):
                    if label[r, c] == k:
                        rows[pos] = r - pad
                        cols[pos] = c - pad
                        pos += 1
            pixels[k] = pos - offsets[k]
            continue
        span = 2 * rad + 1
        # Rows whose pixels' windows can reach the inner part, within the box; the pixel count
        # on the way (the inner part lies within the rows and columns this pass reads).
        a0, a1 = max(r0, i0 - rad), min(r1, i1 + rad)
        whole_row = np.zeros((a1 - a0 + 1, j1 - j0 + 1), np.bool_)
        cnt = 0
        for r in range(a0, a1 + 1):
            inner_row = i0 <= r <= i1
            run = 0
            for c in range(c0, min(c1, j1 + rad) + 1):
                if label[r, c] == k:
                    run += 1
                    if inner_row and j0 <= c <= j1:
                        cnt += 1
                else:
                    run = 0
                j = c - rad  # the column whose row window ends here
                if j >= j0 and run >= span:
                    whole_row[r - a0, j - j0] = True
        pixels[k] = cnt
        if cnt == 0:
            continue
        vrun = np.zeros(j1 - j0 + 1, np.int64)
        for r in range(a0, a1 + 1):
            for c in range(j0, j1 + 1):
                vrun[c - j0] = vrun[c - j0] + 1 if whole_row[r - a0, c - j0] else 0
            i = r - rad  # the row whose column window ends here
            if i < i0 or i > i1:
                continue
            for c in range(j0, j1 + 1):
                if vrun[c - j0] >= span:
                    rows[pos] = i - pad
                    cols[pos] = c - pad
                    pos += 1
    offsets[n] = pos
    return rows[:pos], cols[:pos], offsets, pixels


def _wall_depth(table, k, x, y):  # pragma: no cover (compiled)
    """(n . ray, depth) of wall k of ``table`` along the ray (x, y, 1), as relocalize._pixels
    computes them."""
    denom = table[k, 0] * x + table[k, 1] * y + table[k, 2]
    return denom, -table[k, 3] / denom


def _score_std(zm, sig, coarse):  # pragma: no cover (compiled)
    """relocalize._depth_sigma of one depth, with its terms ``sig`` (relocalize.DEPTH_SIGMA)."""
    sigma = sig[0] + sig[1] * (zm * zm)
    if coarse:
        sigma = sigma + sig[2] + sig[3] * zm
    return sigma


def _pixels_kernel(label, table, z, valid, free, has_free, cols, rows, sig, coarse):  # pragma: no cover (compiled)
    """relocalize._pixels: its numpy code's operations pixel by pixel, in its order."""
    h, w = label.shape
    edge = np.zeros((h, w), np.bool_)
    for r in range(h):
        for c in range(w):
            k = label[r, c]
            if (r > 0 and label[r - 1, c] != k) or (r + 1 < h and label[r + 1, c] != k) \
                    or (c > 0 and label[r, c - 1] != k) or (c + 1 < w and label[r, c + 1] != k):
                edge[r, c] = True
    n_free = 0
    n = 0
    for r in range(h):
        for c in range(w):
            k = label[r, c]
            if k < 0:
                continue
            if valid[r, c]:
                n += 1
            if has_free and free[r, c] and not edge[r, c]:
                zm = z[r, c]
                z_pred = _wall_depth(table, k, cols[c], rows[r])[1]
                if z_pred > 0.0 and zm - z_pred >= 3.0 * _score_std(zm, sig, coarse):
                    n_free += 1
    r_idx = np.empty(n, np.int64)
    c_idx = np.empty(n, np.int64)
    on_edge = np.empty(n, np.bool_)
    lab = np.empty(n, np.int32)
    lab_seen = np.empty(n, np.int32)
    res_own = np.empty(n, np.float64)
    res = np.empty(n, np.float64)
    zms = np.empty(n, np.float64)
    sigmas = np.empty(n, np.float64)
    denoms = np.empty(n, np.float64)
    ds = np.empty(n, np.float64)
    i = 0
    for r in range(h):
        for c in range(w):
            k = label[r, c]
            if k < 0 or not valid[r, c]:
                continue
            zm = z[r, c]
            denom, z_pred = _wall_depth(table, k, cols[c], rows[r])
            sigma = _score_std(zm, sig, coarse)
            own = (zm - z_pred) / sigma
            best = own
            seen = k
            if edge[r, c] and not np.isnan(own):
                # The neighbours up, down, left, right (at the border, the pixel itself): the first
                # strictly nearer fit of another wall wins, as argmin over (own, the four) picks.
                size = abs(own)
                for q in range(4):
                    rr = min(max(r + (-1 if q == 0 else 1 if q == 1 else 0), 0), h - 1)
                    cc = min(max(c + (-1 if q == 2 else 1 if q == 3 else 0), 0), w - 1)
                    kn = label[rr, cc]
                    if kn < 0 or kn == k:
                        continue
                    zp = _wall_depth(table, kn, cols[c], rows[r])[1]
                    rn = (zm - zp) / sigma
                    if zp > 0.0 and abs(rn) < size:
                        size = abs(rn)
                        best = rn
                        seen = kn
            r_idx[i] = r
            c_idx[i] = c
            on_edge[i] = edge[r, c]
            lab[i] = k
            lab_seen[i] = seen
            res_own[i] = own
            res[i] = best
            zms[i] = zm
            sigmas[i] = sigma
            denoms[i] = denom
            ds[i] = table[k, 3]
            i += 1
    return n_free, r_idx, c_idx, on_edge, lab, lab_seen, res_own, res, zms, sigmas, denoms, ds


def _best_line_kernel(pts, pairs, tol):  # pragma: no cover (compiled)
    """relocalize._best_line's numpy loop, point by point in its order of operations."""
    n = pts.shape[0]
    best = -1
    line = (0.0, 0.0, 0.0, 0.0)  # the best line's normal and point
    for k in range(pairs.shape[0]):
        a, b = pairs[k, 0], pairs[k, 1]
        d0 = pts[b, 0] - pts[a, 0]
        d1 = pts[b, 1] - pts[a, 1]
        L = math.hypot(d0, d1)
        if L < 0.1:
            continue
        n0 = -d1 / L
        n1 = d0 / L
        ax, ay = pts[a, 0], pts[a, 1]
        cnt = 0
        for i in range(n):
            if abs((pts[i, 0] - ax) * n0 + (pts[i, 1] - ay) * n1) < tol[i]:
                cnt += 1
        if cnt > best:
            best = cnt
            line = (n0, n1, ax, ay)
    mask = np.zeros(n, np.bool_)
    if best >= 0:
        n0, n1, ax, ay = line
        for i in range(n):
            mask[i] = abs((pts[i, 0] - ax) * n0 + (pts[i, 1] - ay) * n1) < tol[i]
    return best, mask
