"""The protective stop, on rendered D435i frames: obstacles stop or slow the robot, mapped walls do not."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from drivers.sim.render import Box, DepthNoise, SimScene, render_depth_frame
from robot.config import load_robot_config
from robot.config.safety import SafetyConfig
from robot.control.protective_stop import BLIND, CLEAR, SLOWDOWN, STOP, ProtectiveStop, braking_speed, free_distance
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
