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
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from robot.geometry import invert_transform, transform_plane
from robot.plane_index import BACK_FACE_EPS, concat_ranges, packed_polygons
from robot.plane_map import PlaneMap
from robot.visibility import frustum_planes

_SUBPIXEL_BITS = 4
_CULL_EPS = 1e-9  # m: a polygon's box counts as outside a frustum plane only when clearly so


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
    box: Optional[Tuple[int, int, int, int]] = None  # grid box (c0, r0, c1, r1) it was drawn in


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


def _clip(pts: List[List[float]], planes: List[List[float]]) -> Optional[List[List[float]]]:
    """Sutherland-Hodgman clip to the half-spaces n . p + d >= 0, as
    :func:`robot.visibility.clip_polygon`, on Python floats: for the few vertices of a wall
    polygon, per-call numpy overhead costs more than the arithmetic."""
    for a, b, c, d in planes:
        s = [a * x + b * y + c * z + d for x, y, z in pts]
        if min(s) >= 0:
            continue
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

    Vectorised over the candidates: planes seen from behind and polygons whose bounding box lies
    outside one frustum plane (clipping would leave nothing) are dropped together, the remaining
    vertices are moved into C together, and only polygons that cross a frustum plane are clipped
    one by one. Every step works row by row, so a plane's view does not depend on which other
    planes are candidates.
    """
    pk = packed_polygons(plane_map)
    cand = np.asarray(candidates, dtype=np.intp).reshape(-1)
    if len(cand) == 0:
        return []
    cam_G = T_ground_camera[:3, 3]
    pi = pk.planes[cand]
    # The camera must stand on the observable side; otherwise it looks at the back of the face.
    cand = cand[np.einsum("ij,j->i", pi[:, :3], cam_G) + pi[:, 3] > BACK_FACE_EPS]
    polys = pk.polygons_of(cand)
    if len(polys) == 0:
        return []
    T_camera_ground = invert_transform(T_ground_camera)
    frustum = grid.frustum
    bounds = frustum @ T_camera_ground  # the frustum planes in G
    lo, hi = pk.lo[polys], pk.hi[polys]
    reach = np.einsum("ij,kj->ik", lo + hi, 0.5 * bounds[:, :3]) + \
        np.einsum("ij,kj->ik", hi - lo, 0.5 * np.abs(bounds[:, :3])) + bounds[:, 3]
    polys = polys[(reach >= -_CULL_EPS).all(axis=1)]
    if len(polys) == 0:
        return []
    # einsum, not matmul: its result for a row does not depend on how many rows there are.
    starts = pk.start[polys]
    counts = pk.start[polys + 1] - starts
    V = pk.vertices[concat_ranges(starts, starts + counts)]
    P = np.einsum("ij,kj->ik", V, T_camera_ground[:3, :3]) + T_camera_ground[:3, 3]
    first_vertex = np.cumsum(counts) - counts
    vertex_inside = (np.einsum("ij,kj->ik", P, frustum[:, :3]) >= -frustum[:, 3]).all(axis=1)
    inside = np.logical_and.reduceat(vertex_inside, first_vertex).tolist()
    z_min = np.minimum.reduceat(P[:, 2], first_vertex).tolist()
    K = grid.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        px = P[:, :2] / P[:, 2:] * (fx, fy) + (cx, cy)  # rows of polygons that need clipping are redone below
    frustum_list = frustum.tolist()
    starts, ends = first_vertex.tolist(), (first_vertex + counts).tolist()
    plane_of = pk.plane_of[polys].tolist()
    views = []
    k, n_polys = 0, len(plane_of)
    while k < n_polys:
        idx = plane_of[k]
        outlines, z_near = [], math.inf
        while k < n_polys and plane_of[k] == idx:
            a, b = starts[k], ends[k]
            if inside[k]:
                outlines.append(px[a:b])
                z_near = min(z_near, z_min[k])
            else:
                clipped = _clip(P[a:b].tolist(), frustum_list)
                if clipped is not None:
                    z_near = min(z_near, min(p[2] for p in clipped))
                    outlines.append(np.array([[fx * x / z + cx, fy * y / z + cy] for x, y, z in clipped]))
            k += 1
        if outlines and z_near < max_range:
            views.append(PlaneView(idx, plane_map.planes[idx].id, transform_plane(T_ground_camera, pk.planes[idx]),
                                   outlines, z_near))
    return views


def rasterize_views(views: List[PlaneView], grid: CameraGrid) -> np.ndarray:
    """Label image on the grid: index into ``views`` of the nearest plane per pixel, -1 for none.

    The buffer holds inverse depth, 1/z = -(n . ray) / d, which is affine in the pixel's ray
    coordinates: one outer sum per plane, 0 for "nothing", and on a box its largest value is at a
    corner. Planes are drawn nearest first; one whose largest inverse depth on its box does not
    beat what is already drawn everywhere on that box is hidden, and is skipped before rasterizing.
    On equal depth the plane drawn first (nearer z_near, then lower index) keeps the pixel.
    Each drawn view's ``box`` is set to the grid box it was drawn in.
    """
    Kg = grid.K_grid
    h, w = grid.shape
    ibuf = np.zeros((h, w), dtype=np.float32)
    label = np.full((h, w), -1, dtype=np.int32)
    cols = (np.arange(w) - Kg[0, 2]) / Kg[0, 0]
    rows = (np.arange(h) - Kg[1, 2]) / Kg[1, 1]
    scale = 1.0 / grid.stride
    one = float(1 << _SUBPIXEL_BITS)
    for k in sorted(range(len(views)), key=lambda j: views[j].z_near):
        view = views[k]
        view.box = None
        n = view.pi_camera
        if n[3] == 0:
            continue  # the plane passes through the optical centre: seen edge-on
        outlines = view.outlines_px
        q = (outlines[0] if len(outlines) == 1 else np.vstack(outlines)) * scale
        (x0, y0), (x1, y1) = q.min(axis=0).tolist(), q.max(axis=0).tolist()
        c0, r0 = max(math.floor(x0), 0), max(math.floor(y0), 0)
        c1, r1 = min(math.ceil(x1), w - 1), min(math.ceil(y1), h - 1)
        if c1 < c0 or r1 < r0:
            continue
        inv_c = (cols[c0:c1 + 1] * (-n[0] / n[3])).astype(np.float32)
        inv_r = (rows[r0:r1 + 1] * (-n[1] / n[3]) - n[2] / n[3]).astype(np.float32)
        isub = ibuf[r0:r1 + 1, c0:c1 + 1]
        # float32 addition is monotonic, so this is exactly the largest sum on the box.
        top = np.float32(max(inv_c[0], inv_c[-1])) + np.float32(max(inv_r[0], inv_r[-1]))
        if top <= 0 or top <= isub.min():
            continue  # behind the camera on the whole box, or hidden behind what is already drawn
        mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        fixed = np.rint((q - (c0, r0)) * one).astype(np.int32)
        if len(outlines) == 1:
            polys = [fixed]
        else:
            ends = np.cumsum([len(o) for o in outlines]).tolist()
            polys = [fixed[a:b] for a, b in zip([0] + ends[:-1], ends)]
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
        inv = inv_r[:, None] + inv_c[None, :]
        upd = np.greater(inv, isub, where=mask.view(bool), out=np.zeros(mask.shape, bool))
        np.copyto(isub, inv, where=upd)
        np.copyto(label[r0:r1 + 1, c0:c1 + 1], k, where=upd)
        view.box = (c0, r0, c1, r1)
    return label


def shrink_rois(views: List[PlaneView], label: np.ndarray, grid: CameraGrid,
                margin_for: Callable[[PlaneView], float]) -> None:
    """Fill each view's pixel count and its ROI: its own pixels eroded by its margin (in image
    pixels), so pixels that a pose error could hand to a neighbour are left out."""
    pixels = np.bincount(label.ravel() + 1, minlength=len(views) + 1)[1:].tolist()
    H, W = label.shape
    for k, view in enumerate(views):
        view.pixels = pixels[k]
        if view.pixels == 0:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
            continue
        view.margin_px = float(margin_for(view))
        r = int(math.ceil(view.margin_px / grid.stride))
        # A view owns pixels only inside the box it was drawn in (the whole grid if unknown).
        c0, r0, c1, r1 = view.box if view.box is not None else (0, 0, W - 1, H - 1)
        r0, c0 = max(r0 - r, 0), max(c0 - r, 0)
        r1, c1 = min(r1 + r + 1, H), min(c1 + r + 1, W)
        own = (label[r0:r1, c0:c1] == k).view(np.uint8)
        if r > 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            # Border pixels count as "inside": the image edge is not a plane edge. The box reaches
            # r beyond the view's pixels, so only true image edges act as border here.
            own = cv2.erode(own, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1)
        rr, cc = np.nonzero(own)
        view.roi_rows, view.roi_cols = rr + r0, cc + c0
