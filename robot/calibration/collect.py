"""Calibration data from what the localizer reports: each fitted wall back in its camera's frame.

The localizer reports a fitted plane in the robot frame, computed with the mount and the depth
scale of the config it ran with. Undoing the mount gives the plane as the camera saw it
(n_C = R^T n_R, d_C = d_R + t . n_R) and the frame's applied scale is recorded beside it, so the
solve can put any other mount and scale in their place. The localizer's own measurement
covariance carries the errors this calibration is to find (depth scale, mounts), so the noise of
each observation comes from the stereo model instead (``plane_noise``): the random error averaged
over the fitted points plus the matcher's systematic error (``LocalizerConfig.depth_systematic_px``,
z^2 s / (f_x b)), which pixels do not average away.
"""

from __future__ import annotations

import math
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.samples import WheelOdometry
from robot.calibration.model import D435_BASELINE, Dataset, Keyframe, OdometryTrack, ParamLayout, PlaneObservation
from robot.config import RobotConfig
from robot.localization.localizer import LocalizationResult

MIN_HEADING_STD = math.radians(0.02)  # rad: floor on a wall's angle (wave and non-linearity of the matcher)
STEREO_SUBPIXEL = 0.08  # px: the D435i matcher's random disparity error
CORRELATED_POINTS = 8.0  # fitted points per independent one (the matcher's window correlates neighbours)
ROI_EXTENT = 0.3  # a wall's fitted region spans about this fraction of its depth across the image


def observations(result: LocalizationResult, robot: RobotConfig,
                 accepted: Optional[Iterable[str]] = None) -> List[PlaneObservation]:
    """One observation per fitted plane of ``result`` (only ``accepted`` plane ids when given), with
    ``robot`` the config the localizer ran with."""
    keep = None if accepted is None else set(accepted)
    reports = {(p.camera, p.id): p for p in result.planes if p.used and p.normal is not None and p.d is not None}
    out = []
    for m in result.measurements:
        if keep is not None and m.plane_id not in keep:
            continue
        rep = reports.get((m.camera, m.plane_id))
        if rep is None:
            continue
        cam = robot.camera(m.camera)
        T = cam.T_robot_camera
        n_R = np.asarray(rep.normal, float)
        n_R = n_R / np.linalg.norm(n_R)
        n_C = T[:3, :3].T @ n_R
        d_C = float(rep.d) + float(T[:3, 3] @ n_R)
        K = cam.intrinsics_from_fov()
        center, z = image_center(cam, rep.centroid, n_C, d_C)
        fb = float(K[0, 0]) * D435_BASELINE
        sd, sa = plane_noise(z, rep.inliers, fb, robot.localizer.depth_systematic_px)
        out.append(PlaneObservation(m.camera, m.plane_id, np.asarray(m.n_ground, float), float(m.d_ground), n_C,
                                    d_C, float(cam.depth_scale), (sd, sa, sa), center))
    return out


def image_center(cam, centroid_R, n_C: np.ndarray, d_C: float) -> Tuple[Tuple[float, float], float]:
    """Where a wall's fitted points are in the image ((u, v) from the centre in half-widths and
    half-heights) and their mean depth (m), from their mean point in the robot frame (``centroid_R``,
    the localizer's report; None: the optical axis, where the wall crosses it)."""
    if centroid_R is None:
        return (0.0, 0.0), max(d_C / max(abs(float(n_C[2])), 0.3), 0.05)
    T = cam.T_robot_camera
    K = cam.intrinsics_from_fov()
    p_C = T[:3, :3].T @ (np.asarray(centroid_R, float) - T[:3, 3])
    z = float(p_C[2])
    if z <= 0.05:
        return (0.0, 0.0), max(d_C / max(abs(float(n_C[2])), 0.3), 0.05)
    return (float(np.clip(K[0, 0] * p_C[0] / z / (cam.width / 2.0), -1.5, 1.5)),
            float(np.clip(K[1, 1] * p_C[1] / z / (cam.height / 2.0), -1.5, 1.5))), z


def intrinsics_of(cam) -> Tuple[float, float, float, float]:
    """(f_x, f_y, width, height) of a camera at its configured, full resolution."""
    K = cam.intrinsics_from_fov()
    return float(K[0, 0]), float(K[1, 1]), float(cam.width), float(cam.height)


def plane_noise(z: float, inliers: int, fx_b: float, systematic_px: float) -> Tuple[float, float]:
    """(offset m, angle rad) standard deviations of a wall fitted from ``inliers`` points at mean
    depth ``z``: the matcher's random error averaged over the points (neighbours are correlated,
    so over a fraction of them) plus its systematic error, which no number of points removes.
    Only the relative weights matter much: the solve rescales each group from its residuals."""
    sigma_z = STEREO_SUBPIXEL * z * z / fx_b
    n_eff = max(inliers / CORRELATED_POINTS, 1.0)
    offset = math.hypot(sigma_z / math.sqrt(n_eff), systematic_px * z * z / fx_b)
    angle = math.hypot(sigma_z / (math.sqrt(n_eff) * ROI_EXTENT * z), MIN_HEADING_STD)
    return offset, angle


class Collector:
    """Gathers keyframes (localizations) and wheel angles into a ``Dataset``."""

    def __init__(self, robot: RobotConfig, max_gap: float = 0.25):
        self.robot = robot
        self.layout = ParamLayout([c.name for c in robot.cameras])
        self.odometry = OdometryTrack(max_gap)
        self._keyframes: Dict[float, Keyframe] = {}

    def add_odometry(self, odo: WheelOdometry) -> None:
        self.odometry.add(odo.t, odo.angles)

    def add_localization(self, result: LocalizationResult, t: float, accepted: Optional[Iterable[str]] = None,
                         truth: Optional[Tuple[float, float, float]] = None,
                         pose: Optional[Sequence[float]] = None) -> int:
        """Add the planes of one localization at capture time ``t``; the number of observations added.
        ``pose``: the keyframe's starting guess (default the localization's own pose)."""
        obs = observations(result, self.robot, accepted)
        if not obs:
            return 0
        kf = self._keyframes.get(t)
        if kf is None:
            guess = (result.x, result.y, result.phi) if pose is None else pose
            kf = self._keyframes[t] = Keyframe(float(t), tuple(float(v) for v in guess), truth=truth)  # type: ignore[arg-type]
        kf.observations.extend(obs)
        return len(obs)

    def dataset(self) -> Dataset:
        kfs = [self._keyframes[t] for t in sorted(self._keyframes)]
        intrinsics = {c.name: intrinsics_of(c) for c in self.robot.cameras}
        return Dataset(self.layout.cameras, kfs, self.odometry, self.layout.nominal(self.robot), intrinsics,
                       float(self.robot.localizer.depth_systematic_px))

    def keyframe_times(self) -> List[float]:
        return sorted(self._keyframes)

    def __len__(self) -> int:
        return len(self._keyframes)
