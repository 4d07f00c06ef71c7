"""The protective stop: an obstacle picture from the depth frames, and the twist it still allows.

Pure and explicit in time, like the rest of the control core. Per depth frame
(:meth:`ProtectiveStop.update_scan`), a decimated view is back-projected into the robot frame;
points between the floor band and the robot's height that no mapped wall explains, or that
are very close whatever they are, are the camera's obstacle scan. Per control tick
(:meth:`ProtectiveStop.limit`), the commanded twist is limited before it is sent:

- translation: the free distance ``s`` along the direction of travel is how far the footprint
  rectangle can slide before it touches an obstacle point; the speed is capped so that the robot
  can still stop ``stop_margin`` short of it, ``v t_r + v^2 / (2 a) <= s - margin``, and capped at
  the slow-down speed inside the slow-down distance;
- rotation: stopped while an obstacle point is inside the circle the footprint sweeps;
- blindness: a direction no fresh scan looks along is limited to a creep speed (unless the
  config says another sensor guards it).

A camera sees nothing nearer than its minimum range (about 0.2 m for a D435i at 848x480): an
obstacle the robot approaches vanishes from the depth just before the robot reaches it. So the
picture has a memory: obstacle points are kept in the ground frame for ``memory_time`` and carried
into the robot frame of each tick by the current pose, until a newer frame of a camera that looks
at their place sees *through* them (valid depth farther than the point). And a view that is
mostly invalid in its centre is taken as something right in front of the lens.

The decision carries its zone and a reason for the status line, the recording and the live view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import pose_to_T_ground_robot
from robot.config import RobotConfig
from robot.config.safety import SafetyConfig
from robot.control import scan_kernels
from robot.maps.plane_map import PlaneMap

CLEAR = "clear"
SLOWDOWN = "slowdown"
STOP = "stop"
BLIND = "blind"
DISABLED = "disabled"


@dataclass(frozen=True)
class ObstacleScan:
    """One camera's obstacle points at its capture time, in the robot frame of that time."""

    camera: str
    t: float
    points_xy: np.ndarray  # (N, 2) robot frame, m
    walls_ignored: int = 0  # points a mapped wall explained
    near_blind: bool = False  # the view is mostly invalid close up: something may be nearer than the minimum range


@dataclass(frozen=True)
class SafetyDecision:
    twist: Tuple[float, float, float]  # the limited body twist (vx, vy, wz)
    zone: str  # clear, slowdown, stop, blind or disabled
    reason: str  # "" when clear
    free_distance: float  # m along the direction of travel (inf when nothing is in the way)
    speed_limit: float  # m/s the translation was allowed


# One edge of a polygon for the even-odd test: (x_i, y_i, x_j - x_i, y_j - y_i), the crossing
# then x_i when the edge is vertical (x_j == x_i: the interpolation adds 0 to x_i, exactly).
_Edge = Tuple[float, float, float, float]


@dataclass
class _Polygon:
    """A wall polygon in the wall's in-plane axes, prepared for :func:`_inside_prepared`'s test."""

    box: Tuple[float, float, float, float]  # x_lo, x_hi (widened by a rounding margin), y_lo, y_hi
    # Its edges grouped by their y span (y_i, y_j), either way round: the span alone decides which
    # points' rows an edge crosses. Horizontal edges cross no row and are left out.
    spans: List[Tuple[float, float, List[_Edge]]]


def _polygon(vertices: np.ndarray) -> _Polygon:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    margin = _ROUNDING * (1.0 + float(np.abs(vertices).max()))
    spans: Dict[Tuple[float, float], Tuple[float, float, List[_Edge]]] = {}
    xj, yj = vertices[-1].tolist()
    for xi, yi in vertices.tolist():
        if yj != yi:
            spans.setdefault((min(yi, yj), max(yi, yj)), (yi, yj, []))[2].append((xi, yi, xj - xi, yj - yi))
        xj, yj = xi, yi
    return _Polygon((float(lo[0]) - margin, float(hi[0]) + margin, float(lo[1]), float(hi[1])), list(spans.values()))


@dataclass
class _Wall:
    n: np.ndarray  # (3,)
    d: float
    R_plane: np.ndarray  # (2, 3): in-plane axes (horizontal, vertical-ish) for the containment test
    polygons_2d: List[np.ndarray]  # each (K, 2) in those axes
    lo: np.ndarray  # xy bounding box of the wall, for the range pre-filter
    hi: np.ndarray
    off_plane: float = 0.0  # m: how far its farthest vertex lies off the plane (a map allows about 1 mm)
    polygons: List[_Polygon] = field(default_factory=list)  # polygons_2d prepared for the test
    # The polygons for the compiled test: all vertices (V, 2), each polygon's first (P + 1), boxes (P, 4).
    flat: Tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros((0, 2)), np.zeros(1, np.int64), np.zeros((0, 4)))


def _wall_geometry(plane_map: PlaneMap) -> List[_Wall]:
    walls = []
    for p in plane_map.planes:
        n = np.asarray(p.normal, dtype=float)
        a = np.cross([0.0, 0.0, 1.0], n)
        if np.linalg.norm(a) < 1e-6:  # horizontal plane (floor, ceiling): not a wall
            continue
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        R = np.vstack([a, b])
        polys = [np.asarray(poly, dtype=float) @ R.T for poly in p.polygons]
        v = p.vertices
        prepared = [_polygon(q) for q in polys]
        flat = (np.ascontiguousarray(np.vstack(polys)), np.cumsum([0] + [len(q) for q in polys]).astype(np.int64),
                np.array([q.box for q in prepared]).reshape(-1, 4))
        walls.append(_Wall(n, float(p.d), R, polys, v[:, :2].min(axis=0), v[:, :2].max(axis=0),
                           float(np.abs(v @ n + p.d).max()), prepared, flat))
    return walls


# Relative margin that covers the rounding of the containment and distance tests many times over
# (they round to about 1e-15 of the coordinates): a cull by bounding box with it drops only what
# the exact tests would drop too.
_ROUNDING = 1e-9


def _inside_prepared(x: np.ndarray, y: np.ndarray, poly: _Polygon) -> np.ndarray:
    """Whether each point is inside the polygon by the even-odd rule: for each edge (x_i, y_i) to
    (x_j, y_j), with (x_j, y_j) the vertex before, the point's row crosses it when
    ``(y_i > y) != (y_j > y)``, at ``(x_j - x_i) * (y - y_i) / (y_j - y_i) + x_i``; the point is
    inside when an odd number of crossings lie to its right (``x <`` the crossing). The same
    comparisons and crossings as that plain loop over the edges (the tests keep it), without what
    cannot change the answer: horizontal edges, a span's row test repeated per edge, the
    interpolation along vertical edges."""
    inside = np.zeros(len(x), dtype=bool)
    for yi, yj, edges in poly.spans:
        right = None  # whether the point is left of each crossing, XOR over the span's edges
        for xi, yi_e, dx, dy in edges:
            left = x < (xi if dx == 0.0 else dx * (y - yi_e) / dy + xi)
            right = left if right is None else np.logical_xor(right, left, out=right)
        crosses = (yi > y) != (yj > y)
        inside ^= crosses & right
    return inside


def _inside_polygons(qx: np.ndarray, qy: np.ndarray, wall: _Wall) -> np.ndarray:
    """Whether each point (in-plane axes ``qx``, ``qy``) is in any of the wall's polygons (:func:`_inside_prepared`),
    each polygon tested only on the points in its bounding box.

    That cull is exact. Below or above the polygon (y outside [y_lo, y_hi]) no edge crosses the
    point's row, compared exactly. Left of it every crossing is to the right of the point, and a
    closed polygon crosses any row an even number of times; right of it none is. Crossings are
    interpolated between their edge's end points to within about 1e-15 of the coordinates, far
    inside the boxes' margin in x."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if len(wall.polygons) == 1:  # the box tests would cost as much as the polygon's
            return _inside_prepared(qx, qy, wall.polygons[0])
        inside = np.zeros(len(qx), dtype=bool)
        x_lo, x_hi, y_lo, y_hi = float(qx.min()), float(qx.max()), float(qy.min()), float(qy.max())
        for poly in wall.polygons:
            bx0, bx1, by0, by1 = poly.box
            if bx1 < x_lo or bx0 > x_hi or by1 < y_lo or by0 > y_hi:
                continue
            if bx0 <= x_lo and bx1 >= x_hi and by0 <= y_lo and by1 >= y_hi:  # its box holds them all
                inside |= _inside_prepared(qx, qy, poly)
                continue
            sel = ((qx >= bx0) & (qx <= bx1) & (qy >= by0) & (qy <= by1)).nonzero()[0]
            if len(sel):
                inside[sel[_inside_prepared(qx[sel], qy[sel], poly)]] = True
    return inside


def depth_points_robot(depth_m: np.ndarray, K: np.ndarray, T_robot_camera: np.ndarray, stride: int,
                       min_range: float, max_range: float, depth_scale: float = 1.0) -> np.ndarray:
    """Every ``stride``-th valid pixel back-projected to the robot frame, (N, 3) in m. ``depth_m``
    may be the camera's raw units with ``depth_scale`` metres each: only the sampled pixels are
    converted (as ``DepthFrame.depth_m`` would, in float32)."""
    z = _metres(depth_m[::stride, ::stride], depth_scale)
    p_robot = _rotated(_camera_points(z, _pixel_rays(z.shape, K, stride), min_range, max_range), T_robot_camera[:3, :3])
    _add_columns(p_robot, T_robot_camera[:3, 3])
    return p_robot


def _rotated(p: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``p @ R.T`` for (N, k) ``p``, summed as :func:`_product` sums."""
    return _product(p.T, R).T


def _product(P: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R @ P`` for points as the columns of ``P`` (k, N), each sum written out left to right,
    ``(R_j0 P_0 + R_j1 P_1) + ...``: every coordinate change of the scan, rather than a matrix
    product, whose order of operations is its BLAS's (fused multiply-adds on one machine, pairs
    summed on another). The compiled kernels compute the same sums in the same order, on every
    platform. (m, N); a row at a time, each a contiguous pass."""
    out = P[0] * R[:, 0:1]
    for i in range(1, P.shape[0]):
        out += P[i] * R[:, i:i + 1]
    return out


def _pixel_rays(shape: Tuple[int, int], K: np.ndarray, stride: int) -> Tuple[np.ndarray, np.ndarray]:
    """((u - c_x) / f_x, (v - c_y) / f_y) of every sampled pixel (u, v), each (h, w) for the sampled
    shape: the part of the back-projection that only the camera's shape, K and stride decide."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w]
    u = u * stride
    v = v * stride
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    x.flags.writeable = False  # shared by every frame of the camera
    y.flags.writeable = False
    return x, y


def _camera_points(z: np.ndarray, rays: Tuple[np.ndarray, np.ndarray], min_range: float, max_range: float) -> np.ndarray:
    """The sampled pixels with a valid depth ``z`` (m), in camera coordinates (N, 3), row by row."""
    return _camera_rows(z, rays, min_range, max_range).T


def _camera_rows(z: np.ndarray, rays: Tuple[np.ndarray, np.ndarray], min_range: float, max_range: float) -> np.ndarray:
    """:func:`_camera_points` as (3, N): x, y and z each a contiguous row."""
    ok = np.isfinite(z) & (z > min_range) & (z < max_range)
    idx = ok.ravel().nonzero()[0]
    out = np.empty((3, len(idx)))
    out[2] = z.ravel().take(idx)
    np.multiply(rays[0].ravel().take(idx), out[2], out=out[0])
    np.multiply(rays[1].ravel().take(idx), out[2], out=out[1])
    return out


def _robot_band(P: np.ndarray, T: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The camera points (the columns of ``P``, (3, N)) in the robot frame (``T``, robot from
    camera) whose height is within [lo, hi], (N, 3): the height first, the rest for those only."""
    pz = _product(P, T[2:3, :3])[0]
    pz += T[2, 3]
    keep = ((pz >= lo) & (pz <= hi)).nonzero()[0]
    if len(keep) < len(pz):
        P, pz = P.take(keep, axis=1), pz.take(keep)
    out = np.empty((3, len(pz)))
    out[:2] = _product(P, T[:2, :3])
    out[:2] += T[:2, 3:4]
    out[2] = pz
    return out.T


def _add_columns(p: np.ndarray, t: np.ndarray) -> None:
    """``p += t`` for (N, k) ``p``, one column at a time: numpy's broadcast over rows of three
    costs twice as much (the same sums)."""
    for j in range(p.shape[1]):
        p[:, j] += t[j]


def _rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``a[mask]`` for a 2-D ``a`` and a boolean ``mask`` of its rows, the same array: numpy's
    boolean index of rows costs five times the index list and ``take``."""
    return a.take(mask.nonzero()[0], axis=0)


def _compact(mem: np.ndarray, mem_t: np.ndarray, keys: Optional[np.ndarray], keep: np.ndarray
             ) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """The memory's points, times and (when known) cell keys where ``keep``."""
    idx = keep.nonzero()[0]
    return mem.take(idx, axis=0), mem_t[idx], (keys[idx] if keys is not None else None)


def _cell_keys(xy: np.ndarray, cell_size: float) -> np.ndarray:
    """One int64 key per grid cell of each point (x in the high half): a 1-D unique is several
    times cheaper than np.unique over rows; cells are within 2^31 of the origin on any site."""
    cell = np.floor(xy / cell_size).astype(np.int64)
    return (cell[:, 0] << 32) + (cell[:, 1] & 0xFFFFFFFF)


def _metres(depth: np.ndarray, depth_scale: float) -> np.ndarray:
    if depth_scale == 1.0 and depth.dtype.kind == "f":
        return depth
    return depth.astype(np.float32) * np.float32(depth_scale)


def free_distance(points_xy: np.ndarray, half_x: float, half_y: float, offset_x: float, u: Sequence[float]) -> float:
    """How far the footprint rectangle can slide along unit direction ``u`` before it touches a point.

    A point p is hit after sliding s >= 0 when p - s u lies in the rectangle: the intersection of
    the slab intervals in x and y, clipped to s >= 0. Points already inside the footprint are
    ignored (the body itself, or noise that no camera can see that close).
    """
    if len(points_xy) == 0:
        return math.inf
    ux, uy = float(u[0]), float(u[1])
    px = points_xy[:, 0] - offset_x
    py = points_xy[:, 1]
    # Only points in the swept corridor can be hit: drop the rest first (a few array passes instead
    # of twenty over the whole memory, every tick). The margin only keeps rounding from dropping a
    # point the exact test below would hit; the result is that test's, unchanged.
    corridor = half_x * abs(uy) + half_y * abs(ux)
    margin = 1e-9 * (1.0 + corridor + float(np.abs(points_xy).max()))
    if not math.isfinite(margin):  # non-finite points: keep them all, the exact test decides
        margin = math.inf
    near = np.nonzero(np.abs(px * uy - py * ux) <= corridor + margin)[0]
    if len(near) == 0:
        return math.inf
    px, py = px[near], py[near]
    lo = np.zeros(len(px))
    hi = np.full(len(px), np.inf)
    for p, h, c in ((px, half_x, ux), (py, half_y, uy)):
        if abs(c) < 1e-12:
            outside = np.abs(p) > h
            hi = np.where(outside, -np.inf, hi)
        else:
            a, b = (p - h) / c, (p + h) / c
            lo = np.maximum(lo, np.minimum(a, b))
            hi = np.minimum(hi, np.maximum(a, b))
    inside_now = (np.abs(px) <= half_x) & (np.abs(py) <= half_y)
    hit = (lo <= hi) & ~inside_now
    return float(lo[hit].min()) if hit.any() else math.inf


def braking_speed(distance: float, reaction_time: float, decel: float) -> float:
    """The largest v with v t_r + v^2 / (2 a) <= distance."""
    if distance <= 0.0:
        return 0.0
    if math.isinf(distance):
        return math.inf
    return decel * (-reaction_time + math.sqrt(reaction_time * reaction_time + 2.0 * distance / decel))


@dataclass
class _CameraView:
    xy: Tuple[float, float]  # camera position in the robot frame
    yaw: float  # rad, optical axis bearing in the robot frame
    half_fov: float  # rad, less the margin
    min_range: float  # m: nearer than this the camera sees nothing


@dataclass
class ProtectiveStop:
    config: SafetyConfig
    robot: RobotConfig
    plane_map: Optional[PlaneMap] = None
    scans: Dict[str, ObstacleScan] = field(default_factory=dict)
    # (points (N, 2) in the ground frame, capture time of each): one tuple, replaced whole, so that
    # the localization worker can update it while the control loop reads it.
    memory: Tuple[np.ndarray, np.ndarray] = field(default_factory=lambda: (np.zeros((0, 2)), np.zeros(0)))

    def __post_init__(self):
        self._walls = _wall_geometry(self.plane_map) if self.plane_map is not None else []
        self._views: Dict[str, _CameraView] = {}
        for cam in self.robot.cameras:
            axis = cam.T_robot_camera[:3, 2]  # the optical z axis in the robot frame
            pos = cam.T_robot_camera[:3, 3]
            self._views[cam.name] = _CameraView((float(pos[0]), float(pos[1])), math.atan2(axis[1], axis[0]),
                                                math.radians(max(cam.hfov_deg / 2.0 - self.config.fov_margin_deg, 0.0)),
                                                self.robot.localizer.min_range)
        c = self.config
        self._half_x = c.footprint_length / 2.0
        self._half_y = c.footprint_width / 2.0
        self._sweep_radius = math.hypot(self._half_x + abs(c.footprint_offset_x), self._half_y) + c.rotation_margin
        # All walls' pre-filters in one comparison, v < bound for any column skips the wall: the
        # range test (the pose beyond max_range of the wall's box), and the box a point must lie in
        # to be explained by the wall (near the plane and inside a polygon puts it within
        # tolerance + off_plane of the vertices' box; the points' box outside it skips the wall).
        # Negated columns turn "x > hi" into "-x < -hi", the same comparison.
        reach = c.max_range + c.wall_tolerance
        lo = np.array([w.lo for w in self._walls]).reshape(-1, 2)
        hi = np.array([w.hi for w in self._walls]).reshape(-1, 2)
        margin = np.array([c.wall_tolerance + w.off_plane + 1e-6 + _ROUNDING * float(np.abs(np.r_[w.lo, w.hi]).max())
                           for w in self._walls]).reshape(-1, 1)
        self._wall_bounds = np.hstack([lo - reach, -(hi + reach), lo - margin, -(hi + margin)])
        # The walls for the compiled scan: planes (n, d, in-plane axes), the pre-filter, polygons.
        flats = [w.flat for w in self._walls]
        self._wall_table: scan_kernels.WallTable = (
            np.array([np.r_[w.n, w.d, w.R_plane.ravel()] for w in self._walls]).reshape(-1, 10),
            np.ascontiguousarray(self._wall_bounds),
            np.cumsum([0] + [len(f[1]) - 1 for f in flats]).astype(np.int64),
            np.ascontiguousarray(np.vstack([f[0] for f in flats]) if flats else np.zeros((0, 2))),
            np.cumsum([0] + [n for f in flats for n in np.diff(f[1]).tolist()]).astype(np.int64),
            np.ascontiguousarray(np.vstack([f[2] for f in flats]) if flats else np.zeros((0, 4))))
        # The cameras' mounts as the kernels take them (float64, C order, writable like every frame's).
        self._T_robot_camera = {cam.name: np.array(cam.T_robot_camera, dtype=np.float64, order="C")
                                for cam in self.robot.cameras}
        self._footprint = (c.footprint_offset_x, self._half_x, self._half_y, c.always_distance)
        # (shape, stride, K) -> the sampled pixels' rays: built once per camera stream.
        self._rays: Dict[tuple, Tuple[np.ndarray, np.ndarray]] = {}
        # (memory points, their times, their cell keys): the keys of the memory this object wrote
        # last, one per cell; only while ``memory`` still holds those very arrays.
        self._memory_keys: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None
        if len(self.memory[0]) == 0:
            self._memory_keys = (self.memory[0], self.memory[1], np.zeros(0, dtype=np.int64))
        # The kernels compile at their first call; the app loads them before its first frame
        # (scan_kernels.warm_up, with the plane fit's).

    # -- per frame ---------------------------------------------------------------------------

    def update_scan_frame(self, frame, pose: Optional[Tuple[float, float, float]]) -> ObstacleScan:
        """``update_scan`` of a ``DepthFrame`` from its raw depth units: only the pixels the scan
        looks at are converted to metres, not the whole frame (a third of the scan's CPU)."""
        return self.update_scan(frame.camera, frame.t_capture, frame.depth, frame.K, pose, float(frame.depth_scale))

    def update_scan(self, camera: str, t: float, depth_m: np.ndarray, K: np.ndarray,
                    pose: Optional[Tuple[float, float, float]], depth_scale: float = 1.0) -> ObstacleScan:
        """Turn one depth frame into the camera's obstacle scan; ``pose`` explains mapped walls.
        ``depth_m`` is in metres, or in units of ``depth_scale`` metres."""
        c = self.config
        cam = self.robot.camera(camera)
        compiled = scan_kernels.backend() == "numba"
        # The stride is meant at the configured resolution: a decimated frame is sampled as densely.
        stride = max(1, int(round(c.stride * depth_m.shape[1] / float(cam.width))))
        shape = (-(-depth_m.shape[0] // stride), -(-depth_m.shape[1] // stride))  # of depth_m[::stride, ::stride]
        rays = self._pixel_rays(shape, K, stride)
        min_range = self.robot.localizer.min_range
        T_ground_robot = pose_to_T_ground_robot(*pose) if pose is not None else None
        with_walls = T_ground_robot is not None and bool(self._walls)
        kept = got = merged = None
        if compiled:
            # The frame's points, its view blindness, the walls and the memory in one kernel call.
            memory, C, z_test = None, None, 0.0
            if T_ground_robot is not None:
                keys = self._known_keys()
                if keys is not None:
                    memory = (*self.memory, keys)
                    C, z_test = self._camera_view(camera, T_ground_robot)
            got = scan_kernels.scan(depth_m, stride, shape, depth_scale, min_range, c.max_range, rays,
                                    self._T_robot_camera[camera], c.min_height, c.max_height, c.near_blind_fraction,
                                    T_ground_robot, pose[:2] if pose is not None else (0.0, 0.0),
                                    self._wall_table if with_walls else None, self._footprint, c.wall_tolerance,
                                    memory, float(t), c.memory_time, C, z_test, K, c.memory_cell)
        if got is not None:
            p_robot, near_blind, xy, ignored, walls_done, mem, mem_t, keys, memory_done = got
            kept = (xy, ignored) if walls_done else None
            merged = (mem, mem_t, keys) if memory_done else None
        else:
            P = _camera_rows(_metres(depth_m[::stride, ::stride], depth_scale), rays, min_range, c.max_range)
            p_robot = _robot_band(P, cam.T_robot_camera, c.min_height, c.max_height)
            near_blind = self._near_blind(depth_m)
        if kept is None and with_walls and len(p_robot):
            kept = self._kept_points(p_robot, self._explained_by_walls(p_robot, pose, T_ground_robot))
        points_xy, ignored = kept if kept is not None else (np.ascontiguousarray(p_robot[:, :2]), 0)
        scan = ObstacleScan(camera, float(t), points_xy, ignored, near_blind)
        self.scans[camera] = scan
        if merged is not None:
            self._set_memory(*merged)
        elif T_ground_robot is not None:
            self._remember(scan, camera, depth_m, K, T_ground_robot, depth_scale)
        return scan

    def _kept_points(self, p_robot: np.ndarray, explained: np.ndarray) -> Tuple[np.ndarray, int]:
        """(x, y) of the points no wall explains or near the footprint, and how many were dropped."""
        x, y = p_robot[:, 0], p_robot[:, 1]
        wall = explained.nonzero()[0]
        ignored = 0
        if len(wall):
            # Only an explained point can be kept for being near: test just those.
            drop = wall[~self._near_footprint_xy(x.take(wall), y.take(wall), self.config.always_distance)]
            ignored = len(drop)
            if ignored:
                keep = np.ones(len(x), dtype=bool)
                keep[drop] = False
                idx = keep.nonzero()[0]
                x, y = x.take(idx), y.take(idx)
        out = np.empty((len(x), 2))
        out[:, 0] = x
        out[:, 1] = y
        return out, ignored

    def _pixel_rays(self, shape: Tuple[int, int], K: np.ndarray, stride: int) -> Tuple[np.ndarray, np.ndarray]:
        K = np.asarray(K)
        key = (shape, stride, K.dtype.str, K.shape, K.tobytes())
        rays = self._rays.get(key)
        if rays is None:
            if len(self._rays) >= 16:  # K changes only with a new calibration: never grows without bound
                self._rays.clear()
            rays = self._rays[key] = _pixel_rays(shape, K, stride)
        return rays

    def _near_blind(self, depth_m: np.ndarray) -> bool:
        h, w = depth_m.shape
        centre = depth_m[h // 4:3 * h // 4, w // 4:3 * w // 4]
        rows, cols = centre.shape
        limit = self.config.near_blind_fraction * centre.size
        # Counted a block of rows at a time, until the rest cannot change the answer: a view with
        # little invalid depth is decided about half-way (the count reads a whole frame's worth of
        # memory otherwise).
        bad, done = 0, 0
        step = max(1, min(rows, math.ceil(rows - limit / max(cols, 1)) + rows // 8))
        while done < rows:
            block = centre[done:done + step]
            done += len(block)
            if block.dtype.kind == "u":  # raw units: 0 is the camera's "no depth"
                bad += block.size - np.count_nonzero(block)
            elif block.dtype.kind == "i":
                bad += np.count_nonzero(block <= 0)
            else:
                bad += np.count_nonzero(~np.isfinite(block) | (block <= 0.0))
            if bad > limit:
                return True
            if bad + (rows - done) * cols <= limit:
                return False
            step = max(1, rows // 8)
        return bool(bad > limit)

    def _remember(self, scan: ObstacleScan, camera: str, depth_m: np.ndarray, K: np.ndarray,
                  T_ground_robot: np.ndarray, depth_scale: float = 1.0) -> None:
        """Forget what this frame sees through and what is too old; add this frame's points."""
        c = self.config
        mem, mem_t = self.memory
        keys = self._known_keys()
        T_ground_camera, z_test = self._camera_view(camera, T_ground_robot)
        merged = None
        if keys is not None and scan_kernels.backend() == "numba":
            merged = scan_kernels.remember(mem, mem_t, keys, scan.t, c.memory_time, T_ground_camera, z_test, K,
                                           self.robot.localizer.min_range, depth_m, depth_scale, c.wall_tolerance,
                                           scan.points_xy, T_ground_robot, c.memory_cell)
        if merged is None:
            merged = self._remember_numpy(scan, mem, mem_t, keys, depth_m, K, T_ground_robot, T_ground_camera, z_test,
                                          depth_scale)
        self._set_memory(*merged)

    def _known_keys(self) -> Optional[np.ndarray]:
        """The cell keys of ``memory`` when this object wrote it last (None: it was set from outside)."""
        mem, mem_t = self.memory
        known = self._memory_keys
        return known[2] if known is not None and known[0] is mem and known[1] is mem_t else None

    def _camera_view(self, camera: str, T_ground_robot: np.ndarray) -> Tuple[np.ndarray, float]:
        """The camera's pose in the ground frame, and the height its view tests remembered points at."""
        c = self.config
        T_ground_camera = T_ground_robot @ self._T_robot_camera[camera]
        o_z = float(T_ground_camera[2, 3])
        # The remembered points are (x, y) only: test them at mid-height of the band the camera sees.
        z_test = o_z if c.min_height < o_z < c.max_height else float(np.clip(o_z, c.min_height, c.max_height))
        return T_ground_camera, z_test

    def _set_memory(self, mem: np.ndarray, mem_t: np.ndarray, keys: Optional[np.ndarray]) -> None:
        c = self.config
        if len(mem) > c.memory_points:  # bounded: keep the newest
            mem, mem_t = mem[-c.memory_points:], mem_t[-c.memory_points:]
            keys = keys[-c.memory_points:] if keys is not None else None
        self.memory = (mem, mem_t)
        self._memory_keys = (mem, mem_t, keys) if keys is not None else None

    def _remember_numpy(self, scan: ObstacleScan, mem: np.ndarray, mem_t: np.ndarray, keys: Optional[np.ndarray],
                        depth_m: np.ndarray, K: np.ndarray, T_ground_robot: np.ndarray, T_ground_camera: np.ndarray,
                        z_test: float, depth_scale: float) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
        """``_remember``'s memory (points, times, cell keys when known) before its bound on the points."""
        c = self.config
        keep = (scan.t - mem_t) <= c.memory_time
        if not keep.all():
            mem, mem_t, keys = _compact(mem, mem_t, keys, keep)
        alive = None  # the remembered points this frame does not see through (None: all)
        if len(mem):
            R, o = T_ground_camera[:3, :3], T_ground_camera[:3, 3]
            # The points less the camera position; their height is the test height for all, a
            # column of one number whose products are the same for every point.
            p_cam = _product(mem.T - o[:2, None], R[:2].T)
            p_cam += ((z_test - o[2]) * R[2])[:, None]
            seen = self._seen_through(p_cam[0], p_cam[1], p_cam[2], K, depth_m, depth_scale)
            if seen.any():
                alive = ~seen
        if len(scan.points_xy):
            new = _product(scan.points_xy.T, T_ground_robot[:2, :2])
            new += T_ground_robot[:2, 3:4]
            new = new.T
            if alive is not None:
                mem, mem_t, keys = _compact(mem, mem_t, keys, alive)
            if keys is not None:
                mem, mem_t, keys = self._add_to_cells(mem, mem_t, keys, new, scan.t)
            else:
                mem, mem_t, keys = self._one_per_cell(np.vstack([mem, new]),
                                                      np.concatenate([mem_t, np.full(len(new), scan.t)]))
        else:
            if alive is not None:
                mem, mem_t, keys = _compact(mem, mem_t, keys, alive)
            if keys is None and len(mem):
                mem, mem_t, keys = self._one_per_cell(mem, mem_t)
        return mem, mem_t, keys

    def _seen_through(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, K: np.ndarray, depth_m: np.ndarray,
                      depth_scale: float) -> np.ndarray:
        """Which points (camera frame) the frame shows something farther than at their pixel."""
        h, w = depth_m.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(K[0, 0] * x / z + K[0, 2]).astype(np.int64, copy=False)
            v = np.round(K[1, 1] * y / z + K[1, 2]).astype(np.int64, copy=False)
        # As unsigned, a negative index is above any image size: one comparison per bound pair.
        in_view = (z > self.robot.localizer.min_range) & (u.view(np.uint64) < w) & (v.view(np.uint64) < h)
        seen = np.zeros(len(z), dtype=bool)
        idx = in_view.nonzero()[0]
        if len(idx):
            d = _metres(depth_m[v[idx], u[idx]], depth_scale)
            seen[idx] = np.isfinite(d) & (d > z[idx] + self.config.wall_tolerance)
        return seen

    def _one_per_cell(self, mem: np.ndarray, mem_t: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One point per grid cell, the newest (of equal times the first), in memory order: the
        memory stays small however long the robot looks. Returns points, times and cell keys."""
        key = _cell_keys(mem, self.config.memory_cell)
        order = np.argsort(-mem_t, kind="stable")
        _, first = np.unique(key[order], return_index=True)
        pick = np.sort(order[first])
        return mem[pick], mem_t[pick], key[pick]

    def _add_to_cells(self, mem: np.ndarray, mem_t: np.ndarray, keys: np.ndarray, new: np.ndarray,
                      t: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_one_per_cell`` of the memory (one point per cell already, ``keys`` theirs) with the
        points ``new`` of time ``t`` appended, without sorting the memory again: a cell's newest
        point of the new ones is its first; it replaces the remembered one only if that is older
        (of equal times the remembered one comes first)."""
        cell = np.floor(new / self.config.memory_cell).astype(np.int64)
        cx, cy = cell[:, 0], cell[:, 1]
        x0, y0, x1, y1 = int(cx.min()), int(cy.min()), int(cx.max()), int(cy.max())
        nx, ny = x1 - x0 + 1, y1 - y0 + 1
        windowed = nx * ny <= 1 << 16 and -(1 << 31) <= min(x0, y0) and max(x1, y1) < 1 << 31
        if windowed:
            # Cells numbered within the frame's window fit 16 bits, which numpy sorts stably by radix
            # (several times faster than the keys). Inside 32 bits a cell and its key are one-to-one.
            ids = ((cx - x0) * ny + (cy - y0)).astype(np.uint16)
        else:
            ids = (cx << 32) + (cy & 0xFFFFFFFF)
        order = np.argsort(ids, kind="stable")
        sorted_ids = ids[order]
        first = np.empty(len(order), dtype=bool)
        first[0] = True
        np.not_equal(sorted_ids[1:], sorted_ids[:-1], out=first[1:])
        cells, pick = sorted_ids[first], order[first]
        if len(keys):
            if windowed:  # the remembered cells (a key's halves) as ids, where inside the window
                dx = (keys >> 32) - x0
                dy = ((keys << 32) >> 32) - y0
                inside = ((dx.view(np.uint64) < nx) & (dy.view(np.uint64) < ny)).nonzero()[0]
                old_ids = dx[inside] * ny + dy[inside]
            else:
                inside, old_ids = None, keys
            at = np.searchsorted(cells, old_ids)
            np.minimum(at, len(cells) - 1, out=at)
            shared = cells[at] == old_ids
            if shared.any():
                old = shared.nonzero()[0] if inside is None else inside[shared]
                at = at[shared]
                newer = t > mem_t[old]
                if not newer.all():
                    stays = np.ones(len(cells), dtype=bool)
                    stays[at[~newer]] = False
                    pick = pick[stays]
                if newer.any():
                    keep = np.ones(len(mem), dtype=bool)
                    keep[old[newer]] = False
                    mem, mem_t, keys = _rows(mem, keep), mem_t[keep], keys[keep]
        pick = np.sort(pick)
        picked = cell.take(pick, axis=0)
        return (np.concatenate([mem, new.take(pick, axis=0)]), np.concatenate([mem_t, np.full(len(pick), t)]),
                np.concatenate([keys, (picked[:, 0] << 32) + (picked[:, 1] & 0xFFFFFFFF)]))

    def _explained_by_walls(self, p_robot: np.ndarray, pose: Tuple[float, float, float], T_ground_robot: np.ndarray
                            ) -> np.ndarray:
        g = _product(p_robot.T, T_ground_robot[:3, :3])
        g += T_ground_robot[:3, 3:4]
        gx, gy = g[0], g[1]
        x_lo, x_hi, y_lo, y_hi = gx.min(), gx.max(), gy.min(), gy.max()
        tol = self.config.wall_tolerance
        explained = np.zeros(len(gx), dtype=bool)
        xy = np.asarray(pose[:2])
        # The walls within range of the pose whose box the points reach: no other wall can explain
        # any of them, so skipping those changes nothing.
        v = np.array([xy[0], xy[1], -xy[0], -xy[1], x_hi, y_hi, -x_lo, -y_lo])
        some = False
        for k in (~(v < self._wall_bounds).any(axis=1)).nonzero()[0].tolist():
            w = self._walls[k]
            dist = _product(g, w.n[None, :])[0]
            dist += w.d
            close = np.abs(dist) < tol
            if some:
                close &= ~explained
            idx = close.nonzero()[0]
            if len(idx) == 0:
                continue
            q = _product(g.take(idx, axis=1), w.R_plane)
            inside = _inside_polygons(q[0], q[1], w)
            if inside.any():
                explained[idx[inside]] = True
                some = True
        return explained

    def _near_footprint(self, xy: np.ndarray, distance: float) -> np.ndarray:
        return self._near_footprint_xy(xy[:, 0], xy[:, 1], distance)

    def _near_footprint_xy(self, x: np.ndarray, y: np.ndarray, distance: float) -> np.ndarray:
        dx = np.maximum(np.abs(x - self.config.footprint_offset_x) - self._half_x, 0.0)
        dy = np.maximum(np.abs(y) - self._half_y, 0.0)
        return np.hypot(dx, dy) <= distance

    # -- per control tick --------------------------------------------------------------------

    def obstacle_points(self, t: float, pose: Optional[Tuple[float, float, float]]) -> np.ndarray:
        """Every obstacle point that matters at ``t``, in the robot frame at ``pose`` (N, 2)."""
        c = self.config
        if pose is None:  # no pose to carry the memory with: the fresh scans as they were taken
            fresh = [s.points_xy for s in list(self.scans.values()) if abs(t - s.t) <= c.max_scan_age]
            pts = np.vstack(fresh) if fresh else np.zeros((0, 2))
            return self._with_blind_arcs(t, pts)
        mem_xy, mem_t = self.memory
        recent = (t - mem_t) <= c.memory_time
        # The memory is kept oldest first, so the recent points are usually a suffix: slice it (a
        # boolean index copies the whole memory, the largest cost of a tick).
        first = int(np.argmax(recent)) if len(recent) else 0
        if len(recent) and recent[first] and recent[first:].all():
            mem_xy = mem_xy[first:]
        else:
            mem_xy = mem_xy[recent]
        T = pose_to_T_ground_robot(*pose)
        pts = (mem_xy - T[:2, 3]) @ T[:2, :2]
        return self._with_blind_arcs(t, pts)

    def _with_blind_arcs(self, t: float, pts: np.ndarray) -> np.ndarray:
        """``pts`` and, for every fresh view blinded close up, an arc of points just in front of its
        lens (with or without a pose: the relocalization's in-place turn has none)."""
        c = self.config
        blind = [self._views[s.camera] for s in list(self.scans.values())
                 if s.near_blind and abs(t - s.t) <= c.max_scan_age and s.camera in self._views]
        for view in blind:  # something may be right in front of the lens, nearer than it can measure
            a = view.yaw + np.linspace(-view.half_fov, view.half_fov, 9)
            r = c.near_blind_range
            arc = np.column_stack([view.xy[0] + r * np.cos(a), view.xy[1] + r * np.sin(a)])
            pts = np.vstack([pts, arc])
        return pts

    def limit(self, t: float, twist: Sequence[float],
              pose: Optional[Tuple[float, float, float]] = None) -> SafetyDecision:
        """The commanded body twist, limited by the obstacle picture at time ``t`` and ``pose``."""
        vx, vy, wz = (float(v) for v in twist)
        if not self.config.enabled:
            return SafetyDecision((vx, vy, wz), DISABLED, "", math.inf, math.inf)
        c = self.config
        fresh = [s for s in list(self.scans.values()) if abs(t - s.t) <= c.max_scan_age]
        speed = math.hypot(vx, vy)
        # A robot told to stand still needs no obstacle picture: carrying the memory into the
        # robot frame is most of a tick's cost, and a still robot is the usual case between paths.
        moving = speed > 1e-9 or abs(wz) > 1e-9
        points = self.obstacle_points(t, pose) if moving else np.zeros((0, 2))
        zone, reasons = CLEAR, []
        limit = math.inf
        s_free = math.inf
        if not fresh and not c.guarded_sectors_deg:
            # No camera has sent depth lately: the robot is blind in every direction.
            return SafetyDecision((0.0, 0.0, 0.0), BLIND, "no fresh depth from any camera", math.inf, 0.0)
        if speed > 1e-9:
            u = (vx / speed, vy / speed)
            s_free = free_distance(points, self._half_x, self._half_y, c.footprint_offset_x, u)
            limit = braking_speed(s_free - c.stop_margin, c.reaction_time, c.brake_decel)
            if s_free < c.slowdown_distance:
                limit = min(limit, c.slowdown_speed)
            if speed > limit:
                zone = STOP if limit < 1e-3 else SLOWDOWN
                reasons.append(f"obstacle {s_free:.2f} m along the direction of travel")
            bearing = math.atan2(u[1], u[0])
            if speed > c.blind_creep_speed and not self._corridor_seen(u, speed, {s.camera for s in fresh}):
                if c.blind_creep_speed < limit:
                    limit = c.blind_creep_speed
                    zone = BLIND if zone == CLEAR else zone
                reasons.append(f"no fresh camera view toward {math.degrees(bearing):.0f} deg")
        if abs(wz) > 1e-9 and len(points):
            # The exact test on the points roughly inside the circle (a squared-radius pre-filter with margin).
            px, py = points[:, 0], points[:, 1]
            near = np.nonzero(px * px + py * py < (self._sweep_radius * (1.0 + 1e-9)) ** 2)[0]
            pts = points[near]
            r = np.hypot(pts[:, 0], pts[:, 1])
            inside_body = (np.abs(pts[:, 0] - c.footprint_offset_x) <= self._half_x) & (np.abs(pts[:, 1]) <= self._half_y)
            if np.any((r < self._sweep_radius) & ~inside_body):
                wz = 0.0
                zone = STOP if zone in (CLEAR, BLIND) and speed <= 1e-9 else zone
                if zone == CLEAR:
                    zone = SLOWDOWN
                reasons.append("obstacle inside the turning circle")
        if speed > limit:
            k = limit / speed
            vx, vy = vx * k, vy * k
        return SafetyDecision((vx, vy, wz), zone, "; ".join(reasons), s_free, limit)

    def _corridor_seen(self, u: Tuple[float, float], speed: float, cameras: set) -> bool:
        """Whether fresh views cover the leading edge of the footprint ahead along ``u``.

        Checked at the stopping distance, but at least ``lookahead`` ahead: right beside the body
        no camera looks (the cones start at the lenses), and what is there was in view further
        out on the way in (the world is taken as static between frames).
        """
        c = self.config
        reach = max(speed * c.reaction_time + speed * speed / (2.0 * c.brake_decel) + c.stop_margin, c.lookahead)
        bearing = math.atan2(u[1], u[0])
        for lo, hi in c.guarded_sectors_deg:
            b = math.degrees(bearing)
            if any(lo <= b + k <= hi for k in (-360.0, 0.0, 360.0)):
                return True
        hx, hy, ox = self._half_x, self._half_y, c.footprint_offset_x
        corners = [(ox + sx * hx, sy * hy) for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)]
        # The leading edge: the corners (and their midpoint) that face the direction of travel.
        lead = sorted(corners, key=lambda q: -(q[0] * u[0] + q[1] * u[1]))[:2]
        samples = lead + [((lead[0][0] + lead[1][0]) / 2.0, (lead[0][1] + lead[1][1]) / 2.0)]
        for qx, qy in samples:
            px, py = qx + reach * u[0], qy + reach * u[1]
            if not any(self._in_view(self._views[n], px, py) for n in cameras if n in self._views):
                return False
        return True

    @staticmethod
    def _in_view(view: _CameraView, px: float, py: float) -> bool:
        dx, dy = px - view.xy[0], py - view.xy[1]
        return abs(math.remainder(math.atan2(dy, dx) - view.yaw, 2.0 * math.pi)) <= view.half_fov
