"""Per-frame plane-map localization: depth frames + coarse pose -> refined pose with an honest
covariance and protection levels (docs/architecture.md, 'The method';
docs/localization-integrity.md).

For each camera frame: predict the visible map planes from the coarse pose, rasterize their
ROIs (shrunk by a margin that grows with the coarse pose's uncertainty), deproject only ROI
pixels, identify each wall among the surfaces of its ROI (the rear-most one the prior admits)
and fit it, then solve for the pose from all cameras together with every error the planes
carry, pixel noise and systematic. The solution is checked before it is reported: planes must
agree with each other (leave-one-out), and predicted walls whose ROI shows depth where the pose
admits none count against it. When the first solve moves the pose by more than the ROIs could
tolerate, the ROIs are predicted again from the refined pose and the fit repeated
(``max_passes``), each surface found before kept only if it is still the rear-most one.

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
from robot.localization.fit_kernels import gather_roi
from robot.localization.integrity import Checker, ErrorModel, Integrity, Observation, Stack, observation
from robot.localization.measurements import PlaneMeasurement
from robot.localization.plane_fit import FitParams, cross, fit_plane
from robot.localization.pose_solver import ObservedPlane, direction_label, solve_paper
from robot.localization.roi import CameraGrid, PlaneView, predict_views, rasterize_views, shrink_rois
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import MapPlane, PlaneMap

METHODS = ("joint", "paper")
# A full, consistent fix: every direction observed and the walls agreeing; "unprotected" is one
# whose error bound is too wide to vouch for, which a multi-view search may still rank and confirm.
FIX_STATUSES = ("ok", "unprotected")
DEFAULT_COARSE_STD = (0.1, 0.1, math.radians(10.0))  # what a user-typed --init is assumed good to
# Evidence against a pose counts only from a ROI whose pixels mostly have depth: a dark or shiny
# wall with a few valid pixels says nothing about where it is.
MIN_EVIDENCE_VALID = 0.5
LEVER_MAX = 0.2  # m: largest camera lever arm a heading error turns into a plane offset
# A plane known no better than this in offset and in heading adds next to nothing to a pose, and a
# small far patch is the likeliest to be something else (a board, a shelf side): it is not used.
USELESS_OFFSET_STD = 0.1  # m
USELESS_HEADING_STD = math.radians(2.0)


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
    centroid: Optional[List[float]] = None  # mean inlier point in the robot frame (m), for evaluations

    def to_json(self) -> Dict:
        return {"id": self.id, "camera": self.camera, "inliers": self.inliers, "normal": self.normal,
                "d": self.d, "used": self.used, "reason": self.reason}


@dataclass
class LocalizationResult:
    x: float
    y: float
    phi: float
    cov: np.ndarray
    # ok: fully observed, consistent and vouched for (protection levels within the alert limits);
    # unprotected: fully observed and consistent, but a protection level is over its alert limit
    # (the pose is the best estimate, its error bound too wide to vouch for); degenerate: some
    # direction unobserved; inconsistent: the walls or the depth contradict each other or the
    # pose; no_planes: nothing fitted.
    status: str
    unobservable: List[Dict]
    planes: List[PlaneReport]
    measurements: List[PlaneMeasurement] = field(default_factory=list)
    ms: float = 0.0
    passes: int = 1
    # Bounds the error exceeds with probability at most ``risk`` (inf: no bound can be given).
    horizontal_pl: float = math.inf
    heading_pl: float = math.inf
    risk: float = 1e-3
    integrity: Dict = field(default_factory=dict)  # what the checks found, for people and logs
    # The part of ``cov`` due to errors shared by every frame of these cameras and walls (depth
    # scale, mounts, as-built walls): fusing more frames does not shrink it.
    systematic_cov: Optional[np.ndarray] = None

    @property
    def pose(self) -> Tuple[float, float, float]:
        return (self.x, self.y, self.phi)

    @property
    def protection(self) -> Dict:
        def finite(v: float) -> Optional[float]:
            return float(v) if math.isfinite(v) else None

        return {"horizontal_m": finite(self.horizontal_pl), "heading_rad": finite(self.heading_pl), "risk": self.risk}

    def to_json(self) -> Dict:
        return {"x": self.x, "y": self.y, "phi": self.phi, "cov": np.asarray(self.cov).tolist(),
                "status": self.status, "unobservable": self.unobservable,
                "planes": [p.to_json() for p in self.planes], "ms": round(self.ms, 3), "passes": self.passes,
                "protection": self.protection, "integrity": self.integrity}


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


@dataclass
class _Request:
    """One localization's inputs, checked."""

    frames: Sequence[DepthFrame]
    cameras: List[CameraConfig]
    coarse: Tuple[float, float, float]
    cov: np.ndarray  # the coarse pose's covariance: what the gates, ROIs and protection levels trust
    method: str


@dataclass
class _WallFit:
    """One predicted wall in one camera's frame: what its ROI showed."""

    report: PlaneReport
    obs: Optional[ObservedPlane] = None
    observation: Optional[Observation] = None
    evidence: str = ""  # behind | in_front | "": where the ROI's depth says the wall is not
    t_capture: float = 0.0


@dataclass
class _Verdict:
    x: np.ndarray
    cov: np.ndarray
    status: str
    unobservable: List[Dict]
    used: List[_WallFit]  # the walls in the solution, in report order
    integrity: Optional[Integrity] = None
    stack: Optional[Stack] = None
    reason: str = ""
    # The prior for another pass: the solution's covariance, and the coarse pose's where the walls
    # observe nothing (the reported covariance floors those at UNOBSERVED_VARIANCE, which would
    # open the next pass's gates and ROI margins to metres). ``roi_next`` leaves out the shared
    # systematic errors: the solved pose has absorbed them for the walls it used, so their
    # outlines in the image are where it predicts them up to the statistical error alone.
    cov_next: Optional[np.ndarray] = None
    roi_next: Optional[np.ndarray] = None
    checker: Optional[Checker] = None  # what solved it, for the final checks on the same walls
    against_pose: bool = False  # inconsistent because the depth contradicts the pose, not the walls each other


class Localizer:
    """Holds what does not change between frames: map, spatial index, camera grids, error model."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, params: Optional[LocalizerConfig] = None):
        self.robot = robot
        self.map = plane_map
        self.params = params or robot.localizer
        self.index = PlaneIndex(plane_map)
        self.errors = ErrorModel.from_config(self.params)
        # Opt-in for engineers' live views: the last frame's shrunk ROIs per camera as a label
        # image on the sampling grid (map plane index per pixel, -1 for none).
        self.keep_roi_labels = False
        self.last_roi_labels: Dict[str, np.ndarray] = {}
        self._geometry: Dict[Tuple, _FrameGeometry] = {}
        self._geometry_exact: Dict[Tuple, _FrameGeometry] = {}
        self._extent: Dict[int, Tuple[float, float]] = {}
        # Each map plane's normal, offset and heading as Python floats, for the rival-wall check:
        # it runs for every fit over every plane within range (a hundred walls in a floor of alike
        # rooms), where numpy's per-call cost is most of the work (for four walls as for a hundred).
        self._plane_floats = [(float(pl.normal[0]), float(pl.normal[1]), float(pl.normal[2]), float(pl.d),
                               math.atan2(float(pl.normal[1]), float(pl.normal[0]))) for pl in plane_map.planes]

    def localize(self, frames: Sequence[DepthFrame], coarse: Sequence[float],
                 coarse_cov: Optional[np.ndarray] = None, method: str = "joint") -> LocalizationResult:
        """Refine ``coarse`` (x, y, phi) from frames taken at the same instant."""
        t0 = time.perf_counter()
        # The inputs, checked, and the prior that gates, ROIs and protection levels trust.
        req = self._request(frames, coarse, coarse_cov, method)
        pose, cov, roi_cov = req.coarse, req.cov, req.cov
        fits: List[_WallFit] = []
        passes = 0
        while True:
            passes += 1
            # Identify and fit each wall the cameras should see from this pose.
            fits = self._fit_walls(req, pose, cov, roi_cov, fits)
            # The pose from those walls with every error they carry (a pass that may not be the last
            # only checks that they agree as a whole).
            verdict = self._solve(req, fits, final=passes >= self.params.max_passes)
            # Another pass only when the pose moved by more than the ROIs were drawn for.
            if passes >= self.params.max_passes or not self._moved(verdict, pose):
                break
            pose = (float(verdict.x[0]), float(verdict.x[1]), float(verdict.x[2]))
            cov = verdict.cov if verdict.cov_next is None else verdict.cov_next
            roi_cov = cov if verdict.roi_next is None else verdict.roi_next
        # Leave-one-out agreement and protection levels; a wall that alone breaks agreement is left out.
        if verdict.integrity is None and verdict.status != "no_planes":
            verdict = self._solve(req, fits, final=True, checker=verdict.checker)
        # Predicted walls whose ROI shows depth where the pose admits none count against it.
        verdict = self._weigh_evidence(req, verdict, fits)
        # The pose, its protection levels, the fusion's measurements and the per-plane report.
        return self._result(req, fits, verdict, passes, t0)

    # -- the steps ----------------------------------------------------------------------------

    def _request(self, frames: Sequence[DepthFrame], coarse: Sequence[float], coarse_cov: Optional[np.ndarray],
                 method: str) -> _Request:
        if method not in METHODS:
            raise InputError(f"unknown method '{method}' (choose from {', '.join(METHODS)})")
        if len(coarse) != 3 or not all(math.isfinite(v) for v in coarse):
            raise InputError(f"coarse pose must be three finite numbers, got {tuple(coarse)}")
        cams = [self.robot.camera(f.camera) for f in frames]
        if coarse_cov is None:
            cov = coarse_covariance(DEFAULT_COARSE_STD[0], DEFAULT_COARSE_STD[2])
        else:
            cov = np.asarray(coarse_cov, float)
            if cov.shape != (3, 3) or not np.isfinite(cov).all() or np.any(np.linalg.eigvalsh(0.5 * (cov + cov.T)) <= 0):
                raise InputError("coarse covariance must be a finite, positive definite 3x3 matrix")
        return _Request(frames, cams, (float(coarse[0]), float(coarse[1]), float(coarse[2])), cov, method)

    def _fit_walls(self, req: _Request, pose: Tuple[float, float, float], cov: np.ndarray, roi_cov: np.ndarray,
                   previous: Sequence[_WallFit]) -> List[_WallFit]:
        """Every predicted wall of every frame; a surface the last pass fitted is the start of its
        refit, kept only while it is still the rear-most admissible one. ``cov`` opens the gates,
        ``roi_cov`` the ROI margins."""
        starts = {(w.report.camera, w.report.id): (w.obs.fit.n_camera, w.obs.fit.d_camera)
                  for w in previous if w.obs is not None}
        out: List[_WallFit] = []
        for frame, cam in zip(req.frames, req.cameras):
            out += self._fit_frame(frame, cam, pose, cov, roi_cov, starts)
        return out

    def _solve(self, req: _Request, fits: Sequence[_WallFit], final: bool = True,
               checker: Optional[Checker] = None) -> _Verdict:
        """The pose from the fitted walls; ``final``: with exclusion of a wall that alone breaks the
        others' agreement, and the protection levels of what is left. Otherwise (a pass that only
        steers the next one's ROIs) the full checks run only if the walls disagree as a whole.
        ``checker``: the one a non-final solve of these same fits built (its stack and solutions
        are reused)."""
        p = self.params
        cand = [w for w in fits if w.observation is not None]
        if not cand:
            return _Verdict(np.array(req.coarse), req.cov.copy(), "no_planes",
                            [direction_label(np.eye(3)[i]) for i in range(3)], [])
        if checker is None or len(checker.stack.obs) != len(cand) or any(
                o is not w.observation for o, w in zip(checker.stack.obs, cand)):
            stack = Stack([w.observation for w in cand], self.errors)
            checker = Checker(stack, req.coarse, req.cov, p.unobservable_std, p.false_alarm, p.integrity_risk)
        stack = checker.stack
        if not final:
            sol = checker.solve(range(len(cand)))
            if checker.agree_as_a_whole(sol):
                cov_next = sol.covariance(req.cov, 0.0)
                status = "ok" if sol.fully_observed else "degenerate"
                return _Verdict(sol.x.copy(), sol.covariance(req.cov), status, [], cand, None, stack,
                                cov_next=cov_next, roi_next=cov_next - sol.A @ stack.R_sys @ sol.A.T,
                                checker=checker)
        integ = checker.check()
        out = {j for j, _ in integ.excluded}
        for j, why in integ.excluded:
            cand[j].report.used, cand[j].report.reason = False, why
        members = [j for j in range(len(cand)) if j not in out]
        used = [cand[j] for j in members]
        if integ.status == "inconsistent":
            return _Verdict(np.array(req.coarse), req.cov.copy(), "inconsistent", [], used, integ, stack, integ.reason)
        sol = integ.solution
        x, cov = sol.x.copy(), integ.cov
        if req.method == "paper":
            rows = stack.rows(members)
            est = solve_paper([cand[j].obs for j in members], req.coarse, req.cov, p.unobservable_std,
                              stack.R[np.ix_(rows, rows)])
            x_paper = np.array([est.x, est.y, est.phi])
            # The protection levels bound the GLS solution; the paper's is that far from it.
            gap = x_paper - x
            integ.horizontal_pl += math.hypot(gap[0], gap[1])
            integ.heading_pl += abs(float(wrap_angle(gap[2])))
            x, cov = x_paper, est.cov
        unobs = [direction_label(v) for v in sol.unobservable_directions()]
        cov_next = sol.covariance(req.cov, 0.0)
        roi_next = cov_next - integ.systematic_cov if integ.systematic_cov is not None else cov_next
        return _Verdict(x, cov, integ.status, unobs, used, integ, stack, cov_next=cov_next, roi_next=roi_next)

    @staticmethod
    def _moved(verdict: _Verdict, pose: Tuple[float, float, float]) -> bool:
        if verdict.status in ("no_planes", "inconsistent"):
            return False
        moved = math.hypot(verdict.x[0] - pose[0], verdict.x[1] - pose[1])
        turned = abs(float(wrap_angle(verdict.x[2] - pose[2])))
        return moved >= 0.01 or turned >= math.radians(0.5)

    def _weigh_evidence(self, req: _Request, verdict: _Verdict, fits: Sequence[_WallFit]) -> _Verdict:
        """Depth behind where the pose admits a wall is impossible if the pose is right (nothing of
        a wall's ROI lies behind it); depth in front of it is also what an occluder gives, so it
        counts only when it is the rule rather than the exception."""
        behind = [w for w in fits if w.evidence == "behind"]
        front = [w for w in fits if w.evidence == "in_front"]
        if verdict.status == "inconsistent" or not (behind or (len(front) >= 2 and len(front) >= len(verdict.used))):
            return verdict
        names = ", ".join(f"{w.report.id} ({w.report.camera}, depth {'behind' if w.evidence == 'behind' else 'in front of'} it)"
                          for w in behind + front)
        # Where the cameras see through a wall, the pose is wrong or the wall is not built yet: the
        # second is for a person on the site to say (the map's ``built: false``), never for this.
        hint = ("; if a wall is not built yet, mark it 'built: false' in the map" if behind else "")
        return _Verdict(np.array(req.coarse), req.cov.copy(), "inconsistent", [], verdict.used, verdict.integrity,
                        verdict.stack, f"the depth contradicts the pose where it predicts {names}{hint}",
                        against_pose=True)

    def _result(self, req: _Request, fits: Sequence[_WallFit], verdict: _Verdict, passes: int,
                t0: float) -> LocalizationResult:
        integ = verdict.integrity
        measurements: List[PlaneMeasurement] = []
        hpl = vpl = math.inf
        sys_cov = None
        if verdict.status == "inconsistent":
            for w in verdict.used:
                w.report.used, w.report.reason = False, f"fitted, but not used: {verdict.reason}"
        elif verdict.stack is not None and integ is not None:
            index = {id(o): j for j, o in enumerate(verdict.stack.obs)}
            for w in verdict.used:
                j = index[id(w.observation)]
                R = verdict.stack.R[3 * j:3 * j + 2, 3 * j:3 * j + 2]
                o = w.obs
                measurements.append(PlaneMeasurement(o.plane_id, o.camera, w.t_capture, o.n_ground, o.d_ground,
                                                     np.array([o.d_robot, o.psi_robot]), R.copy(), o.fit.inliers))
            hpl, vpl, sys_cov = integ.horizontal_pl, integ.heading_pl, integ.systematic_cov
        info = {"reason": verdict.reason, "walls_used": len(verdict.used) if verdict.status != "inconsistent" else 0,
                "chi2": None if integ is None else round(float(integ.chi2), 3),
                "dof": None if integ is None else int(integ.dof),
                "excluded": [{"id": verdict.stack.obs[j].plane_id, "camera": verdict.stack.obs[j].camera, "reason": why}
                             for j, why in (integ.excluded if integ is not None else [])],
                "evidence_against": [{"id": w.report.id, "camera": w.report.camera, "depth": w.evidence}
                                     for w in fits if w.evidence],
                # Inconsistent because that depth outweighs the walls' agreement with the pose (the
                # pose is wrong), rather than because the walls contradict one another.
                "depth_against_pose": verdict.against_pose,
                # How far one wrong wall could have moved the pose unseen (leave-one-out), m and rad.
                "separation_m": None if integ is None or verdict.status == "inconsistent" else round(integ.separation_h, 6),
                "separation_rad": None if integ is None or verdict.status == "inconsistent" else round(integ.separation_heading, 8),
                # The largest protection levels (m, rad) among the hypotheses that only the prior
                # bounds where the walls leave a direction unobserved (0: none): a wrong-wall one's
                # bound is worth what the prior is (robot.fusion.quality carries them).
                "prior_bound_m": None if integ is None or verdict.status == "inconsistent" else round(integ.prior_bound_h, 6),
                "prior_bound_rad": (None if integ is None or verdict.status == "inconsistent"
                                    else round(integ.prior_bound_heading, 8)),
                # ... each: the walls it takes for wrong, the directions left to the prior, its bounds.
                "prior_bounded": ([] if integ is None or verdict.status == "inconsistent" else
                                  [{"walls": list(w), "directions": [[round(v, 6) for v in u] for u in U],
                                    "horizontal_m": round(h, 6), "heading_rad": round(a, 8)}
                                   for w, U, h, a in integ.prior_bounded])}
        status = verdict.status
        if status == "ok":
            over = self._over_alert_limits(hpl, vpl)
            if over:
                status, info["reason"] = "unprotected", over
        x = verdict.x
        return LocalizationResult(float(x[0]), float(x[1]), float(wrap_angle(x[2])), verdict.cov, status,
                                  verdict.unobservable, [w.report for w in fits], measurements,
                                  (time.perf_counter() - t0) * 1e3, passes, hpl, vpl, self.params.integrity_risk, info,
                                  sys_cov)

    def _over_alert_limits(self, hpl: float, vpl: float) -> str:
        """Why these protection levels do not vouch for the pose ('' when they do)."""
        q = self.robot.quality
        over = []
        if not hpl <= q.horizontal_alert_limit:
            over.append(f"horizontal protection level {1000 * hpl:.0f} mm over the "
                        f"{1000 * q.horizontal_alert_limit:.0f} mm alert limit")
        if not vpl <= math.radians(q.heading_alert_limit_deg):
            over.append(f"heading protection level {math.degrees(vpl):.2f} deg over the "
                        f"{q.heading_alert_limit_deg:g} deg alert limit")
        return "; ".join(over)

    # -- one frame ------------------------------------------------------------------------------

    def frame_geometry(self, cam: CameraConfig, K: np.ndarray, width: int, height: int) -> _FrameGeometry:
        K = np.asarray(K)
        # Every frame of a camera brings the same K: its bytes find the geometry without rounding.
        exact = (cam.name, width, height, K.dtype.str, K.tobytes())
        geo = self._geometry_exact.get(exact)
        if geo is not None:
            return geo
        key = (cam.name, width, height, tuple(np.round(K.ravel(), 6)))
        geo = self._geometry.get(key)
        if geo is None:
            scale = width / float(cam.width)
            nominal = max(1, self.params.pixel_stride) * scale
            stride = max(1, int(round(nominal)))
            grid = CameraGrid(np.asarray(K, float), width, height, stride)
            cols, rows = grid.rays
            geo = self._geometry[key] = _FrameGeometry(grid, scale, (nominal / stride) ** 2,
                                                       np.array(cols, float), np.array(rows, float))
        if len(self._geometry_exact) < 64:  # (a K that changes from frame to frame keeps the rounded key)
            self._geometry_exact[exact] = geo
        return geo

    def _fit_params(self, geo: _FrameGeometry, depth_unit: float, cov: np.ndarray, n_ground: np.ndarray,
                    up_camera: Optional[np.ndarray] = None, d_pred: float = 0.0,
                    tolerance: Optional[float] = None) -> FitParams:
        """The fit's gates: what the prior admits (the coarse pose's uncertainty) widened by what
        the systematic errors can move a plane by at distance ``d_pred`` (m, camera to plane)."""
        p, e = self.params, self.errors
        std_phi = math.sqrt(max(cov[2, 2], 0.0))
        nxy = np.asarray(n_ground, float)[:2]
        std_along_n = math.sqrt(max(float(nxy @ cov[:2, :2] @ nxy), 0.0))
        tol = 0.0 if tolerance is None else float(tolerance)
        fx_b = float(geo.grid.K[0, 0]) / geo.scale * 0.050  # the full-resolution matcher's f_x b
        systematic = math.sqrt((e.depth_scale_std * d_pred) ** 2 + tol**2 + e.mount_position_std**2
                               + (LEVER_MAX * e.mount_angle_std) ** 2
                               + (e.disparity_systematic_px / fx_b * d_pred * d_pred) ** 2)
        angle_sys = math.sqrt(std_phi**2 + e.mount_angle_std**2 + (tol / 2.0) ** 2)
        return FitParams(
            iterations=p.ransac_iterations, sample=p.ransac_sample, min_threshold=p.inlier_threshold / 3.0,
            # Counted in points at the configured stride: as many as the frame's grid holds.
            min_inliers=max(3, int(round(p.min_inliers * geo.density))),
            angle_gate=min(math.radians(p.angle_gate_deg) + 3.0 * angle_sys, math.radians(60.0)),
            up=None if up_camera is None else tuple(float(v) for v in up_camera),
            tilt_gate=math.radians(p.angle_gate_deg) + 3.0 * e.mount_angle_std,
            tilt_sigma=math.hypot(e.mount_angle_std, tol),  # the plumb of a wall a metre or more high
            systematic_px=e.disparity_systematic_px,
            # Heading error also moves the plane through the camera's lever arm (<= ~0.2 m).
            offset_gate=p.offset_gate + 3.0 * math.hypot(std_along_n, systematic) + LEVER_MAX * 3.0 * std_phi,
            # Stereo noise is the full-resolution matcher's, whatever the frame was decimated to.
            noise_fx_b=fx_b,
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
        views = predict_views(self.map, self.index, T_ground_camera, pgrid, p.max_range)
        label = rasterize_views(views, pgrid)
        shrink_rois(views, label, pgrid, margin_for, pad)
        return views

    def _fit_frame(self, frame: DepthFrame, cam: CameraConfig, pose: Tuple[float, float, float], cov: np.ndarray,
                   roi_cov: np.ndarray, starts: Dict[Tuple[str, str], Tuple[np.ndarray, float]]) -> List[_WallFit]:
        p = self.params
        h, w = frame.depth.shape
        geo = self.frame_geometry(cam, frame.K, w, h)
        stride = geo.grid.stride
        T_robot_camera = cam.T_robot_camera
        T_ground_robot = pose_to_T_ground_robot(*pose)
        T_ground_camera = T_ground_robot @ T_robot_camera
        candidates = self.index.candidates(T_ground_camera[:3, 3], p.max_range)
        views = self.plane_rois(geo, T_ground_camera, roi_cov)
        if self.keep_roi_labels:
            labels = np.full(geo.grid.shape, -1, np.int32)
            for view in views:
                labels[view.roi_rows, view.roi_cols] = view.plane_index
            self.last_roi_labels[cam.name] = labels
        full_px = (stride / geo.scale) ** 2  # configured-resolution pixels per grid pixel
        up_camera = T_robot_camera[2, :3]  # the robot's z axis in the camera frame: R_RC^T e_z
        inflation = self.errors.correlation_inflation(stride / geo.scale)
        depth_scale = float(frame.depth_scale)
        out: List[_WallFit] = []
        for view in views:
            if view.pixels == 0 and view.box[2] >= view.box[0]:
                continue  # only in the margin around the image, not in it
            plane = self.map.planes[view.plane_index]
            rr, cc = view.roi_rows, view.roi_cols
            if len(rr) * full_px < p.min_roi_pixels:
                out.append(_WallFit(PlaneReport(view.plane_id, cam.name, 0, None, None, False,
                                                f"ROI too small after occlusion and margin ({len(rr)} grid pixels)")))
                continue
            z, rx, ry, n_roi = gather_roi(frame.depth, rr, cc, stride, depth_scale, p.min_range, p.max_range,
                                          geo.ray_cols, geo.ray_rows)
            params = self._fit_params(geo, float(frame.depth_scale), cov, plane.normal, up_camera,
                                      abs(float(view.pi_camera[3])), plane.tolerance)
            fit = fit_plane(rx, ry, z, view.pi_camera, params, starts.get((cam.name, plane.id)))
            if not fit.ok:
                valid = len(z) / max(n_roi, 1)
                evidence, reason = fit.evidence, fit.reason
                if evidence and valid < MIN_EVIDENCE_VALID:
                    evidence = ""
                    reason += f" (only {100 * valid:.0f} % of the ROI has depth: not counted against the pose)"
                out.append(_WallFit(PlaneReport(view.plane_id, cam.name, fit.inliers, None, None, False, reason, len(z)),
                                    evidence=evidence))
                continue
            obs = ObservedPlane(plane.id, cam.name, plane.normal, plane.d, fit, T_robot_camera)
            m = fit.inlier_mask
            rival = self._rival_plane(obs, view.plane_index, candidates, pose, cov,
                                      lambda m=m, rx=rx, ry=ry, z=z: (rx[m], ry[m], z[m]))
            if rival is not None:
                out.append(_WallFit(PlaneReport(plane.id, cam.name, fit.inliers, None, None, False,
                                                f"ambiguous: the fit is also consistent with plane '{rival}' "
                                                "within the coarse pose's uncertainty", len(z))))
                continue
            meas = self._observation(obs, plane, view.plane_index, params, inflation, T_ground_robot)
            if meas is not None and (meas.R_own[0, 0] > USELESS_OFFSET_STD**2 and meas.R_own[1, 1] > USELESS_HEADING_STD**2):
                out.append(_WallFit(PlaneReport(plane.id, cam.name, fit.inliers, None, None, False,
                                                f"too imprecise to help: {1000 * math.sqrt(meas.R_own[0, 0]):.0f} mm and "
                                                f"{math.degrees(math.sqrt(meas.R_own[1, 1])):.1f} deg (a small, far "
                                                "patch)", len(z))))
                continue
            report = PlaneReport(plane.id, cam.name, fit.inliers, [round(float(c), 6) for c in obs.n_robot],
                                 round(obs.d_robot, 6), meas is not None,
                                 "ok" if meas is not None else "not a wall: its normal has no heading", len(z),
                                 [float(c) for c in T_robot_camera[:3, :3] @ fit.centroid + T_robot_camera[:3, 3]])
            out.append(_WallFit(report, obs, meas, "", frame.t_capture))
        return out

    def _observation(self, obs: ObservedPlane, plane: MapPlane, plane_index: int, params: FitParams,
                     inflation: float, T_ground_robot: np.ndarray) -> Optional[Observation]:
        """The fitted plane as a measurement with its errors (integrity.observation)."""
        fit = obs.fit
        # The matcher's systematic disparity error is fixed over a patch: z^2 s_sys / (f_x b) along
        # the optical axis, seen along the normal; over the patch's width it also turns the normal.
        sd2 = (self.errors.disparity_systematic_px / params.noise_fx_b * fit.z2_mean * abs(float(fit.n_camera[2]))) ** 2
        R_rc, t_rc = obs.T_robot_camera[:3, :3], obs.T_robot_camera[:3, 3]
        c_R = R_rc @ fit.centroid + t_rc
        # Turning the patch by e about an axis in it through its centre c turns the normal by e and
        # moves d_R by -e (u . c), u the direction the normal turns to: far along the wall, a small
        # tilt of a small patch is a large offset at the robot. Turned about the vertical the patch
        # changes psi_R, about the horizontal tilt_R; the systematic disparity error and unexplained
        # scatter over the patch's half-width set the turn.
        n = obs.n_robot
        h_R = np.array([-n[1], n[0], 0.0]) / max(math.hypot(n[0], n[1]), 1e-9)
        v_R = cross(n, h_R)
        length, height = self._plane_extent(plane_index)
        # Two parts: scatter the fit itself shows (weighted by, as pixel noise is), and errors that
        # are there whatever this frame shows (in the covariance only). The matcher's systematic
        # error is a fixed pattern over each camera's image, so it is not what sets one plane's
        # weight against another's; a built wall's shape, bowed or wavy, turns its local direction
        # where this camera looks by about twice its tolerance over its length (at least 4 m).
        slope = 2.0 * plane.tolerance / max(length, 4.0)
        ex = fit.excess_var
        l1, l2 = -float(h_R @ c_R), -float(v_R @ c_R)  # d_R per unit turn about the vertical, the horizontal
        q1 = 1.0 / max(math.sqrt(3.0) * fit.lateral_std, 0.1) ** 2
        q2 = 1.0 / max(math.sqrt(3.0) * fit.vertical_std, 0.1) ** 2

        def turns(offset2: float, w1: float, w2: float) -> np.ndarray:
            # offset2 along d_R, plus turns of variance w1 (psi) and w2 (tilt) about the patch centre.
            return np.array([[offset2 + w1 * l1 * l1 + w2 * l2 * l2, w1 * l1, w2 * l2],
                             [w1 * l1, w1, 0.0], [w2 * l2, 0.0, w2]])

        seen = turns(ex, ex * q1, ex * q2)
        unseen = turns(sd2, sd2 * q1 + slope * slope, sd2 * q2)
        centre = T_ground_robot[:3, :3] @ c_R + T_ground_robot[:3, 3]
        return observation(plane.id, obs.camera, plane.normal, plane.d, obs.n_robot, obs.d_robot, fit.d_camera, t_rc,
                           obs.J_fit, fit.cov, inflation, seen, plane.tolerance, length, height,
                           T_ground_robot[:2, 3] - centre[:2], unseen)

    def _plane_extent(self, plane_index: int) -> Tuple[float, float]:
        """(horizontal length, height) of a map plane, m."""
        ext = self._extent.get(plane_index)
        if ext is None:
            pl = self.map.planes[plane_index]
            v = pl.vertices
            nxy = pl.normal[:2]
            h = math.hypot(nxy[0], nxy[1])
            along = np.array([-nxy[1], nxy[0]]) / h if h > 1e-9 else np.array([1.0, 0.0])
            ext = self._extent[plane_index] = (float(np.ptp(v[:, :2] @ along)), float(np.ptp(v[:, 2])))
        return ext

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
        floats = self._plane_floats
        cnx, cny, cnz, cd, _ = floats[claimed]
        c00, c01, c10, c11 = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 0]), float(cov[1, 1])
        x0, y0, phi0 = float(coarse[0]), float(coarse[1]), float(coarse[2])
        psi, d_robot = obs.psi_robot, obs.d_robot
        same_cos = math.cos(math.radians(1.0))
        extent = None
        for j in candidates:
            if j == claimed:
                continue
            nx, ny, nz, d, heading = floats[j]
            if abs(nz) > 0.5:
                continue  # not a wall: its heading is undefined and the normal gate already separates it
            if nx * cnx + ny * cny + nz * cnz > same_cos and abs(d - cd) < 0.01:
                continue  # the same physical plane split in the map: an equivalent measurement
            if abs(wrap_angle(heading - psi - phi0)) > win_phi:
                continue
            sd = math.sqrt(max((nx * c00 + ny * c10) * nx + (nx * c01 + ny * c11) * ny, 0.0))
            if abs(d_robot - (nx * x0 + ny * y0 + d)) > 4.0 * sd + 0.2 * win_phi + 0.02:
                continue
            pl = self.map.planes[j]
            nxy = pl.normal[:2]
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
