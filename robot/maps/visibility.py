"""Which map polygons a camera can see: the first step of every localization. Pure numpy.

The paper classifies vertices in an *extended image coordinate system* and tests edges against
the frustum. That misses a polygon that covers the whole view with every vertex and edge
outside it (standing close to a large wall), so visibility here is decided by clipping the
polygon against the view frustum, which is exact. The classification is kept because it is a
cheap, explainable first answer and the paper's vocabulary.
"""

from __future__ import annotations

import enum
from typing import List, Optional, Sequence

import numpy as np

NEAR_PLANE = 0.01  # m: clip in front of the optical centre so projection never divides by ~0


class Region(enum.IntEnum):
    """Where a camera-frame point falls in the extended image coordinate system."""

    VFR = 0  # view-field region: |u| < 1, |v| < 1, z > 0
    POVR = 1  # positive out-of-view region: z > 0 but outside the field of view
    NR = 2  # negative region: z <= 0, behind the camera


def extended_image_coords(p_camera: np.ndarray, hfov: float, vfov: float):
    """Angular image coordinates of (N, 3) camera-frame points (optical frame, z forward).

    u = atan2(x, z) / (hfov / 2), v = atan2(y, z) / (vfov / 2): the field of view maps to
    [-1, 1]^2 and, unlike pixels, the coordinates stay finite for points beside or behind the
    camera (atan2 runs to +-pi), so any vertex can be placed.
    """
    p = np.atleast_2d(p_camera)
    u = np.arctan2(p[:, 0], p[:, 2]) / (hfov / 2.0)
    v = np.arctan2(p[:, 1], p[:, 2]) / (vfov / 2.0)
    return u, v


def classify_points(p_camera: np.ndarray, hfov: float, vfov: float) -> np.ndarray:
    """Region (VFR / POVR / NR) of each camera-frame point, as an int array of Region values."""
    p = np.atleast_2d(p_camera)
    u, v = extended_image_coords(p, hfov, vfov)
    out = np.full(len(p), int(Region.POVR), dtype=np.int8)
    out[p[:, 2] <= 0] = int(Region.NR)
    out[(p[:, 2] > 0) & (np.abs(u) < 1) & (np.abs(v) < 1)] = int(Region.VFR)
    return out


def frustum_planes(K: np.ndarray, width: int, height: int, near: float = NEAR_PLANE) -> np.ndarray:
    """(5, 4) inward-facing planes (n, d) of the pixel frustum: near, left, right, top, bottom.

    The side planes pass through the optical centre and the outer edges of the border pixels
    (pixel centres are at integer coordinates, so the image spans -0.5 .. W-0.5).
    """
    Kinv = np.linalg.inv(K)

    def ray(u, v):
        return Kinv @ np.array([u, v, 1.0])

    u0, u1, v0, v1 = -0.5, width - 0.5, -0.5, height - 0.5
    corners = [ray(u0, v0), ray(u1, v0), ray(u1, v1), ray(u0, v1)]  # tl, tr, br, bl
    planes = [np.array([0.0, 0.0, 1.0, -near])]
    # Consecutive corner pairs going around; the cross product order makes the normal point inward.
    for a, b in ((corners[3], corners[0]), (corners[1], corners[2]), (corners[0], corners[1]), (corners[2], corners[3])):
        n = np.cross(a, b)
        n /= np.linalg.norm(n)
        planes.append(np.array([*n, 0.0]))
    P = np.array(planes)
    centre = Kinv @ np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
    flip = (P[:, :3] @ centre) < 0  # guarantee inward orientation whatever K's handedness
    P[flip] *= -1.0
    P[0] = [0.0, 0.0, 1.0, -near]
    return P


def clip_polygon(poly: np.ndarray, planes: np.ndarray) -> Optional[np.ndarray]:
    """Clip a convex or concave planar (K, 3) polygon to the half-spaces n . p + d >= 0 of the
    (M, 4) ``planes``; None if nothing remains. The work is :func:`clip_vertex_list`'s."""
    out = np.asarray(poly, dtype=float)
    outside = (out @ planes[:, :3].T + planes[:, 3] < 0).any(axis=0)
    if not outside.any():
        return out  # entirely inside: the common case for a wall in front of the camera
    clipped = clip_vertex_list(out.tolist(), planes[outside].tolist())
    return None if clipped is None else np.array(clipped)


def clip_vertex_list(pts: List[List[float]], planes: Sequence[Sequence[float]]) -> Optional[List[List[float]]]:
    """Sutherland-Hodgman clip of a polygon, as a list of [x, y, z], to the half-spaces
    n . p + d >= 0 of ``planes`` (each [nx, ny, nz, d]); None if fewer than 3 vertices remain.

    Python floats, not numpy: for the few vertices of a wall polygon, per-call numpy overhead
    costs more than the arithmetic, and this runs for every polygon that crosses the frustum in
    every frame. Callers may pass only the planes that some vertex is outside of: clipping never
    moves a vertex outside another half-space, as new vertices lie between old ones.
    """
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


def project(K: np.ndarray, p_camera: np.ndarray) -> np.ndarray:
    """Pinhole projection of (N, 3) points with z > 0 to (N, 2) pixel coordinates (col, row)."""
    z = p_camera[:, 2]
    return np.stack([K[0, 0] * p_camera[:, 0] / z + K[0, 2], K[1, 1] * p_camera[:, 1] / z + K[1, 2]], axis=1)

