"""Regions of interest: which pixels each visible map plane should cover (DESIGN.md section 4 step 2).

Visible polygons are rasterized with OpenCV into a label image through a depth buffer computed
from each plane's exact depth along the pixel rays. DESIGN.md suggests drawing far planes first; a
depth buffer gives the same answer where that works and stays right where polygons overlap in
depth (a long wall that is both nearer and farther than another), at the same cost. Planes are
drawn nearest first so that one hidden behind nearer walls is recognised from its box and skipped.

Work happens on a decimated pixel grid (every ``stride``-th pixel in rows and columns): only
those pixels are ever deprojected, so there is no reason to label the others.

On a building floor most of the per-frame cost is Python overhead per plane and polygon, so the
work is arranged to be vectorised over the candidates and to touch a plane's pixels only when
it can own some (measured in scripts/bench_buildings.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from robot.maps.plane_index import BACK_FACE_EPS, packed_polygons
from robot.maps.plane_map import PlaneMap
from robot.maps.visibility import NEAR_PLANE, frustum_planes

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
    def shape(self):
        return (len(range(0, self.height, self.stride)), len(range(0, self.width, self.stride)))

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
    def rays(self):
        """Ray coordinates x/z of the grid's columns and y/z of its rows (float64), and the same
        as float32 images of the grid's shape (x/z, y/z at every grid pixel)."""
        r = self.__dict__.get("_rays")
        if r is None:
            Kg = self.K_grid
            h, w = self.shape
            cols = (np.arange(w) - Kg[0, 2]) / Kg[0, 0]
            rows = (np.arange(h) - Kg[1, 2]) / Kg[1, 1]
            x_img = np.ascontiguousarray(np.broadcast_to(cols.astype(np.float32), (h, w)))
            y_img = np.ascontiguousarray(np.broadcast_to(rows.astype(np.float32)[:, None], (h, w)))
            r = self.__dict__["_rays"] = (cols, rows, x_img, y_img)
        return r


def _clip(pts: List[List[float]], planes: List[List[float]]) -> Optional[List[List[float]]]:
    """Sutherland-Hodgman clip to the half-spaces n . p + d >= 0, as
    :func:`robot.maps.visibility.clip_polygon`, on Python floats: for the few vertices of a wall
    polygon, per-call numpy overhead costs more than the arithmetic. Only the planes given are
    applied: those that some vertex is outside of (clipping never moves a vertex outside
    another plane, its new vertices lie between old ones)."""
    for a, b, c, d in planes:
        s = [a * x + b * y + c * z + d for x, y, z in pts]
        if max(s) < 0:
            return None
        out = []
        n = len(pts)
        for i in range(n):
            j = i + 1 if i + 1 < n else 0
            si, sj = s[i], s[j]
            if si >= 0:
                out.append(pts[i])
            if (si >= 0) != (sj >= 0):
                t = si / (si - sj)
                p, q = pts[i], pts[j]
                out.append([p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), p[2] + t * (q[2] - p[2])])
        pts = out
    return pts if len(pts) >= 3 else None


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
    cand = np.asarray(candidates, dtype=np.intp).reshape(-1)
    if len(cand) == 0:
        return []
    cam_G = T_ground_camera[:3, 3]
    pi = pk.planes[cand]
    # The camera must stand on the observable side; otherwise it looks at the back of the face.
    front = np.einsum("ij,j->i", pi[:, :3], cam_G) + pi[:, 3] > BACK_FACE_EPS
    cand = cand[front]
    pi_camera = np.einsum("ij,jk->ik", pi[front], T_ground_camera)  # pi_C = pi_G T_GC, per row
    cand_list = cand.tolist()
    if not cand_list:
        return []
    R_T = T_ground_camera[:3, :3].T
    t_C = -R_T @ cam_G
    V = np.concatenate([pk.plane_vertices[i] for i in cand_list])
    counts = [c for i in cand_list for c in pk.plane_counts[i]]
    plane_of = [i for i in cand_list for _ in pk.plane_counts[i]]
    P = np.einsum("ij,kj->ik", V, R_T) + t_C
    first = [0]
    for c in counts[:-1]:
        first.append(first[-1] + c)
    first_vertex = np.array(first, np.intp)
    frustum = grid.frustum
    outside = np.einsum("ij,kj->ik", P, frustum[:, :3]) < -frustum[:, 3]
    # A polygon with every vertex outside one frustum plane is gone; for the others, bit j set
    # means some vertex is outside plane j, so it is clipped against those planes only.
    gone = np.logical_and.reduceat(outside, first_vertex, axis=0).any(axis=1).tolist()
    cross = np.bitwise_or.reduceat(outside @ (1 << np.arange(len(frustum))), first_vertex).tolist()
    # Clip the polygons that cross the frustum (Python floats), then project everything together.
    P_list = P.tolist()
    frustum_list = frustum.tolist()
    # kept: (polygon, its segment in the stacked vertex array: P's polygons, then the clipped ones)
    kept, clipped_pts, clipped_starts = [], [], []
    n_polys = len(counts)
    for k, (a, n, bits) in enumerate(zip(first, counts, cross)):
        if gone[k]:
            continue
        if not bits:
            kept.append((k, k))
            continue
        clipped = _clip(P_list[a:a + n], [f for j, f in enumerate(frustum_list) if bits >> j & 1])
        if clipped is not None:
            kept.append((k, n_polys + len(clipped_starts)))
            clipped_starts.append(len(P) + len(clipped_pts))
            clipped_pts += clipped
    if not kept:
        return []
    Q = np.vstack([P, clipped_pts]) if clipped_pts else P
    seg = np.concatenate([first_vertex, np.array(clipped_starts, np.intp)])
    seg_end = np.append(seg[1:], len(Q)).tolist()
    K = grid.K
    # Rows of polygons that cross the frustum are not used; their clipped copies are.
    px = Q[:, :2] / np.maximum(Q[:, 2:], NEAR_PLANE)
    px *= (K[0, 0], K[1, 1])
    px += K[:2, 2]
    fixed = np.rint(px * (float(1 << _SUBPIXEL_BITS) / grid.stride)).astype(np.int32)
    z_min = np.minimum.reduceat(Q[:, 2], seg).tolist()
    px_lo = np.minimum.reduceat(px, seg).tolist()
    px_hi = np.maximum.reduceat(px, seg).tolist()
    seg = seg.tolist()
    scale = 1.0 / grid.stride
    gh, gw = grid.shape
    found = []
    i, n_kept = 0, len(kept)
    while i < n_kept:
        idx = plane_of[kept[i][0]]
        outlines, fixed_outlines, z_near = [], [], math.inf
        u0 = v0 = math.inf
        u1 = v1 = -math.inf
        while i < n_kept and plane_of[kept[i][0]] == idx:
            j = kept[i][1]
            a, b = seg[j], seg_end[j]
            outlines.append(px[a:b])
            fixed_outlines.append(fixed[a:b])
            z_near = min(z_near, z_min[j])
            (lo_u, lo_v), (hi_u, hi_v) = px_lo[j], px_hi[j]
            u0, v0, u1, v1 = min(u0, lo_u), min(v0, lo_v), max(u1, hi_u), max(v1, hi_v)
            i += 1
        if z_near < max_range:
            box = (max(math.floor(u0 * scale), 0), max(math.floor(v0 * scale), 0),
                   min(math.ceil(u1 * scale), gw - 1), min(math.ceil(v1 * scale), gh - 1))
            found.append((idx, outlines, z_near, box, fixed_outlines))
    row = {c: r for r, c in enumerate(cand_list)}
    return [PlaneView(idx, plane_map.planes[idx].id, pi_camera[row[idx]], outlines, z_near, box=box,
                      fixed_px=(grid.stride, fixed_outlines))
            for idx, outlines, z_near, box, fixed_outlines in found]


def _grid_box(view: PlaneView, grid: CameraGrid) -> Tuple[int, int, int, int]:
    h, w = grid.shape
    pts = np.vstack(view.outlines_px) / grid.stride
    (x0, y0), (x1, y1) = pts.min(axis=0).tolist(), pts.max(axis=0).tolist()
    return max(math.floor(x0), 0), max(math.floor(y0), 0), min(math.ceil(x1), w - 1), min(math.ceil(y1), h - 1)


def rasterize_views(views: List[PlaneView], grid: CameraGrid) -> np.ndarray:
    """Label image on the grid: index into ``views`` of the nearest plane per pixel, -1 for none.

    The buffer holds inverse depth, 1/z = -(n . ray) / d, which is affine in the pixel's ray
    coordinates: one weighted sum of the grid's ray images per plane, 0 for "nothing", and on a
    box its largest value is at a corner. Planes are drawn nearest first; one whose largest inverse depth on its box does not
    beat what is already drawn everywhere on that box is hidden: it is skipped before
    rasterizing and its ``box`` set empty. On equal depth the plane drawn first (nearer z_near,
    then lower index) keeps the pixel.
    """
    h, w = grid.shape
    ibuf = np.zeros((h, w), dtype=np.float32)
    label = np.full((h, w), -1, dtype=np.int32)
    cols, rows, x_img, y_img = grid.rays
    one = 1 << _SUBPIXEL_BITS
    sub = float(one) / grid.stride  # full-resolution pixels to fixed-point grid pixels
    drawn = False  # nothing drawn yet: nothing can hide the first plane
    for k in sorted(range(len(views)), key=lambda j: views[j].z_near):
        view = views[k]
        if view.box is None:
            view.box = _grid_box(view, grid)
        c0, r0, c1, r1 = view.box
        n = view.pi_camera
        if c1 < c0 or r1 < r0 or n[3] == 0:
            view.box = (0, 0, -1, -1)
            continue  # off the grid, or a plane through the optical centre (seen edge-on)
        a, b, c = -n[0] / n[3], -n[1] / n[3], -n[2] / n[3]
        # Largest inverse depth on the box, at a corner; with room for the float32 rounding of
        # the per-pixel values below (a few 1e-7 of the terms' magnitudes), so that the test
        # never skips a plane that would win a pixel.
        ia, ib = max(a * cols[c0], a * cols[c1]), max(b * rows[r0], b * rows[r1])
        top = ia + ib + c + 1e-6 * (abs(a) * max(-cols[0], cols[-1]) + abs(b) * max(-rows[0], rows[-1]) + abs(c))
        isub = ibuf[r0:r1 + 1, c0:c1 + 1]
        if top <= 0 or (drawn and top <= isub.min()):
            view.box = (0, 0, -1, -1)
            continue  # behind the camera on the whole box, or hidden behind what is already drawn
        if view.fixed_px is not None and view.fixed_px[0] == grid.stride:
            polys = view.fixed_px[1]
        else:
            polys = [np.rint(o * sub).astype(np.int32) for o in view.outlines_px]
        # The box origin goes in as fillPoly's offset, in the same fixed-point units.
        mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS, offset=(-c0 * one, -r0 * one))
        inv = cv2.addWeighted(x_img[r0:r1 + 1, c0:c1 + 1], a, y_img[r0:r1 + 1, c0:c1 + 1], b, c)
        inv *= mask  # 0 ("nothing") outside the polygon: never beats the buffer, which is >= 0
        upd = inv > isub
        np.maximum(isub, inv, out=isub)
        label[r0:r1 + 1, c0:c1 + 1][upd] = k
        drawn = True
    return label


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
    H, W = label.shape
    for k, view in enumerate(views):
        view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
        view.pixels = 0
        # A view owns pixels only inside its box (unknown: the whole grid). The crop reaches r
        # beyond it, so only the grid's edges act as border for the erosion below.
        c0, r0, c1, r1 = view.box if view.box is not None else (0, 0, W - 1, H - 1)
        # The part of the box inside the inner grid: what can be reported.
        i0, j0, i1, j1 = max(r0, pad), max(c0, pad), min(r1, H - 1 - pad), min(c1, W - 1 - pad)
        if i1 < i0 or j1 < j0:
            continue
        margin = float(margin_for(view))
        r = int(math.ceil(margin / grid.stride))
        r0, c0 = max(r0 - r, 0), max(c0 - r, 0)
        own = (label[r0:r1 + r + 1, c0:c1 + r + 1] == k).view(np.uint8)
        inner = (slice(i0 - r0, i1 + 1 - r0), slice(j0 - c0, j1 + 1 - c0))
        view.pixels = int(np.count_nonzero(own[inner]))
        if view.pixels == 0:
            continue
        view.margin_px = margin
        if r > 0:
            kernel = _KERNELS.get(r)
            if kernel is None:
                kernel = _KERNELS[r] = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            own = cv2.erode(own, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        # cv2.findNonZero lists (col, row) in row-major order, as np.nonzero, at half its cost.
        found = cv2.findNonZero(np.ascontiguousarray(own[inner]))
        if found is not None:
            view.roi_rows, view.roi_cols = found[:, 0, 1] + (i0 - pad), found[:, 0, 0] + (j0 - pad)
