"""What ``robotctl visible`` reports: each visible plane's un-shrunk ROI at full resolution."""

from __future__ import annotations

from typing import Dict, List, Tuple

from robot.base.geometry import pose_to_T_ground_robot
from robot.config import CameraConfig
from robot.localization.roi import CameraGrid, predict_plane_views, rasterize_views
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap

VISIBLE_RANGE = 10.0  # m: report what is geometrically in view, beyond the localizer's useful range


def visible_planes(plane_map: PlaneMap, cam: CameraConfig, pose: Tuple[float, float, float]) -> List[Dict]:
    grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, 1)
    T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    candidates = PlaneIndex(plane_map).in_view(T_ground_camera, grid.frustum, VISIBLE_RANGE)
    views = predict_plane_views(plane_map, candidates, T_ground_camera, grid, VISIBLE_RANGE)
    label = rasterize_views(views, grid)
    out = []
    for k, v in enumerate(views):
        pixels = int((label == k).sum())
        if pixels == 0:
            continue  # fully occluded by nearer planes
        polys = [[[round(float(c), 2), round(float(r), 2)] for c, r in o] for o in v.outlines_px]
        out.append({"id": v.plane_id, "pixels": pixels, "polygon": max(polys, key=len), "polygons": polys})
    return out
