"""Large maps: the spatial index and the vectorised pre-cull give exactly what a brute-force pass
over every plane gives, and a wall hidden behind a nearer wall is neither visible nor given pixels."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.sim.building import free_space_poses, room_grid_map
from drivers.sim.render import Box, SimScene, render_depth_metres
from robot.base.geometry import pose_to_T_ground_robot, transform_plane, transform_points
from robot.config import load_robot_config
from robot.localization.roi import CameraGrid, predict_plane_views, rasterize_views, shrink_rois
from robot.localization.visible_planes import visible_planes
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap, load_plane_map, make_plane
from robot.maps.visibility import clip_polygon, project

ROOT = Path(__file__).resolve().parents[1]
ROBOT = load_robot_config(ROOT / "config/robot.yaml")
MAX_RANGE = ROBOT.localizer.max_range
IMPORTED = ["fzk_haus_ground.yaml", "duplex_level1.yaml", "institute_ground.yaml"]


def brute_force_views(plane_map, T_ground_camera, grid, max_range):
    """Every plane, every polygon, clipped with the reference clipper: no index, no pre-cull."""
    T_camera_ground = np.linalg.inv(T_ground_camera)
    cam = T_ground_camera[:3, 3]
    out = []
    for i, plane in enumerate(plane_map.planes):
        if plane.normal @ cam + plane.d <= 1e-6:
            continue
        outlines, z_near = [], math.inf
        for poly in plane.polygons:
            clipped = clip_polygon(transform_points(T_camera_ground, poly), grid.frustum)
            if clipped is not None:
                z_near = min(z_near, float(clipped[:, 2].min()))
                outlines.append(project(grid.K, clipped))
        if outlines and z_near < max_range:
            out.append((i, transform_plane(T_ground_camera, plane.pi), outlines, z_near))
    return out


def brute_force_labels(views, grid):
    """Plane index of the nearest plane per grid pixel (-1: none) and its depth, float64 z-buffer."""
    h, w = grid.shape
    Kg = grid.K_grid
    x = (np.arange(w) - Kg[0, 2]) / Kg[0, 0]
    y = (np.arange(h) - Kg[1, 2]) / Kg[1, 1]
    zbuf = np.full((h, w), np.inf)
    label = np.full((h, w), -1)
    for i, n, outlines, _ in views:
        mask = np.zeros((h, w), np.uint8)
        polys = [np.rint(o / grid.stride * 16).astype(np.int32) for o in outlines]
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=4)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = -n[3] / (n[0] * x[None, :] + n[1] * y[:, None] + n[2])
        upd = (mask > 0) & (z > 0) & (z < zbuf)
        zbuf[upd] = z[upd]
        label[upd] = i
    return label, zbuf


def check_against_brute_force(plane_map, poses, strides=(4,)):
    index = PlaneIndex(plane_map)
    frames = seen = 0
    for stride in strides:
        for cam in ROBOT.cameras:
            grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, stride)
            for pose in poses:
                T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
                ref = brute_force_views(plane_map, T, grid, MAX_RANGE)
                views = predict_plane_views(plane_map, index.in_view(T, grid.frustum, MAX_RANGE), T, grid, MAX_RANGE)
                # The same planes, clipped to the same outlines.
                assert [v.plane_index for v in views] == [r[0] for r in ref], pose
                for v, (_, n, outlines, z_near) in zip(views, ref):
                    assert v.z_near == pytest.approx(z_near, abs=1e-9)
                    assert np.allclose(v.pi_camera, n, atol=1e-12)
                    assert len(v.outlines_px) == len(outlines)
                    for a, b in zip(v.outlines_px, outlines):
                        assert a.shape == b.shape and np.allclose(a, b, atol=1e-6)
                # The same owner for every pixel, except where two planes are at the same depth
                # (coplanar faces of neighbouring rooms meeting in the image): either is nearest.
                label = rasterize_views(views, grid)
                ids = np.array([v.plane_index for v in views] + [-1])[label]
                ref_ids, ref_z = brute_force_labels(ref, grid)
                differ = ids != ref_ids
                assert differ.mean() < 0.01, (pose, int(differ.sum()))
                Kg = grid.K_grid
                by_index = {v.plane_index: v.pi_camera for v in views}
                for r, c in np.argwhere(differ):
                    assert ids[r, c] >= 0 and ref_ids[r, c] >= 0, (pose, r, c)
                    n = by_index[ids[r, c]]
                    z = -n[3] / (n[0] * (c - Kg[0, 2]) / Kg[0, 0] + n[1] * (r - Kg[1, 2]) / Kg[1, 1] + n[2])
                    assert z == pytest.approx(ref_z[r, c], rel=1e-5), (pose, r, c)
                # A plane seen by one and not the other may only own such tied pixels.
                visible = {int(i) for i in np.unique(ids) if i >= 0}
                ref_visible = {int(i) for i in np.unique(ref_ids) if i >= 0}
                for i in visible ^ ref_visible:
                    assert differ[(ids == i) | (ref_ids == i)].all(), (pose, plane_map.planes[i].id)
                frames += 1
                seen += len(visible)
    return frames, seen


def random_poses(plane_map, n, seed):
    """Poses inside rooms and corridors, plus poses anywhere (in walls, outside the building)."""
    rng = np.random.default_rng(seed)
    poses = free_space_poses(plane_map, n, rng)
    lo, hi = plane_map.bounds()
    poses += [(float(rng.uniform(lo[0] - 2, hi[0] + 2)), float(rng.uniform(lo[1] - 2, hi[1] + 2)),
               float(rng.uniform(-math.pi, math.pi))) for _ in range(n // 4)]
    return poses


def test_culling_matches_brute_force_in_a_many_room_floor():
    plane_map = room_grid_map(8, 7, seed=3)
    assert len(plane_map) >= 250
    poses = random_poses(plane_map, 52, seed=1)
    assert len(poses) >= 60
    frames, seen = check_against_brute_force(plane_map, poses)
    assert frames == 2 * len(poses)
    assert seen > 2 * frames  # rooms with doors: several walls per frame, not an empty test


def test_culling_matches_brute_force_at_full_resolution():
    # visible_planes works on every pixel and up to 10 m: the pre-cull must hold there too.
    plane_map = room_grid_map(4, 3, seed=5)
    check_against_brute_force(plane_map, random_poses(plane_map, 8, seed=2), strides=(1,))


@pytest.mark.parametrize("name", IMPORTED)
def test_culling_matches_brute_force_in_imported_buildings(name):
    path = ROOT / "config/maps" / name
    if not path.exists():
        pytest.skip(f"{path} not there: import it with `robotctl map import-ifc` (needs the bim extra)")
    plane_map = load_plane_map(path)
    frames, seen = check_against_brute_force(plane_map, random_poses(plane_map, 50, seed=4))
    assert seen > frames


def test_index_candidates_are_the_planes_within_range():
    plane_map = room_grid_map(6, 5, seed=1)
    index = PlaneIndex(plane_map)
    rng = np.random.default_rng(0)
    lo = np.array([p.vertices[:, :2].min(axis=0) for p in plane_map.planes])
    hi = np.array([p.vertices[:, :2].max(axis=0) for p in plane_map.planes])
    for _ in range(50):
        p = rng.uniform(-3, 30, 2)
        r = rng.uniform(0.5, 8.0)
        gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        expected = np.flatnonzero(np.hypot(gap[:, 0], gap[:, 1]) <= r).tolist()
        assert index.candidates(p, r) == expected


def wall(pid, x, y0, y1, height=2.7, door=None):
    """A wall face at x, seen from -x (normal -x), from y1 down to y0; door = (ya, yb, top)."""
    if door is None:
        return make_plane(pid, [[[x, y1, 0], [x, y0, 0], [x, y0, height], [x, y1, height]]])
    ya, yb, top = door
    return make_plane(pid, [[[x, y1, 0], [x, yb, 0], [x, yb, height], [x, y1, height]],
                            [[x, ya, 0], [x, y0, 0], [x, y0, height], [x, ya, height]],
                            [[x, yb, top], [x, ya, top], [x, ya, height], [x, yb, height]]])


def rois(plane_map, pose, cam_name="front", stride=4, margin=0.0):
    cam = ROBOT.camera(cam_name)
    grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, stride)
    T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    views = predict_plane_views(plane_map, PlaneIndex(plane_map).in_view(T, grid.frustum, MAX_RANGE), T, grid, MAX_RANGE)
    label = rasterize_views(views, grid)
    shrink_rois(views, label, grid, lambda v: margin)
    return {v.plane_id: v for v in views}, grid, T


def test_a_wall_behind_a_nearer_wall_is_not_visible_and_gets_no_pixels():
    plane_map = PlaneMap([wall("near", 2.0, -4.0, 4.0), wall("far", 4.0, -1.5, 1.5)])
    views, grid, _ = rois(plane_map, (0.0, 0.0, 0.0))
    # The far wall is inside the frustum and within range: only occlusion hides it.
    assert set(views) == {"near", "far"}
    assert views["far"].pixels == 0 and len(views["far"].roi_rows) == 0
    assert views["far"].box[2] < views["far"].box[0]  # recognised as hidden without rasterizing it
    assert views["near"].pixels > 0
    assert [p["id"] for p in visible_planes(plane_map, ROBOT.camera("front"), (0.0, 0.0, 0.0))] == ["near"]


def test_the_far_walls_roi_never_takes_the_near_walls_pixels():
    # Through a door in the near wall the camera sees part of the far wall.
    near = wall("near", 2.0, -4.0, 4.0, door=(-0.3, 0.6, 2.0))
    far = wall("far", 4.0, -3.0, 3.0)
    plane_map = PlaneMap([near, far])
    pose = (0.3, 0.1, 0.15)
    cam = ROBOT.camera("front")
    for margin in (0.0, 12.0):
        views, grid, T = rois(plane_map, pose, margin=margin)
        rr, cc = views["far"].roi_rows, views["far"].roi_cols
        assert views["far"].pixels > 0 and len(rr) > 0
        near_px = set(zip(views["near"].roi_rows.tolist(), views["near"].roi_cols.tolist()))
        assert near_px.isdisjoint(zip(rr.tolist(), cc.tolist()))
        # Independent check with the simulator's renderer (full resolution): the ray of a far-ROI
        # pixel never meets the near wall; once shrunk by a margin, every one meets the far wall.
        depth = render_depth_metres(SimScene(plane_map, floor=False, backdrop=False), T, grid.K, cam.width, cam.height)
        z = depth[rr * grid.stride, cc * grid.stride]
        K = grid.K
        ray = np.stack([(cc * grid.stride - K[0, 2]) / K[0, 0], (rr * grid.stride - K[1, 2]) / K[1, 1], np.ones(len(rr))])
        z_near, z_far = (-n[3] / (n[:3] @ ray) for n in (transform_plane(T, near.pi), transform_plane(T, far.pi)))
        assert not np.isclose(z, z_near, rtol=1e-6).any()
        if margin > 0:
            assert np.allclose(z, z_far, rtol=1e-6)
        else:
            assert np.isclose(z, z_far, rtol=1e-6).mean() > 0.95  # the rest: rounding at the door's edges
    # With a margin the far ROI shrinks away from the door's edges (a pose error could move them).
    assert len(rois(plane_map, pose, margin=12.0)[0]["far"].roi_rows) < len(rois(plane_map, pose)[0]["far"].roi_rows)


def test_a_long_wall_both_nearer_and_farther_than_another_keeps_its_near_pixels():
    # A wall receding to the left passes in front of a short wall at one end and behind it at the
    # other: drawing nearest-first must still give each pixel to the nearer surface.
    slanted = make_plane("slanted", [[[3.5, 3.0, 0], [1.0, -1.0, 0], [1.0, -1.0, 2.7], [3.5, 3.0, 2.7]]])
    short = wall("short", 2.2, -0.5, 1.6)
    plane_map = PlaneMap([short, slanted])
    views, grid, T = rois(plane_map, (0.0, 0.0, 0.0))
    assert views["short"].pixels > 0 and views["slanted"].pixels > 0
    cam = ROBOT.camera("front")
    depth = render_depth_metres(SimScene(plane_map, floor=False, backdrop=False), T, grid.K, cam.width, cam.height)
    for pid, v in rois(plane_map, (0.0, 0.0, 0.0), margin=8.0)[0].items():
        n = v.pi_camera
        K = grid.K
        rr, cc = v.roi_rows, v.roi_cols
        ray = np.stack([(cc * grid.stride - K[0, 2]) / K[0, 0], (rr * grid.stride - K[1, 2]) / K[1, 1], np.ones(len(rr))])
        assert np.allclose(depth[rr * grid.stride, cc * grid.stride], -n[3] / (n[:3] @ ray), rtol=1e-6), pid


def test_the_renderer_never_draws_the_back_of_a_map_face():
    # A wall 0.2 m thick with a door: its two faces are two planes, each seen from its own room.
    # Looking obliquely through the door, rays leave the near face's opening and meet the far
    # face's plane beside its opening, from behind: a real camera sees the door's reveal there
    # (not in the map), never a surface 0.2 m behind the near face.
    near = wall("near", 2.0, -4.0, 4.0, door=(-0.3, 0.6, 2.0))
    other = wall("other_side", 2.2, -4.0, 4.0, door=(-0.3, 0.6, 2.0))
    other = make_plane("other_side", [poly[::-1] for poly in other.polygons])  # faces +x, into the next room
    far = wall("far", 5.0, -4.0, 4.0)
    plane_map = PlaneMap([near, other, far])
    assert other.normal[0] > 0.99
    cam = ROBOT.camera("front")
    K = cam.intrinsics_from_fov()
    T = pose_to_T_ground_robot(0.4, 0.1, 0.1) @ cam.T_robot_camera
    depth = render_depth_metres(SimScene(plane_map, floor=False, backdrop=False), T, K, cam.width, cam.height)
    rr, cc = np.nonzero(depth > 0)
    ray = np.stack([(cc - K[0, 2]) / K[0, 0], (rr - K[1, 2]) / K[1, 1], np.ones(len(rr))])
    z = {p.id: -n[3] / (n[:3] @ ray) for p in plane_map.planes for n in [transform_plane(T, p.pi)]}
    on = {pid: np.isclose(depth[rr, cc], zp, rtol=1e-6) for pid, zp in z.items()}
    assert on["near"].sum() > 1000 and on["far"].sum() > 1000  # the wall, and the next room through the door
    assert not on["other_side"].any()
    # Every pixel shows the near wall or, through the door, the far one: beside the opening,
    # where a double-sided renderer shows the other face from behind, the far wall too.
    assert (on["far"] | on["near"]).all()


def test_a_one_sided_face_seen_from_behind_is_not_drawn_but_clutter_is_from_both_sides():
    cam = ROBOT.camera("front")
    K = cam.intrinsics_from_fov()
    T = pose_to_T_ground_robot(0.0, 0.0, 0.0) @ cam.T_robot_camera
    facing_away = make_plane("away", [[[2.0, -1.0, 0], [2.0, 1.0, 0], [2.0, 1.0, 1.0], [2.0, -1.0, 1.0]]])
    assert facing_away.normal[0] > 0.99  # observable from +x only
    scene = SimScene(PlaneMap([facing_away]), floor=False, backdrop=False)
    assert not (render_depth_metres(scene, T, K, cam.width, cam.height) > 0).any()
    boxed = SimScene(PlaneMap([facing_away]), clutter=[Box(1.0, 0.0, 0.2, 0.2, 0.3)], floor=False, backdrop=False)
    assert (render_depth_metres(boxed, T, K, cam.width, cam.height) > 0).sum() > 100
