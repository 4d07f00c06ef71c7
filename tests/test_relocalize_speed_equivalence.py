"""The relocalizer's cluster ranking, vectorized over every cluster at once, against the
one-pose-at-a-time code it replaced (kept here as the reference): the same agreement for every
cluster, so the same clusters are verified in the same order."""

from __future__ import annotations

import math
from typing import List

import numpy as np
import pytest

from drivers.sim.clutter import random_site_clutter
from drivers.sim.render import DepthNoise, SimScene, render_depth_frame
from robot.config import load_robot_config
from robot.localization.relocalize import (
    ANGLE_TOL,
    ObservedWall,
    Relocalizer,
    _cluster,
    _hypotheses,
    _MapWalls,
    _span_fits,
    _wall_agreements,
    extract_walls,
)
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")
MAPS = ["paper_arena", "fzk_haus_ground", "institute_ground", "duplex_level1"]


def reference_wall_agreement(walls: List[ObservedWall], mw: _MapWalls, x: float, y: float, phi: float) -> float:
    """The previous code, one pose at a time (relocalize.py before the vectorized ranking)."""
    c, s = math.cos(phi), math.sin(phi)
    total = 0.0
    for w in walls:
        n_g = np.array([c * w.n_r[0] - s * w.n_r[1], s * w.n_r[0] + c * w.n_r[1]])
        d_g = w.d_r - float(n_g @ np.array([x, y]))
        same = (mw.n @ n_g > math.cos(ANGLE_TOL)) & (np.abs(mw.d - d_g) < 0.08)
        if not same.any():
            continue
        k = np.nonzero(same)[0]
        ends = np.array(w.span)
        ok = _span_fits(ends, np.full(len(k), phi), np.tile([x, y], (len(k), 1)), mw, k, 0.15)
        if ok.any():
            total += w.points
    return total


@pytest.fixture(scope="module")
def relocalizers():
    return {m: Relocalizer(ROBOT, load_plane_map(f"config/maps/{m}.yaml")) for m in MAPS}


@pytest.mark.parametrize("name", MAPS)
def test_every_cluster_of_rendered_cluttered_views_ranks_as_before(relocalizers, name):
    rel = relocalizers[name]
    rng = np.random.default_rng(7)
    from drivers.sim.building import free_space_poses

    checked = 0
    for pose in free_space_poses(rel.map, 6, rng, z=0.15):
        pose = tuple(float(v) for v in pose)
        scene = SimScene(rel.map, clutter=list(random_site_clutter(rel.map, rng, 4, keep_clear=[pose[:2]])))
        walls = []
        for cam in ROBOT.cameras:
            f = render_depth_frame(ROBOT, scene, cam.name, pose, rng=rng, noise=DepthNoise())
            walls += extract_walls(f, cam, rng, min_range=ROBOT.localizer.min_range, max_range=rel.max_range)
        lo, hi = rel.map.bounds()
        clusters = _cluster(_hypotheses(walls, rel.walls, rel.pairs, (lo[:2], hi[:2])))
        if not clusters:
            continue
        poses = np.array([c[:3] for c in clusters], float)
        got = _wall_agreements(walls, rel.walls, poses)
        want = [reference_wall_agreement(walls, rel.walls, *p) for p in poses]
        assert got.tolist() == want
        checked += len(clusters)
    assert checked > 20  # the scenes made hypotheses to rank


def test_poses_at_the_thresholds_rank_as_before(relocalizers):
    """Observed walls made from map walls and poses jittered around them, so that many pairs sit
    near the angle, offset and extent thresholds, where a changed rounding would show."""
    rel = relocalizers["fzk_haus_ground"]
    mw = rel.walls
    rng = np.random.default_rng(3)
    for _ in range(40):
        truth = np.array([rng.uniform(0, 12), rng.uniform(0, 10), rng.uniform(-math.pi, math.pi)])
        c, s = math.cos(truth[2]), math.sin(truth[2])
        walls = []
        for k in rng.choice(len(mw.n), size=6, replace=False):
            n_r = np.array([c * mw.n[k, 0] + s * mw.n[k, 1], -s * mw.n[k, 0] + c * mw.n[k, 1]])
            d_r = float(mw.d[k] + mw.n[k] @ truth[:2])
            ends = []
            for e in (mw.a_end[k], mw.b_end[k]):
                dx, dy = e - truth[:2]
                ends.append(np.array([c * dx + s * dy, -s * dx + c * dy]) + rng.normal(0, 0.1, 2))
            walls.append(ObservedWall("front", n_r, d_r + rng.normal(0, 0.05), (ends[0], ends[1]), int(rng.integers(50, 5000))))
        poses = truth + np.column_stack([rng.normal(0, 0.06, 200), rng.normal(0, 0.06, 200), rng.normal(0, ANGLE_TOL, 200)])
        got = _wall_agreements(walls, mw, poses)
        want = [reference_wall_agreement(walls, mw, *p) for p in poses]
        assert got.tolist() == want


def test_no_walls_or_no_poses_agree_with_nothing(relocalizers):
    mw = relocalizers["paper_arena"].walls
    assert _wall_agreements([], mw, np.zeros((3, 3))).tolist() == [0.0, 0.0, 0.0]
    w = ObservedWall("front", np.array([1.0, 0.0]), 0.5, (np.zeros(2), np.ones(2)), 10)
    assert _wall_agreements([w], mw, np.zeros((0, 3))).shape == (0,)
