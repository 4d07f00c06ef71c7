"""Per-frame plane-map localization: depth frames + coarse pose -> refined pose (DESIGN.md section 4).

For each camera frame: predict the visible map planes from the coarse pose, rasterize their
ROIs (shrunk by a margin that grows with the coarse pose's uncertainty), deproject only ROI
pixels, fit each plane with the prediction as a prior, then solve for the pose from all cameras
together. When the first solve moves the pose by more than the ROIs could tolerate, the ROIs are
predicted again from the refined pose and the fit repeated (``max_passes``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.config import CameraConfig, LocalizerConfig, RobotConfig
from robot.errors import InputError
from robot.frames import DepthFrame
from robot.geometry import pose_to_T_ground_robot, wrap_angle
from robot.measurements import PlaneMeasurement
from robot.plane_fit import FitParams, fit_plane
from robot.plane_index import PlaneIndex
from robot.plane_map import PlaneMap
from robot.pose_solver import ObservedPlane, PoseEstimate, solve_joint, solve_paper
from robot.roi import CameraGrid, PlaneView, predict_plane_views, rasterize_views, shrink_rois

METHODS = ("joint", "paper")
DEFAULT_COARSE_STD = (0.1, 0.1, math.radians(10.0))  # what a user-typed --init is assumed good to
MIN_OFFSET_STD = 0.0005  # m: floor on a plane measurement (calibration, correlated stereo noise)
MIN_ANGLE_STD = math.radians(0.05)


@dataclass
class PlaneReport:
    id: str
    camera: str
    inliers: int
    normal: Optional[List[float]]  # fitted normal in the robot frame
    d: Optional[float]  # fitted offset in the robot frame
    used: bool
    reason: str
    roi_points: int = 0

    def to_json(self) -> Dict:
        return {"id": self.id, "camera": self.camera, "inliers": self.inliers, "normal": self.normal,
                "d": self.d, "used": self.used, "reason": self.reason}


@dataclass
class LocalizationResult:
    x: float
    y: float
    phi: float
    cov: np.ndarray
    status: str
    unobservable: List[Dict]
    planes: List[PlaneReport]
    measurements: List[PlaneMeasurement] = field(default_factory=list)
    ms: float = 0.0
    passes: int = 1

    @property
    def pose(self) -> Tuple[float, float, float]:
        return (self.x, self.y, self.phi)

    def to_json(self) -> Dict:
        return {"x": self.x, "y": self.y, "phi": self.phi, "cov": np.asarray(self.cov).tolist(),
                "status": self.status, "unobservable": self.unobservable,
                "planes": [p.to_json() for p in self.planes], "ms": round(self.ms, 3), "passes": self.passes}


def coarse_covariance(std_xy: float, std_phi: float) -> np.ndarray:
    return np.diag([std_xy**2, std_xy**2, std_phi**2])


class Localizer:
    """Holds what does not change between frames: map, spatial index, camera grids."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, params: Optional[LocalizerConfig] = None):
        self.robot = robot
        self.map = plane_map
        self.params = params or robot.localizer
        self.index = PlaneIndex(plane_map)
        self._grids: Dict[Tuple, CameraGrid] = {}

    def _grid(self, frame: DepthFrame) -> CameraGrid:
        h, w = frame.depth.shape
        key = (frame.camera, w, h, tuple(np.round(frame.K.ravel(), 6)))
        g = self._grids.get(key)
        if g is None:
            g = self._grids[key] = CameraGrid(frame.K, w, h, max(1, self.params.pixel_stride))
        return g

    def _fit_params(self, K: np.ndarray, cov: np.ndarray, n_ground: np.ndarray) -> FitParams:
        p = self.params
        std_phi = math.sqrt(max(cov[2, 2], 0.0))
        nxy = n_ground[:2]
        std_along_n = math.sqrt(max(float(nxy @ cov[:2, :2] @ nxy), 0.0))
        return FitParams(
            iterations=p.ransac_iterations, sample=p.ransac_sample, min_threshold=p.inlier_threshold / 3.0,
            min_inliers=p.min_inliers,
            angle_gate=min(math.radians(p.angle_gate_deg) + 3.0 * std_phi, math.radians(60.0)),
            # Heading error also moves the plane through the camera's lever arm (<= ~0.2 m).
            offset_gate=p.offset_gate + 3.0 * std_along_n + 0.2 * 3.0 * std_phi,
            noise_fx_b=float(K[0, 0]) * 0.050,
        )

    def _observe_frame(self, frame: DepthFrame, cam: CameraConfig, coarse, cov,
                       rng: np.random.Generator, reports: List[PlaneReport]) -> List[ObservedPlane]:
        p = self.params
        grid = self._grid(frame)
        T_ground_camera = pose_to_T_ground_robot(*coarse) @ cam.T_robot_camera
        candidates = self.index.candidates(T_ground_camera[:3, 3], p.max_range)
        in_view = self.index.in_view(T_ground_camera, grid.frustum, p.max_range)
        views = predict_plane_views(self.map, in_view, T_ground_camera, grid, p.max_range)
        label = rasterize_views(views, grid)
        std_phi = math.sqrt(max(cov[2, 2], 0.0))
        std_pos = math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))
        fx = float(frame.K[0, 0])

        def margin_for(view: PlaneView) -> float:
            grow = 2.0 * (fx * std_phi + fx * std_pos / max(view.z_near, 0.3))
            return min(p.margin_px + grow, p.max_margin_px)

        shrink_rois(views, label, grid, margin_for)
        depth_grid = frame.depth[:: grid.stride, :: grid.stride]
        K = frame.K
        observed = []
        for view in views:
            plane = self.map.planes[view.plane_index]
            rr, cc = view.roi_rows, view.roi_cols
            if len(rr) * grid.stride**2 < p.min_roi_pixels:
                reports.append(PlaneReport(view.plane_id, cam.name, 0, None, None, False,
                                           f"ROI too small after occlusion and margin ({len(rr)} grid pixels)"))
                continue
            z = depth_grid[rr, cc].astype(np.float64) * frame.depth_scale
            ok = (z > p.min_range) & (z < p.max_range)
            z, rr, cc = z[ok], rr[ok], cc[ok]
            pts = np.column_stack([(cc * grid.stride - K[0, 2]) / K[0, 0] * z,
                                   (rr * grid.stride - K[1, 2]) / K[1, 1] * z, z])
            fit_params = self._fit_params(K, cov, plane.normal)
            fit = fit_plane(pts, view.pi_camera, fit_params, rng)
            if not fit.ok:
                reports.append(PlaneReport(view.plane_id, cam.name, fit.inliers, None, None, False, fit.reason, len(pts)))
                continue
            obs = ObservedPlane(plane.id, cam.name, plane.normal, plane.d, fit, cam.T_robot_camera,
                                pts[fit.inlier_mask], fit_params)
            rival = self._rival_plane(obs, view.plane_index, candidates, coarse, cov)
            if rival is not None:
                reports.append(PlaneReport(plane.id, cam.name, fit.inliers, None, None, False,
                                           f"ambiguous: the fit is also consistent with plane '{rival}' "
                                           "within the coarse pose's uncertainty", len(pts)))
                continue
            observed.append(obs)
            reports.append(PlaneReport(plane.id, cam.name, fit.inliers, [round(float(c), 6) for c in obs.n_robot],
                                       round(obs.d_robot, 6), True, "ok", len(pts)))
        return observed

    def localize(self, frames: Sequence[DepthFrame], coarse: Sequence[float],
                 coarse_cov: Optional[np.ndarray] = None, method: str = "joint") -> LocalizationResult:
        """Refine ``coarse`` (x, y, phi) from frames taken at the same instant."""
        if method not in METHODS:
            raise InputError(f"unknown method '{method}' (choose from {', '.join(METHODS)})")
        if not all(math.isfinite(v) for v in coarse):
            raise InputError(f"coarse pose must be finite, got {tuple(coarse)}")
        t0 = time.perf_counter()
        cams = [self.robot.camera(f.camera) for f in frames]
        pose = tuple(float(v) for v in coarse)
        cov = coarse_covariance(DEFAULT_COARSE_STD[0], DEFAULT_COARSE_STD[2]) if coarse_cov is None else np.asarray(coarse_cov, float)
        seed = sum(int(f.frame_number) * 31 + i for i, f in enumerate(frames))
        estimate: Optional[PoseEstimate] = None
        passes = 0
        for passes in range(1, max(1, self.params.max_passes) + 1):
            rng = np.random.default_rng(seed + passes)
            reports: List[PlaneReport] = []
            observed: List[ObservedPlane] = []
            for frame, cam in zip(frames, cams):
                observed += self._observe_frame(frame, cam, pose, cov, rng, reports)
            solve = solve_joint if method == "joint" else solve_paper
            estimate = solve(observed, coarse, np.asarray(coarse_cov) if coarse_cov is not None else cov,
                             self.params.unobservable_std)
            moved = math.hypot(estimate.x - pose[0], estimate.y - pose[1])
            turned = abs(float(wrap_angle(estimate.phi - pose[2])))
            if estimate.status == "no_planes" or (moved < 0.01 and turned < math.radians(0.5)):
                break
            pose = (estimate.x, estimate.y, estimate.phi)
            cov = np.minimum(estimate.cov, cov) if estimate.status == "degenerate" else estimate.cov
        measurements = [self._measurement(o, f.t_capture) for o in observed for f in frames if f.camera == o.camera]
        ms = (time.perf_counter() - t0) * 1e3
        return LocalizationResult(estimate.x, estimate.y, estimate.phi, estimate.cov, estimate.status,
                                  estimate.unobservable, reports, measurements, ms, passes)

    def _rival_plane(self, obs: ObservedPlane, claimed: int, candidates: Sequence[int], coarse, cov) -> Optional[str]:
        """Another map plane that would explain this fit as well, given how wrong the coarse pose
        may be. In a symmetric room a large heading error makes the wrong wall *more* consistent
        with the prior than the right one; no gate can tell them apart, so such a fit is dropped
        rather than risk a wrong identification."""
        win_phi = 4.0 * math.sqrt(max(cov[2, 2], 0.0)) + math.radians(1.0)
        claimed_plane = self.map.planes[claimed]
        for j in candidates:
            if j == claimed:
                continue
            pl = self.map.planes[j]
            if abs(pl.normal[2]) > 0.5:
                continue  # not a wall: its heading is undefined and the normal gate already separates it
            if pl.normal @ claimed_plane.normal > math.cos(math.radians(1.0)) and abs(pl.d - claimed_plane.d) < 0.01:
                continue  # the same physical plane split in the map: an equivalent measurement
            phi_j = math.atan2(pl.normal[1], pl.normal[0]) - obs.psi_robot
            if abs(float(wrap_angle(phi_j - coarse[2]))) > win_phi:
                continue
            nxy = pl.normal[:2]
            sd = math.sqrt(max(float(nxy @ cov[:2, :2] @ nxy), 0.0))
            d_pred = float(nxy @ np.asarray(coarse[:2])) + pl.d
            if abs(obs.d_robot - d_pred) <= 4.0 * sd + 0.2 * win_phi + 0.02:
                return pl.id
        return None

    @staticmethod
    def _measurement(o: ObservedPlane, t_capture: float) -> PlaneMeasurement:
        R = o.cov_d_psi + np.diag([MIN_OFFSET_STD**2, MIN_ANGLE_STD**2])
        return PlaneMeasurement(o.plane_id, o.camera, t_capture, o.n_ground, o.d_ground,
                                np.array([o.d_robot, o.psi_robot]), R, o.fit.inliers)
