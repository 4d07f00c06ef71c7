"""What ``robotctl visible`` reports: each visible plane's un-shrunk ROI at full resolution."""

from __future__ import annotations

from typing import Dict, List, Tuple

from robot.config import CameraConfig
from robot.localization.roi import camera_views
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap

VISIBLE_RANGE = 10.0  # m: report what is geometrically in view, beyond the localizer's useful range


def visible_planes(plane_map: PlaneMap, cam: CameraConfig, pose: Tuple[float, float, float]) -> List[Dict]:
    views, label, _ = camera_views(plane_map, PlaneIndex(plane_map), cam, pose, VISIBLE_RANGE)
    out = []
    for k, v in enumerate(views):
        pixels = int((label == k).sum())
        if pixels == 0:
            continue  # fully occluded by nearer planes
        polys = [[[round(float(c), 2), round(float(r), 2)] for c, r in o] for o in v.outlines_px]
        out.append({"id": v.plane_id, "pixels": pixels, "polygon": max(polys, key=len), "polygons": polys})
    return out
