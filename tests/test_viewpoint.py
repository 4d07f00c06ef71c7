"""The move that tells a relocalization's hypotheses apart (robot/localization/viewpoint.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.clutter import random_site_clutter
from drivers.sim.render import SimScene, render_depth_frame, resolve_noise
from robot.base.geometry import compose_se2
from robot.config import load_robot_config
from robot.control.recovery import views_from_latest
from robot.localization.relocalize import AMBIGUOUS, UNIQUE, Relocalizer
from robot.localization.viewpoint import CLEARANCE, MIN_SHARE, ViewpointPlanner, plan_recovery_move, segment_distance, wall_segments
from robot.maps.plane_map import PlaneMap, load_plane_map, make_plane

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
HOUSE = load_plane_map("config/maps/fzk_haus_ground.yaml")


def _near(h, pose, xy=0.02, phi=math.radians(1.0)) -> bool:
    return math.hypot(h.x - pose[0], h.y - pose[1]) < xy and abs(math.remainder(h.phi - pose[2], 2 * math.pi)) < phi


def _point_segment(p, s):
    a, b = np.array(s[:2]), np.array(s[2:])
    d = b - a
    u = np.clip((p - a) @ d / max(d @ d, 1e-300), 0.0, 1.0)
    return float(np.hypot(*(p - (a + u * d))))


def test_segment_distance_agrees_with_sampling_both_segments():
    rng = np.random.default_rng(3)
    for _ in range(200):
        p0, p1 = rng.uniform(-2, 2, 2), rng.uniform(-2, 2, 2)
        segs = rng.uniform(-2, 2, (3, 4))
        got = segment_distance(p0, p1, segs)
        # Sampled densely on the path, the distance to each segment is exact from the segment's side.
        ts = np.linspace(0.0, 1.0, 2001)
        sampled = min(_point_segment(p0 + t * (p1 - p0), s) for s in segs for t in ts)
        assert got <= sampled + 1e-9
        assert sampled - got < 2.0 * np.hypot(*(p1 - p0)) / 2000 + 1e-9


def test_walls_block_the_robot_where_they_reach_its_height_and_a_door_leaves_a_gap():
    # A wall along y = 0 from x = 0 to 4 with a door 1.5..2.5 m (a notch up to 2 m), a lintel
    # spanning a passage above the robot, and a floor.
    wall = [[0, 0, 0], [1.5, 0, 0], [1.5, 0, 2.0], [2.5, 0, 2.0], [2.5, 0, 0], [4, 0, 0], [4, 0, 2.5], [0, 0, 2.5]]
    lintel = [[0, 3, 2.0], [4, 3, 2.0], [4, 3, 2.5], [0, 3, 2.5]]
    floor = [[0, 0, 0], [4, 0, 0], [4, 3, 0], [0, 3, 0]]
    m = PlaneMap([make_plane("wall", [wall]), make_plane("lintel", [lintel]), make_plane("floor", [floor])])
    segs = wall_segments(m, 0.02, 0.6)
    assert len(segs) > 0
    assert np.allclose(segs[:, 1], 0.0) and np.allclose(segs[:, 3], 0.0)  # only the wall at y = 0
    xs = np.sort(segs[:, [0, 2]], axis=1)
    covered = lambda x: bool(np.any((xs[:, 0] <= x) & (x <= xs[:, 1])))  # noqa: E731
    assert covered(0.5) and covered(3.5) and not covered(2.0)  # the door is open
    # Through the door there is a way; through the wall none.
    assert segment_distance(np.array([2.0, -1.0]), np.array([2.0, 1.0]), segs) == pytest.approx(0.5)
    assert segment_distance(np.array([0.7, -1.0]), np.array([0.7, 1.0]), segs) == 0.0


def test_a_true_symmetry_offers_no_move():
    # The square arena's centre: the four headings see the same from anywhere after the same move.
    planner = ViewpointPlanner(ROBOT, ARENA)
    c = (0.5, 0.5)
    poses = [(c[0], c[1], 0.3 + k * math.pi / 2) for k in range(4)]
    assert planner.plan(poses, max_distance=0.3, clearance=0.02) is None
    assert planner.plan(poses[:1]) is None  # one place: nothing to tell apart


def _house_scene(seed, i_pose, pose):
    rng = np.random.default_rng([seed, i_pose])
    clutter = list(random_site_clutter(HOUSE, rng, 4, keep_clear=[pose[:2]]))
    return SimScene(HOUSE, clutter=clutter), rng


# Poses of the relocalization benchmark's house (its seed 101) where one view is ambiguous: the
# house looks the same from a twin place there, with the realistic camera and site clutter.
HOUSE_AMBIGUOUS = [(22, (1.1934549462332757, 2.3480209116222897, 2.883404738242165)),
                   (33, (2.8508090500118737, 8.120563145298586, -0.8492020261550768))]


@pytest.mark.parametrize("i_pose, pose", HOUSE_AMBIGUOUS)
def test_one_planned_move_turns_an_ambiguous_house_view_into_the_right_unique_one(i_pose, pose):
    noise = resolve_noise("realistic")
    scene, rng = _house_scene(101, i_pose, pose)
    frames = [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, noise=noise) for c in ROBOT.cameras]
    rel = Relocalizer(ROBOT, HOUSE)
    res = rel.relocalize(frames, seed=int(rng.integers(1 << 30)))
    assert res.verdict == AMBIGUOUS and any(_near(h, pose, 0.05, math.radians(2.0)) for h in res.hypotheses)
    hyps = [(h.x, h.y, h.phi) for h in res.hypotheses if h.refined]
    planner = ViewpointPlanner(ROBOT, HOUSE, rel.index)
    move = planner.plan(hyps)
    assert move is not None and move.alike < move.alike_here and 0.0 < move.distance <= 2.0 + 1e-9
    # The straight move keeps the robot's circle and the clearance off every wall in every
    # hypothesis (sampled along the way, against the walls' floor-plan segments).
    need = planner.radius + CLEARANCE
    for h in planner.places(hyps):
        end = compose_se2(h, (move.dx, move.dy, move.dphi))
        for t in np.linspace(0.0, 1.0, 41):
            p = np.array(h[:2]) + t * (np.array(end[:2]) - np.array(h[:2]))
            assert min(_point_segment(p, s) for s in planner.segments) >= need - 1e-9
    # The robot faces the way: the front camera looks along it.
    assert move.dphi == pytest.approx(math.atan2(move.dy, move.dx))
    # Driven (odometry 1 % and 0.3 deg off), a second view with the first tells the places apart.
    moved = compose_se2(pose, (move.dx, move.dy, move.dphi))
    odo = (move.dx * 1.01, move.dy * 0.99, move.dphi + math.radians(0.3))
    frames2 = [render_depth_frame(ROBOT, scene, c.name, moved, rng=rng, noise=noise) for c in ROBOT.cameras]
    first, more = views_from_latest([(frames, (0.0, 0.0, 0.0)), (frames2, odo)])
    res2 = rel.relocalize(first, more_views=more, seed=int(rng.integers(1 << 30)))
    assert res2.verdict == UNIQUE, res2.reason
    assert _near(res2.hypotheses[0], moved)


# Two offices of the institute floor 6 m apart, alike from where the robot stands in either (the
# relocalization benchmark's turn left these two), near the office's wall: every single move that
# would show a difference runs into a wall in one of them.
INSTITUTE_TWINS = [(5.579, 6.283, 3.068), (11.579, 6.283, 3.068)]


def test_where_no_single_move_tells_two_offices_apart_a_path_of_two_does():
    plane_map = load_plane_map("config/maps/institute_ground.yaml")
    planner = ViewpointPlanner(ROBOT, plane_map)
    assert planner.alike_pairs(INSTITUTE_TWINS, MIN_SHARE) == 1
    assert planner.plan(INSTITUTE_TWINS) is None  # one move allowed: none helps
    move = planner.plan(INSTITUTE_TWINS, moves=2)
    assert move is not None and move.then is not None and move.alike == 0 and move.alike_here == 1
    first = (move.dx, move.dy, move.dphi)
    second = move.then
    # Each move faces its way, and each is clear of every wall in both offices from where it starts.
    for dx, dy, dphi in (first, second):
        assert dphi == pytest.approx(math.atan2(dy, dx)) and 0.0 < math.hypot(dx, dy) <= 2.0 + 1e-9
    there = [compose_se2(p, first) for p in INSTITUTE_TWINS]
    assert planner.clear(INSTITUTE_TWINS, first[:2], CLEARANCE) and planner.clear(there, second[:2], CLEARANCE)
    # The first alone leaves the offices alike; after the second they look different.
    assert planner.alike_pairs(there, MIN_SHARE) == 1
    assert planner.alike_pairs([compose_se2(p, second) for p in there], MIN_SHARE) == 0
    assert "then" in move.to_json()
    # The recovery asks for two only with two moves left.
    hyps = [_Hyp(*p) for p in INSTITUTE_TWINS]
    assert plan_recovery_move(planner, hyps, 2.0, CLEARANCE, moves_left=1) == (
        None, "no move of up to 2.0 m would tell the places apart")
    assert plan_recovery_move(planner, hyps, 2.0, CLEARANCE, moves_left=2) == (first, "")


class _Hyp:
    def __init__(self, x, y, phi):
        self.x, self.y, self.phi, self.refined = x, y, phi, True
