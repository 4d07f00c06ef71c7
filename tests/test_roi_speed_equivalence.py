"""The ROI stage's fast paths give exactly what the plain code gives.

``robot.localization.roi`` and ``robot.maps.plane_index`` reuse buffers between frames, share
per-grid constants, clip in tuned Python and fold several numpy steps into one. The reference
below is the stage as it was written before that: a fresh depth buffer and label image per
call, one numpy step per idea, the crop around each plane reaching its margin beyond its box.
Every output must be identical, not close: views, boxes, nearest depths, pixel counts, the ROIs'
row and column arrays, and the label image.
"""

from __future__ import annotations

import itertools
import math
import threading
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
import pytest

import robot.localization.localizer as localizer_module
from drivers.sim.building import free_space_poses
from robot.base.geometry import pose_to_T_ground_robot
from robot.config import load_robot_config
from robot.localization.localizer import Localizer, coarse_covariance
from robot.localization.roi import CameraGrid, PlaneView, camera_views, predict_plane_views, predict_views, rasterize_views, shrink_rois
from robot.maps.plane_index import BACK_FACE_EPS, PlaneIndex, packed_polygons
from robot.maps.plane_map import load_plane_map
from robot.maps.visibility import NEAR_PLANE

ROOT = Path(__file__).resolve().parents[1]
ROBOT = load_robot_config(ROOT / "config/robot.yaml")
MAX_RANGE = ROBOT.localizer.max_range
COVARIANCES = {"tracking": coarse_covariance(0.02, math.radians(1.0)), "cold": coarse_covariance(0.1, math.radians(10.0))}
SHIFT = 4  # fillPoly's fixed-point bits, as in roi.py


# -- the reference: the stage written plainly ------------------------------------------------------


def ref_clip(pts: List[List[float]], planes) -> Optional[List[List[float]]]:
    for a, b, c, d in planes:
        s = [a * x + b * y + c * z + d for x, y, z in pts]
        if max(s) < 0:
            return None
        out = []
        n = len(pts)
        for i in range(n):
            j = i + 1 if i + 1 < n else 0
            si, sj = s[i], s[j]
            if si >= 0:
                out.append(pts[i])
            if (si >= 0) != (sj >= 0):
                t = si / (si - sj)
                p, q = pts[i], pts[j]
                out.append([p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), p[2] + t * (q[2] - p[2])])
        pts = out
    return pts if len(pts) >= 3 else None


def ref_in_view(index: PlaneIndex, T_ground_camera: np.ndarray, frustum: np.ndarray, max_range: float) -> List[int]:
    pk = index.packed
    corners_C, planes_C = index._view_bounds(frustum, max_range)
    R, t = T_ground_camera[:3, :3], T_ground_camera[:3, 3]
    xy = corners_C @ R[:2].T + t[:2]
    polys = index._polygons.query(xy.min(axis=0).tolist(), xy.max(axis=0).tolist())
    if len(polys) == 0:
        return []
    n_G = planes_C[:, :3] @ R.T
    d_G = planes_C[:, 3] - n_G @ t
    reach = pk.box6[polys] @ np.vstack([n_G.T, np.abs(n_G).T]) + d_G
    planes = np.unique(pk.plane_of[polys[(reach >= -1e-9).all(axis=1)]])
    pi = pk.planes[planes]
    return planes[pi[:, :3] @ t + pi[:, 3] > BACK_FACE_EPS - 1e-9].tolist()


def ref_grid_box(u0, v0, u1, v1, grid):
    h, w = grid.shape
    s = grid.stride
    return (max(math.floor(u0 / s), 0), max(math.floor(v0 / s), 0),
            min(math.ceil(u1 / s), w - 1), min(math.ceil(v1 / s), h - 1))


def ref_predict(plane_map, candidates, T_ground_camera, grid, max_range) -> List[PlaneView]:
    pk = packed_polygons(plane_map)
    cand = np.asarray(candidates, dtype=np.intp).reshape(-1)
    pi = pk.planes[cand]
    front = np.einsum("ij,j->i", pi[:, :3], T_ground_camera[:3, 3]) + pi[:, 3] > BACK_FACE_EPS
    facing = cand[front].tolist()
    pi_camera = np.einsum("ij,jk->ik", pi[front], T_ground_camera)
    if not facing:
        return []
    R_T = T_ground_camera[:3, :3].T
    t_C = -R_T @ T_ground_camera[:3, 3]
    V = np.concatenate([pk.plane_vertices[i] for i in facing])
    counts = [c for i in facing for c in pk.plane_counts[i]]
    plane_of = [i for i in facing for _ in pk.plane_counts[i]]
    first = [0, *itertools.accumulate(counts[:-1])]
    P = np.einsum("ij,kj->ik", V, R_T) + t_C
    # Frustum: drop polygons all outside one plane, clip those crossing some.
    frustum = grid.frustum
    first_vertex = np.array(first, np.intp)
    outside = np.einsum("ij,kj->ik", P, frustum[:, :3]) < -frustum[:, 3]
    gone = np.logical_and.reduceat(outside, first_vertex, axis=0).any(axis=1).tolist()
    cross = np.bitwise_or.reduceat(outside @ (1 << np.arange(len(frustum))), first_vertex).tolist()
    P_list, frustum_list = P.tolist(), frustum.tolist()
    kept, clipped_pts, clipped_starts = [], [], []
    for k, (a, n, bits) in enumerate(zip(first, counts, cross)):
        if gone[k]:
            continue
        if not bits:
            kept.append((k, k))
            continue
        clipped = ref_clip(P_list[a:a + n], [f for j, f in enumerate(frustum_list) if bits >> j & 1])
        if clipped is not None:
            kept.append((k, len(counts) + len(clipped_starts)))
            clipped_starts.append(len(P) + len(clipped_pts))
            clipped_pts += clipped
    if not kept:
        return []
    Q = np.vstack([P, clipped_pts]) if clipped_pts else P
    starts = np.concatenate([first_vertex, np.array(clipped_starts, np.intp)])
    # Projection, fixed point, and per plane its outlines, nearest depth and box.
    K = grid.K
    px = Q[:, :2] / np.maximum(Q[:, 2:], NEAR_PLANE)
    px *= (K[0, 0], K[1, 1])
    px += K[:2, 2]
    fixed = np.rint(px * (float(1 << SHIFT) / grid.stride)).astype(np.int32)
    z_min = np.minimum.reduceat(Q[:, 2], starts).tolist()
    px_lo = np.minimum.reduceat(px, starts).tolist()
    px_hi = np.maximum.reduceat(px, starts).tolist()
    seg_end = np.append(starts[1:], len(Q)).tolist()
    seg = starts.tolist()
    row = {c: r for r, c in enumerate(facing)}
    views = []
    for idx, group in itertools.groupby(kept, key=lambda kj: plane_of[kj[0]]):
        outlines, fixed_outlines, z_near = [], [], math.inf
        u0 = v0 = math.inf
        u1 = v1 = -math.inf
        for _, j in group:
            outlines.append(px[seg[j]:seg_end[j]])
            fixed_outlines.append(fixed[seg[j]:seg_end[j]])
            z_near = min(z_near, z_min[j])
            (lo_u, lo_v), (hi_u, hi_v) = px_lo[j], px_hi[j]
            u0, v0, u1, v1 = min(u0, lo_u), min(v0, lo_v), max(u1, hi_u), max(v1, hi_v)
        if z_near < max_range:
            views.append(PlaneView(idx, plane_map.planes[idx].id, pi_camera[row[idx]], outlines, z_near,
                                   box=ref_grid_box(u0, v0, u1, v1, grid), fixed_px=(grid.stride, fixed_outlines)))
    return views


def ref_rasterize(views: List[PlaneView], grid: CameraGrid) -> np.ndarray:
    h, w = grid.shape
    ibuf = np.zeros((h, w), dtype=np.float64)
    label = np.full((h, w), -1, dtype=np.int32)
    cols, rows = grid.rays
    one = 1 << SHIFT
    drawn = False
    for k in sorted(range(len(views)), key=lambda j: views[j].z_near):
        view = views[k]
        if view.box is None:
            pts = np.vstack(view.outlines_px)
            view.box = ref_grid_box(*pts.min(axis=0).tolist(), *pts.max(axis=0).tolist(), grid)
        c0, r0, c1, r1 = view.box
        n = view.pi_camera
        if c1 < c0 or r1 < r0 or n[3] == 0:
            view.box = (0, 0, -1, -1)
            continue
        a, b, c = -n[0] / n[3], -n[1] / n[3], -n[2] / n[3]
        ia, ib = max(a * cols[c0], a * cols[c1]), max(b * rows[r0], b * rows[r1])
        top = ia + ib + c + 1e-6 * (abs(a) * max(-cols[0], cols[-1]) + abs(b) * max(-rows[0], rows[-1]) + abs(c))
        isub = ibuf[r0:r1 + 1, c0:c1 + 1]
        if top <= 0 or (drawn and top <= isub.min()):
            view.box = (0, 0, -1, -1)
            continue
        if view.fixed_px is not None and view.fixed_px[0] == grid.stride:
            polys = view.fixed_px[1]
        else:
            polys = [np.rint(o * (float(1 << SHIFT) / grid.stride)).astype(np.int32) for o in view.outlines_px]
        mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        cv2.fillPoly(mask, polys, 1, lineType=cv2.LINE_8, shift=SHIFT, offset=(-c0 * one, -r0 * one))
        # Inverse depth in float64, a x + b y first, then c (the product's order of operations).
        inv = (a * cols[c0:c1 + 1])[None, :] + (b * rows[r0:r1 + 1])[:, None]
        inv += c
        inv *= mask
        upd = inv > isub
        np.maximum(isub, inv, out=isub)
        label[r0:r1 + 1, c0:c1 + 1][upd] = k
        drawn = True
    return label


def ref_shrink(views: List[PlaneView], label: np.ndarray, grid: CameraGrid, margin_for, pad: int = 0) -> None:
    H, W = label.shape
    for k, view in enumerate(views):
        view.roi_rows = view.roi_cols = np.zeros(0, np.intp)
        view.pixels = 0
        c0, r0, c1, r1 = view.box if view.box is not None else (0, 0, W - 1, H - 1)
        i0, j0, i1, j1 = max(r0, pad), max(c0, pad), min(r1, H - 1 - pad), min(c1, W - 1 - pad)
        if i1 < i0 or j1 < j0:
            continue
        margin = float(margin_for(view))
        r = int(math.ceil(margin / grid.stride))
        r0, c0 = max(r0 - r, 0), max(c0 - r, 0)
        own = (label[r0:r1 + r + 1, c0:c1 + r + 1] == k).view(np.uint8)
        inner = (slice(i0 - r0, i1 + 1 - r0), slice(j0 - c0, j1 + 1 - c0))
        view.pixels = int(np.count_nonzero(own[inner]))
        if view.pixels == 0:
            continue
        view.margin_px = margin
        if r > 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
            own = cv2.erode(own, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        found = cv2.findNonZero(np.ascontiguousarray(own[inner]))
        if found is not None:
            view.roi_rows, view.roi_cols = found[:, 0, 1] + (i0 - pad), found[:, 0, 0] + (j0 - pad)


def ref_predict_views(plane_map, index, T_ground_camera, grid, max_range) -> List[PlaneView]:
    """roi.predict_views written plainly: the reference in_view, then the reference prediction."""
    return ref_predict(plane_map, ref_in_view(index, T_ground_camera, grid.frustum, max_range), T_ground_camera, grid,
                       max_range)


# -- comparing -------------------------------------------------------------------------------------


def same_array(a: np.ndarray, b: np.ndarray) -> bool:
    return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape \
        and np.array_equal(a, b)


def assert_same_views(got: List[PlaneView], ref: List[PlaneView], where) -> None:
    assert [v.plane_index for v in got] == [v.plane_index for v in ref], where
    for g, r in zip(got, ref):
        assert g.plane_id == r.plane_id, where
        assert type(g.plane_index) is int, where
        assert g.z_near == r.z_near and g.box == r.box and g.pixels == r.pixels and g.margin_px == r.margin_px, where
        assert same_array(g.pi_camera, r.pi_camera), where
        assert len(g.outlines_px) == len(r.outlines_px), where
        assert all(same_array(a, b) for a, b in zip(g.outlines_px, r.outlines_px)), where
        assert g.fixed_px[0] == r.fixed_px[0] and all(same_array(a, b) for a, b in zip(g.fixed_px[1], r.fixed_px[1])), where
        if r.roi_rows is None:
            assert g.roi_rows is None and g.roi_cols is None, where
        else:
            assert same_array(g.roi_rows, r.roi_rows) and same_array(g.roi_cols, r.roi_cols), where


def reference_plane_rois(loc: Localizer, geo, T_ground_camera, cov, monkeypatch) -> List[PlaneView]:
    """What Localizer.plane_rois gives with the reference stage in place of roi.py's and the index's."""
    with monkeypatch.context() as m:
        m.setattr(localizer_module, "predict_views", ref_predict_views)
        m.setattr(localizer_module, "rasterize_views", ref_rasterize)
        m.setattr(localizer_module, "shrink_rois", ref_shrink)
        return loc.plane_rois(geo, T_ground_camera, cov)


MAPS: Dict[str, object] = {}


def plane_map_and_poses(name: str, n: int, seed: int) -> Tuple[object, List[Tuple[float, float, float]]]:
    """A map and random poses in it: inside rooms (free space) and anywhere around its bounds
    (behind walls, outside the building, facing every way)."""
    if name not in MAPS:
        MAPS[name] = load_plane_map(ROOT / "config/maps" / f"{name}.yaml")
    plane_map = MAPS[name]
    rng = np.random.default_rng(seed)
    poses = free_space_poses(plane_map, n // 2, rng) if name != "paper_arena" else []
    lo, hi = plane_map.bounds()
    while len(poses) < n:
        x, y = rng.uniform(lo[:2] - 0.5, hi[:2] + 0.5)
        poses.append((float(x), float(y), float(rng.uniform(-math.pi, math.pi))))
    return plane_map, poses


@pytest.mark.parametrize("name, seed", [("paper_arena", 1), ("institute_ground", 2)])
def test_plane_rois_identical_to_reference(name, seed, monkeypatch):
    plane_map, poses = plane_map_and_poses(name, 30, seed)
    loc = Localizer(ROBOT, plane_map)
    seen = rois = 0
    for pose in poses:  # frames one after another on the same grids: the reused buffers are reset
        for cam in ROBOT.cameras:
            geo = loc.frame_geometry(cam, cam.intrinsics_from_fov(), cam.width, cam.height)
            T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            for label, cov in COVARIANCES.items():
                got = loc.plane_rois(geo, T, cov)
                ref = reference_plane_rois(loc, geo, T, cov, monkeypatch)
                assert_same_views(got, ref, (name, pose, cam.name, label))
                seen += len(ref)
                rois += sum(len(v.roi_rows) > 0 for v in ref)
    assert seen > 50 and rois > 30  # the poses exercised the stage, not just empty views


@pytest.mark.parametrize("name, seed, stride", [("paper_arena", 3, 4), ("institute_ground", 4, 4), ("institute_ground", 5, 2)])
def test_stages_identical_to_reference(name, seed, stride):
    """in_view, predict_plane_views, the label image of rasterize_views and shrink_rois one by one,
    on an unpadded grid and (with the margin reaching past the border) a padded one."""
    plane_map, poses = plane_map_and_poses(name, 24, seed)
    index = PlaneIndex(plane_map)
    for cam in ROBOT.cameras:
        K = cam.intrinsics_from_fov()
        grids = [CameraGrid(K, cam.width, cam.height, stride)]
        pad = 6
        Kp = K.copy()
        Kp[:2, 2] += pad * stride
        h, w = grids[0].shape
        grids.append(CameraGrid(Kp, (w + 2 * pad) * stride, (h + 2 * pad) * stride, stride))
        for k, pose in enumerate(poses):
            T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            for g, grid in enumerate(grids):
                where = (name, pose, cam.name, g)
                cands = index.in_view(T, grid.frustum, MAX_RANGE)
                assert cands == ref_in_view(index, T, grid.frustum, MAX_RANGE), where
                got = predict_plane_views(plane_map, cands, T, grid, MAX_RANGE)
                ref = ref_predict(plane_map, cands, T, grid, MAX_RANGE)
                assert_same_views(got, ref, where)
                assert_same_views(predict_views(plane_map, index, T, grid, MAX_RANGE), ref, where)
                if k % 3 == 0:  # also views whose box is yet unknown
                    for v in got + ref:
                        v.box = None
                label = rasterize_views(got, grid)
                ref_label = ref_rasterize(ref, grid)
                assert same_array(label, ref_label), where
                assert [v.box for v in got] == [v.box for v in ref], where

                def margin(v):
                    return 3.0 + 30.0 / max(v.z_near, 0.3)

                shrink_rois(got, label, grid, margin, pad * g)
                ref_shrink(ref, ref_label, grid, margin, pad * g)
                assert_same_views(got, ref, where)


def test_camera_views_identical_to_reference():
    """The report path (a fresh grid per call, full resolution) gives the plain label image."""
    plane_map, poses = plane_map_and_poses("institute_ground", 6, 6)
    index = PlaneIndex(plane_map)
    for pose in poses:
        for cam in ROBOT.cameras:
            views, label, grid = camera_views(plane_map, index, cam, pose, 10.0)
            T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            ref = ref_predict(plane_map, ref_in_view(index, T, grid.frustum, 10.0), T, grid, 10.0)
            assert same_array(label, ref_rasterize(ref, grid)), pose
            assert_same_views(views, ref, pose)


def test_threads_sharing_grids_get_their_own_buffers():
    """Two threads rasterizing on the same grids at once (buffers are per thread): each result is
    the reference's."""
    plane_map, poses = plane_map_and_poses("institute_ground", 24, 7)
    index = PlaneIndex(plane_map)
    grids = {cam.name: CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, 4) for cam in ROBOT.cameras}
    jobs = [(cam, pose) for pose in poses for cam in ROBOT.cameras]
    failures: List[str] = []
    start = threading.Barrier(2)

    def work(order):
        start.wait()
        for _ in range(3):
            for cam, pose in order:
                grid = grids[cam.name]
                T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
                cands = index.in_view(T, grid.frustum, MAX_RANGE)
                views = predict_plane_views(plane_map, cands, T, grid, MAX_RANGE)
                label = rasterize_views(views, grid).copy()
                shrink_rois(views, label, grid, lambda v: 20.0)
                ref = ref_predict(plane_map, cands, T, grid, MAX_RANGE)
                ref_label = ref_rasterize(ref, grid)
                ref_shrink(ref, ref_label, grid, lambda v: 20.0)
                if not same_array(label, ref_label):
                    failures.append(f"label {cam.name} {pose}")
                try:
                    assert_same_views(views, ref, pose)
                except AssertionError:
                    failures.append(f"views {cam.name} {pose}")

    threads = [threading.Thread(target=work, args=(order,)) for order in (jobs, jobs[::-1])]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures, failures[:5]


def test_label_image_is_reused_and_reset():
    """The label image is the grid's buffer: a later frame on the same grid overwrites it, and what
    an earlier frame drew is gone from the next one."""
    plane_map, poses = plane_map_and_poses("paper_arena", 12, 8)
    index = PlaneIndex(plane_map)
    cam = ROBOT.cameras[0]
    grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, 4)
    labels = []
    for pose in poses:
        T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
        cands = index.in_view(T, grid.frustum, MAX_RANGE)
        label = rasterize_views(predict_plane_views(plane_map, cands, T, grid, MAX_RANGE), grid)
        assert same_array(label, ref_rasterize(ref_predict(plane_map, cands, T, grid, MAX_RANGE), grid)), pose
        labels.append(label)
    assert all(a is labels[0] for a in labels)
    # No views: all -1, whatever was drawn before.
    assert (rasterize_views([], grid) == -1).all()


def _floor_or_map_and_poses(name: str, seed: int) -> Tuple[object, List[Tuple[float, float, float]]]:
    """40 poses in and around a map: the 288-plane floor of alike rooms (``room_grid``, whose
    cells hold a dozen polygons, most crossing a view's frustum) or a map of config/maps."""
    from drivers.sim.building import grid_for_planes, room_grid_map

    if name != "room_grid":
        return plane_map_and_poses(name, 40, seed)
    plane_map = room_grid_map(*grid_for_planes(288), seed=288)
    rng = np.random.default_rng(seed)
    lo, hi = plane_map.bounds()
    return plane_map, [(float(x), float(y), float(rng.uniform(-math.pi, math.pi)))
                       for x, y in rng.uniform(lo[:2] - 0.5, hi[:2] + 0.5, (40, 2))]


def _grids(cam):
    """(stride, pad, grid): the relocalizer's coarse grid, the localizer's and a padded one."""
    K = cam.intrinsics_from_fov()
    for stride, pad in ((32, 0), (4, 0), (4, 6)):
        Kp = K.copy()
        Kp[:2, 2] += pad * stride
        yield stride, pad, CameraGrid(Kp, cam.width + 2 * pad * stride, cam.height + 2 * pad * stride, stride)


@pytest.mark.parametrize("name", ["room_grid", "institute_ground", "paper_arena"])
def test_the_compiled_outlines_are_the_numpy_outlines(name):
    """fit_kernels.outlines (clip, project, per-plane box) against the numpy code it replaces, on
    the same stacked polygons: poses anywhere in and around a floor of alike rooms (a dozen
    polygons per view, most crossing the frustum), a building and the arena, on the relocalizer's
    coarse grid, the localizer's and a padded one."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (the perf extra)")
    from robot.localization import fit_kernels, roi

    if fit_kernels.backend() != "numba":
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy)")
    plane_map, poses = _floor_or_map_and_poses(name, 9 if name == "room_grid" else 6)
    index = PlaneIndex(plane_map)
    pk = packed_polygons(plane_map)
    clipped = kept = 0
    for cam in ROBOT.cameras:
        for stride, pad, grid in _grids(cam):
            consts = grid._per_frame()
            for pose in poses:
                T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
                facing, _ = roi._facing_camera(pk, index.in_view(T, grid.frustum, MAX_RANGE), T)
                if not facing:
                    continue
                polys = roi._stack_in_camera(pk, facing, T)
                ref = roi._outlines(polys, consts, grid, MAX_RANGE)
                got = roi._outlines_compiled(polys, consts, grid, MAX_RANGE)
                where = (name, pose, cam.name, stride, pad)
                assert [g[0] for g in got] == [r[0] for r in ref], where
                for g, r in zip(got, ref):
                    assert type(g[0]) is int and g[3] == r[3] and g[4] == r[4], where
                    assert len(g[1]) == len(r[1]) and len(g[2]) == len(r[2]), where
                    assert all(same_array(a, b) for a, b in zip(g[1], r[1])), where
                    assert all(same_array(a, b) for a, b in zip(g[2], r[2])), where
                c = roi._clip_to_frustum(polys, consts)
                clipped += sum(1 for k, j in c.kept if j != k)
                kept += len(ref)
    assert kept > 100 and clipped > 50  # the views held planes, and many polygons were clipped


@pytest.mark.parametrize("name", ["room_grid", "institute_ground", "paper_arena", "fzk_haus_ground"])
def test_the_compiled_views_are_in_view_then_predict(name):
    """fit_kernels.views (in_view's cull, the facing test, the polygons moved into C, their
    outside-bits and outlines in one call) gives the views of in_view then predict_plane_views
    on the numpy code, to the bit: the same planes in the same order, their planes in C, outlines,
    fixed-point outlines, nearest depths and boxes. Poses anywhere in and around a floor of
    alike rooms (its cells hold a dozen polygons), two buildings and the arena, outside them too;
    the relocalizer's coarse grid, the localizer's and a padded one; two ranges."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (the perf extra)")
    from robot.localization import fit_kernels

    if fit_kernels.backend() != "numba":
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy): predict_views is in_view then predict there")
    plane_map, poses = _floor_or_map_and_poses(name, 19 if name == "room_grid" else 16)
    index = PlaneIndex(plane_map)
    views = empty = 0
    for cam in ROBOT.cameras:
        for stride, pad, grid in _grids(cam):
            for pose in poses:
                T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
                for max_range in (MAX_RANGE, 10.0):
                    cands = index.in_view(T, grid.frustum, max_range)
                    ref = predict_plane_views(plane_map, cands, T, grid, max_range) if cands else []
                    got = predict_views(plane_map, index, T, grid, max_range)
                    assert_same_views(got, ref, (name, pose, cam.name, stride, pad, max_range))
                    views += len(ref)
                    empty += not ref
    assert views > 300 and empty > 0  # planes were seen, and some poses saw none (outside, facing away)


def test_the_compiled_depth_buffer_is_the_numpy_one():
    """fit_kernels.zbuffer against roi._zbuffer, the numpy code, on random boxes, planes and
    polygon masks drawn into buffers that already hold nearer and farther planes: the same
    labels and the same buffer, to the bit, with and without writing the buffer."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (the perf extra)")
    from robot.localization import fit_kernels, roi

    if fit_kernels.backend() != "numba":
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy)")
    rng = np.random.default_rng(23)
    grid = CameraGrid(ROBOT.cameras[0].intrinsics_from_fov(), 848, 480, 4)
    cols, rows = grid.rays
    h, w = grid.shape
    won = 0
    for trial in range(60):
        ibuf = np.where(rng.random((h, w)) < 0.5, rng.uniform(0.1, 1.0, (h, w)), 0.0)
        label = np.where(ibuf > 0, rng.integers(0, 5, (h, w)), -1).astype(np.int32)
        mask = (rng.random((h, w)) < 0.6).astype(np.uint8)
        r0, c0 = int(rng.integers(0, h - 1)), int(rng.integers(0, w - 1))
        box = (r0, int(rng.integers(r0 + 1, h + 1)), c0, int(rng.integers(c0 + 1, w + 1)))
        # A plane 1 to 3 m away, tilted: inverse depths around the buffer's on part of the box.
        a, b = rng.normal(0.0, 0.3, 2)
        c = float(rng.uniform(0.3, 1.0))
        write = bool(trial % 2)
        ref_buf, ref_label = ibuf.copy(), label.copy()
        roi._zbuffer(mask, ref_buf, ref_label, cols, rows, a, b, c, 7, box, write)
        fit_kernels.zbuffer(mask, ibuf, label, cols, rows, a, b, c, 7, box, write)
        assert same_array(label, ref_label) and same_array(ibuf, ref_buf), trial
        won += int((ref_label == 7).sum())
    assert won > 10000  # the plane won many pixels, and lost others


def test_the_compiled_hidden_test_is_the_numpy_one():
    """fit_kernels.hidden against roi._hidden (the box's minimum against the plane's largest
    inverse depth) on random buffers, boxes and thresholds, at and around the minimum."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (the perf extra)")
    from robot.localization import fit_kernels, roi

    if fit_kernels.backend() != "numba":
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy)")
    rng = np.random.default_rng(29)
    h, w = 30, 53
    answers = set()
    for trial in range(400):
        ibuf = np.where(rng.random((h, w)) < 0.1 * (trial % 10), 0.0, rng.uniform(0.2, 1.0, (h, w)))
        r0, c0 = int(rng.integers(0, h - 1)), int(rng.integers(0, w - 1))
        box = (r0, int(rng.integers(r0 + 1, h + 1)), c0, int(rng.integers(c0 + 1, w + 1)))
        low = float(ibuf[box[0]:box[1], box[2]:box[3]].min())
        for top in (low, np.nextafter(low, 2.0), np.nextafter(low, -1.0), low * 0.5, float(rng.uniform(0.0, 1.2))):
            ref = roi._hidden(ibuf, box, float(top))
            assert fit_kernels.hidden(ibuf, box, float(top)) is ref, (trial, top)
            answers.add(ref)
    assert answers == {True, False}


def test_the_compiled_shrink_is_opencvs():
    """roi.shrink_rois with the compiled pixel work (fit_kernels.shrink) against ref_shrink, the
    OpenCV compare, erode and findNonZero, on random label images of blobs and scattered pixels:
    boxes at and across the grid's edges, padded grids, erosion radii from none to wider than the
    box, views with no pixels: the same counts, margins and ROIs, dtype and all."""
    pytest.importorskip("numba", reason="the compiled kernels need numba (the perf extra)")
    from robot.localization import fit_kernels

    if fit_kernels.backend() != "numba":
        pytest.skip("the pass on the numpy code (ROBOT_KERNELS=numpy)")
    rng = np.random.default_rng(31)
    kept = empty = 0
    for trial in range(300):
        stride = int(rng.choice([1, 4, 8]))
        h, w = int(rng.integers(5, 60)), int(rng.integers(5, 90))
        grid = CameraGrid(ROBOT.cameras[0].intrinsics_from_fov(), w * stride, h * stride, stride)
        pad = int(rng.integers(0, 4)) if trial % 3 else 0
        n = int(rng.integers(1, 6))
        label = np.full((h, w), -1, np.int32)
        views = []
        for k in range(n):
            r0, c0 = int(rng.integers(0, h)), int(rng.integers(0, w))
            r1, c1 = int(rng.integers(r0, h)), int(rng.integers(c0, w))
            if trial % 4 == 0:  # solid rectangles, erosion's own shape, and scattered pixels
                label[r0:r1 + 1, c0:c1 + 1] = k
            sub = label[r0:r1 + 1, c0:c1 + 1]
            sub[rng.random(sub.shape) < float(rng.uniform(0.3, 1.0))] = k
            box = (c0, r0, c1, r1) if k % 5 != 4 else None  # a view without a box: the whole grid
            views.append(PlaneView(k, f"p{k}", np.zeros(4), [], 1.0, box=box))
        # Outside its box a view owns nothing (the rasterization draws it inside its box only).
        for k, v in enumerate(views):
            if v.box is not None:
                c0, r0, c1, r1 = v.box
                outside = np.ones((h, w), bool)
                outside[r0:r1 + 1, c0:c1 + 1] = False
                label[outside & (label == k)] = -1
        radius_px = {k: float(rng.choice([0.0, 0.5, 3.0, 1.0 * stride, 2.5 * stride, 40.0 * stride])) for k in range(n)}
        got = [PlaneView(v.plane_index, v.plane_id, v.pi_camera, [], 1.0, box=v.box) for v in views]
        ref = [PlaneView(v.plane_index, v.plane_id, v.pi_camera, [], 1.0, box=v.box) for v in views]
        margin = radius_px.__getitem__
        shrink_rois(got, label, grid, lambda v, m=margin: m(v.plane_index), pad)
        ref_shrink(ref, label, grid, lambda v, m=margin: m(v.plane_index), pad)
        for g, r in zip(got, ref):
            assert g.pixels == r.pixels and g.margin_px == r.margin_px, trial
            assert same_array(g.roi_rows, r.roi_rows) and same_array(g.roi_cols, r.roi_cols), trial
            kept += len(r.roi_rows)
            empty += int(len(r.roi_rows) == 0 and r.pixels > 0)
    assert kept > 5000 and empty > 10  # ROIs were kept, and some views were eroded away
