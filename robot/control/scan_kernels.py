"""Compiled kernels for the protective stop's per-frame scan, and the choice between them and numpy.

The scan (:meth:`robot.control.protective_stop.ProtectiveStop.update_scan`) runs on every depth
frame of every camera. Its numpy code is a few dozen small calls on a few thousand points each,
whose per-call overhead is most of their cost; here it is one kernel call (:func:`scan`), three
compiled passes:

* the sampled pixels with a valid depth, back-projected into the robot frame, those in the
  height band kept, and whether the view is blinded close up (:func:`scan_frame` alone);
* their ground coordinates, the walls' pre-filter, each near wall's plane distance and polygons
  (the even-odd rule), and the points left as obstacles (:func:`walls` alone);
* the memory: what is too old or seen through goes, the frame's points come in, one per grid
  cell, a hash instead of a sort (:func:`remember` alone, its merge :func:`merge_cells`).

The walls' and the memory's parts are also kernels of their own (the caller's way on where the
walls' part declined, and the tests' way to each); :func:`scan_frame` is the call without them.

The numpy code in ``protective_stop`` stays the reference and the fallback, and the kernels give
its results exactly, not to a rounding: the same operations on the same floats in the same order
(fastmath is off: no reassociation, no fused multiply-adds), comparisons in the type numpy
compares in, integers otherwise. Where numpy's answer would hang on a platform's conversion of a
NaN or huge float to int64, or on a hypotenuse (libm's), a kernel declines (returns None) and the
caller uses numpy. That includes the coordinate changes: the numpy code writes each of them out
(``protective_stop._rotated``, each sum left to right) rather than calling a matrix product,
whose order of operations is its BLAS's and differs between machines (fused multiply-adds on
this one's OpenBLAS), so that the kernels can repeat it on every platform.

The kernels release the GIL (``nogil``): the scan runs on the localization worker beside the
event loop.

Backend: the plane fit's (:func:`robot.localization.fit_kernels.backend`, environment variable
``ROBOT_KERNELS``), so one switch decides every kernel: the scan's kernels run when that backend
is numba and they compiled. If they do not compile, ``auto`` falls back to numpy
(:func:`backend_note` says why) and ``numba`` raises. numba is imported only then, never by
importing this module. Compiled code is cached on disk (``cache=True``) where
``NUMBA_CACHE_DIR`` says. :func:`warm_up` compiles the kernels (half a minute to a minute of
CPU on the development machine: BENCHMARKS.md, "The localizer, step by step", gives each run's
figure; expect 5 to 8 times that on the Nano) or loads them from the cache (0.2 s); the app
calls it at start-up, so that no frame pays for it.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any, Dict, Optional, Tuple

import numpy as np

from robot.base.kernel_cache import compile_kernel_set, jit_table
from robot.localization import fit_kernels

_nb: Dict[str, Any] = {}  # kernel name -> numba dispatcher, once they compiled
_failed = ""  # why the kernels did not compile ("": they did, or were not tried)
_lock = threading.Lock()  # one compilation, whichever thread scans first
_KERNELS = ("_scan_kernel", "_walls_kernel", "_remember_kernel", "_merge_kernel")
# The kernels the others call: compiled into each caller (and those in _KERNELS on their own too).
_INLINED = ("_frame_kernel", "_walls_kernel", "_remember_kernel", "_merge_kernel")
_registered: list = []  # whether numba knows them (once per process)


def backend() -> str:
    """"numba" when the plane fit's backend is numba and the scan's kernels compiled, else "numpy"."""
    if fit_kernels.backend() != "numba":
        return "numpy"
    if not _nb and not _failed:
        warm_up()
    return "numba" if _nb else "numpy"


def backend_note() -> str:
    """One line on whether the scan's kernels run, and why not."""
    if backend() == "numba":
        return f"numba {_nb.get('version', '')}"
    return f"numpy ({_failed})" if _failed else f"numpy (the plane fit's backend is numpy: {fit_kernels.backend_note()})"


def warm_up() -> float:
    """Compile the kernels, or load them from numba's cache, on tiny inputs of the types the scan
    passes (raw uint16 and float32 metres). Returns the seconds it took (0 with the numpy backend).
    If compiling fails, "auto" falls back to numpy and "numba" (ROBOT_KERNELS) raises."""
    global _failed
    if fit_kernels.backend() != "numba":
        return 0.0
    t0 = time.perf_counter()
    with _lock:
        if not (_nb or _failed):
            # (The scan's callers read the module's table: it is filled before they run.)
            _failed = compile_kernel_set(_nb, _load, lambda kernels: (_nb.update(kernels), _run_each_kernel()),
                                         "the scan's numba kernels",
                                         os.environ.get(fit_kernels.ENV, "auto").strip().lower() == "numba")
    return time.perf_counter() - t0


def _load() -> Dict[str, Any]:
    """numba's dispatchers of the kernels (they compile, or load from the cache, at their first call),
    or the plane fit's backend's kernels compiled ahead of time."""
    return fit_kernels.kernel_table("scan", jit_kernels)


def jit_kernels() -> Dict[str, Any]:
    """Fresh numba dispatchers of the kernels (also what the ahead-of-time module falls back to
    for an argument type it was not built for)."""
    import numba

    if not _registered:  # plain Python functions here: numba compiles them where a kernel calls them
        for name in _INLINED:
            numba.extending.register_jitable(error_model="numpy")(globals()[name])
        _registered.append(True)
    return jit_table(numba, globals(), _KERNELS, error_model="numpy")


def _run_each_kernel() -> None:
    """Each kernel once, on the argument types the scan passes (a frame in raw uint16 units or in
    float32 metres, writable or not; the read-only ray tables; C-contiguous arrays of its own)."""
    rays = np.zeros((2, 2)), np.zeros((2, 2))
    for r in rays:
        r.flags.writeable = False
    K = np.array([[2.0, 0.0, 1.5], [0.0, 2.0, 1.5], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    p = np.array([[0.0, 0.0, 1.0], [0.1, -0.1, 2.0]])
    table = (np.zeros((1, 10)), np.zeros((1, 8)), np.array([0, 1], np.int64),
             np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), np.array([0, 4], np.int64),
             np.array([[0.0, 1.0, 0.0, 1.0]]))
    for depth, scale in ((np.full((4, 4), 1000, np.uint16), 0.001), (np.full((4, 4), 1.0, np.float32), 1.0)):
        for writeable in (True, False):  # a replayed frame may be a read-only view of its message
            depth.flags.writeable = writeable
            scan_frame(depth, 2, (2, 2), scale, 0.2, 3.0, rays, T, 0.04, 1.8, 0.6)
            scan(depth, 2, (2, 2), scale, 0.2, 3.0, rays, T, 0.04, 1.8, 0.6, T, (0.0, 0.0), table, (0.0, 0.11, 0.11, 0.06),
                 0.04, (p[:, :2].copy(), np.zeros(2), np.zeros(2, np.int64)), 1.0, 3.0, T, 0.5, K, 0.02)
            remember(p[:, :2].copy(), np.zeros(2), np.zeros(2, np.int64), 1.0, 3.0, T, 0.5, K, 0.2, depth, scale,
                     0.04, p[:, :2].copy(), T, 0.02)
    walls(p, T, (0.0, 0.0), table, 0.04, 0.0, 0.11, 0.11, 0.06)
    merge_cells(np.array([(3 << 32) + 4], np.int64), np.zeros(1), np.ones(1, np.bool_), p[:, :2].copy(), 1.0, 0.02)


# -- the kernels (plain Python here; numba compiles them) --------------------------------------

_LIMIT = 2.0 ** 31  # cells within this of the origin have a key of two int32 halves
_HASH = -7046029254386353131  # 0x9E3779B97F4A7C15 as int64: Fibonacci hashing (multiplies wrap)


def _frame_kernel(depth, stride, h, w, convert, scale, lo, hi, rays_x, rays_y, T, z_lo, z_hi, r0, r1, c0, c1, limit):
    """The sampled pixels' points in the height band, in the robot frame: ``_camera_points``,
    ``_rotated`` by ``T``'s rotation and ``_in_band`` in one pass, no array between them. And
    ``_near_blind``: whether more than ``limit`` depths of ``depth[r0:r1, c0:c1]`` are invalid
    (not finite or not positive), counted a row at a time until the rest cannot change it."""
    out = np.empty((h * w, 3))
    r00, r01, r02, t0 = T[0, 0], T[0, 1], T[0, 2], T[0, 3]
    r10, r11, r12, t1 = T[1, 0], T[1, 1], T[1, 2], T[1, 3]
    r20, r21, r22, t2 = T[2, 0], T[2, 1], T[2, 2], T[2, 3]
    n = 0
    for r in range(h):
        for c in range(w):
            raw = depth[r * stride, c * stride]
            z = np.float32(raw) * scale if convert else raw
            if np.isfinite(z) and z > lo and z < hi:
                z64 = np.float64(z)
                x = rays_x[r, c] * z64
                y = rays_y[r, c] * z64
                pz = x * r20 + y * r21 + z64 * r22 + t2
                if pz >= z_lo and pz <= z_hi:
                    out[n, 0] = x * r00 + y * r01 + z64 * r02 + t0
                    out[n, 1] = x * r10 + y * r11 + z64 * r12 + t1
                    out[n, 2] = pz
                    n += 1
    bad = 0
    for r in range(r0, r1):
        row = depth[r, c0:c1]
        in_row = np.int32(0)  # a narrow sum per row: the loop is vectorised (4 times faster)
        for i in range(row.shape[0]):
            v = row[i]
            in_row += np.int32(not (v > 0 and np.isfinite(v)))
        bad += in_row
        if bad > limit:
            return out[:n], True
        if bad + (r1 - 1 - r) * (c1 - c0) <= limit:
            return out[:n], False
    return out[:n], bad > limit


def _walls_kernel(p, G, pose_x, pose_y, planes, bounds, wall_polys, vertices, starts, boxes, tolerance, offset_x,
                  half_x, half_y, distance, beyond):
    """``_explained_by_walls`` and ``_kept_points`` of the robot-frame points ``p`` (N, 3) at the
    pose whose ground transform is ``G``: the points in the ground frame and their box, the walls'
    pre-filter (``bounds``, as ``ProtectiveStop._wall_bounds``), each wall's plane (``planes``: n,
    d, then the in-plane axes' two rows) and polygons (``wall_polys[k]`` to ``wall_polys[k + 1]``
    of ``starts`` and ``boxes``, as ``_inside_kernel``), then ``_kept_kernel``'s test. Returns the
    obstacle points (x, y), how many a wall explained, done (False as ``_kept_kernel``'s)."""
    n = p.shape[0]
    # The transform in locals: the compiler need not read G again after each store.
    g00, g01, g02, g03 = G[0, 0], G[0, 1], G[0, 2], G[0, 3]
    g10, g11, g12, g13 = G[1, 0], G[1, 1], G[1, 2], G[1, 3]
    g20, g21, g22, g23 = G[2, 0], G[2, 1], G[2, 2], G[2, 3]
    x_lo, x_hi, y_lo, y_hi = np.inf, -np.inf, np.inf, -np.inf
    nan_x, nan_y = False, False
    for i in range(n):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        x = px * g00 + py * g01 + pz * g02 + g03
        y = px * g10 + py * g11 + pz * g12 + g13
        if x != x:
            nan_x = True
        else:
            x_lo = min(x_lo, x)
            x_hi = max(x_hi, x)
        if y != y:
            nan_y = True
        else:
            y_lo = min(y_lo, y)
            y_hi = max(y_hi, y)
    if nan_x:
        x_lo, x_hi = np.nan, np.nan
    if nan_y:
        y_lo, y_hi = np.nan, np.nan
    v = np.array([pose_x, pose_y, -pose_x, -pose_y, x_hi, y_hi, -x_lo, -y_lo])
    near = np.empty(bounds.shape[0], np.int64)  # the walls the pre-filter keeps, in order
    m = 0
    for k in range(bounds.shape[0]):
        skip = False
        for j in range(8):
            if v[j] < bounds[k, j]:
                skip = True
        if not skip:
            near[m] = k
            m += 1
    out = np.empty((n, 2))
    kept = 0
    dropped = 0
    for i in range(n):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        explained = False
        # The ground coordinates again, as above: cheaper than storing them.
        gx = px * g00 + py * g01 + pz * g02 + g03
        gy = px * g10 + py * g11 + pz * g12 + g13
        gz = px * g20 + py * g21 + pz * g22 + g23
        for jw in range(m):
            k = near[jw]
            dist = gx * planes[k, 0] + gy * planes[k, 1] + gz * planes[k, 2]
            dist += planes[k, 3]
            if not abs(dist) < tolerance:
                continue
            x = gx * planes[k, 4] + gy * planes[k, 5] + gz * planes[k, 6]
            y = gx * planes[k, 7] + gy * planes[k, 8] + gz * planes[k, 9]
            for kp in range(wall_polys[k], wall_polys[k + 1]):
                if not (boxes[kp, 0] <= x <= boxes[kp, 1] and boxes[kp, 2] <= y <= boxes[kp, 3]):
                    continue
                a, b = starts[kp], starts[kp + 1]
                odd = False
                xj = vertices[b - 1, 0]
                yj = vertices[b - 1, 1]
                for e in range(a, b):
                    xi = vertices[e, 0]
                    yi = vertices[e, 1]
                    if (yi > y) != (yj > y) and x < (xj - xi) * (y - yi) / (yj - yi) + xi:
                        odd = not odd
                    xj = xi
                    yj = yi
                if odd:
                    explained = True
                    break
            if explained:
                break
        if explained:
            dx = max(abs(px - offset_x) - half_x, 0.0)
            dy = max(abs(py) - half_y, 0.0)
            if dx == 0.0:
                close = dy <= distance
            elif dy == 0.0:
                close = dx <= distance
            elif dx > beyond or dy > beyond:
                close = False
            else:
                return out[:0], 0, False
            if not close:
                dropped += 1
                continue
        out[kept, 0] = px
        out[kept, 1] = py
        kept += 1
    return out[:kept], dropped, True


def _scan_kernel(depth, stride, h, w, convert, scale, lo, hi, rays_x, rays_y, T, z_lo, z_hi, r0, r1, c0, c1, limit,
                 with_walls, G, pose_x, pose_y, planes, bounds, wall_polys, vertices, starts, boxes, tolerance, offset_x,
                 half_x, half_y, distance, beyond,
                 with_memory, mem, mem_t, keys, t, memory_time, C, z_test, fx, cx, fy, cy, min_range, cell_size):
    """A frame's whole scan in one call: ``_frame_kernel``, then ``_walls_kernel`` (``with_walls``;
    else the band points' x, y are the obstacle points), then ``_remember_kernel`` (``with_memory``),
    their arguments in that order (the depth, its conversion and the wall tolerance shared).
    Returns (band points, blinded, obstacle points, how many a wall explained, walls done, memory
    points, times, keys, memory done): a part not done (declined or not asked) is left to the caller."""
    p, blind = _frame_kernel(depth, stride, h, w, convert, scale, lo, hi, rays_x, rays_y, T, z_lo, z_hi, r0, r1, c0, c1,
                             limit)
    n = p.shape[0]
    if with_walls and n:
        xy, dropped, done = _walls_kernel(p, G, pose_x, pose_y, planes, bounds, wall_polys, vertices, starts, boxes,
                                          tolerance, offset_x, half_x, half_y, distance, beyond)
        if not done:
            return p, blind, xy, 0, False, mem[:0], mem_t[:0], keys[:0], False
    else:
        xy = np.empty((n, 2))
        for i in range(n):
            xy[i, 0] = p[i, 0]
            xy[i, 1] = p[i, 1]
        dropped = 0
    if not with_memory:
        return p, blind, xy, dropped, True, mem[:0], mem_t[:0], keys[:0], False
    mem, mem_t, keys, done = _remember_kernel(mem, mem_t, keys, t, memory_time, C, z_test, fx, cx, fy, cy, min_range,
                                              depth, scale, convert, tolerance, xy, G, cell_size)
    return p, blind, xy, dropped, True, mem, mem_t, keys, done


def _merge_kernel(keys, mem_t, alive, new, t, cell_size):
    """``ProtectiveStop._add_to_cells`` on a hash of the cells. ``keys`` (one per cell) and ``mem_t``
    of the memory, ``alive`` its points still kept, ``new`` (M, 2) points of time ``t``. Returns
    (which memory points stay, the new points' indices that are added, ascending, their keys,
    done): done is False when a cell is not within 2^31 of the origin (NaN points included), where
    numpy's float-to-int conversion decides and the caller uses numpy."""
    n_old = len(keys)
    n_new = new.shape[0]
    stays = alive.copy()
    added = np.zeros(n_new, np.bool_)
    new_keys = np.empty(n_new, np.int64)
    capacity = 16
    while capacity < 2 * (n_old + n_new):
        capacity *= 2
    mask = capacity - 1
    slot_key = np.empty(capacity, np.int64)
    slot_of = np.full(capacity, -1, np.int64)  # a memory point i >= 0, or a new point j as -2 - j
    for i in range(n_old):
        if not alive[i]:
            continue
        k = keys[i]
        s = ((k * _HASH) >> 40) & mask
        while slot_of[s] != -1:
            s = (s + 1) & mask
        slot_key[s] = k
        slot_of[s] = i
    for j in range(n_new):
        cx = np.floor(new[j, 0] / cell_size)
        cy = np.floor(new[j, 1] / cell_size)
        if not (-_LIMIT <= cx < _LIMIT and -_LIMIT <= cy < _LIMIT):
            return stays, np.zeros(0, np.int64), np.zeros(0, np.int64), False
        k = (np.int64(cx) << 32) + (np.int64(cy) & 0xFFFFFFFF)
        new_keys[j] = k
        s = ((k * _HASH) >> 40) & mask
        while True:
            r = slot_of[s]
            if r == -1:  # a new cell: its first point
                slot_key[s] = k
                slot_of[s] = -2 - j
                added[j] = True
                break
            if slot_key[s] == k:
                # The cell's remembered point gives way to a newer one; of equal times it comes
                # first. A later new point of the cell never replaces the first.
                if r >= 0 and t > mem_t[r]:
                    stays[r] = False
                    slot_of[s] = -2 - j
                    added[j] = True
                break
            s = (s + 1) & mask
    pick = np.nonzero(added)[0]
    return stays, pick, new_keys[pick], True


def _remember_kernel(mem, mem_t, keys, t, memory_time, C, z_test, fx, cx, fy, cy, min_range, depth, scale, convert,
                     tolerance, xy, G, cell_size):
    """``ProtectiveStop._remember`` up to its bound on the points, for a memory whose cell keys are
    known: the points older than ``memory_time`` go, then those the frame sees through (the camera
    at ``C``, ground to camera, points at height ``z_test``: ``_seen_through_kernel``'s test), then
    the scan's points ``xy`` taken to the ground by ``G`` are added, one per cell
    (``_merge_kernel``). Returns (points, times, keys, done); done False where those kernels decline."""
    n_old = len(keys)
    stays = np.empty(n_old, np.bool_)
    h, w = depth.shape
    scale32 = np.float32(scale)
    for i in range(n_old):
        stays[i] = t - mem_t[i] <= memory_time
    ox, oy, oz = C[0, 3], C[1, 3], C[2, 3]
    pz = z_test - oz
    for i in range(n_old):
        if not stays[i]:
            continue
        px = mem[i, 0] - ox
        py = mem[i, 1] - oy
        z = px * C[0, 2] + py * C[1, 2] + pz * C[2, 2]
        if not z > min_range:
            continue
        u = np.rint(fx * (px * C[0, 0] + py * C[1, 0] + pz * C[2, 0]) / z + cx)
        v = np.rint(fy * (px * C[0, 1] + py * C[1, 1] + pz * C[2, 1]) / z + cy)
        if u != u or v != v:
            return mem[:0], mem_t[:0], keys[:0], False
        if not (0.0 <= u < w and 0.0 <= v < h):
            continue
        raw = depth[int(v), int(u)]
        d = np.float32(raw) * scale32 if convert else raw
        if np.isfinite(d) and d > z + tolerance:
            stays[i] = False
    n_new = xy.shape[0]
    new = np.empty((n_new, 2))
    for j in range(n_new):
        new[j, 0] = xy[j, 0] * G[0, 0] + xy[j, 1] * G[0, 1] + G[0, 3]
        new[j, 1] = xy[j, 0] * G[1, 0] + xy[j, 1] * G[1, 1] + G[1, 3]
    pick = np.zeros(0, np.int64)
    new_keys = np.zeros(0, np.int64)
    if n_new:
        stays, pick, new_keys, done = _merge_kernel(keys, mem_t, stays, new, t, cell_size)
        if not done:
            return mem[:0], mem_t[:0], keys[:0], False
    m = 0
    for i in range(n_old):
        if stays[i]:
            m += 1
    out = np.empty((m + len(pick), 2))
    out_t = np.empty(m + len(pick))
    out_keys = np.empty(m + len(pick), np.int64)
    m = 0
    for i in range(n_old):
        if stays[i]:
            out[m, 0] = mem[i, 0]
            out[m, 1] = mem[i, 1]
            out_t[m] = mem_t[i]
            out_keys[m] = keys[i]
            m += 1
    for j in range(len(pick)):
        out[m + j, 0] = new[pick[j], 0]
        out[m + j, 1] = new[pick[j], 1]
        out_t[m + j] = t
        out_keys[m + j] = new_keys[j]
    return out, out_t, out_keys, True


# -- the kernels' callers: numpy's arguments in, the numpy code's values out (None: numpy decides) --

_FRAME_TYPES = tuple(np.dtype(t) for t in (np.uint8, np.uint16, np.float32, np.float64))  # native byte order


def _frame_type(depth: np.ndarray) -> bool:
    """Whether the kernels take this depth image (else numpy scans it)."""
    return depth.ndim == 2 and depth.dtype in _FRAME_TYPES


def merge_cells(keys: np.ndarray, mem_t: np.ndarray, alive: np.ndarray, new: np.ndarray, t: float,
                cell_size: float) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(memory points that stay, new points added (ascending indices), their cell keys), or None."""
    stays, pick, new_keys, done = _nb["_merge_kernel"](keys, np.ascontiguousarray(mem_t, np.float64), alive,
                                                       new, float(t), float(cell_size))
    return (stays, pick, new_keys) if done else None


# (planes (W, 10), pre-filter bounds (W, 8), each wall's first polygon (W + 1), vertices (V, 2),
# each polygon's first vertex (P + 1), polygon boxes (P, 4)): ``ProtectiveStop``'s walls for the kernel.
WallTable = Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


# (depth dtype, convert, min_range, max_range) -> the depth bounds as the kernels compare them
_BOUNDS: Dict[Tuple[Any, bool, float, float], Tuple[Any, Any]] = {}


def _depth_bounds(depth: np.ndarray, convert: bool, min_range: float, max_range: float) -> Tuple[Any, Any]:
    """The bounds in the type numpy compares the depths in: float32 depths against a Python float
    are compared in float32 (numpy 1's value-based casting and numpy 2's weak scalars alike)."""
    key = (depth.dtype, convert, min_range, max_range)
    b = _BOUNDS.get(key)
    if b is None:
        z_type = np.empty(0, np.float32 if convert else depth.dtype)
        b = _BOUNDS[key] = (np.result_type(z_type, min_range).type(min_range),
                            np.result_type(z_type, max_range).type(max_range))
    return b


def scan_frame(depth: np.ndarray, stride: int, shape: Tuple[int, int], depth_scale: float, min_range: float,
               max_range: float, rays: Tuple[np.ndarray, np.ndarray], T: np.ndarray, z_lo: float, z_hi: float,
               blind_fraction: float) -> Optional[Tuple[np.ndarray, bool]]:
    """(the sampled points in the height band, robot frame, as ``ProtectiveStop.update_scan``'s numpy
    code finds them; ``ProtectiveStop._near_blind`` with ``blind_fraction``), or None for a depth
    image the kernels do not take. ``T``: the camera's robot transform (4, 4)."""
    got = scan(depth, stride, shape, depth_scale, min_range, max_range, rays, T, z_lo, z_hi, blind_fraction)
    return None if got is None else (got[0], got[1])


_NO_WALLS = (np.zeros((0, 10)), np.zeros((0, 8)), np.zeros(1, np.int64), np.zeros((0, 2)), np.zeros(1, np.int64),
             np.zeros((0, 4)))
_NO_MEMORY = (np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))


def scan(depth: np.ndarray, stride: int, shape: Tuple[int, int], depth_scale: float, min_range: float, max_range: float,
         rays: Tuple[np.ndarray, np.ndarray], T: np.ndarray, z_lo: float, z_hi: float, blind_fraction: float,
         G: Optional[np.ndarray] = None, pose_xy: Tuple[float, float] = (0.0, 0.0),
         table: Optional[WallTable] = None, footprint: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
         tolerance: float = 0.0, memory: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None, t: float = 0.0,
         memory_time: float = 0.0, C: Optional[np.ndarray] = None, z_test: float = 0.0,
         K: Optional[np.ndarray] = None, cell_size: float = 1.0) -> Optional[Tuple[Any, ...]]:
    """A frame's scan in one kernel call: :func:`scan_frame`, then, at a pose (``G``, ground from
    robot, and ``pose_xy``), :func:`walls` with ``table`` (when given) and ``footprint`` (offset x,
    half x, half y, always distance), then :func:`remember` of ``memory`` (points, times, keys;
    when given, with ``C``, ground from camera). None for a depth image the kernels do not take;
    else (band points, blinded, obstacle points, walls explained, walls done, memory points,
    times, keys, memory done), a part not done left to the caller."""
    if not _frame_type(depth):
        return None
    convert = not (depth_scale == 1.0 and depth.dtype.kind == "f")
    lo, hi = _depth_bounds(depth, convert, min_range, max_range)
    h, w = depth.shape
    r0, r1, c0, c1 = h // 4, 3 * h // 4, w // 4, 3 * w // 4
    offset_x, half_x, half_y, distance = footprint
    mem, mem_t, keys = _NO_MEMORY if memory is None else memory
    if K is None:
        fx = cx = fy = cy = 0.0
    else:
        fx, cx, fy, cy = float(K[0, 0]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])
    return _nb["_scan_kernel"](
        depth, stride, shape[0], shape[1], convert, np.float32(depth_scale), lo, hi, rays[0], rays[1], T, float(z_lo),
        float(z_hi), r0, r1, c0, c1, blind_fraction * ((r1 - r0) * (c1 - c0)),
        G is not None and table is not None, _EYE if G is None else G, float(pose_xy[0]), float(pose_xy[1]),
        *(_NO_WALLS if table is None else table), float(tolerance), float(offset_x), float(half_x), float(half_y),
        float(distance), distance * (1.0 + 1e-9) + 1e-300,
        G is not None and memory is not None, mem, mem_t, keys, float(t), float(memory_time), _EYE if C is None else C,
        float(z_test), fx, cx, fy, cy, float(min_range), float(cell_size))


_EYE = np.eye(4)


def walls(p: np.ndarray, G: np.ndarray, pose_xy: Tuple[float, float], table: WallTable, tolerance: float,
          offset_x: float, half_x: float, half_y: float, distance: float) -> Optional[Tuple[np.ndarray, int]]:
    """(obstacle points (x, y), how many a wall explained) of the robot-frame points ``p`` at the pose
    ``G`` (ground from robot, (4, 4)) and ``pose_xy``, or None where numpy decides."""
    beyond = distance * (1.0 + 1e-9) + 1e-300
    xy, dropped, done = _nb["_walls_kernel"](p, G, float(pose_xy[0]), float(pose_xy[1]), *table, float(tolerance),
                                             float(offset_x), float(half_x), float(half_y), float(distance), beyond)
    return (xy, int(dropped)) if done else None


def remember(mem: np.ndarray, mem_t: np.ndarray, keys: np.ndarray, t: float, memory_time: float, C: np.ndarray,
             z_test: float, K: np.ndarray, min_range: float, depth: np.ndarray, depth_scale: float, tolerance: float,
             xy: np.ndarray, G: np.ndarray, cell_size: float) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``ProtectiveStop._remember``'s memory (points, times, cell keys) before its bound on the
    points, or None where numpy decides. ``C``: ground to camera (4, 4); ``G``: ground from robot."""
    if not _frame_type(depth):
        return None
    convert = not (depth_scale == 1.0 and depth.dtype.kind == "f")
    mem, mem_t, keys, done = _nb["_remember_kernel"](
        mem, mem_t, keys, float(t), float(memory_time), C, float(z_test), float(K[0, 0]), float(K[0, 2]),
        float(K[1, 1]), float(K[1, 2]), float(min_range), depth, float(depth_scale), convert, float(tolerance), xy, G,
        float(cell_size))
    return (mem, mem_t, keys) if done else None
