"""The integrity benchmark's ground truth (scripts/bench_integrity.py, WallView): which pixels are
a wall's own, and what surface a used fit's patch lies on. Its counts of wrong identifications
stand on these, so they are tested on their own: a coplanar segment of another wall is not the
wall, and clutter is told from the wall as the camera's depth noise allows."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import bench_integrity as bi  # noqa: E402

from drivers.sim.clutter import built_walls, parallel_panel  # noqa: E402
from drivers.sim.render import DepthNoise, SimScene  # noqa: E402
from robot.base.geometry import invert_transform, pose_to_T_ground_robot, transform_points  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.maps.plane_map import PlaneMap, make_plane  # noqa: E402

ROBOT = load_robot_config(bi.ROOT / "config" / "robot.yaml")
X_WALL = 4.0
TRUTH = (0.0, 0.0, 0.0)


def segment(pid: str, y0: float, y1: float, height: float = 2.7):
    """One face of the wall x = 4 m seen from the robot (normal -x), from y1 down to y0."""
    x = X_WALL
    return make_plane(pid, [[[x, y1, 0], [x, y0, 0], [x, y0, height], [x, y1, height]]])


def scene_with(clutter) -> bi.Scene:
    # Two segments of one long wall, split where a crossing wall would meet it: one plane, two ids.
    plane_map = PlaneMap([segment("a", -3.0, -0.4), segment("b", 0.4, 3.0)])
    built = built_walls(plane_map, {})
    sim = SimScene(plane_map, clutter(plane_map), walls=built, backdrop=False)  # the robot stands outside the map's box
    return bi.Scene("two segments", TRUTH, TRUTH, np.eye(3), "cold", [], ROBOT, {"front": 0.0}, built, [], [], sim,
                    DepthNoise.realistic())


def in_camera(scene: bi.Scene, p_ground) -> np.ndarray:
    T = pose_to_T_ground_robot(*scene.truth) @ scene.true_robot.camera("front").T_robot_camera
    return transform_points(invert_transform(T), np.array([p_ground], float))[0]


def test_a_coplanar_segment_of_another_wall_is_not_the_wall():
    scene = scene_with(lambda m: [])
    a, b = bi.WallView(scene, "a", "front"), bi.WallView(scene, "b", "front")
    assert a.own.sum() > 1000 and b.own.sum() > 1000
    assert not (a.own & b.own).any()  # the same infinite plane, told apart by their polygons
    assert a.share > 0.99 and b.share > 0.99  # (the floor takes a row of pixels at their foot)


def test_clutter_in_front_of_one_segment_hides_that_one_only():
    scene = scene_with(lambda m: [parallel_panel(m["b"], 0.2, 1.0)])
    assert bi.WallView(scene, "a", "front").share > 0.99
    assert bi.WallView(scene, "b", "front").share < bi.HIDDEN_SHARE


@pytest.mark.parametrize("offset, kind", [(0.05, bi.WITHIN_NOISE), (0.1, bi.WITHIN_NOISE), (0.3, bi.SEEN)])
def test_a_patch_on_a_panel_is_told_from_the_wall_as_the_depth_noise_allows(offset, kind):
    scene = scene_with(lambda m: [parallel_panel(m["b"], offset, 0.5)])
    view = bi.WallView(scene, "b", "front")
    assert 0.3 < view.share < 0.7
    got, why = view.distinct(in_camera(scene, (X_WALL - offset, 1.7, 1.0)))  # the panel's middle
    assert got == kind, why
    # What the fit's own 'behind' test can separate at 4 m: three depth std of the camera there.
    fx = float(scene.true_robot.camera("front").intrinsics_from_fov()[0, 0])
    three_sigma = 3.0 * float(scene.noise.sigma(np.array(X_WALL), fx))
    assert (offset < three_sigma) == (kind == bi.WITHIN_NOISE)
    gap_mm = float(why.split(" mm in front")[0].rsplit(" ", 1)[1])
    assert math.isclose(gap_mm, 1000 * offset, abs_tol=20.0), why  # along the axis, the camera pitched down a little


def test_a_patch_on_the_wall_itself_is_the_wall_and_one_behind_a_full_panel_is_hidden():
    half = scene_with(lambda m: [parallel_panel(m["b"], 0.2, 0.5)])
    got, _ = bi.WallView(half, "b", "front").distinct(in_camera(half, (X_WALL, 0.6, 1.0)))  # beside the panel
    assert got == bi.ON_WALL
    full = scene_with(lambda m: [parallel_panel(m["b"], 0.2, 1.0)])
    got, _ = bi.WallView(full, "b", "front").distinct(in_camera(full, (X_WALL - 0.2, 1.7, 1.0)))
    assert got == bi.HIDDEN
