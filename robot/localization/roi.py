"""Regions of interest: which pixels each visible map plane should cover.

Visible polygons are rasterized with OpenCV into a label image through a depth buffer computed
from each plane's exact depth along the pixel rays. A painter's algorithm would draw far planes first; a
depth buffer gives the same answer where that works and stays right where polygons overlap in
depth (a long wall that is both nearer and farther than another), at the same cost. Planes are
drawn nearest first so that one hidden behind nearer walls is recognised from its box and skipped.

Work happens on a decimated pixel grid (every ``stride``-th pixel in rows and columns): only
those pixels are ever deprojected, so there is no reason to label the others.

On a building floor most of the per-frame cost is Python overhead per plane and polygon, so the
work is arranged to be vectorised over the candidates and to touch a plane's pixels only when
it can own some (measured in scripts/bench_buildings.py). The images a frame draws in are kept
per grid and thread and reset where the last frame drew, not allocated per frame; every
shortcut gives exactly what the plain code gives (tests/test_roi_speed_equivalence.py holds
the plain code and checks).
"""

from __future__ import annotations

import itertools
import math
import threading
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from robot.base.geometry import pose_to_T_ground_robot
from robot.config import CameraConfig
from robot.localization import fit_kernels
from robot.maps.plane_index import BACK_FACE_EPS, CULL_EPS, PackedPolygons, PlaneIndex, packed_polygons
from robot.maps.plane_map import PlaneMap
from robot.maps.visibility import NEAR_PLANE, clip_vertex_list, frustum_planes

_SUBPIXEL_BITS = 4
_KERNELS: Dict[int, np.ndarray] = {}  # erosion kernels by radius


@dataclass
class PlaneView:
    """One map plane as a camera should see it from the coarse pose."""

    plane_index: int
    plane_id: str
    pi_camera: np.ndarray  # (4,) predicted plane in C, normal towards the observable side
    outlines_px: List[np.ndarray]  # clipped polygon outlines in full-resolution pixels (col, row)
    z_near: float  # m, nearest predicted depth of its visible part
    pixels: int = 0  # grid pixels it owns after occlusion, before shrinking
    roi_rows: Optional[np.ndarray] = None  # grid indices of its shrunk ROI
    roi_cols: Optional[np.ndarray] = None
    margin_px: float = 0.0
    # Grid pixels (c0, r0, c1, r1), inclusive, around its outlines: all it can own. Set by
    # predict_plane_views; empty (c1 < c0) once rasterize_views finds it hidden.
    box: Optional[Tuple[int, int, int, int]] = None
    # (stride, outlines in fixed-point grid pixels) as fillPoly takes them; computed if absent.
    fixed_px: Optional[Tuple[int, List[np.ndarray]]] = field(default=None, repr=False)


@dataclass
class CameraGrid:
    """A decimated pixel grid of one camera: grid pixel (r, c) is image pixel (r*stride, c*stride)."""

    K: np.ndarray
    width: int
    height: int
    stride: int

    @property
    def shape(self) -> Tuple[int, int]:
        s = self.__dict__.get("_shape")
        if s is None:
            s = self.__dict__["_shape"] = (len(range(0, self.height, self.stride)),
                                           len(range(0, self.width, self.stride)))
        return s

    @property
    def frustum(self) -> np.ndarray:
        f = self.__dict__.get("_frustum")
        if f is None:
            f = self.__dict__["_frustum"] = frustum_planes(self.K, self.width, self.height)
        return f

    @property
    def K_grid(self) -> np.ndarray:
        s = float(self.stride)
        return np.array([[self.K[0, 0] / s, 0, self.K[0, 2] / s], [0, self.K[1, 1] / s, self.K[1, 2] / s], [0, 0, 1]])

    @property
    def rays(self) -> Tuple[np.ndarray, np.ndarray]:
        """Ray coordinates x/z of the grid's columns and y/z of its rows (float64)."""
        r = self.__dict__.get("_rays")
        if r is None:
            Kg = self.K_grid
            h, w = self.shape
            r = self.__dict__["_rays"] = ((np.arange(w) - Kg[0, 2]) / Kg[0, 0], (np.arange(h) - Kg[1, 2]) / Kg[1, 1])
        return r

    def _per_frame(self) -> _GridConstants:
        """What every frame on this grid reads, in the form it reads it (computed once)."""
        c = self.__dict__.get("_constants")
        if c is None:
            c = self.__dict__["_constants"] = _GridConstants(self)
        return c

    def _scratch(self) -> _Scratch:
        """This thread's depth buffer and label image on this grid (one set per thread, so that
        cameras or searches on other threads never share them)."""
        by_thread = self.__dict__.get("_scratch_by_thread")
        if by_thread is None:
            by_thread = self.__dict__["_scratch_by_thread"] = {}
        key = threading.get_ident()
        s = by_thread.get(key)
        if s is None:
            if len(by_thread) >= 4:  # forget the buffers of threads that have ended
                alive = {t.ident for t in threading.enumerate()}
                for gone in [t for t in by_thread if t not in alive]:
                    del by_thread[gone]
            s = by_thread[key] = _Scratch(self.shape)
        return s


class _GridConstants:
    """A grid's fixed numbers in the form the per-frame loops use them."""

    def __init__(self, grid: CameraGrid):
        cols, rows = grid.rays
        self.cols: List[float] = cols.tolist()
        self.rows: List[float] = rows.tolist()
        # Largest |x/z| and |y/z| on the grid: the scale of the rounding in rasterize_views' hidden test.
        self.col_span = max(-self.cols[0], self.cols[-1])
        self.row_span = max(-self.rows[0], self.rows[-1])
        frustum = grid.frustum
        # The operands of the vertex-frustum product, as predict_plane_views has always passed them.
        self.frustum_normals = frustum[:, :3]
        self.frustum_neg_d = -frustum[:, 3]
        self.bit_weights = 1 << np.arange(len(frustum))
        self.frustum_list: List[List[float]] = frustum.tolist()
        self.frustum_array = np.ascontiguousarray(frustum, float)
        self.planes_for_bits: Dict[int, List[List[float]]] = {}  # frustum planes by outside-bit set
        self.f_px = np.array([grid.K[0, 0], grid.K[1, 1]])  # (f_x, f_y)
        self.c_px = np.array(grid.K[:2, 2])  # (c_x, c_y)
        self.fixed_scale = float(1 << _SUBPIXEL_BITS) / grid.stride

    def frustum_planes_for(self, bits: int) -> List[List[float]]:
        got = self.planes_for_bits.get(bits)
        if got is None:
            got = self.planes_for_bits[bits] = [f for j, f in enumerate(self.frustum_list) if bits >> j & 1]
        return got


class _Scratch:
    """A grid's images reused from frame to frame instead of allocated for each: what the last
    rasterization drew is reset at the start of the next."""

    def __init__(self, shape: Tuple[int, int]):
        self.ibuf = np.zeros(shape, np.float64)  # inverse depth drawn so far, 0 for nothing
        self.label = np.full(shape, -1, np.int32)
        self.dirty: List[Tuple[int, int, int, int]] = []  # boxes (r0, r1, c0, c1) drawn last


class _Work:
    """Images for one plane at a time, on its box (views into grid-sized buffers): nothing in
    them outlives the plane, so grids of one size share them (the cameras' grids, usually),
    which keeps what a frame touches small enough to stay in cache."""

    def __init__(self, shape: Tuple[int, int]):
        self.mask = np.zeros(shape, np.uint8)  # the plane's polygons (1)


_work = threading.local()
_WORK_SHAPES = 4  # grid sizes a thread keeps work images for (the cameras' usually share one)


def _work_buffers(shape: Tuple[int, int]) -> _Work:
    """This thread's work images for grids of ``shape``."""
    by_shape: Optional[Dict[Tuple[int, int], _Work]] = getattr(_work, "by_shape", None)
    if by_shape is None:
        by_shape = _work.by_shape = {}
    w = by_shape.pop(shape, None)
    if w is None:
        if len(by_shape) >= _WORK_SHAPES:
            del by_shape[next(iter(by_shape))]  # the size used longest ago
        w = _Work(shape)
    by_shape[shape] = w  # last in the order: most recently used
    return w


def camera_views(plane_map: PlaneMap, index: PlaneIndex, cam: CameraConfig, pose: Tuple[float, float, float],
                 max_range: float, stride: int = 1) -> Tuple[List[PlaneView], np.ndarray, CameraGrid]:
    """What a camera sees from the robot pose (x, y, phi), nearer than ``max_range``: the views, the
    label image on its grid (index into the views of the plane each grid pixel sees, -1 for none)
    and the grid. No margins and no border padding: for reports and bounds, not for localizing."""
    grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, stride)
    T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    views = predict_views(plane_map, index, T_ground_camera, grid, max_range)
    return views, rasterize_views(views, grid), grid


def predict_plane_views(plane_map: PlaneMap, candidates: Sequence[int], T_ground_camera: np.ndarray,
                        grid: CameraGrid, max_range: float) -> List[PlaneView]:
    """Clip the candidate planes' polygons to the frustum and keep those in front of the camera.

    Vectorised over the candidates: planes seen from behind are dropped together, all their
    vertices are moved into C together, polygons with every vertex outside one frustum plane are
    dropped, and only polygons that cross a frustum plane are clipped one by one (against just the
    planes they cross); the results are projected together. Every step works row by row (einsum,
    elementwise), so a plane's view does not depend on which other planes are candidates.
    """
    pk = packed_polygons(plane_map)
    consts = grid._per_frame()
    # Keep the candidates the camera sees from their observable side, with their planes in C.
    facing, pi_camera = _facing_camera(pk, candidates, T_ground_camera)
    if not facing:
        return []
    # Stack their polygons' vertices, in C.
    polys = _stack_in_camera(pk, facing, T_ground_camera)
    if fit_kernels.backend() == "numba":
        found = _outlines_compiled(polys, consts, grid, max_range)
    else:
        found = _outlines(polys, consts, grid, max_range)
    # One view per plane left, with its plane in C.
    row = {c: r for r, c in enumerate(facing)}
    planes = plane_map.planes
    stride = grid.stride
    return [PlaneView(idx, planes[idx].id, pi_camera[row[idx]], outlines, z_near, box=box,
                      fixed_px=(stride, fixed_outlines))
            for idx, outlines, fixed_outlines, z_near, box in found]


def predict_views(plane_map: PlaneMap, index: PlaneIndex, T_ground_camera: np.ndarray, grid: CameraGrid,
                  max_range: float) -> List[PlaneView]:
    """The views of the planes a camera at ``T_ground_camera`` sees up to ``max_range``:
    ``predict_plane_views`` of ``index.in_view``'s candidates. With the compiled kernels, both in
    one call (fit_kernels.views: the same views, tests/test_roi_speed_equivalence.py); the numpy
    code took a few dozen small numpy calls per view: over a third of a relocalization's scoring
    and two fifths of the localizer's ROI prediction."""
    if fit_kernels.backend() != "numba" or not isinstance(index, PlaneIndex):  # (a stand-in index: its in_view)
        candidates = index.in_view(T_ground_camera, grid.frustum, max_range)
        return predict_plane_views(plane_map, candidates, T_ground_camera, grid, max_range) if candidates else []
    pk = index.packed
    consts = grid._per_frame()
    corners, cull = index.view_bounds(grid.frustum, max_range)
    h, w = grid.shape
    facing, pi_camera, px, fixed, seg, planes, plane_polys, z_near, boxes = fit_kernels.views(
        T_ground_camera, corners, cull, index.polygon_cells(), pk.box6, pk.plane_of, pk.planes, pk.first,
        pk.vertices, pk.vertex_first, consts.frustum_array, consts.f_px, consts.c_px, consts.fixed_scale, NEAR_PLANE,
        grid.stride, h, w, max_range, BACK_FACE_EPS, CULL_EPS)
    if not len(planes):
        return []
    row = {c: r for r, c in enumerate(facing.tolist())}
    map_planes = plane_map.planes
    stride = grid.stride
    return [PlaneView(idx, map_planes[idx].id, pi_camera[row[idx]], outlines, z_near, box=box,
                      fixed_px=(stride, fixed_outlines))
            for idx, outlines, fixed_outlines, z_near, box in _split_outlines(px, fixed, seg, planes, plane_polys,
                                                                                z_near, boxes)]


def _outlines(polys: _StackedPolygons, consts: _GridConstants, grid: CameraGrid, max_range: float
              ) -> List[Tuple[int, List[np.ndarray], List[np.ndarray], float, Tuple[int, int, int, int]]]:
    """The planes' outlines, clipped to the frustum and projected (see :func:`_plane_outlines`): the
    numpy code, the reference of :func:`fit_kernels.outlines`."""
    # Drop the polygons outside the frustum and clip those that cross it.
    clipped = _clip_to_frustum(polys, consts)
    if not clipped.kept:
        return []
    # Project every vertex: full-resolution pixels, and the fixed-point grid pixels fillPoly takes.
    px = _project(clipped.Q_camera, consts.f_px, consts.c_px)
    fixed = np.rint(px * consts.fixed_scale).astype(np.int32)  # as _fixed_point(px, grid.stride)
    # Gather each plane's outlines, nearest depth and grid box; drop the planes beyond max_range.
    return _plane_outlines(polys.plane_of, clipped, px, fixed, grid, max_range)


def _outlines_compiled(polys: _StackedPolygons, consts: _GridConstants, grid: CameraGrid, max_range: float
                       ) -> List[Tuple[int, List[np.ndarray], List[np.ndarray], float, Tuple[int, int, int, int]]]:
    """:func:`_outlines` with its loops compiled (fit_kernels.outlines); the outside-bits stay numpy's."""
    P = polys.P_camera
    first_vertex, every, some = _outside_bits(polys, consts)
    h, w = grid.shape
    return _split_outlines(*fit_kernels.outlines(
        np.ascontiguousarray(P), every.astype(np.int64), some.astype(np.int64), first_vertex.astype(np.int64),
        np.array(polys.counts, np.int64), np.array(polys.plane_of, np.int64), consts.frustum_array, consts.f_px,
        consts.c_px, consts.fixed_scale, NEAR_PLANE, grid.stride, h, w, max_range))


def _split_outlines(px: np.ndarray, fixed: np.ndarray, seg: np.ndarray, planes: np.ndarray, plane_polys: np.ndarray,
                    z_near: np.ndarray, boxes: np.ndarray
                    ) -> List[Tuple[int, List[np.ndarray], List[np.ndarray], float, Tuple[int, int, int, int]]]:
    """fit_kernels.outlines' arrays as :func:`_plane_outlines` gives them: per plane (index, its
    outlines in pixels, the same in fixed point, nearest depth, grid box)."""
    seg_l = seg.tolist()
    return [(idx, [px[seg_l[j]:seg_l[j + 1]] for j in range(p0, p1)],
             [fixed[seg_l[j]:seg_l[j + 1]] for j in range(p0, p1)], z, tuple(box))
            for idx, (p0, p1), z, box in zip(planes.tolist(), plane_polys.tolist(), z_near.tolist(), boxes.tolist())]


@dataclass
class _StackedPolygons:
    """Polygons of several planes, their vertices stacked in one array, plane after plane."""

    P_camera: np.ndarray  # (N, 3) every vertex, camera frame
    first: List[int]  # row of each polygon's first vertex
    counts: List[int]  # vertices of each polygon
    plane_of: List[int]  # map plane index of each polygon


@dataclass
class _ClippedPolygons:
    """What the frustum leaves of stacked polygons, as segments of one vertex array."""

    Q_camera: np.ndarray  # (M, 3) the stacked vertices, then those of the clipped polygons
    starts: np.ndarray  # first row of every segment: the stacked polygons', then the clipped ones'
    kept: List[Tuple[int, int]]  # (polygon, its segment) for each polygon with something left


def _facing_camera(pk: PackedPolygons, candidates: Sequence[int],
                   T_ground_camera: np.ndarray) -> Tuple[List[int], np.ndarray]:
    """The candidates whose observable side the camera stands on (otherwise it looks at the back of
    the face), and their planes in C, pi_C = pi_G T_GC row by row. The camera's side is pi_C's
    last entry, n . t + d (the bottom row of T_GC is (0, 0, 0, 1)), so one product gives both."""
    cand = np.asarray(candidates, dtype=np.intp).reshape(-1)
    pi_camera = np.einsum("ij,jk->ik", pk.planes[cand], T_ground_camera)
    front = pi_camera[:, 3] > BACK_FACE_EPS
    if front.all():
        return cand.tolist(), pi_camera
    return cand[front].tolist(), pi_camera[front]


def _stack_in_camera(pk: PackedPolygons, planes: List[int], T_ground_camera: np.ndarray) -> _StackedPolygons:
    """The polygons of ``planes``, plane after plane, with their vertices moved into C."""
    R_T = T_ground_camera[:3, :3].T
    t_C = -R_T @ T_ground_camera[:3, 3]
    V = np.concatenate([pk.plane_vertices[i] for i in planes])
    counts: List[int] = []
    plane_of: List[int] = []
    for i in planes:
        c = pk.plane_counts[i]
        counts += c
        plane_of += [i] * len(c)
    first = [0, *itertools.accumulate(counts[:-1])]
    return _StackedPolygons(np.einsum("ij,kj->ik", V, R_T) + t_C, first, counts, plane_of)


def _outside_bits(polys: _StackedPolygons, consts: _GridConstants) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each polygon's first row, and the AND and the OR of its vertices' outside-bits: bit j of a
    vertex's word says it is outside frustum plane j. A polygon is gone when the AND is not 0
    (all outside one plane); it crosses the planes its OR has."""
    first_vertex = np.array(polys.first, np.intp)
    words = (np.einsum("ij,kj->ik", polys.P_camera, consts.frustum_normals) < consts.frustum_neg_d) @ consts.bit_weights
    return first_vertex, np.bitwise_and.reduceat(words, first_vertex), np.bitwise_or.reduceat(words, first_vertex)


def _clip_to_frustum(polys: _StackedPolygons, consts: _GridConstants) -> _ClippedPolygons:
    """Drop the polygons with every vertex outside one frustum plane; clip those that cross some
    plane, against just those planes (Python floats, one by one); keep the others as they are."""
    P = polys.P_camera
    first = polys.first
    first_vertex, every_a, some_a = _outside_bits(polys, consts)
    every, some = every_a.tolist(), some_a.tolist()
    planes_for = consts.frustum_planes_for
    kept: List[Tuple[int, int]] = []
    clipped_pts: List[List[float]] = []
    clipped_starts: List[int] = []
    n_polys = len(first)
    n_rows = len(P)
    for k in range(n_polys):
        if every[k]:
            continue
        bits = some[k]
        if not bits:
            kept.append((k, k))
            continue
        a = first[k]
        clipped = clip_vertex_list(P[a:a + polys.counts[k]].tolist(), planes_for(bits))
        if clipped is not None:
            kept.append((k, n_polys + len(clipped_starts)))
            clipped_starts.append(n_rows + len(clipped_pts))
            clipped_pts += clipped
    # Rows of polygons that cross the frustum stay in Q unused; their clipped copies follow.
    if not clipped_pts:
        return _ClippedPolygons(P, first_vertex, kept)
    # A flat list of floats converts to an array several times faster than a list of triples.
    Q = np.concatenate((P, np.array(list(itertools.chain.from_iterable(clipped_pts))).reshape(-1, 3)))
    return _ClippedPolygons(Q, np.concatenate((first_vertex, np.array(clipped_starts, np.intp))), kept)


def _project(P_camera: np.ndarray, f_px: np.ndarray, c_px: np.ndarray) -> np.ndarray:
    """Full-resolution pixels (col, row) of camera-frame points; depth floored at the near plane.
    ``f_px`` is (f_x, f_y), ``c_px`` (c_x, c_y)."""
    px = P_camera[:, :2] / np.maximum(P_camera[:, 2:], NEAR_PLANE)
    px *= f_px
    px += c_px
    return px


def _fixed_point(px: np.ndarray, stride: int) -> np.ndarray:
    """Full-resolution pixels to the fixed-point grid pixels fillPoly takes (shift _SUBPIXEL_BITS)."""
    return np.rint(px * (float(1 << _SUBPIXEL_BITS) / stride)).astype(np.int32)


def _plane_outlines(plane_of: List[int], clipped: _ClippedPolygons, px: np.ndarray, fixed: np.ndarray,
                    grid: CameraGrid, max_range: float
                    ) -> List[Tuple[int, List[np.ndarray], List[np.ndarray], float, Tuple[int, int, int, int]]]:
    """(plane, outlines in pixels, the same in fixed point, nearest depth, grid box) of each plane
    whose nearest visible point is within ``max_range``. Kept polygons come grouped by plane."""
    starts = clipped.starts
    z_min = np.minimum.reduceat(clipped.Q_camera[:, 2], starts).tolist()
    px_lo = np.minimum.reduceat(px, starts).tolist()
    px_hi = np.maximum.reduceat(px, starts).tolist()
    seg = starts.tolist()
    seg_end = seg[1:]
    seg_end.append(len(px))
    found = []
    kept = clipped.kept
    i, n_kept = 0, len(kept)
    while i < n_kept:
        idx = plane_of[kept[i][0]]
        outlines, fixed_outlines, z_near = [], [], math.inf
        u0 = v0 = math.inf
        u1 = v1 = -math.inf
        while i < n_kept:
            k, j = kept[i]
            if plane_of[k] != idx:
                break
            a, b = seg[j], seg_end[j]
            outlines.append(px[a:b])
            fixed_outlines.append(fixed[a:b])
            z = z_min[j]
            if z < z_near:
                z_near = z
            lo_u, lo_v = px_lo[j]
            hi_u, hi_v = px_hi[j]
            if lo_u < u0:
                u0 = lo_u
            if lo_v < v0:
                v0 = lo_v
            if hi_u > u1:
                u1 = hi_u
            if hi_v > v1:
                v1 = hi_v
            i += 1
        if z_near < max_range:
            found.append((idx, outlines, fixed_outlines, z_near, _grid_box(u0, v0, u1, v1, grid)))
    return found


def _grid_box(u0: float, v0: float, u1: float, v1: float, grid: CameraGrid) -> Tuple[int, int, int, int]:
    """Grid pixels (c0, r0, c1, r1), inclusive and on the grid, around full-resolution pixels from
    (u0, v0) to (u1, v1)."""
    h, w = grid.shape
    s = grid.stride
    return (max(math.floor(u0 / s), 0), max(math.floor(v0 / s), 0),
            min(math.ceil(u1 / s), w - 1), min(math.ceil(v1 / s), h - 1))


def _outline_box(outlines_px: List[np.ndarray], grid: CameraGrid) -> Tuple[int, int, int, int]:
    pts = np.vstack(outlines_px)
    (u0, v0), (u1, v1) = pts.min(axis=0).tolist(), pts.max(axis=0).tolist()
    return _grid_box(u0, v0, u1, v1, grid)


def rasterize_views(views: List[PlaneView], grid: CameraGrid) -> np.ndarray:
    """Label image on the grid: index into ``views`` of the nearest plane per pixel, -1 for none.

    The buffer holds inverse depth, 1/z = -(n . ray) / d, which is affine in the pixel's ray
    coordinates (``_zbuffer``), 0 for "nothing", and on a box its largest value is at a corner.
    Planes are drawn nearest first; one whose largest inverse depth on its box does not beat
    what is already drawn everywhere on that box is hidden: it is skipped before rasterizing
    and its ``box`` set empty. On equal depth the plane drawn first (nearer z_near,
    then lower index) keeps the pixel.

    The label image returned is the grid's buffer for this thread, not a new array (which saves
    allocating and clearing two full images per frame): read it before the next call on the
    same grid, which overwrites it, and do not write to it; copy it to keep it.
    """
    scratch = grid._scratch()
    ibuf, label = scratch.ibuf, scratch.label
    for r0, r1, c0, c1 in scratch.dirty:
        ibuf[r0:r1, c0:c1] = 0.0
        label[r0:r1, c0:c1] = -1
    dirty = scratch.dirty = []
    work = _work_buffers(grid.shape)
    consts = grid._per_frame()
    cols, rows = consts.cols, consts.rows
    col_span, row_span = consts.col_span, consts.row_span
    cols_a, rows_a = grid.rays
    zbuffer, hidden = (fit_kernels.zbuffer, fit_kernels.hidden) if fit_kernels.backend() == "numba" \
        else (_zbuffer, _hidden)
    one = 1 << _SUBPIXEL_BITS
    order = sorted(range(len(views)), key=lambda j: views[j].z_near)
    last = order[-1] if order else -1
    for k in order:
        view = views[k]
        if view.box is None:
            view.box = _outline_box(view.outlines_px, grid)
        c0, r0, c1, r1 = view.box
        n0, n1, n2, n3 = view.pi_camera.tolist()
        if c1 < c0 or r1 < r0 or n3 == 0:
            view.box = (0, 0, -1, -1)
            continue  # off the grid, or a plane through the optical centre (seen edge-on)
        a, b, c = -n0 / n3, -n1 / n3, -n2 / n3
        # Largest inverse depth on the box, at a corner; with room for the rounding of the
        # per-pixel values (a few 1e-16 of the terms' magnitudes), so that the test never skips
        # a plane that would win a pixel.
        ia, ib = max(a * cols[c0], a * cols[c1]), max(b * rows[r0], b * rows[r1])
        top = ia + ib + c + 1e-6 * (abs(a) * col_span + abs(b) * row_span + abs(c))
        # (With nothing drawn yet, nothing can hide the first plane.)
        if top <= 0 or (dirty and hidden(ibuf, (r0, r1 + 1, c0, c1 + 1), top)):
            view.box = (0, 0, -1, -1)
            continue  # behind the camera on the whole box, or hidden behind what is already drawn
        if view.fixed_px is not None and view.fixed_px[0] == grid.stride:
            polys = view.fixed_px[1]
        else:
            polys = [_fixed_point(o, grid.stride) for o in view.outlines_px]
        # The box origin goes in as fillPoly's offset, in the same fixed-point units.
        mask = work.mask[r0:r1 + 1, c0:c1 + 1]
        mask.fill(0)
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS, offset=(-c0 * one, -r0 * one))
        dirty.append((r0, r1 + 1, c0, c1 + 1))  # before writing: reset next time whatever happens
        # (No plane after the last one reads the buffer.)
        zbuffer(work.mask, ibuf, label, cols_a, rows_a, a, b, c, k, (r0, r1 + 1, c0, c1 + 1), k != last)
    return label


def _hidden(ibuf: np.ndarray, box: Tuple[int, int, int, int], top: float) -> bool:
    """Whether the buffer holds at least ``top`` everywhere on ``box`` (r0, r1, c0, c1, the ends
    excluded): a plane whose inverse depth is nowhere above ``top`` there is hidden."""
    r0, r1, c0, c1 = box
    return bool(top <= ibuf[r0:r1, c0:c1].min())


def _zbuffer(mask: np.ndarray, ibuf: np.ndarray, label: np.ndarray, cols: np.ndarray, rows: np.ndarray, a: float,
             b: float, c: float, k: int, box: Tuple[int, int, int, int], write: bool) -> None:
    """A plane's pixels into the label image: on ``box`` (r0, r1, c0, c1, the ends excluded), a
    pixel inside its polygons (``mask``) where its inverse depth, 1/z = a x + b y + c at the
    pixel's ray (x, y, 1), beats the buffer's takes label ``k``; with ``write`` its inverse depth
    goes into the buffer. (The buffer is >= 0, so a pixel where the plane lies behind the camera
    never wins.) In float64, in this order of operations, which fit_kernels.zbuffer repeats: the
    same pixels on every machine (OpenCV's float32 weighted sum rounds differently with and
    without Intel's IPP, which decided pixels where two walls meet)."""
    r0, r1, c0, c1 = box
    inv = (a * cols[c0:c1])[None, :] + (b * rows[r0:r1])[:, None]
    inv += c
    isub = ibuf[r0:r1, c0:c1]
    won = (inv > isub) & (mask[r0:r1, c0:c1] != 0)
    if write:
        isub[won] = inv[won]
    label[r0:r1, c0:c1][won] = k


def shrink_rois(views: List[PlaneView], label: np.ndarray, grid: CameraGrid,
                margin_for: Callable[[PlaneView], float], pad: int = 0) -> None:
    """Fill each view's pixel count and its ROI: its own pixels eroded by its margin (in image
    pixels), so pixels that a pose error could hand to a neighbour are left out.

    The grid's border counts as outside: what lies beyond it is unknown here, and a plane cut by
    the border may end just beyond it, where a pose error would bring its edge into view. To
    keep the pixels of a plane that runs on well past the border, rasterize on a grid padded by
    ``pad`` pixels on every side (at least the largest margin, in grid pixels): the erosion then
    sees what lies beyond the image, and pixel counts and ROIs cover the inner grid only, in its
    coordinates (what :meth:`robot.localization.localizer.Localizer.plane_rois` does)."""
    if fit_kernels.backend() == "numba":
        _shrink_compiled(views, label, grid, margin_for, pad)
        return
    H, W = label.shape
    stride = grid.stride
    for k, view in enumerate(views):
        view.pixels = 0
        # A view owns pixels only inside its box (unknown: the whole grid).
        c0, r0, c1, r1 = view.box if view.box is not None else (0, 0, W - 1, H - 1)
        # The part of the box inside the inner grid: what can be reported.
        i0, j0, i1, j1 = max(r0, pad), max(c0, pad), min(r1, H - 1 - pad), min(c1, W - 1 - pad)
        if i1 < i0 or j1 < j0:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
            continue
        margin = float(margin_for(view))
        r = int(math.ceil(margin / stride))
        own = cv2.compare(label[r0:r1 + 1, c0:c1 + 1], k, cv2.CMP_EQ)  # 255 where it owns
        inner = (slice(i0 - r0, i1 + 1 - r0), slice(j0 - c0, j1 + 1 - c0))
        view.pixels = cv2.countNonZero(own[inner])
        if view.pixels == 0:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
            continue
        view.margin_px = margin
        if r > 0:
            kernel = _KERNELS.get(r)
            if kernel is None:
                kernel = _KERNELS[r] = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            # Beyond the box it owns nothing, so a border of zeros around the box is what it
            # has there, and only the grid's edges act as border.
            own = cv2.erode(own, kernel, dst=own, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        # cv2.findNonZero lists (col, row) in row-major order, as np.nonzero, at half its cost.
        found = cv2.findNonZero(own[inner])
        if found is None:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
        else:
            view.roi_rows, view.roi_cols = found[:, 0, 1] + (i0 - pad), found[:, 0, 0] + (j0 - pad)


def _shrink_compiled(views: List[PlaneView], label: np.ndarray, grid: CameraGrid,
                     margin_for: Callable[[PlaneView], float], pad: int) -> None:
    """:func:`shrink_rois` with the pixel work of every view in one compiled call
    (fit_kernels.shrink: the same counts and ROIs as OpenCV's compare, erode and findNonZero
    above, tests/test_roi_speed_equivalence.py)."""
    H, W = label.shape
    stride = grid.stride
    n = len(views)
    boxes = np.empty((n, 4), np.int64)
    radii = np.zeros(n, np.int64)
    margins: List[Optional[float]] = [None] * n
    for k, view in enumerate(views):
        c0, r0, c1, r1 = view.box if view.box is not None else (0, 0, W - 1, H - 1)
        # Boxes come clipped to the grid (_grid_box); clipped again here because the kernel reads
        # without bounds checks, and a box past the grid would read outside the label image.
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, W - 1), min(r1, H - 1)
        boxes[k] = (c0, r0, c1, r1)
        # The margin only where the view has a part on the inner grid (as the plain loop asks it).
        if min(r1, H - 1 - pad) >= max(r0, pad) and min(c1, W - 1 - pad) >= max(c0, pad):
            margin = margins[k] = float(margin_for(view))
            radii[k] = int(math.ceil(margin / stride))
    rows, cols, offsets, pixels = fit_kernels.shrink(label, boxes, radii, pad)
    off, pix = offsets.tolist(), pixels.tolist()
    for k, view in enumerate(views):
        view.pixels = pix[k]
        if view.pixels == 0:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
            continue
        view.margin_px = margins[k]
        a, b = off[k], off[k + 1]
        if a == b:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
        else:
            view.roi_rows, view.roi_cols = rows[a:b], cols[a:b]
