"""The localizer on rendered D435i frames: both estimators, degeneracy, clutter, gating."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.depth_render import Box, SimScene, render_depth_frame
from robot.config import load_robot_config
from robot.localizer import Localizer, coarse_covariance
from robot.plane_map import PlaneMap, load_plane_map, make_plane

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")


def frames_at(plane_map, pose, seed=0, clutter=(), cameras=("front", "left")):
    rng = np.random.default_rng(seed)
    scene = SimScene(plane_map, clutter)
    return [render_depth_frame(ROBOT, scene, c, pose, rng=rng) for c in cameras]


def pose_error(res, truth):
    return math.hypot(res.x - truth[0], res.y - truth[1]), abs(math.remainder(res.phi - truth[2], 2 * math.pi))


@pytest.mark.parametrize("method", ["joint", "paper"])
@pytest.mark.parametrize("truth,offset", [
    ((0.5, 0.5, math.pi), (0.06, -0.05, 0.12)),
    ((0.5, 0.5, 5 * math.pi / 6), (-0.07, 0.04, -0.15)),
    ((0.2, 0.9, 0.3), (0.05, 0.05, 0.1)),
    ((1.0, 0.0, 2.4), (-0.05, 0.07, -0.1)),
])
def test_estimators_recover_known_poses(method, truth, offset):
    frames = frames_at(ARENA, truth, seed=hash(truth) % 1000)
    coarse = tuple(np.add(truth, offset))
    res = Localizer(ROBOT, ARENA).localize(frames, coarse, method=method)
    pos, head = pose_error(res, truth)
    assert res.status == "ok"
    assert pos < 0.002 and head < math.radians(0.1)
    # The reported covariance is a covariance: symmetric, positive definite, small but not zero.
    assert np.allclose(res.cov, res.cov.T) and np.all(np.linalg.eigvalsh(res.cov) > 0)
    assert math.sqrt(res.cov[0, 0]) < 0.005
    used = {p.id for p in res.planes if p.used}
    assert len(used) >= 2


def test_joint_is_at_least_as_accurate_as_paper_on_average():
    errs = {"joint": [], "paper": []}
    truth = (0.3, 0.8, 0.4)
    for seed in range(6):
        frames = frames_at(ARENA, truth, seed=seed)
        for m in errs:
            res = Localizer(ROBOT, ARENA).localize(frames, truth, coarse_covariance(0.01, 0.01), method=m)
            errs[m].append(pose_error(res, truth)[0])
    assert np.sqrt(np.mean(np.square(errs["joint"]))) <= np.sqrt(np.mean(np.square(errs["paper"])))


def corridor_map(length=30.0):
    h = 1.0
    # Counter-clockwise seen from inside the corridor: normals face the robot.
    left = make_plane("left", [[[-length, 1.0, 0], [length, 1.0, 0], [length, 1.0, h], [-length, 1.0, h]]])
    right = make_plane("right", [[[length, -1.0, 0], [-length, -1.0, 0], [-length, -1.0, h], [length, -1.0, h]]])
    return PlaneMap([left, right])


@pytest.mark.parametrize("method", ["joint", "paper"])
def test_single_wall_is_degenerate_along_the_wall(method):
    wall = make_plane("wall", [[[1.5, 3, 0], [1.5, -3, 0], [1.5, -3, 1.0], [1.5, 3, 1.0]]])  # x = 1.5, faces -x
    pm = PlaneMap([wall])
    truth = (0.0, 0.0, 0.0)
    coarse = (0.03, 0.04, 0.05)
    res = Localizer(ROBOT, pm).localize(frames_at(pm, truth, cameras=("front",)), coarse, method=method)
    assert res.status == "degenerate"
    assert [u["label"] for u in res.unobservable] == ["y"]
    assert abs(res.x - truth[0]) < 0.002  # along the normal: measured
    assert abs(math.remainder(res.phi - truth[2], 2 * math.pi)) < math.radians(0.2)
    assert res.y == pytest.approx(coarse[1], abs=1e-9)  # along the wall: kept at the coarse value
    assert res.cov[1, 1] >= 0.1**2  # and honestly uncertain
    assert res.cov[0, 0] < 0.002**2


@pytest.mark.parametrize("method", ["joint", "paper"])
def test_corridor_leaves_position_along_it_unobservable(method):
    pm = corridor_map()
    truth = (0.0, 0.2, 0.0)
    coarse = (0.05, 0.17, -0.04)
    frames = frames_at(pm, truth)
    res = Localizer(ROBOT, pm).localize(frames, coarse, method=method)
    assert res.status == "degenerate"
    assert [u["label"] for u in res.unobservable] == ["x"]
    assert res.x == pytest.approx(coarse[0], abs=1e-9)
    assert abs(res.y - truth[1]) < 0.002
    assert abs(res.phi - truth[2]) < math.radians(0.2)
    assert res.cov[0, 0] >= 0.1**2


def test_box_face_parallel_to_the_wall_is_not_taken_as_the_wall():
    truth = (0.5, 0.5, math.pi)  # front camera faces wall_west (x = -0.25) at 0.65 m
    # A box face 0.1 m in front of the wall, parallel to it, with more pixels than the visible wall:
    # RANSAC alone would take the box; the rear-most rule must take the wall.
    box = Box(-0.10, 0.5, 0.1, 0.5, 0.24)
    frames = frames_at(ARENA, truth, clutter=[box])
    res = Localizer(ROBOT, ARENA).localize(frames, (0.52, 0.48, math.pi + 0.05), method="joint")
    west = [p for p in res.planes if p.id == "wall_west" and p.used]
    assert west, [p.to_json() for p in res.planes]
    assert west[0].d == pytest.approx(0.75, abs=0.003)  # the wall's distance from the robot centre, not the box's
    assert pose_error(res, truth)[0] < 0.003


def test_no_planes_when_nothing_is_in_view():
    pm = PlaneMap([make_plane("far", [[[50, 1, 0], [50, -1, 0], [50, -1, 1], [50, 1, 1]]])])
    res = Localizer(ROBOT, pm).localize(frames_at(ARENA, (0.5, 0.5, 0.0)), (0.5, 0.5, 0.0))
    assert res.status == "no_planes"
    assert (res.x, res.y, res.phi) == (0.5, 0.5, 0.0)


def test_wrong_plane_prediction_is_dropped_not_misidentified():
    # Coarse heading 60 deg off and claimed to be good to 1 deg: the walls the prior predicts are not
    # where the fits put them, so they must be dropped rather than matched to the wrong wall.
    truth = (0.5, 0.5, math.pi)
    frames = frames_at(ARENA, truth)
    res = Localizer(ROBOT, ARENA).localize(frames, (0.5, 0.5, math.pi + math.radians(60)),
                                           coarse_covariance(0.01, math.radians(1)))
    for p in res.planes:
        if p.used:
            # Anything used must really be the wall it is claimed to be: its normal in R must match
            # the true one for that wall at the true pose.
            n_G = ARENA[p.id].normal
            c, s = math.cos(truth[2]), math.sin(truth[2])
            n_R_true = np.array([c * n_G[0] + s * n_G[1], -s * n_G[0] + c * n_G[1]])
            assert np.dot(n_R_true, p.normal[:2]) > math.cos(math.radians(2))
