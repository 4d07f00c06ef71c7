"""Extended image coordinates, exact frustum clipping (incl. fill-the-view) and occlusion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.config import load_robot_config
from robot.localization.visible_planes import visible_planes
from robot.maps.plane_map import PlaneMap, make_plane
from robot.maps.visibility import Region, classify_points, clip_polygon, clip_vertex_list, extended_image_coords, frustum_planes

HFOV, VFOV = math.radians(87), math.radians(58)


def test_classification_regions():
    pts = np.array([[0, 0, 1.0], [0.5, 0, 1.0], [2.0, 0, 1.0], [0, 1.0, 1.0], [0, 0, -1.0], [0.3, 0.2, 0.0]])
    reg = classify_points(pts, HFOV, VFOV)
    assert list(reg) == [Region.VFR, Region.VFR, Region.POVR, Region.POVR, Region.NR, Region.NR]
    u, v = extended_image_coords(np.array([[math.tan(HFOV / 2), 0, 1.0]]), HFOV, VFOV)
    assert u[0] == np.float64(1.0) or math.isclose(u[0], 1.0)
    # Behind the camera the coordinates stay finite (angular, not perspective).
    u, v = extended_image_coords(np.array([[1.0, 1.0, -1.0]]), HFOV, VFOV)
    assert np.isfinite(u).all() and abs(u[0]) > 1


def _K():
    cam = load_robot_config("config/robot.yaml").camera("front")
    return cam.intrinsics_from_fov(), cam.width, cam.height


def test_clip_polygon_filling_the_whole_view():
    K, w, h = _K()
    big = np.array([[-50, -50, 0.5], [50, -50, 0.5], [50, 50, 0.5], [-50, 50, 0.5]], float)
    # Every vertex and every edge is outside the view: the paper's vertex/edge test finds nothing.
    assert (classify_points(big, HFOV, VFOV) == Region.POVR).all()
    clipped = clip_polygon(big, frustum_planes(K, w, h))
    assert clipped is not None
    px = clipped[:, :2] / clipped[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    # The clipped polygon is the image rectangle itself.
    assert np.allclose(px.min(axis=0), [-0.5, -0.5], atol=1e-6)
    assert np.allclose(px.max(axis=0), [w - 0.5, h - 0.5], atol=1e-6)


def test_clip_polygon_behind_and_beside():
    K, w, h = _K()
    fr = frustum_planes(K, w, h)
    behind = np.array([[-1, -1, -0.5], [1, -1, -0.5], [1, 1, -0.5]], float)
    beside = np.array([[5, 0, 1.0], [6, 0, 1.0], [6, 1, 1.0]], float)
    assert clip_polygon(behind, fr) is None
    assert clip_polygon(beside, fr) is None
    # A polygon crossing the camera plane keeps only its front part.
    crossing = np.array([[-0.1, 0, -1.0], [0.1, 0, -1.0], [0.1, 0, 2.0], [-0.1, 0, 2.0]], float)
    c = clip_polygon(crossing, fr)
    assert c is not None and c[:, 2].min() >= 0.01 - 1e-9


def _area_xy(poly):
    x, y = np.asarray(poly)[:, 0], np.asarray(poly)[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def test_clip_keeps_the_right_part_of_a_concave_wall_with_a_doorway():
    # A 4 m x 2 m wall 2 m ahead with a 1 m x 1 m doorway cut from its bottom edge: a U-shaped
    # polygon. The half-space x >= 0 keeps the right half: 2 m x 2 m less half the doorway.
    wall = [[-2.0, -1.0, 2.0], [2.0, -1.0, 2.0], [2.0, 1.0, 2.0], [0.5, 1.0, 2.0],
            [0.5, 0.0, 2.0], [-0.5, 0.0, 2.0], [-0.5, 1.0, 2.0], [-2.0, 1.0, 2.0]]
    right = clip_vertex_list(wall, [[1.0, 0.0, 0.0, 0.0]])
    assert right is not None and min(p[0] for p in right) >= 0.0
    assert _area_xy(right) == pytest.approx(4.0 - 0.5)
    assert np.allclose(clip_polygon(np.array(wall), np.array([[1.0, 0.0, 0.0, 0.0]])), right)
    # Both half-spaces 0 <= x <= 0.25 run through the doorway: only the wall above it is left.
    strip = clip_vertex_list(wall, [[1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.25]])
    assert _area_xy(strip) == pytest.approx(0.25 * 1.0)


def test_clip_leaves_a_polygon_inside_the_view_as_it_is():
    K, w, h = _K()
    inside = np.array([[-0.2, -0.1, 2.0], [0.2, -0.1, 2.0], [0.2, 0.1, 2.0]])
    assert np.array_equal(clip_polygon(inside, frustum_planes(K, w, h)), inside)
    assert clip_vertex_list(inside.tolist(), frustum_planes(K, w, h).tolist()) == inside.tolist()


def test_clipping_against_only_the_crossed_planes_is_the_full_clip():
    # What predict_plane_views relies on: planes no vertex is outside of change nothing.
    K, w, h = _K()
    fr = frustum_planes(K, w, h)
    rng = np.random.default_rng(3)
    clipped_some = 0
    for _ in range(300):
        centre = rng.uniform([-3.0, -2.0, -1.0], [3.0, 2.0, 6.0])
        quad = centre + rng.normal(0.0, 1.5, (4, 3))
        outside = (quad @ fr[:, :3].T + fr[:, 3] < 0).any(axis=0)
        full = clip_vertex_list(quad.tolist(), fr.tolist())
        some = clip_vertex_list(quad.tolist(), fr[outside].tolist())
        assert (full is None) == (some is None)
        if full is None:
            continue
        assert np.allclose(full, some, atol=1e-12)
        assert (np.asarray(full) @ fr[:, :3].T + fr[:, 3] >= -1e-9).all()
        clipped_some += bool(outside.any())
    assert clipped_some > 30


def test_robot_close_to_a_large_wall_sees_it():
    robot = load_robot_config("config/robot.yaml")
    wall = make_plane("big", [[[0.3, 50, -20], [0.3, -50, -20], [0.3, -50, 20], [0.3, 50, 20]]])
    planes = visible_planes(PlaneMap([wall]), robot.camera("front"), (0.0, 0.0, 0.0))
    assert [p["id"] for p in planes] == ["big"]
    assert planes[0]["pixels"] == 848 * 480


def test_occlusion_hides_a_wall_behind_a_nearer_wall():
    robot = load_robot_config("config/robot.yaml")
    near = make_plane("near", [[[1.0, 0.3, 0], [1.0, -0.3, 0], [1.0, -0.3, 1.0], [1.0, 0.3, 1.0]]])
    far = make_plane("far", [[[3.0, 0.4, 0], [3.0, -0.4, 0], [3.0, -0.4, 0.5], [3.0, 0.4, 0.5]]])
    wide = make_plane("wide", [[[3.0, 3.0, 0], [3.0, -3.0, 0], [3.0, -3.0, 0.5], [3.0, 3.0, 0.5]]])
    cam = robot.camera("front")
    ids = [p["id"] for p in visible_planes(PlaneMap([near, far]), cam, (0.0, 0.0, 0.0))]
    assert ids == ["near"]  # entirely behind the nearer wall
    res = {p["id"]: p["pixels"] for p in visible_planes(PlaneMap([near, wide]), cam, (0.0, 0.0, 0.0))}
    alone = visible_planes(PlaneMap([wide]), cam, (0.0, 0.0, 0.0))[0]["pixels"]
    # Partly hidden: the far wall keeps only the pixels the near wall does not cover.
    assert 0 < res["wide"] < alone
    assert res["near"] > 0
