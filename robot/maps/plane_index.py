"""Spatial index over map planes so visibility never tests every plane of a large map.

Planes and their polygons are bucketed in uniform 2-D grids over their footprints (x, y extent).
``candidates`` returns the planes near a point (everything within the camera's range, whichever
way it looks: what the localizer weighs as rival explanations of a fit). ``in_view`` returns
only the planes that can show up in one camera's view: the grid cells under the camera's
range-truncated frustum, then every polygon's bounding box against the frustum planes and the
far plane at once, then a back-face test per plane. The tests are conservative: a plane is left
out only when clipping it would leave nothing, so the visible set equals a brute-force pass over
the whole map (tests/test_large_maps.py). Per frame the cost follows what is near the camera,
not the map's size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.maps.plane_map import PlaneMap

MAX_CELLS = 1 << 20  # a map spread over kilometres gets coarser cells, not a huge grid
BACK_FACE_EPS = 1e-6  # m: the camera must be this far on the observable side (as in roi.py)
CULL_EPS = 1e-9  # m: a box counts as outside a plane only when clearly so (rounding)


@dataclass(frozen=True)
class PackedPolygons:
    """A map's polygons in arrays, for vectorised per-frame work. Polygons are numbered plane by
    plane in map order: plane i owns polygons ``first[i]:first[i + 1]``."""

    planes: np.ndarray  # (N, 4) (n, d) of each plane
    first: np.ndarray  # (N + 1,)
    plane_of: np.ndarray  # (P,) plane of each polygon
    lo: np.ndarray  # (P, 3) bounding box of each polygon
    hi: np.ndarray  # (P, 3)
    box6: np.ndarray  # (P, 6) centre and half-size of that box
    plane_vertices: Tuple[np.ndarray, ...]  # per plane: its polygons' vertices stacked
    plane_counts: Tuple[Tuple[int, ...], ...]  # per plane: vertex count of each of its polygons
    vertices: np.ndarray  # (V, 3) every polygon's vertices, polygon after polygon
    vertex_first: np.ndarray  # (P + 1,) polygon k's vertices are rows vertex_first[k]:vertex_first[k + 1]


def _concat_ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, e) for each pair, without a Python loop."""
    counts = stops - starts
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.intp)
    ends = np.cumsum(counts)
    return np.arange(total, dtype=np.intp) + np.repeat(starts - (ends - counts), counts)


def packed_polygons(plane_map: PlaneMap) -> PackedPolygons:
    """The map's polygons packed; computed once per map object and cached on it (maps are not
    edited in place once loaded)."""
    key = (id(plane_map.planes), len(plane_map.planes))
    cached = plane_map.__dict__.get("_packed_polygons")
    if cached is not None and cached[0] == key:
        return cached[1]
    polys = [poly for p in plane_map.planes for poly in p.polygons]
    per_plane = np.array([len(p.polygons) for p in plane_map.planes], dtype=np.intp)
    lo = np.array([poly.min(axis=0) for poly in polys]).reshape(-1, 3)
    hi = np.array([poly.max(axis=0) for poly in polys]).reshape(-1, 3)
    packed = PackedPolygons(
        planes=plane_map.plane_array,
        first=np.concatenate([[0], np.cumsum(per_plane)]).astype(np.intp),
        plane_of=np.repeat(np.arange(len(plane_map.planes), dtype=np.intp), per_plane),
        lo=lo, hi=hi, box6=np.hstack([0.5 * (lo + hi), 0.5 * (hi - lo)]),
        plane_vertices=tuple(p.vertices for p in plane_map.planes),
        plane_counts=tuple(tuple(len(poly) for poly in p.polygons) for p in plane_map.planes),
        vertices=np.ascontiguousarray(np.concatenate(polys), float).reshape(-1, 3) if polys else np.zeros((0, 3)),
        vertex_first=np.concatenate([[0], np.cumsum([len(poly) for poly in polys], dtype=np.int64)]).astype(np.int64))
    plane_map.__dict__["_packed_polygons"] = (key, packed)
    return packed


class _Grid:
    """Uniform 2-D grid of item ids in compressed rows: cell c holds ids[offsets[c]:offsets[c + 1]]."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, cell: float):
        self.origin = np.floor(lo.min(axis=0) / cell) * cell if len(lo) else np.zeros(2)
        extent = (hi.max(axis=0) - self.origin) if len(lo) else np.ones(2)
        while np.prod(np.floor(extent / cell) + 1) > MAX_CELLS:
            cell *= 2.0
        self.cell = cell
        self.ni, self.nj = (int(v) for v in np.floor(extent / cell) + 1)
        i0, j0 = self._cells(lo).T
        i1, j1 = self._cells(hi).T
        wi, wj = i1 - i0 + 1, j1 - j0 + 1
        counts = wi * wj
        item = np.repeat(np.arange(len(lo), dtype=np.intp), counts)
        k = _concat_ranges(np.zeros_like(counts), counts)  # position inside each item's block of cells
        wj_rep = np.repeat(wj, counts)
        cell_id = (np.repeat(i0, counts) + k // wj_rep) * self.nj + np.repeat(j0, counts) + k % wj_rep
        order = np.argsort(cell_id, kind="stable")
        self.ids = item[order]
        self.offsets = np.concatenate([[0], np.cumsum(np.bincount(cell_id, minlength=self.ni * self.nj))])

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        ij = np.floor((np.asarray(xy, float) - self.origin) / self.cell).astype(np.intp)
        return np.clip(ij, 0, [self.ni - 1, self.nj - 1])

    def query(self, lo: Sequence[float], hi: Sequence[float]) -> np.ndarray:
        """Ids in the cells overlapping the box [lo, hi] (x, y); an id may repeat."""
        ox, oy = float(self.origin[0]), float(self.origin[1])
        i0, j0 = math.floor((lo[0] - ox) / self.cell), math.floor((lo[1] - oy) / self.cell)
        i1, j1 = math.floor((hi[0] - ox) / self.cell), math.floor((hi[1] - oy) / self.cell)
        if i1 < 0 or j1 < 0 or i0 >= self.ni or j0 >= self.nj:
            return np.zeros(0, np.intp)
        i0, j0, i1, j1 = max(i0, 0), max(j0, 0), min(i1, self.ni - 1), min(j1, self.nj - 1)
        off, nj = self.offsets, self.nj
        # Cells of one grid row are contiguous: one slice per row, whatever the query's width.
        parts = [self.ids[off[i * nj + j0]:off[i * nj + j1 + 1]] for i in range(i0, i1 + 1)]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _sorted_unique(ids: np.ndarray) -> np.ndarray:
    """np.unique of an int array; for the few dozen ids of one view a Python set costs half as
    much (np.unique's per-call overhead dominates there)."""
    if len(ids) > 512:
        return np.unique(ids)
    return np.array(sorted(set(ids.tolist())), dtype=ids.dtype)


def frustum_corners(frustum: np.ndarray, z_near: float, z_far: float) -> np.ndarray:
    """(8, 3) corners, in the camera frame, of the frustum cut at depths z_near and z_far.

    ``frustum`` is :func:`robot.maps.visibility.frustum_planes`' (near, left, right, top, bottom);
    each corner ray is where two adjacent side planes meet.
    """
    left, right, top, bottom = frustum[1:5, :3]
    out = []
    for a, b in ((left, top), (top, right), (right, bottom), (bottom, left)):
        r = np.cross(a, b)
        r = r / r[2]  # z = 1; the frustum's corners are in front of the camera
        out += [r * z_near, r * z_far]
    return np.array(out)


class PlaneIndex:
    def __init__(self, plane_map: PlaneMap, cell: float = 2.0):
        self.n = len(plane_map)
        self.packed = packed_polygons(plane_map)
        pk = self.packed
        first = pk.first[:-1]
        self._lo = np.minimum.reduceat(pk.lo[:, :2], first, axis=0) if self.n else np.zeros((0, 2))
        self._hi = np.maximum.reduceat(pk.hi[:, :2], first, axis=0) if self.n else np.zeros((0, 2))
        self._planes = _Grid(self._lo, self._hi, cell)
        self._lo_rows: List[List[float]] = self._lo.tolist()  # the same boxes as Python floats
        self._hi_rows: List[List[float]] = self._hi.tolist()
        self._polygons = _Grid(pk.lo[:, :2], pk.hi[:, :2], cell)
        self.cell = cell
        self._bounds_cache: Dict[Tuple[bytes, float], Tuple[np.ndarray, np.ndarray]] = {}
        self._cells: Optional[Tuple[float, float, float, int, int, np.ndarray, np.ndarray]] = None

    def candidates(self, position, max_range: float) -> List[int]:
        """Indices (sorted) of planes whose footprint box lies within ``max_range`` of ``position``."""
        x, y = float(position[0]), float(position[1])
        ids = self._planes.query((x - max_range, y - max_range), (x + max_range, y + max_range))
        if len(ids) == 0:
            return []
        # Exact test: distance from the point to each candidate's footprint box. Per frame there
        # are a handful, for which Python floats cost a fifth of numpy's calls (the same sums).
        r2 = max_range * max_range
        if len(ids) <= 64:
            lo, hi = self._lo_rows, self._hi_rows
            out = []
            for i in sorted(set(ids.tolist())):
                (lx, ly), (hx, hy) = lo[i], hi[i]
                gx, gy = max(max(lx - x, x - hx), 0.0), max(max(ly - y, y - hy), 0.0)
                if gx * gx + gy * gy <= r2:
                    out.append(i)
            return out
        idx = np.unique(ids)
        p = np.array([x, y])
        gap = np.maximum(np.maximum(self._lo[idx] - p, p - self._hi[idx]), 0.0)
        keep = np.einsum("ij,ij->i", gap, gap) <= r2
        return idx[keep].tolist()

    def near_box(self, lo, hi, max_range: float) -> List[int]:
        """Indices (sorted) of planes whose footprint box comes within ``max_range`` of the box lo..hi."""
        lo = np.asarray(lo[:2], float)
        hi = np.asarray(hi[:2], float)
        idx = np.unique(self._planes.query(lo - max_range, hi + max_range))
        if len(idx) == 0:
            return []
        gap = np.maximum(np.maximum(self._lo[idx] - hi, lo - self._hi[idx]), 0.0)
        keep = np.einsum("ij,ij->i", gap, gap) <= max_range * max_range
        return idx[keep].tolist()

    def polygon_cells(self) -> Tuple[float, float, float, int, int, np.ndarray, np.ndarray]:
        """The polygon grid as arrays: (origin x, origin y, cell size, rows, columns, offsets, ids);
        cell (i, j) holds polygons ``ids[offsets[i * columns + j]:offsets[i * columns + j + 1]]``."""
        if self._cells is None:
            g = self._polygons
            self._cells = (float(g.origin[0]), float(g.origin[1]), float(g.cell), g.ni, g.nj,
                           g.offsets.astype(np.int64), g.ids.astype(np.int64))
        return self._cells

    def view_bounds(self, frustum: np.ndarray, max_range: float) -> Tuple[np.ndarray, np.ndarray]:
        """(8, 3) corners and the six bounding planes (frustum, then the far plane at ``max_range``)
        of the range-truncated frustum, in the camera frame; cached per frustum."""
        return self._view_bounds(frustum, max_range)

    def _view_bounds(self, frustum: np.ndarray, max_range: float):
        """Corners of the range-truncated frustum and its six bounding planes (camera frame)."""
        key = (frustum.tobytes(), max_range)
        got = self._bounds_cache.get(key)
        if got is None:
            corners = frustum_corners(frustum, -frustum[0, 3], max_range)
            planes = np.vstack([frustum, [0.0, 0.0, -1.0, max_range]])
            got = self._bounds_cache[key] = (corners, planes)
        return got

    def in_view(self, T_ground_camera: np.ndarray, frustum: np.ndarray, max_range: float) -> List[int]:
        """Indices (sorted) of the planes that may be seen by a camera at ``T_ground_camera`` with
        the frustum ``frustum`` (camera frame, from :func:`robot.maps.visibility.frustum_planes`),
        up to depth ``max_range``.

        Conservative against :func:`robot.localization.roi.predict_plane_views` with the same ``max_range``:
        a plane left out is one it would drop (no polygon inside the frustum, seen from behind,
        or nearest visible depth beyond ``max_range``).
        """
        pk = self.packed
        corners_C, planes_C = self._view_bounds(frustum, max_range)
        R, t = T_ground_camera[:3, :3], T_ground_camera[:3, 3]
        xy = corners_C @ R[:2].T + t[:2]
        polys = self._polygons.query(xy.min(axis=0).tolist(), xy.max(axis=0).tolist())
        if len(polys) == 0:
            return []
        # The view's planes in G: pi_G = pi_C T_CG with T_CG = [R^T, -R^T t]. A box is outside a
        # plane when even its corner furthest along the plane's normal is behind it.
        n_G = planes_C[:, :3] @ R.T
        d_G = planes_C[:, 3] - n_G @ t
        n_T = n_G.T
        reach = pk.box6[polys] @ np.concatenate((n_T, np.abs(n_T))) + d_G
        planes = _sorted_unique(pk.plane_of[polys[(reach >= -CULL_EPS).all(axis=1)]])
        pi = pk.planes[planes]
        # Same back-face rule as predict_plane_views, with room for rounding.
        return planes[pi[:, :3] @ t + pi[:, 3] > BACK_FACE_EPS - CULL_EPS].tolist()
