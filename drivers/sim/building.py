"""Synthetic building floors and free-space poses for the simulated world.

``room_grid_map`` builds a floor of nx x ny rooms with a door in every inner wall: every room
wall face is its own plane (split around its door), as an IFC import would give, so the plane
count grows as 4 nx ny + 2 (nx + ny) and the visibility cost can be measured from ten planes to
tens of thousands. ``free_space_poses`` samples robot poses inside any plane map's rooms and
corridors, away from walls, for benchmarks and tests; ``in_free_space`` tells whether one point
is such a place.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np

from robot.maps.plane_map import MapPlane, PlaneMap, make_plane


def _face(plane_id: str, a: Sequence[float], b: Sequence[float], z0: float, z1: float,
          door: Optional[Tuple[float, float, float]] = None) -> MapPlane:
    """Vertical face over the floor segment a -> b; its normal is (b - a) turned clockwise, so walk
    a -> b with the observable side on your right. ``door`` = (start, width, height) along a -> b."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length

    def quad(s0, s1, h0, h1):
        p0, p1 = a + s0 * u, a + s1 * u
        return [[p0[0], p0[1], h0], [p1[0], p1[1], h0], [p1[0], p1[1], h1], [p0[0], p0[1], h1]]

    if door is None:
        polys = [quad(0.0, length, z0, z1)]
    else:
        s, w, h = door
        polys = [quad(0.0, s, z0, z1), quad(s, s + w, h, z1), quad(s + w, length, z0, z1)]
    return make_plane(plane_id, polys)


def room_grid_map(nx: int, ny: int, room: float = 4.0, wall: float = 0.2, height: float = 2.7,
                  door: float = 0.9, door_height: float = 2.1, seed: int = 0) -> PlaneMap:
    """A floor of nx x ny square rooms (``room`` m inside) separated by ``wall``-thick walls with
    one door per inner wall (position random along the wall); the outer walls' outside faces are
    planes too. Plane ids: ``r<i>_<j>_<side>`` (side s/e/n/w, facing into room i, j) and ``out_<side><k>``."""
    rng = np.random.default_rng(seed)
    pitch = room + wall
    doors = {}  # (i, j, side) -> position along the wall measured from its west/south end

    def door_at(key):
        if key not in doors:
            doors[key] = float(rng.uniform(0.3, room - door - 0.3))
        return doors[key]

    planes: List[MapPlane] = []
    for i in range(nx):
        for j in range(ny):
            x0, y0 = wall + i * pitch, wall + j * pitch
            x1, y1 = x0 + room, y0 + room
            # A shared wall's door is at the same place seen from both rooms: key it by the wall.
            south = door_at(("h", i, j)) if j > 0 else None
            north = door_at(("h", i, j + 1)) if j < ny - 1 else None
            west = door_at(("v", i, j)) if i > 0 else None
            east = door_at(("v", i + 1, j)) if i < nx - 1 else None
            # Walk each face with the room on the right; the door offset is from the walk's start.
            planes.append(_face(f"r{i}_{j}_s", (x1, y0), (x0, y0), 0.0, height,
                                None if south is None else (room - south - door, door, door_height)))
            planes.append(_face(f"r{i}_{j}_e", (x1, y1), (x1, y0), 0.0, height,
                                None if east is None else (room - east - door, door, door_height)))
            planes.append(_face(f"r{i}_{j}_n", (x0, y1), (x1, y1), 0.0, height,
                                None if north is None else (north, door, door_height)))
            planes.append(_face(f"r{i}_{j}_w", (x0, y0), (x0, y1), 0.0, height,
                                None if west is None else (west, door, door_height)))
    X, Y = nx * pitch + wall, ny * pitch + wall
    for i in range(nx):
        planes.append(_face(f"out_s{i}", (i * pitch, 0.0), ((i + 1) * pitch + (wall if i == nx - 1 else 0), 0.0), 0.0, height))
        planes.append(_face(f"out_n{i}", ((i + 1) * pitch + (wall if i == nx - 1 else 0), Y), (i * pitch, Y), 0.0, height))
    for j in range(ny):
        planes.append(_face(f"out_w{j}", (0.0, (j + 1) * pitch + (wall if j == ny - 1 else 0)), (0.0, j * pitch), 0.0, height))
        planes.append(_face(f"out_e{j}", (X, j * pitch), (X, (j + 1) * pitch + (wall if j == ny - 1 else 0)), 0.0, height))
    return PlaneMap(planes, source=f"<room grid {nx}x{ny}>")


def grid_for_planes(n_planes: int) -> Tuple[int, int]:
    """(nx, ny) of the most nearly square room grid whose plane count is closest to ``n_planes``."""
    best = (1, 1)
    for nx in range(1, int(math.sqrt(max(n_planes, 1))) + 2):
        for ny in (nx, nx + 1):
            if abs(4 * nx * ny + 2 * (nx + ny) - n_planes) < abs(4 * best[0] * best[1] + 2 * sum(best) - n_planes):
                best = (nx, ny)
    return best


def wall_segments(plane_map: PlaneMap, z: float) -> np.ndarray:
    """(M, 2, 2) floor-plan segments where the map's vertical polygons cut the height ``z``.

    Each polygon's cut is taken from its lowest to its highest crossing along the wall, so a
    polygon with a hole counts as solid there: conservative for clearance checks. Segments run
    with the observable side on their right, so (dy, -dx) is the plane's horizontal normal.
    """
    segs = []
    for p in plane_map.planes:
        if abs(p.normal[2]) > 0.1:
            continue
        along = np.array([-p.normal[1], p.normal[0]])
        for poly in p.polygons:
            nxt = np.roll(poly, -1, axis=0)
            dz = nxt[:, 2] - poly[:, 2]
            pts = []
            for k in range(len(poly)):
                lo, hi = min(poly[k, 2], nxt[k, 2]), max(poly[k, 2], nxt[k, 2])
                if lo <= z <= hi:
                    t = 0.0 if dz[k] == 0 else (z - poly[k, 2]) / dz[k]
                    pts.append(poly[k, :2] + t * (nxt[k, :2] - poly[k, :2]))
            if len(pts) < 2:
                continue
            pts = np.array(pts)
            s = pts @ along
            segs.append([pts[int(np.argmin(s))], pts[int(np.argmax(s))]])
    return np.array(segs, float).reshape(-1, 2, 2)


def _point_segment_distance(p: np.ndarray, segs: np.ndarray) -> np.ndarray:
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0.0, 1.0)
    q = a + t[:, None] * ab
    return np.hypot(*(p - q).T)


def _enclosed(p: np.ndarray, segs: np.ndarray, normals: np.ndarray, offsets: np.ndarray, rays: int,
              max_dist: float, min_hits: float) -> bool:
    """Rays from ``p`` meet walls on their observable side, never on their back, and at most a few
    escape (through doors and gaps): the point is inside a room or corridor, not outside the
    building or inside a wall."""
    a, b = segs[:, 0], segs[:, 1]
    e = b - a
    hits = 0
    for ang in np.linspace(0.0, 2 * math.pi, rays, endpoint=False):
        r = np.array([math.cos(ang), math.sin(ang)])
        den = r[0] * e[:, 1] - r[1] * e[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            w = a - p
            t = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / den  # distance along the ray
            s = (w[:, 0] * r[1] - w[:, 1] * r[0]) / den  # position along the segment
        hit = np.isfinite(t) & (t > 0) & (s >= 0) & (s <= 1) & (t < max_dist)
        if not hit.any():
            continue
        k = np.flatnonzero(hit)[int(np.argmin(t[hit]))]
        if normals[k] @ p + offsets[k] <= 0:
            return False
        hits += 1
    return hits >= min_hits * rays


def in_free_space(plane_map: PlaneMap, xy: Sequence[float], clearance: float = 0.0, z: float = 0.3, rays: int = 24,
                  max_dist: float = 30.0, min_hits: float = 0.8) -> bool:
    """Whether the floor point ``xy`` is inside the building (enclosed by walls seen from their
    front, as for :func:`free_space_poses`) and ``clearance`` from every wall face cut at ``z``."""
    segs = wall_segments(plane_map, z)
    if len(segs) == 0:
        return False
    d = segs[:, 1] - segs[:, 0]
    normals = np.column_stack([d[:, 1], -d[:, 0]]) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    offsets = -np.einsum("ij,ij->i", normals, segs[:, 0])
    p = np.asarray(xy[:2], float)
    if clearance > 0 and _point_segment_distance(p, segs).min() < clearance:
        return False
    return _enclosed(p, segs, normals, offsets, rays, max_dist, min_hits)


def free_space_poses(plane_map: PlaneMap, count: int, rng: np.random.Generator, clearance: float = 0.4,
                     z: float = 0.3, rays: int = 24, max_dist: float = 30.0, min_hits: float = 0.8,
                     max_tries: int = 20000) -> List[Tuple[float, float, float]]:
    """Random poses (x, y, heading) inside the building: at least ``clearance`` from every wall face
    cut at height ``z`` and enclosed by walls seen from their front side (at least ``min_hits`` of
    the rays cast from it meet a wall's front and none meets a back). May return fewer than
    ``count`` if the map has little free space."""
    segs = wall_segments(plane_map, z)
    if len(segs) == 0:
        return []
    d = segs[:, 1] - segs[:, 0]
    normals = np.column_stack([d[:, 1], -d[:, 0]]) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]
    offsets = -np.einsum("ij,ij->i", normals, segs[:, 0])
    lo, hi = plane_map.bounds()
    poses: List[Tuple[float, float, float]] = []
    tries = 0
    while len(poses) < count and tries < max_tries:
        tries += 1
        p = rng.uniform(lo[:2], hi[:2])
        if _point_segment_distance(p, segs).min() < clearance:
            continue
        if not _enclosed(p, segs, normals, offsets, rays, max_dist, min_hits):
            continue
        poses.append((float(p[0]), float(p[1]), float(rng.uniform(-math.pi, math.pi))))
    return poses
