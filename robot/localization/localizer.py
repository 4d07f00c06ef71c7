"""Per-frame plane-map localization: depth frames + coarse pose -> refined pose (DESIGN.md section 4).

For each camera frame: predict the visible map planes from the coarse pose, rasterize their
ROIs (shrunk by a margin that grows with the coarse pose's uncertainty), deproject only ROI
pixels, fit each plane with the prediction as a prior, then solve for the pose from all cameras
together. When the first solve moves the pose by more than the ROIs could tolerate, the ROIs are
predicted again from the refined pose and the fit repeated (``max_passes``), each plane found
before refined from its previous fit rather than searched for again.

Frames may be decimated (W/d x H/d with K scaled, as librealsense's decimation filter gives):
``LocalizerConfig.pixel_stride`` and the pixel and point counts are meant at the configured
resolution and scale with the frame, and the stereo noise stays the full-resolution matcher's.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import InputError
from robot.base.geometry import pose_to_T_ground_robot, wrap_angle
from robot.base.samples import DepthFrame
from robot.config import CameraConfig, LocalizerConfig, RobotConfig
from robot.localization.measurements import PlaneMeasurement
from robot.localization.plane_fit import FitParams, fit_plane
from robot.localization.pose_solver import ObservedPlane, PoseEstimate, solve_joint, solve_paper
from robot.localization.roi import CameraGrid, PlaneView, predict_plane_views, rasterize_views, shrink_rois
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap

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


@dataclass
class _FrameGeometry:
    """How one camera's frames of one size are sampled (cached per camera, size and K).

    A frame may be smaller than the configured resolution (a decimation filter: W/d x H/d with K
    scaled). ``LocalizerConfig.pixel_stride`` is meant at the configured resolution, so the
    stride is scaled with the frame, and thresholds that count pixels or points follow."""

    grid: CameraGrid  # the frame's sampling grid, at the effective stride
    scale: float  # frame pixels per configured-resolution pixel (1/d for decimation d)
    density: float  # grid points per point of the configured stride on a full frame (1 when exact)
    ray_cols: np.ndarray  # x/z of each grid column's pixel ray
    ray_rows: np.ndarray  # y/z of each grid row's pixel ray
    padded: Dict[int, CameraGrid] = field(default_factory=dict)

    def padded_grid(self, pad: int) -> CameraGrid:
        """The grid grown by ``pad`` grid pixels on every side (K shifted to match): grid pixel
        (r, c) of it is pixel (r - pad, c - pad) of ``grid``."""
        g = self.padded.get(pad)
        if g is None:
            s = self.grid.stride
            K = self.grid.K.copy()
            K[0, 2] += pad * s
            K[1, 2] += pad * s
            gh, gw = self.grid.shape
            g = self.padded[pad] = CameraGrid(K, (gw + 2 * pad) * s, (gh + 2 * pad) * s, s)
        return g


class Localizer:
    """Holds what does not change between frames: map, spatial index, camera grids."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, params: Optional[LocalizerConfig] = None):
        self.robot = robot
        self.map = plane_map
        self.params = params or robot.localizer
        self.index = PlaneIndex(plane_map)
        # Opt-in for engineers' live views: the last frame's shrunk ROIs per camera as a label
        # image on the sampling grid (map plane index per pixel, -1 for none).
        self.keep_roi_labels = False
        self.last_roi_labels: Dict[str, np.ndarray] = {}
        self._geometry: Dict[Tuple, _FrameGeometry] = {}

    def frame_geometry(self, cam: CameraConfig, K: np.ndarray, width: int, height: int) -> _FrameGeometry:
        key = (cam.name, width, height, tuple(np.round(np.asarray(K).ravel(), 6)))
        geo = self._geometry.get(key)
        if geo is None:
            scale = width / float(cam.width)
            nominal = max(1, self.params.pixel_stride) * scale
            stride = max(1, int(round(nominal)))
            grid = CameraGrid(np.asarray(K, float), width, height, stride)
            cols, rows, _, _ = grid.rays
            geo = self._geometry[key] = _FrameGeometry(grid, scale, (nominal / stride) ** 2,
                                                       np.array(cols, float), np.array(rows, float))
        return geo

    def _fit_params(self, geo: _FrameGeometry, depth_unit: float, cov: np.ndarray, n_ground: np.ndarray,
                    up_camera: Optional[np.ndarray] = None) -> FitParams:
        p = self.params
        std_phi = math.sqrt(max(cov[2, 2], 0.0))
        nxy = n_ground[:2]
        std_along_n = math.sqrt(max(float(nxy @ cov[:2, :2] @ nxy), 0.0))
        return FitParams(
            iterations=p.ransac_iterations, sample=p.ransac_sample, min_threshold=p.inlier_threshold / 3.0,
            # Counted in points at the configured stride: as many as the frame's grid holds.
            min_inliers=max(3, int(round(p.min_inliers * geo.density))),
            angle_gate=min(math.radians(p.angle_gate_deg) + 3.0 * std_phi, math.radians(60.0)),
            up=None if up_camera is None else tuple(float(v) for v in up_camera), tilt_gate=math.radians(p.angle_gate_deg),
            # Heading error also moves the plane through the camera's lever arm (<= ~0.2 m).
            offset_gate=p.offset_gate + 3.0 * std_along_n + 0.2 * 3.0 * std_phi,
            # Stereo noise is the full-resolution matcher's, whatever the frame was decimated to.
            noise_fx_b=float(geo.grid.K[0, 0]) / geo.scale * 0.050,
            depth_unit=depth_unit,
            min_inlier_fraction=p.min_inlier_fraction,
        )

    def plane_rois(self, geo: _FrameGeometry, T_ground_camera: np.ndarray, cov: np.ndarray) -> List[PlaneView]:
        """The planes a camera at ``T_ground_camera`` should see, each with its ROI (grid rows and
        columns of ``geo.grid``) shrunk by a margin that grows with the pose uncertainty ``cov``.

        Margins are in the frame's pixels: the configured ones (full resolution) times the
        frame's scale, plus twice the image motion one standard deviation of heading and position
        error causes. The margin applies at the image border too, where the plane runs on beyond
        it: a pose error can bring its outline in there as anywhere else. So the rasterization
        runs on a grid padded by the largest margin, and a plane that reaches past the border by
        more than its margin keeps its border pixels while one whose edge lies just outside the
        image loses them (an unpadded erosion would either keep or drop both)."""
        p = self.params
        grid = geo.grid
        std_phi = math.sqrt(max(cov[2, 2], 0.0))
        std_pos = math.sqrt(max(cov[0, 0] + cov[1, 1], 0.0))
        fx = float(grid.K[0, 0])
        base, cap = p.margin_px * geo.scale, p.max_margin_px * geo.scale

        def margin_for(view: PlaneView) -> float:
            return min(base + 2.0 * (fx * std_phi + fx * std_pos / max(view.z_near, 0.3)), cap)

        largest = min(base + 2.0 * (fx * std_phi + fx * std_pos / 0.3), cap)
        pad = int(math.ceil(largest / grid.stride))
        pgrid = geo.padded_grid(pad)
        in_view = self.index.in_view(T_ground_camera, pgrid.frustum, p.max_range)
        views = predict_plane_views(self.map, in_view, T_ground_camera, pgrid, p.max_range)
        label = rasterize_views(views, pgrid)
        shrink_rois(views, label, pgrid, margin_for, pad)
        return views

    def _observe_frame(self, frame: DepthFrame, cam: CameraConfig, coarse, cov, rng: np.random.Generator,
                       reports: List[PlaneReport], seeds: Dict[Tuple[str, str], ObservedPlane]) -> List[ObservedPlane]:
        p = self.params
        h, w = frame.depth.shape
        geo = self.frame_geometry(cam, frame.K, w, h)
        stride = geo.grid.stride
        T_ground_camera = pose_to_T_ground_robot(*coarse) @ cam.T_robot_camera
        candidates = self.index.candidates(T_ground_camera[:3, 3], p.max_range)
        views = self.plane_rois(geo, T_ground_camera, cov)
        if self.keep_roi_labels:
            labels = np.full(geo.grid.shape, -1, np.int32)
            for view in views:
                labels[view.roi_rows, view.roi_cols] = view.plane_index
            self.last_roi_labels[cam.name] = labels
        full_px = (stride / geo.scale) ** 2  # configured-resolution pixels per grid pixel
        up_camera = cam.T_robot_camera[2, :3]  # the robot's z axis in the camera frame: R_RC^T e_z
        observed = []
        for view in views:
            if view.pixels == 0 and view.box[2] >= view.box[0]:
                continue  # only in the margin around the image, not in it
            plane = self.map.planes[view.plane_index]
            rr, cc = view.roi_rows, view.roi_cols
            if len(rr) * full_px < p.min_roi_pixels:
                reports.append(PlaneReport(view.plane_id, cam.name, 0, None, None, False,
                                           f"ROI too small after occlusion and margin ({len(rr)} grid pixels)"))
                continue
            z = frame.depth[rr * stride, cc * stride] * float(frame.depth_scale)
            ok = (z > p.min_range) & (z < p.max_range)
            z, rr, cc = z[ok], rr[ok], cc[ok]
            seed = seeds.get((cam.name, plane.id))
            rx, ry = geo.ray_cols[cc], geo.ray_rows[rr]
            fit = fit_plane(rx, ry, z, view.pi_camera,
                            self._fit_params(geo, float(frame.depth_scale), cov, plane.normal, up_camera), rng,
                            None if seed is None else (seed.fit.n_camera, seed.fit.d_camera))
            if not fit.ok:
                reports.append(PlaneReport(view.plane_id, cam.name, fit.inliers, None, None, False, fit.reason, len(z)))
                continue
            obs = ObservedPlane(plane.id, cam.name, plane.normal, plane.d, fit, cam.T_robot_camera)
            m = fit.inlier_mask
            rival = self._rival_plane(obs, view.plane_index, candidates, coarse, cov,
                                      lambda m=m, rx=rx, ry=ry, z=z: (rx[m], ry[m], z[m]))
            if rival is not None:
                reports.append(PlaneReport(plane.id, cam.name, fit.inliers, None, None, False,
                                           f"ambiguous: the fit is also consistent with plane '{rival}' "
                                           "within the coarse pose's uncertainty", len(z)))
                continue
            observed.append(obs)
            reports.append(PlaneReport(plane.id, cam.name, fit.inliers, [round(float(c), 6) for c in obs.n_robot],
                                       round(obs.d_robot, 6), True, "ok", len(z)))
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
        # A later pass refines each plane the previous one fitted (same frame, shifted ROI)
        # instead of searching for it again.
        seeds: Dict[Tuple[str, str], ObservedPlane] = {}
        for passes in range(1, max(1, self.params.max_passes) + 1):
            rng = np.random.default_rng(seed + passes)
            reports: List[PlaneReport] = []
            observed: List[ObservedPlane] = []
            for frame, cam in zip(frames, cams):
                observed += self._observe_frame(frame, cam, pose, cov, rng, reports, seeds)
            seeds = {(o.camera, o.plane_id): o for o in observed}
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

    def _rival_plane(self, obs: ObservedPlane, claimed: int, candidates: Sequence[int], coarse, cov,
                     patch) -> Optional[str]:
        """Another map plane that would explain this fit as well, given how wrong the coarse pose
        may be. In a symmetric room a large heading error makes the wrong wall *more* consistent
        with the prior than the right one; no gate can tell them apart, so such a fit is dropped
        rather than risk a wrong identification.

        A rival must face the same way (within the heading window), lie at the same distance
        (within the position window), and reach where the fitted points are: in a building many
        walls are in line with each other a few centimetres apart, metres along the wall from the
        points, where no pose within the uncertainty could put them. ``patch`` = (x/z, y/z, z) of
        the fit's inlier points, as a function: only a fit with a rival needs them."""
        win_phi = 4.0 * math.sqrt(max(cov[2, 2], 0.0)) + math.radians(1.0)
        claimed_plane = self.map.planes[claimed]
        extent = None
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
            if abs(obs.d_robot - d_pred) > 4.0 * sd + 0.2 * win_phi + 0.02:
                continue
            # Where along the wall the points are: with heading phi_j the fit's along-wall
            # direction in R turns into the rival's, t_j = (-n_y, n_x), so the points' position
            # along it in G is their robot-frame coordinate plus t_j . (x, y).
            if extent is None:
                extent = self._along_wall_extent(obs, patch())
            t_j = np.array([-nxy[1], nxy[0]]) / max(float(np.linalg.norm(nxy)), 1e-12)
            offset = float(t_j @ np.asarray(coarse[:2]))
            slack = 4.0 * math.sqrt(max(float(t_j @ cov[:2, :2] @ t_j), 0.0)) + 0.05
            along = pl.vertices[:, :2] @ t_j
            if along.min() > extent[1] + offset + slack or along.max() < extent[0] + offset - slack:
                continue  # the rival ends before the points begin, whatever the pose within the window
            return pl.id
        return None

    @staticmethod
    def _along_wall_extent(obs: ObservedPlane, patch) -> Tuple[float, float]:
        """Interval the fit's inlier points span along the fitted wall's horizontal direction
        (-n_Ry, n_Rx) in the robot frame."""
        rx, ry, z = patch
        n = obs.n_robot
        h = math.hypot(n[0], n[1])
        t_R = np.array([-n[1], n[0], 0.0]) / max(h, 1e-12)
        R, t = obs.T_robot_camera[:3, :3], obs.T_robot_camera[:3, 3]
        a = R.T @ t_R  # t_R . (R p_C + t) = a . p_C + t_R . t
        s = (a[0] * rx + a[1] * ry + a[2]) * z
        return float(s.min()) + float(t_R @ t), float(s.max()) + float(t_R @ t)

    @staticmethod
    def _measurement(o: ObservedPlane, t_capture: float) -> PlaneMeasurement:
        R = o.cov_d_psi + np.diag([MIN_OFFSET_STD**2, MIN_ANGLE_STD**2])
        return PlaneMeasurement(o.plane_id, o.camera, t_capture, o.n_ground, o.d_ground,
                                np.array([o.d_robot, o.psi_robot]), R, o.fit.inliers)
