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


@dataclass
class _Wall:
    n: np.ndarray  # (3,)
    d: float
    R_plane: np.ndarray  # (2, 3): in-plane axes (horizontal, vertical-ish) for the containment test
    polygons_2d: List[np.ndarray]  # each (K, 2) in those axes
    lo: np.ndarray  # xy bounding box of the wall, for the range pre-filter
    hi: np.ndarray


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
        walls.append(_Wall(n, float(p.d), R, polys, v[:, :2].min(axis=0), v[:, :2].max(axis=0)))
    return walls


def _inside_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule, vectorised over points; polygons have few vertices."""
    x, y = pts[:, 0], pts[:, 1]
    inside = np.zeros(len(pts), dtype=bool)
    xj, yj = poly[-1]
    with np.errstate(divide="ignore", invalid="ignore"):  # once: entering it costs as much as an edge
        for xi, yi in poly.tolist():
            crosses = (yi > y) != (yj > y)
            x_cross = (xj - xi) * (y - yi) / (yj - yi) + xi
            inside ^= crosses & (x < x_cross)
            xj, yj = xi, yi
    return inside


def depth_points_robot(depth_m: np.ndarray, K: np.ndarray, T_robot_camera: np.ndarray, stride: int,
                       min_range: float, max_range: float, depth_scale: float = 1.0) -> np.ndarray:
    """Every ``stride``-th valid pixel back-projected to the robot frame, (N, 3) in m. ``depth_m``
    may be the camera's raw units with ``depth_scale`` metres each: only the sampled pixels are
    converted (as ``DepthFrame.depth_m`` would, in float32)."""
    z = _metres(depth_m[::stride, ::stride], depth_scale)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w]
    u = u * stride
    v = v * stride
    ok = np.isfinite(z) & (z > min_range) & (z < max_range)
    z = z[ok].astype(float)
    x_c = (u[ok] - K[0, 2]) / K[0, 0] * z
    y_c = (v[ok] - K[1, 2]) / K[1, 1] * z
    p_camera = np.stack([x_c, y_c, z], axis=1)
    return p_camera @ T_robot_camera[:3, :3].T + T_robot_camera[:3, 3]


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
        # The stride is meant at the configured resolution: a decimated frame is sampled as densely.
        stride = max(1, int(round(c.stride * depth_m.shape[1] / float(cam.width))))
        p_robot = depth_points_robot(depth_m, K, cam.T_robot_camera, stride, self.robot.localizer.min_range,
                                     c.max_range, depth_scale)
        band = (p_robot[:, 2] >= c.min_height) & (p_robot[:, 2] <= c.max_height)
        p_robot = p_robot[band]
        ignored = 0
        if pose is not None and self._walls and len(p_robot):
            wall = self._explained_by_walls(p_robot, pose)
            near = self._near_footprint(p_robot[:, :2], c.always_distance)
            keep = ~wall | near
            ignored = int(np.count_nonzero(~keep))
            p_robot = p_robot[keep]
        near_blind = self._near_blind(depth_m)
        scan = ObstacleScan(camera, float(t), np.ascontiguousarray(p_robot[:, :2]), ignored, near_blind)
        self.scans[camera] = scan
        if pose is not None:
            self._remember(scan, camera, depth_m, K, pose, depth_scale)
        return scan

    def _near_blind(self, depth_m: np.ndarray) -> bool:
        h, w = depth_m.shape
        centre = depth_m[h // 4:3 * h // 4, w // 4:3 * w // 4]
        if centre.dtype.kind in "ui":  # raw units: 0 is the camera's "no depth"
            bad = np.count_nonzero(centre <= 0)
        else:
            bad = np.count_nonzero(~np.isfinite(centre) | (centre <= 0.0))
        return bool(bad > self.config.near_blind_fraction * centre.size)

    def _remember(self, scan: ObstacleScan, camera: str, depth_m: np.ndarray, K: np.ndarray,
                  pose: Tuple[float, float, float], depth_scale: float = 1.0) -> None:
        """Forget what this frame sees through and what is too old; add this frame's points."""
        c = self.config
        mem_xy, mem_t = self.memory
        keep = (scan.t - mem_t) <= c.memory_time
        mem, mem_t = mem_xy[keep], mem_t[keep]
        if len(mem):
            cam = self.robot.camera(camera)
            T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            R, o = T_ground_camera[:3, :3], T_ground_camera[:3, 3]
            # The remembered points are (x, y) only: test them at mid-height of the band the camera sees.
            z_test = float(np.clip(o[2], c.min_height, c.max_height))
            p_ground = np.column_stack([mem, np.full(len(mem), z_test)])
            p_cam = (p_ground - o) @ R
            z = p_cam[:, 2]
            h, w = depth_m.shape
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.round(K[0, 0] * p_cam[:, 0] / z + K[0, 2]).astype(np.int64, copy=False)
                v = np.round(K[1, 1] * p_cam[:, 1] / z + K[1, 2]).astype(np.int64, copy=False)
            in_view = (z > self.robot.localizer.min_range) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            seen_through = np.zeros(len(mem), dtype=bool)
            idx = np.nonzero(in_view)[0]
            if len(idx):
                d = _metres(depth_m[v[idx], u[idx]], depth_scale)
                seen_through[idx] = np.isfinite(d) & (d > z[idx] + c.wall_tolerance)
            mem, mem_t = mem[~seen_through], mem_t[~seen_through]
        if len(scan.points_xy):
            T = pose_to_T_ground_robot(*pose)
            new = scan.points_xy @ T[:2, :2].T + T[:2, 3]
            mem = np.vstack([mem, new])
            mem_t = np.concatenate([mem_t, np.full(len(new), scan.t)])
        if len(mem):  # one point per grid cell (the newest): the memory stays small however long the robot looks
            cell = np.floor(mem / c.memory_cell).astype(np.int64)
            # One int64 key per cell (x in the high half): a 1-D unique, several times cheaper
            # than np.unique over rows; cells are within 2^31 of the origin on any site.
            key = (cell[:, 0] << 32) + (cell[:, 1] & 0xFFFFFFFF)
            order = np.argsort(-mem_t, kind="stable")
            _, first = np.unique(key[order], return_index=True)
            pick = np.sort(order[first])
            mem, mem_t = mem[pick], mem_t[pick]
        if len(mem) > c.memory_points:  # bounded: keep the newest
            mem, mem_t = mem[-c.memory_points:], mem_t[-c.memory_points:]
        self.memory = (mem, mem_t)

    def _explained_by_walls(self, p_robot: np.ndarray, pose: Tuple[float, float, float]) -> np.ndarray:
        T = pose_to_T_ground_robot(*pose)
        p_ground = p_robot @ T[:3, :3].T + T[:3, 3]
        tol = self.config.wall_tolerance
        explained = np.zeros(len(p_ground), dtype=bool)
        reach = self.config.max_range + tol
        xy = np.asarray(pose[:2])
        for w in self._walls:
            if np.any(xy < w.lo - reach) or np.any(xy > w.hi + reach):
                continue
            dist = p_ground @ w.n + w.d
            close = np.abs(dist) < tol
            if not close.any():
                continue
            idx = np.nonzero(close & ~explained)[0]
            if len(idx) == 0:
                continue
            q = p_ground[idx] @ w.R_plane.T
            inside = np.zeros(len(idx), dtype=bool)
            for poly in w.polygons_2d:
                inside |= _inside_polygon(q, poly)
            explained[idx[inside]] = True
        return explained

    def _near_footprint(self, xy: np.ndarray, distance: float) -> np.ndarray:
        dx = np.maximum(np.abs(xy[:, 0] - self.config.footprint_offset_x) - self._half_x, 0.0)
        dy = np.maximum(np.abs(xy[:, 1]) - self._half_y, 0.0)
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
        points = self.obstacle_points(t, pose)
        speed = math.hypot(vx, vy)
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
