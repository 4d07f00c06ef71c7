"""The protective stop, on rendered D435i frames: obstacles stop or slow the robot, mapped walls do not."""

from __future__ import annotations

import functools
import math
from collections import namedtuple
from dataclasses import replace

import numpy as np
import pytest

from drivers.sim.render import Box, DepthNoise, SimScene, render_depth_frame
from robot.base.geometry import pose_to_T_ground_robot
from robot.config import load_robot_config
from robot.config.safety import SafetyConfig
from robot.control import protective_stop as ps
from robot.control import scan_kernels
from robot.control.protective_stop import BLIND, CLEAR, SLOWDOWN, STOP, ProtectiveStop, braking_speed, free_distance
from robot.localization import fit_kernels
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
BIG_ROOM = load_plane_map("config/maps/institute_ground.yaml")


def _scan_all(stop: ProtectiveStop, scene: SimScene, pose, t: float, seed: int = 0, decimation: int = 2):
    rng = np.random.default_rng(seed)
    for cam in ROBOT.cameras:
        f = render_depth_frame(ROBOT, scene, cam.name, pose, rng=rng, noise=DepthNoise(), decimation=decimation)
        stop.update_scan(cam.name, t, f.depth_m(), f.K, pose)


def test_free_distance_of_a_sliding_rectangle_is_exact():
    pts = np.array([[1.0, 0.0], [0.5, 0.5], [-1.0, 0.0]])
    # Forward: the point at x = 1 is hit when the front edge (x = 0.1) has moved 0.9 m.
    assert free_distance(pts, 0.1, 0.1, 0.0, (1.0, 0.0)) == pytest.approx(0.9)
    # Left: nothing within |x| <= 0.1 along +y except none -> the point (0.5, 0.5) is out of the corridor.
    assert free_distance(pts, 0.1, 0.1, 0.0, (0.0, 1.0)) == math.inf
    # Diagonal: the corner (0.1, 0.1) reaches (0.5, 0.5) after sliding 0.4 * sqrt(2).
    u = (math.sqrt(0.5), math.sqrt(0.5))
    assert free_distance(pts, 0.1, 0.1, 0.0, u) == pytest.approx(0.4 * math.sqrt(2.0))
    # A point inside the body is ignored, one behind is never hit moving forward.
    assert free_distance(np.array([[0.0, 0.05]]), 0.1, 0.1, 0.0, (1.0, 0.0)) == math.inf


def test_braking_speed_stops_within_the_distance():
    for d in (0.05, 0.3, 1.0):
        v = braking_speed(d, 0.15, 0.5)
        assert v * 0.15 + v * v / (2 * 0.5) == pytest.approx(d)
    assert braking_speed(-0.1, 0.15, 0.5) == 0.0


def test_mapped_walls_are_not_obstacles_but_a_person_is():
    stop = ProtectiveStop(SafetyConfig(), ROBOT, ARENA)
    pose = (0.5, 0.5, 0.0)  # front camera looks at the east wall 0.75 m away
    _scan_all(stop, SimScene(ARENA), pose, t=1.0)
    d = stop.limit(1.0, (0.3, 0.0, 0.0), pose)
    assert d.zone == CLEAR and d.twist[0] == pytest.approx(0.3), d
    assert stop.scans["front"].walls_ignored > 100
    person = Box(1.0, 0.5, 0.3, 0.5, 1.75)  # its near face 0.35 m in front of the robot centre
    stop2 = ProtectiveStop(SafetyConfig(), ROBOT, ARENA)
    _scan_all(stop2, SimScene(ARENA, clutter=[person]), pose, t=1.0)
    d2 = stop2.limit(1.0, (0.3, 0.0, 0.0), pose)
    assert d2.zone in (STOP, SLOWDOWN)
    assert d2.free_distance == pytest.approx(1.0 - 0.15 - (0.5 + 0.11), abs=0.02)  # near face minus front edge
    v = d2.twist[0]
    c = SafetyConfig()
    assert v * c.reaction_time + v * v / (2 * c.brake_decel) <= d2.free_distance - c.stop_margin + 1e-9
    # Moving away from it is not limited by it.
    assert stop2.limit(1.0, (0.0, 0.15, 0.0), pose).twist[1] == pytest.approx(0.15)


def test_approaching_a_person_stops_even_when_they_vanish_below_the_minimum_range():
    """Frames taken while creeping toward a person: the last ones cannot see them any more."""
    pose0 = _free_pose(BIG_ROOM)
    c, s = math.cos(pose0[2]), math.sin(pose0[2])
    person = Box(pose0[0] + 0.9 * c, pose0[1] + 0.9 * s, 0.3, 0.5, 1.75, pose0[2])
    scene = SimScene(BIG_ROOM, clutter=[person])
    stop = ProtectiveStop(SafetyConfig(), ROBOT, BIG_ROOM)
    last = None
    for k, ahead in enumerate(np.linspace(0.0, 0.60, 11)):  # near face from 0.75 m to 0.15 m ahead of the centre
        pose = (pose0[0] + ahead * c, pose0[1] + ahead * s, pose0[2])
        t = 0.2 * k
        _scan_all(stop, scene, pose, t=t, seed=k)
        last = stop.limit(t, (0.3, 0.0, 0.5), pose)
    near_face = 0.9 - 0.15 - 0.60  # m ahead of the centre at the last pose
    assert near_face - 0.11 < SafetyConfig().stop_margin  # closer than the stop margin: must be a full stop
    assert last.zone == STOP and last.twist == (0.0, 0.0, 0.0), last
    # Without the memory, the last frame alone would have shown nothing there.
    alone = ProtectiveStop(SafetyConfig(memory_time=0.0), ROBOT, BIG_ROOM)
    _scan_all(alone, scene, pose, t=9.0)
    assert len(alone.scans["front"].points_xy) == 0 or alone.scans["front"].near_blind


def test_a_person_stepping_in_front_of_the_lens_blinds_the_view_and_stops():
    pose = _free_pose(BIG_ROOM)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    person = Box(pose[0] + 0.28 * c, pose[1] + 0.28 * s, 0.1, 0.8, 1.75, pose[2])  # 0.08 m from the front lens
    stop = ProtectiveStop(SafetyConfig(), ROBOT, BIG_ROOM)
    _scan_all(stop, SimScene(BIG_ROOM, clutter=[person]), pose, t=1.0)
    assert stop.scans["front"].near_blind
    d = stop.limit(1.0, (0.3, 0.0, 0.0), pose)
    assert d.zone == STOP and d.twist[0] == 0.0


def _free_pose(plane_map):
    stop = ProtectiveStop(SafetyConfig(), ROBOT, plane_map)
    lo, hi = plane_map.bounds()
    rng = np.random.default_rng(4)
    for _ in range(200):
        pose = (float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1])), float(rng.uniform(-math.pi, math.pi)))
        _scan_all(stop, SimScene(plane_map), pose, t=0.0, decimation=4)
        if stop.limit(0.0, (0.3, 0.0, 0.0), pose).zone == CLEAR and stop.limit(0.0, (0.0, 0.0, 0.5), pose).zone == CLEAR:
            f = stop.scans["front"]
            if f.walls_ignored > 50:  # inside the building, looking at a wall it knows
                return pose
    raise AssertionError("no free pose found")


def test_directions_no_camera_sees_creep():
    stop = ProtectiveStop(SafetyConfig(), ROBOT, ARENA)
    pose = (0.5, 0.5, 0.0)
    _scan_all(stop, SimScene(ARENA), pose, t=1.0)
    back = stop.limit(1.0, (-0.3, 0.0, 0.0), pose)
    right = stop.limit(1.0, (0.0, -0.3, 0.0), pose)
    for d in (back, right):
        assert d.zone == BLIND and math.hypot(d.twist[0], d.twist[1]) == pytest.approx(SafetyConfig().blind_creep_speed)
    # A sector declared guarded by another sensor is not blind.
    guarded = ProtectiveStop(SafetyConfig(guarded_sectors_deg=((135.0, 225.0),)), ROBOT, ARENA)
    _scan_all(guarded, SimScene(ARENA), pose, t=1.0)
    assert guarded.limit(1.0, (-0.3, 0.0, 0.0), pose).zone == CLEAR
    # Stale scans guard nothing: after max_scan_age even forward motion is blind.
    assert stop.limit(1.0 + SafetyConfig().max_scan_age + 0.01, (0.3, 0.0, 0.0), pose).zone == BLIND


def test_without_a_pose_walls_count_as_obstacles():
    stop = ProtectiveStop(SafetyConfig(), ROBOT, ARENA)
    pose = (0.8, 0.5, 0.0)  # east wall 0.45 m ahead of the centre
    rng = np.random.default_rng(1)
    for cam in ROBOT.cameras:
        f = render_depth_frame(ROBOT, SimScene(ARENA), cam.name, pose, rng=rng, decimation=2)
        stop.update_scan(cam.name, 1.0, f.depth_m(), f.K, None)
    d = stop.limit(1.0, (0.3, 0.0, 0.0), None)
    assert d.zone in (SLOWDOWN, STOP) and d.free_distance == pytest.approx(0.45 - 0.11, abs=0.03)


def test_safety_config_refuses_values_that_disable_it():
    for bad in ({"reaction_time": 5.0}, {"max_scan_age": 1e308}, {"brake_decel": 0.0}, {"stride": 0},
                {"min_height": 2.0}, {"guarded_sectors_deg": ((10.0, 5.0),)}):
        with pytest.raises(ValueError):
            SafetyConfig(**bad)


def test_a_scan_from_the_raw_depth_units_is_the_scan_from_metres():
    """The app scans each frame from its raw units (only the sampled pixels converted): the same
    obstacle points, wall explanations, blindness and memory as from the frame in metres."""
    scene = SimScene(ARENA, clutter=[Box(1.0, 0.75, 0.3, 0.5, 1.75)])
    stops = [ProtectiveStop(SafetyConfig(), ROBOT, ARENA), ProtectiveStop(SafetyConfig(), ROBOT, ARENA)]
    rng = np.random.default_rng(5)
    for k, pose in enumerate([(0.5, 0.6, 0.2), (0.55, 0.62, 0.25), (0.6, 0.64, 0.3)]):
        for cam in ROBOT.cameras:
            f = render_depth_frame(ROBOT, scene, cam.name, pose, rng=rng, noise=DepthNoise())
            f = replace(f, t_capture=1.0 + 0.1 * k)
            assert f.depth.dtype == np.uint16
            a = stops[0].update_scan(cam.name, f.t_capture, f.depth_m(), f.K, pose)
            b = stops[1].update_scan_frame(f, pose)
            assert np.array_equal(a.points_xy, b.points_xy) and len(a.points_xy) > 20
            assert a.near_blind == b.near_blind
    assert np.array_equal(stops[0].memory[0], stops[1].memory[0]) and len(stops[0].memory[0]) > 20
    assert stops[0].limit(1.2, (0.3, 0.0, 0.0), (0.6, 0.64, 0.3)) == stops[1].limit(1.2, (0.3, 0.0, 0.0),
                                                                                    (0.6, 0.64, 0.3))


# -- the per-frame scan, held to its plain implementation --------------------------------------
# The scan as it was written first (robot/control/protective_stop.py at commit 88c1e98),
# kept here as the reference the faster one must match exactly: the same obstacle points in the
# same order, the same wall counts, blindness and memory, so the same decisions. Its matrix
# products are written out as the scan computes them (each sum left to right, no fused
# multiply-add), since a product's own order is the BLAS's of the machine; ``_BlasStop`` keeps
# numpy's products, and the scan matches it to rounding with the same decisions.


def _plain_product(p, M):
    """``p @ M.T``, each sum left to right."""
    return np.stack([functools.reduce(np.add, [p[:, i] * M[j, i] for i in range(p.shape[1])])
                     for j in range(M.shape[0])], axis=1)

_PlainWall = namedtuple("_PlainWall", "n d R_plane polygons_2d lo hi")


def _plain_wall_geometry(plane_map):
    walls = []
    for p in plane_map.planes:
        n = np.asarray(p.normal, dtype=float)
        a = np.cross([0.0, 0.0, 1.0], n)
        if np.linalg.norm(a) < 1e-6:
            continue
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        R = np.vstack([a, b])
        polys = [np.asarray(poly, dtype=float) @ R.T for poly in p.polygons]
        v = p.vertices
        walls.append(_PlainWall(n, float(p.d), R, polys, v[:, :2].min(axis=0), v[:, :2].max(axis=0)))
    return walls


def _plain_inside_polygon(pts, poly):
    x, y = pts[:, 0], pts[:, 1]
    inside = np.zeros(len(pts), dtype=bool)
    xj, yj = poly[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        for xi, yi in poly.tolist():
            crosses = (yi > y) != (yj > y)
            x_cross = (xj - xi) * (y - yi) / (yj - yi) + xi
            inside ^= crosses & (x < x_cross)
            xj, yj = xi, yi
    return inside


def _plain_metres(depth, depth_scale):
    if depth_scale == 1.0 and depth.dtype.kind == "f":
        return depth
    return depth.astype(np.float32) * np.float32(depth_scale)


def _plain_depth_points_robot(depth_m, K, T_robot_camera, stride, min_range, max_range, depth_scale=1.0,
                              product=_plain_product):
    z = _plain_metres(depth_m[::stride, ::stride], depth_scale)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w]
    u = u * stride
    v = v * stride
    ok = np.isfinite(z) & (z > min_range) & (z < max_range)
    z = z[ok].astype(float)
    x_c = (u[ok] - K[0, 2]) / K[0, 0] * z
    y_c = (v[ok] - K[1, 2]) / K[1, 1] * z
    p_camera = np.stack([x_c, y_c, z], axis=1)
    return product(p_camera, T_robot_camera[:3, :3]) + T_robot_camera[:3, 3]


class _PlainStop(ProtectiveStop):
    """The protective stop with the plain per-frame scan; the per-tick ``limit`` is the same code."""

    product = staticmethod(_plain_product)

    def __post_init__(self):
        super().__post_init__()
        self._plain_walls = _plain_wall_geometry(self.plane_map) if self.plane_map is not None else []

    def update_scan(self, camera, t, depth_m, K, pose, depth_scale=1.0):
        c = self.config
        cam = self.robot.camera(camera)
        stride = max(1, int(round(c.stride * depth_m.shape[1] / float(cam.width))))
        p_robot = _plain_depth_points_robot(depth_m, K, cam.T_robot_camera, stride, self.robot.localizer.min_range,
                                            c.max_range, depth_scale, self.product)
        band = (p_robot[:, 2] >= c.min_height) & (p_robot[:, 2] <= c.max_height)
        p_robot = p_robot[band]
        ignored = 0
        if pose is not None and self._plain_walls and len(p_robot):
            wall = self._plain_explained_by_walls(p_robot, pose)
            near = self._near_footprint(p_robot[:, :2], c.always_distance)
            keep = ~wall | near
            ignored = int(np.count_nonzero(~keep))
            p_robot = p_robot[keep]
        h, w = depth_m.shape
        centre = depth_m[h // 4:3 * h // 4, w // 4:3 * w // 4]
        if centre.dtype.kind in "ui":
            bad = np.count_nonzero(centre <= 0)
        else:
            bad = np.count_nonzero(~np.isfinite(centre) | (centre <= 0.0))
        near_blind = bool(bad > c.near_blind_fraction * centre.size)
        scan = ps.ObstacleScan(camera, float(t), np.ascontiguousarray(p_robot[:, :2]), ignored, near_blind)
        self.scans[camera] = scan
        if pose is not None:
            self._plain_remember(scan, camera, depth_m, K, pose, depth_scale)
        return scan

    def _plain_remember(self, scan, camera, depth_m, K, pose, depth_scale):
        c = self.config
        mem_xy, mem_t = self.memory
        keep = (scan.t - mem_t) <= c.memory_time
        mem, mem_t = mem_xy[keep], mem_t[keep]
        if len(mem):
            cam = self.robot.camera(camera)
            T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            R, o = T_ground_camera[:3, :3], T_ground_camera[:3, 3]
            z_test = float(np.clip(o[2], c.min_height, c.max_height))
            p_ground = np.column_stack([mem, np.full(len(mem), z_test)])
            p_cam = self.product(p_ground - o, R.T)
            z = p_cam[:, 2]
            h, w = depth_m.shape
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.round(K[0, 0] * p_cam[:, 0] / z + K[0, 2]).astype(np.int64, copy=False)
                v = np.round(K[1, 1] * p_cam[:, 1] / z + K[1, 2]).astype(np.int64, copy=False)
            in_view = (z > self.robot.localizer.min_range) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            seen_through = np.zeros(len(mem), dtype=bool)
            idx = np.nonzero(in_view)[0]
            if len(idx):
                d = _plain_metres(depth_m[v[idx], u[idx]], depth_scale)
                seen_through[idx] = np.isfinite(d) & (d > z[idx] + c.wall_tolerance)
            mem, mem_t = mem[~seen_through], mem_t[~seen_through]
        if len(scan.points_xy):
            T = pose_to_T_ground_robot(*pose)
            new = self.product(scan.points_xy, T[:2, :2]) + T[:2, 3]
            mem = np.vstack([mem, new])
            mem_t = np.concatenate([mem_t, np.full(len(new), scan.t)])
        if len(mem):
            mem, mem_t = _plain_one_per_cell(mem, mem_t, c.memory_cell)
        if len(mem) > c.memory_points:
            mem, mem_t = mem[-c.memory_points:], mem_t[-c.memory_points:]
        self.memory = (mem, mem_t)

    def _plain_explained_by_walls(self, p_robot, pose):
        T = pose_to_T_ground_robot(*pose)
        p_ground = self.product(p_robot, T[:3, :3]) + T[:3, 3]
        tol = self.config.wall_tolerance
        explained = np.zeros(len(p_ground), dtype=bool)
        reach = self.config.max_range + tol
        xy = np.asarray(pose[:2])
        for w in self._plain_walls:
            if np.any(xy < w.lo - reach) or np.any(xy > w.hi + reach):
                continue
            dist = self.product(p_ground, w.n[None, :])[:, 0] + w.d
            close = np.abs(dist) < tol
            if not close.any():
                continue
            idx = np.nonzero(close & ~explained)[0]
            if len(idx) == 0:
                continue
            q = self.product(p_ground[idx], w.R_plane)
            inside = np.zeros(len(idx), dtype=bool)
            for poly in w.polygons_2d:
                inside |= _plain_inside_polygon(q, poly)
            explained[idx[inside]] = True
        return explained


def _plain_one_per_cell(mem, mem_t, memory_cell):
    cell = np.floor(mem / memory_cell).astype(np.int64)
    key = (cell[:, 0] << 32) + (cell[:, 1] & 0xFFFFFFFF)
    order = np.argsort(-mem_t, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    pick = np.sort(order[first])
    return mem[pick], mem_t[pick]


@pytest.fixture(params=["numpy", "numba"])
def scan_backend(request, monkeypatch):
    """Each test once with the scan's numpy code and once with its compiled kernels (when numba
    is installed): the plane fit's backend decides both, and conftest puts it back afterwards."""
    if request.param == "numba":
        pytest.importorskip("numba", reason="the compiled kernels need numba (pip install -e '.[perf]')")
    assert fit_kernels.set_backend(request.param) == request.param
    assert scan_kernels.backend() == request.param, scan_kernels.backend_note()
    return request.param


def _same(a, b) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


TWISTS = [(0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (-0.2, 0.1, 0.0), (0.1, -0.25, 0.0), (0.0, 0.0, 0.5), (0.2, 0.2, 0.3)]
# A pose on the institute's ground floor from which the front camera sees walls the map knows
# (and doors: walls of several polygons), and one in another room.
INSTITUTE_POSES = [(39.608, 8.181, 2.992), (36.550, 4.589, 0.648)]


def _frame_sequence(plane_map, pose0, clutter, n, step, turn, seed, decimation=1, dt=0.1, skew=-0.03):
    """Frames of both cameras along a short drive; the side camera's a little older than the front
    one's (``skew``: frames arrive out of capture order), both at the same time every third step."""
    scene = SimScene(plane_map, clutter=clutter)
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        c, s = math.cos(pose0[2]), math.sin(pose0[2])
        pose = (pose0[0] + k * step * c, pose0[1] + k * step * s, pose0[2] + k * turn)
        for cam in ROBOT.cameras:
            t = dt * k + (0.0 if cam.name == "front" or k % 3 == 2 else skew)
            frames.append(render_depth_frame(ROBOT, scene, cam.name, pose, rng=rng, noise=DepthNoise(),
                                             decimation=decimation, t_capture=1.0 + t))
    return frames


def _assert_scans_match_the_plain_ones(frames, plane_map, config, no_pose_every=0):
    fast, plain = ProtectiveStop(config, ROBOT, plane_map), _PlainStop(config, ROBOT, plane_map)
    seen = {"points": 0, "ignored": 0, "memory": 0}
    for i, f in enumerate(frames):
        pose = None if no_pose_every and i % no_pose_every == no_pose_every - 1 else \
            (f.truth[0] + 0.004, f.truth[1] - 0.003, f.truth[2] + 0.002)  # the localizer is a little off
        if i % 2:  # the app's raw units and the frame in metres
            a, b = fast.update_scan_frame(f, pose), plain.update_scan_frame(f, pose)
        else:
            depth = f.depth_m()
            a, b = fast.update_scan(f.camera, f.t_capture, depth, f.K, pose), plain.update_scan(
                f.camera, f.t_capture, depth, f.K, pose)
        assert _same(a.points_xy, b.points_xy), (i, len(a.points_xy), len(b.points_xy))
        assert (a.camera, a.t, a.walls_ignored, a.near_blind) == (b.camera, b.t, b.walls_ignored, b.near_blind), i
        assert _same(fast.memory[0], plain.memory[0]) and _same(fast.memory[1], plain.memory[1]), i
        for twist in TWISTS:
            assert fast.limit(f.t_capture + 0.01, twist, pose) == plain.limit(f.t_capture + 0.01, twist, pose), (i, twist)
        seen["points"] += len(a.points_xy)
        seen["ignored"] += a.walls_ignored
        seen["memory"] = max(seen["memory"], len(fast.memory[0]))
    return seen


ARENA_CLUTTER = [Box(1.0, 0.75, 0.3, 0.5, 1.75), Box(0.6, 1.0, 0.2, 0.2, 0.5, 0.4), Box(0.2, 0.4, 0.15, 0.3, 0.3, 1.0)]


@pytest.mark.parametrize("config", [SafetyConfig(), SafetyConfig(stride=4, memory_time=0.25, memory_points=300),
                                    SafetyConfig(stride=13, memory_cell=0.05, wall_tolerance=0.08)],
                         ids=["default", "short-memory", "coarse"])
def test_the_arena_scan_is_the_plain_scan_frame_by_frame(scan_backend, config):
    frames = _frame_sequence(ARENA, (0.3, 0.5, 0.2), ARENA_CLUTTER, 6, 0.03, 0.08, seed=1)
    seen = _assert_scans_match_the_plain_ones(frames, ARENA, config, no_pose_every=5)
    assert seen["points"] > 1000 and seen["ignored"] > 1000 and seen["memory"] > 100, seen
    if config.memory_points == 300:
        assert seen["memory"] == 300  # the bound was reached


def test_a_decimated_arena_scan_is_the_plain_scan(scan_backend):
    frames = _frame_sequence(ARENA, (0.5, 0.3, 1.8), ARENA_CLUTTER, 4, 0.02, -0.1, seed=2, decimation=2)
    seen = _assert_scans_match_the_plain_ones(frames, ARENA, SafetyConfig())
    assert seen["points"] > 100 and seen["ignored"] > 100, seen


@pytest.mark.parametrize("pose0", INSTITUTE_POSES)
def test_the_building_scan_is_the_plain_scan_frame_by_frame(scan_backend, pose0):
    c, s = math.cos(pose0[2]), math.sin(pose0[2])
    clutter = [Box(pose0[0] + 1.2 * c, pose0[1] + 1.2 * s, 0.3, 0.5, 1.75, pose0[2]),
               Box(pose0[0] + 0.8 * c - 0.5 * s, pose0[1] + 0.8 * s + 0.5 * c, 0.4, 0.4, 0.8, 0.3),
               Box(pose0[0] - 0.6 * s, pose0[1] + 0.6 * c, 0.3, 0.3, 1.0)]
    frames = _frame_sequence(BIG_ROOM, pose0, clutter, 6, 0.05, 0.05, seed=3)
    seen = _assert_scans_match_the_plain_ones(frames, BIG_ROOM, SafetyConfig(), no_pose_every=4)
    assert seen["points"] > 1000 and seen["ignored"] > 500, seen


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")  # the NaN points' cells
def test_a_blinded_view_and_a_memory_set_from_outside_are_the_plain_ones(scan_backend):
    """A person right at the lens (most of the view invalid), a memory the caller replaced (with
    points in one cell, out of time order) and a pose gone NaN once (a filter's failure, NaN points
    in the memory): the scan goes on from them as the plain one does."""
    pose = (0.45, 0.5, 0.0)
    scene = SimScene(ARENA, clutter=[Box(pose[0] + 0.28, pose[1], 0.1, 0.8, 1.75)])
    fast, plain = ProtectiveStop(SafetyConfig(), ROBOT, ARENA), _PlainStop(SafetyConfig(), ROBOT, ARENA)
    rng = np.random.default_rng(7)
    mem = (np.array([[0.9, 0.5], [0.901, 0.501], [1.0, 0.2], [0.9005, 0.5005]]), np.array([0.95, 0.97, 0.9, 0.97]))
    fast.memory = plain.memory = mem
    nan_seen = False
    for k in range(4):
        for cam in ROBOT.cameras:
            f = render_depth_frame(ROBOT, scene, cam.name, pose, rng=rng, noise=DepthNoise(), t_capture=1.0 + 0.1 * k)
            p = (math.nan, pose[1], pose[2]) if k == 1 and cam.name == "left" else pose
            a, b = fast.update_scan_frame(f, p), plain.update_scan_frame(f, p)
            assert _same(a.points_xy, b.points_xy) and a.walls_ignored == b.walls_ignored
            assert a.near_blind == b.near_blind
            for x, y in zip(fast.memory, plain.memory):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True)
            nan_seen = nan_seen or bool(np.isnan(fast.memory[0]).any())
    assert nan_seen
    assert fast.scans["front"].near_blind
    assert fast.limit(1.25, (0.3, 0.0, 0.0), pose) == plain.limit(1.25, (0.3, 0.0, 0.0), pose)


def test_the_view_blindness_count_is_the_plain_one_around_its_limit(scan_backend):
    """The blindness count stops early once the rest of the view cannot change it: the same answer
    as counting all of it, for raw units and metres, just below, at and above the limit."""
    stop = ProtectiveStop(SafetyConfig(), ROBOT, ARENA)
    rays = ps._pixel_rays((60, 106), np.array([[400.0, 0.0, 424.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]]), 8)
    rng = np.random.default_rng(3)
    h, w = 480, 848
    size = (h // 2) * (w // 2)
    limit = SafetyConfig().near_blind_fraction * size
    for bad in [0, 1, int(limit) - 1, int(limit), int(limit) + 1, int(limit) + w // 4, size - 1, size]:
        for layout in ("first rows", "last rows", "random"):
            depth = np.full((h, w), 1000, np.uint16)
            flat = {"first rows": np.arange(size), "last rows": np.arange(size)[::-1]}.get(layout, rng.permutation(size))
            centre = np.full(size, 1000, np.uint16)
            centre[flat[:bad]] = 0
            depth[h // 4:3 * h // 4, w // 4:3 * w // 4] = centre.reshape(h // 2, w // 2)
            assert np.count_nonzero(depth == 0) == bad
            metres = depth.astype(np.float32) * np.float32(0.001)
            metres[metres == 0] = rng.choice([0.0, np.nan, -1.0, np.inf * -1], size=int(np.count_nonzero(metres == 0)))
            for image in (depth, metres):
                c = image[h // 4:3 * h // 4, w // 4:3 * w // 4]
                plain_bad = np.count_nonzero(c <= 0) if image.dtype.kind in "ui" else \
                    np.count_nonzero(~np.isfinite(c) | (c <= 0.0))
                assert stop._near_blind(image) == bool(plain_bad > limit), (bad, layout, image.dtype)
                if scan_backend == "numba":
                    got = scan_kernels.scan_frame(image, 8, (60, 106), 0.001 if image.dtype.kind == "u" else 1.0, 0.2,
                                                  3.0, rays, np.eye(4), 0.04, 1.8, SafetyConfig().near_blind_fraction)
                    assert got is not None and got[1] == bool(plain_bad > limit), (bad, layout, image.dtype)


def test_the_polygon_tests_are_the_plain_even_odd_rule(scan_backend):
    """Points on, just off and far from the building's wall polygons (doors, windows): the culled
    and merged tests give the plain rule's answer for every polygon set."""
    stop = ProtectiveStop(SafetyConfig(), ROBOT, BIG_ROOM)
    rng = np.random.default_rng(11)
    walls = [w for w in stop._walls if len(w.polygons) > 1][:6] + stop._walls[:3]
    for w in walls:
        verts = np.vstack(w.polygons_2d)
        q = np.vstack([verts + rng.normal(0.0, 1e-12, verts.shape),  # at the vertices, both sides
                       verts,
                       rng.uniform(verts.min(axis=0) - 0.5, verts.max(axis=0) + 0.5, (2000, 2)),
                       np.column_stack([rng.choice(verts[:, 0], 500), rng.uniform(verts[:, 1].min(), verts[:, 1].max(), 500)])])
        plain = np.zeros(len(q), dtype=bool)
        for poly in w.polygons_2d:
            plain |= _plain_inside_polygon(q, poly)
        assert 0 < np.count_nonzero(plain) < len(q)
        assert np.array_equal(ps._inside_polygons(q[:, 0], q[:, 1], w), plain)
        if scan_backend == "numba":
            # The kernel tests the walls on points in the robot frame: these points on the wall's
            # plane, from a pose beside it, tested against the in-plane coordinates it finds.
            g = q @ w.R_plane - w.d * w.n
            away = w.n[:2] / np.linalg.norm(w.n[:2])  # the robot 0.6 m off the wall: no point near it
            pose = (float(g[:, 0].mean() + 0.6 * away[0]), float(g[:, 1].mean() + 0.6 * away[1]), 0.3)
            G = pose_to_T_ground_robot(*pose)
            p = np.ascontiguousarray((g - G[:3, 3]) @ G[:3, :3])
            g = _plain_product(p, G[:3, :3]) + G[:3, 3]
            inside = np.zeros(len(q), dtype=bool)
            for poly in w.polygons_2d:
                inside |= _plain_inside_polygon(_plain_product(g, w.R_plane), poly)
            want = inside & (np.abs(_plain_product(g, w.n[None, :])[:, 0] + w.d) < stop.config.wall_tolerance)
            assert 0 < np.count_nonzero(want) < len(q)
            k = [id(v) for v in stop._walls].index(id(w))
            got = scan_kernels.walls(p, G, pose[:2], _one_wall_table(stop, k), stop.config.wall_tolerance, 0.0, 0.11,
                                     0.11, 0.06)
            assert got is not None and got[1] == np.count_nonzero(want)
            assert _same(got[0], np.ascontiguousarray(p[~want, :2]))


def _one_wall_table(stop, k):
    """The compiled scan's table of the walls, of wall ``k`` alone."""
    planes, bounds, wall_polys, vertices, starts, boxes = stop._wall_table
    a, b = wall_polys[k], wall_polys[k + 1]
    return (planes[k:k + 1].copy(), bounds[k:k + 1].copy(), np.array([0, b - a], np.int64),
            vertices[starts[a]:starts[b]].copy(), starts[a:b + 1] - starts[a], boxes[a:b].copy())


def test_the_memory_merge_keeps_the_newest_point_per_cell_as_the_plain_sort(scan_backend):
    """Random memories with many points per cell, equal and out-of-order times: adding a frame's
    points keeps what the plain sort keeps (the newest per cell, of equal times the first)."""
    stop = ProtectiveStop(SafetyConfig(memory_cell=0.05), ROBOT, ARENA)
    rng = np.random.default_rng(5)
    for trial in range(80):
        spread = 0.3 if trial % 4 else 8.0  # a frame's points in a small window of cells, or not
        old = rng.uniform(-spread, spread, (int(rng.integers(0, 200)), 2)) + rng.uniform(-50.0, 50.0, 2)
        old_t = rng.choice([0.5, 0.6, 0.7, 0.8], len(old))
        old, old_t = _plain_one_per_cell(old, old_t, 0.05)
        keys = ps._cell_keys(old, 0.05)
        base = old.mean(axis=0) if len(old) else rng.uniform(-50.0, 50.0, 2)
        k = int(rng.integers(0, len(old) + 1))
        new = np.vstack([old[rng.permutation(len(old))[:k]] + rng.normal(0.0, 0.005, (k, 2)),  # mostly remembered cells
                         base + rng.uniform(-spread, spread, (int(rng.integers(1, 300)), 2))])
        t = float(rng.choice([0.6, 0.7, 0.9]))  # older than, as old as and newer than remembered points
        want = _plain_one_per_cell(np.vstack([old, new]), np.concatenate([old_t, np.full(len(new), t)]), 0.05)
        if scan_backend == "numba":
            stays, pick, new_keys = scan_kernels.merge_cells(keys, old_t, np.ones(len(old), bool), new, t, 0.05)
            got = (np.concatenate([old[stays], new[pick]]), np.concatenate([old_t[stays], np.full(len(pick), t)]),
                   np.concatenate([keys[stays], new_keys]))
        else:
            got = stop._add_to_cells(old, old_t, keys, new, t)
        assert _same(got[0], want[0]) and _same(got[1], want[1]), trial
        assert np.array_equal(got[2], ps._cell_keys(want[0], 0.05)), trial


def test_the_kernels_leave_to_numpy_what_its_conversions_decide(scan_backend):
    """NaN and out-of-range points make numpy's float-to-int conversions decide (the platform's),
    a point off a corner of the footprint libm's hypot: the kernels decline them."""
    if scan_backend != "numba":
        pytest.skip("the numpy scan has no kernels to decline")
    keys = np.array([(3 << 32) + 4], np.int64)
    for bad in ([np.nan, 0.0], [1e300, 0.0], [0.0, -1e12]):
        assert scan_kernels.merge_cells(keys, np.zeros(1), np.ones(1, bool), np.array([[0.1, 0.1], bad]), 1.0, 0.02) is None
    # The memory: a camera at the origin looking along ground +x (its optical z), the frame 2 m deep.
    K = np.array([[400.0, 0.0, 50.0], [0.0, 400.0, 40.0], [0.0, 0.0, 1.0]])
    depth = np.full((80, 100), 2000, np.uint16)
    C = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0]])
    mem = np.array([[1.0, 0.0], [3.0, 0.0], [1.0, -1e9], [-1.0, 0.0]])  # seen through, behind, out of view, behind the lens
    keys = ps._cell_keys(mem, 0.02)

    def remember(mem, xy, K=K):
        return scan_kernels.remember(mem, np.ones(len(mem)), keys[:len(mem)], 1.0, 3.0, C, 0.5, K, 0.2, depth, 0.001,
                                     0.04, xy, np.eye(4), 0.02)
    got = remember(mem, np.zeros((0, 2)))
    assert got is not None and _same(got[0], mem[1:]) and _same(got[2], keys[1:])
    for bad in ([np.nan, 0.0], [1e300, 0.0], [0.0, -1e12]):
        assert remember(mem, np.array([[0.1, 0.1], bad])) is None
    assert remember(mem, np.zeros((0, 2)), np.diag([np.nan, 400.0, 1.0])) is None  # a NaN pixel column
    # A wall along ground x = 0.14 that explains a point off a corner of the footprint, within
    # always_distance of it: hypot decides whether it is kept.
    table = (np.array([[1.0, 0.0, 0.0, -0.14, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]]), np.full((1, 8), -np.inf),
             np.array([0, 1], np.int64), np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 2.0], [-1.0, 2.0]]),
             np.array([0, 4], np.int64), np.array([[-1.0, 1.0, -1.0, 2.0]]))
    assert scan_kernels.walls(np.array([[0.14, 0.14, 0.5]]), np.eye(4), (0.0, 0.0), table, 0.04, 0.0, 0.11, 0.11,
                              0.06) is None
    got = scan_kernels.walls(np.array([[0.14, 0.5, 0.5], [0.14, 0.14, 2.5], [0.5, 0.5, 0.5]]), np.eye(4), (0.0, 0.0),
                             table, 0.04, 0.0, 0.11, 0.11, 0.06)
    assert got is not None and got[1] == 1 and got[0].tolist() == [[0.14, 0.14], [0.5, 0.5]]


def test_the_depth_validity_bounds_compare_as_numpy_does(scan_backend):
    """Depths at the bounds of the valid range, in float32 metres and in raw units: the kernel
    compares in the type numpy compares in (float32 for float32 depths)."""
    lo, hi = 0.2, 3.0
    edge = [np.float32(lo), np.nextafter(np.float32(lo), np.float32(1)), np.nextafter(np.float32(lo), np.float32(0)),
            np.float32(hi), np.nextafter(np.float32(hi), np.float32(0)), np.float32(np.inf), np.float32(np.nan), 0.0]
    metres, raw, small = np.zeros((12, 16), np.float32), np.zeros((12, 16), np.uint16), np.zeros((12, 16), np.uint8)
    metres[::2, ::2] = np.resize(np.array(edge, np.float32), (6, 8))  # the pixels a stride of 2 samples
    raw[::2, ::2] = np.resize(np.array([199, 200, 201, 2999, 3000, 3001, 0, 65535], np.uint16), (6, 8))
    small[::2, ::2] = np.resize(np.array([0, 1, 2, 3, 255], np.uint8), (6, 8))
    rays = ps._pixel_rays((6, 8), np.array([[8.0, 0.0, 7.5], [0.0, 8.0, 5.5], [0.0, 0.0, 1.0]]), 2)
    for depth, scale in ((metres, 1.0), (raw, 0.001), (small, 1.0), (metres.astype(np.float64), 1.0), (metres, 0.5)):
        want = ps._camera_points(ps._metres(depth[::2, ::2], scale), rays, lo, hi)
        assert 0 < len(want) < 48
        if scan_backend == "numba":  # the kernel's points, in a robot frame that is the camera's
            got = scan_kernels.scan_frame(depth, 2, (6, 8), scale, lo, hi, rays, np.eye(4), -np.inf, np.inf, 0.6)
            assert got is not None and _same(got[0], want), (depth.dtype, scale)


def test_the_scan_backend_follows_robot_kernels(monkeypatch):
    """One switch for every kernel: the scan runs compiled exactly when the plane fit does, and
    kernels that do not compile fall back to numpy under "auto" with the reason, or raise under "numba"."""
    monkeypatch.setattr(scan_kernels, "_nb", {})
    monkeypatch.setattr(scan_kernels, "_failed", "")
    monkeypatch.setenv("ROBOT_KERNELS", "numpy")
    assert fit_kernels.set_backend(None) == "numpy"
    assert scan_kernels.backend() == "numpy" and scan_kernels.warm_up() == 0.0
    assert "plane fit's backend is numpy" in scan_kernels.backend_note()
    pytest.importorskip("numba", reason="the compiled kernels need numba (pip install -e '.[perf]')")

    def broken():
        raise TypeError("cannot compile this")

    monkeypatch.setattr(scan_kernels, "_run_each_kernel", broken)
    monkeypatch.setenv("ROBOT_KERNELS", "auto")
    assert fit_kernels.set_backend(None) == "numba"
    assert scan_kernels.backend() == "numpy" and "did not compile" in scan_kernels.backend_note()
    assert not scan_kernels._nb  # no half-loaded kernels are left to call
    monkeypatch.setattr(scan_kernels, "_failed", "")
    monkeypatch.setenv("ROBOT_KERNELS", "numba")
    with pytest.raises(TypeError):
        scan_kernels.warm_up()


def test_the_scan_with_every_kernel_declining_is_the_plain_scan(scan_backend, monkeypatch):
    """Where a kernel declines (numpy's conversions decide), the scan goes on in numpy: the same."""
    if scan_backend != "numba":
        pytest.skip("the numpy scan has no kernels to decline")
    for name in ("scan_frame", "walls", "remember"):
        monkeypatch.setattr(scan_kernels, name, lambda *args, **kwargs: None)
    frames = _frame_sequence(ARENA, (0.3, 0.5, 0.2), ARENA_CLUTTER, 3, 0.03, 0.08, seed=4)
    seen = _assert_scans_match_the_plain_ones(frames, ARENA, SafetyConfig(), no_pose_every=4)
    assert seen["points"] > 500 and seen["ignored"] > 500, seen


def test_the_wall_and_memory_kernels_are_the_numpy_code_on_random_inputs(scan_backend):
    """Random points at random poses in the building (on and off its walls, some beside the
    footprint) and random memories seen by random frames: the kernels' results are the numpy
    code's, exactly, wherever they do not decline."""
    if scan_backend != "numba":
        pytest.skip("the numpy code is the reference here")
    stop = ProtectiveStop(SafetyConfig(), ROBOT, BIG_ROOM)
    c = stop.config
    rng = np.random.default_rng(17)
    compared = {"walls": 0, "explained": 0, "remember": 0, "seen": 0}
    for trial in range(60):
        w = stop._walls[int(rng.integers(len(stop._walls)))]
        q = rng.uniform(np.vstack(w.polygons_2d).min(axis=0) - 0.3, np.vstack(w.polygons_2d).max(axis=0) + 0.3, (400, 2))
        g = q @ w.R_plane - w.d * w.n + np.outer(rng.normal(0.0, 0.03, len(q)), w.n)
        pose = (float(g[0, 0] + rng.normal(0.0, 1.0)), float(g[0, 1] + rng.normal(0.0, 1.0)), float(rng.uniform(-4, 4)))
        G = pose_to_T_ground_robot(*pose)
        p = np.vstack([(g - G[:3, 3]) @ G[:3, :3],
                       np.column_stack([rng.uniform(-3.0, 3.0, (300, 2)), rng.uniform(0.04, 1.8, 300)])])
        if trial % 3 == 0:  # points beside the footprint: on the axes or off a corner
            p = np.vstack([p, [[0.11 + 0.05, 0.0, 0.5], [0.0, -0.11 - 0.07, 0.5], [0.2, 0.2, 0.5]]])
        got = scan_kernels.walls(p, G, pose[:2], stop._wall_table, c.wall_tolerance, c.footprint_offset_x,
                                 stop._half_x, stop._half_y, c.always_distance)
        want = stop._kept_points(p, stop._explained_by_walls(p, pose, G))
        if got is not None:
            assert _same(got[0], want[0]) and got[1] == want[1], trial
            compared["walls"] += 1
            compared["explained"] += got[1]

        n_mem = int(rng.integers(0, 500))
        mem, mem_t = _plain_one_per_cell(rng.uniform(-2.0, 2.0, (n_mem, 2)) + pose[:2],
                                         rng.choice([0.5, 1.0, 2.0, 3.9], n_mem), c.memory_cell)
        keys = ps._cell_keys(mem, c.memory_cell)
        cam = ROBOT.cameras[trial % len(ROBOT.cameras)]
        K = cam.intrinsics_from_fov()
        depth = rng.choice([0, 300, 800, 1500, 2500, 4000], (cam.height, cam.width)).astype(np.uint16)
        scan = ps.ObstacleScan(cam.name, 4.0, np.ascontiguousarray(want[0][:int(rng.integers(0, 200))]))
        C = G @ stop._T_robot_camera[cam.name]
        z_test = float(np.clip(C[2, 3], c.min_height, c.max_height))
        got = scan_kernels.remember(mem, mem_t, keys, scan.t, c.memory_time, C, z_test, K, ROBOT.localizer.min_range,
                                    depth, 0.001, c.wall_tolerance, scan.points_xy, G, c.memory_cell)
        want = stop._remember_numpy(scan, mem, mem_t, keys, depth, K, G, C, z_test, 0.001)
        assert got is not None, trial
        assert all(_same(a, b) for a, b in zip(got, want)), trial
        compared["remember"] += 1
        compared["seen"] += n_mem - int(np.count_nonzero(np.isin(keys, got[2])))
    assert compared["walls"] > 40 and compared["explained"] > 1000 and compared["seen"] > 100, compared


class _BlasStop(_PlainStop):
    """The plain scan with numpy's matrix products (the machine's BLAS), as the scan computed them
    before its products were written out."""

    product = staticmethod(lambda p, M: p @ M.T)


@pytest.mark.parametrize("plane_map, pose0", [(ARENA, (0.3, 0.5, 0.2)), (BIG_ROOM, INSTITUTE_POSES[0])],
                         ids=["arena", "building"])
def test_the_written_out_products_differ_from_blas_by_rounding_only(plane_map, pose0):
    """The order of a sum moves its result by an ulp or so: the same points within 1e-12 m, the same
    wall counts and memory sizes, and the same decisions on rendered frames with clutter."""
    c, s = math.cos(pose0[2]), math.sin(pose0[2])
    clutter = [Box(pose0[0] + 0.9 * c, pose0[1] + 0.9 * s, 0.3, 0.5, 1.75, pose0[2]),
               Box(pose0[0] + 0.6 * c - 0.3 * s, pose0[1] + 0.6 * s + 0.3 * c, 0.2, 0.2, 0.5, 0.4)]
    frames = _frame_sequence(plane_map, pose0, clutter, 5, 0.04, 0.06, seed=5)
    fast, blas = ProtectiveStop(SafetyConfig(), ROBOT, plane_map), _BlasStop(SafetyConfig(), ROBOT, plane_map)
    differ = 0
    for f in frames:
        pose = (f.truth[0] + 0.004, f.truth[1] - 0.003, f.truth[2] + 0.002)
        a, b = fast.update_scan_frame(f, pose), blas.update_scan_frame(f, pose)
        assert (a.walls_ignored, a.near_blind, a.points_xy.shape) == (b.walls_ignored, b.near_blind, b.points_xy.shape)
        assert np.allclose(a.points_xy, b.points_xy, rtol=0.0, atol=1e-12)
        differ += int(np.count_nonzero(fast.memory[0] != blas.memory[0]))
        assert fast.memory[0].shape == blas.memory[0].shape and np.array_equal(fast.memory[1], blas.memory[1])
        assert np.allclose(fast.memory[0], blas.memory[0], rtol=0.0, atol=1e-12)
        for twist in TWISTS:
            x, y = fast.limit(f.t_capture + 0.01, twist, pose), blas.limit(f.t_capture + 0.01, twist, pose)
            assert (x.zone, x.reason) == (y.zone, y.reason), twist
            assert np.allclose(x.twist, y.twist, rtol=1e-9, atol=0.0)
            assert x.free_distance == y.free_distance or abs(x.free_distance - y.free_distance) < 1e-12
    assert differ > 0  # this machine's BLAS does round otherwise (fused multiply-adds)
