"""Regions of interest: which pixels each visible map plane should cover (DESIGN.md section 4 step 2).

Visible polygons are rasterized with OpenCV into a label image through a z-buffer computed from
each plane's exact depth along the pixel rays. DESIGN.md suggests drawing far planes first; a
z-buffer gives the same answer where that works and stays right where polygons overlap in depth
(a long wall that is both nearer and farther than another), at the same cost.

Work happens on a decimated pixel grid (every ``stride``-th pixel in rows and columns): only
those pixels are ever deprojected, so there is no reason to label the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, List, Optional, Sequence

import cv2
import numpy as np

from robot.geometry import invert_transform, transform_plane, transform_points
from robot.plane_map import PlaneMap
from robot.visibility import clip_polygon, frustum_planes, project

_SUBPIXEL_BITS = 4


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


def predict_plane_views(plane_map: PlaneMap, candidates: Sequence[int], T_ground_camera: np.ndarray,
                        grid: CameraGrid, max_range: float) -> List[PlaneView]:
    """Clip the candidate planes' polygons to the frustum and keep those in front of the camera."""
    T_camera_ground = invert_transform(T_ground_camera)
    frustum = grid.frustum
    cam_G = T_ground_camera[:3, 3]
    views = []
    for idx in candidates:
        plane = plane_map.planes[idx]
        # The camera must stand on the observable side; otherwise it looks at the back of the face.
        if plane.normal @ cam_G + plane.d <= 1e-6:
            continue
        outlines, z_near = [], math.inf
        for poly in plane.polygons:
            clipped = clip_polygon(transform_points(T_camera_ground, poly), frustum)
            if clipped is None:
                continue
            z_near = min(z_near, float(clipped[:, 2].min()))
            outlines.append(project(grid.K, clipped))
        if outlines and z_near < max_range:
            views.append(PlaneView(idx, plane.id, transform_plane(T_ground_camera, plane.pi), outlines, z_near))
    return views


def rasterize_views(views: List[PlaneView], grid: CameraGrid) -> np.ndarray:
    """Label image on the grid: index into ``views`` of the nearest plane per pixel, -1 for none."""
    Kg = grid.K_grid
    h, w = grid.shape
    zbuf = np.full((h, w), np.inf, dtype=np.float32)
    label = np.full((h, w), -1, dtype=np.int32)
    cols = ((np.arange(w) - Kg[0, 2]) / Kg[0, 0]).astype(np.float32)
    rows = ((np.arange(h) - Kg[1, 2]) / Kg[1, 1]).astype(np.float32)
    scale = 1.0 / grid.stride
    for k, view in enumerate(views):
        pts_all = [o * scale for o in view.outlines_px]
        lo = np.floor(np.min([p.min(axis=0) for p in pts_all], axis=0)).astype(int)
        hi = np.ceil(np.max([p.max(axis=0) for p in pts_all], axis=0)).astype(int)
        c0, r0 = max(lo[0], 0), max(lo[1], 0)
        c1, r1 = min(hi[0], w - 1), min(hi[1], h - 1)
        if c1 < c0 or r1 < r0:
            continue
        mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        polys = [np.round((p - (c0, r0)) * (1 << _SUBPIXEL_BITS)).astype(np.int32) for p in pts_all]
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
        n = view.pi_camera
        denom = n[0] * cols[None, c0:c1 + 1] + n[1] * rows[r0:r1 + 1, None] + np.float32(n[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.float32(-n[3]) / denom
        zsub = zbuf[r0:r1 + 1, c0:c1 + 1]
        upd = (mask > 0) & (z > 0) & (z < zsub)
        zsub[upd] = z[upd]
        label[r0:r1 + 1, c0:c1 + 1][upd] = k
    return label


def shrink_rois(views: List[PlaneView], label: np.ndarray, grid: CameraGrid,
                margin_for: Callable[[PlaneView], float]) -> None:
    """Fill each view's pixel count and its ROI: its own pixels eroded by its margin (in image
    pixels), so pixels that a pose error could hand to a neighbour are left out."""
    for k, view in enumerate(views):
        own = label == k
        view.pixels = int(own.sum())
        if view.pixels == 0:
            view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
            continue
        view.margin_px = float(margin_for(view))
        r = int(math.ceil(view.margin_px / grid.stride))
        if r > 0:
            rows_any = np.flatnonzero(own.any(axis=1))
            cols_any = np.flatnonzero(own.any(axis=0))
            r0, r1 = max(rows_any[0] - r, 0), min(rows_any[-1] + r + 1, own.shape[0])
            c0, c1 = max(cols_any[0] - r, 0), min(cols_any[-1] + r + 1, own.shape[1])
            sub = own[r0:r1, c0:c1].astype(np.uint8)
            kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            # Border pixels count as "inside": the image edge is not a plane edge.
            sub = cv2.erode(sub, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1)
            rr, cc = np.nonzero(sub)
            view.roi_rows, view.roi_cols = rr + r0, cc + c0
        else:
            view.roi_rows, view.roi_cols = np.nonzero(own)
