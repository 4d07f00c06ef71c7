"""Online calibration beside the pose filter: depth scales, mount corrections and wheel radii as slow states.

Per camera it estimates the depth scale and, where the data shows them, corrections of the mount's
x, y, pitch and yaw; for the wheels the mean radius, the differences between the wheels and
lx + ly (docs/calibration.md). The pose filter stays as it is: this estimator only corrects each
plane measurement before the pose filter sees it and learns from the planes the pose filter
accepted, so the pose filter never carries calibration states.

How it learns: keyframes (the accepted planes of a localization, in their camera's frame, and the
fused pose at that instant as a starting guess) and the wheel angles between them are gathered
for ``window`` seconds; then the batch solve of ``robot.calibration.solver`` runs over that window
with the current estimate as its prior, the window's poses free. The poses are solved for and
dropped, so a window only moves what it observes: one wall seen from one distance cannot tell a
depth scale from a position and leaves the estimate where it was. Windows do not overlap, so no
datum counts twice, and a small random walk between windows lets the states drift slowly
(temperature, tyre wear). This is a Kalman filter on the calibration states whose measurement
is a window's information with the poses marginalised out.

What it reports: per state the estimate, its standard deviation and whether the data so far
observed it (the information gathered from the windows alone, prior excluded, gives a standard
deviation within the state's bound and no correlation near 1 with another state). What it
applies: the estimate, with its uncertainty added to each corrected measurement's covariance, so
a state the data has not observed is used only at its prior with the prior's uncertainty.

It warns once per camera, through ``logging``, when a camera's scale leaves its configured
bound (three times ``localizer.depth_scale_std`` from the configured scale): the localizer's
error model then no longer covers that camera.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Dict, Iterable, List, Optional, Sequence

import numpy as np

from robot.base.samples import WheelOdometry
from robot.calibration.collect import Collector, image_center, intrinsics_of
from robot.calibration.model import (
    CAMERA_PARAMS,
    DISPARITY_PARAMS,
    ODOMETRY_PARAMS,
    WALL_PARAMS,
    WALL_PREFIX,
    ParamLayout,
    camera_rotation,
    disparity_effect,
    disparity_prior_std,
    is_nuisance,
    is_wall_param,
    wall_prior,
)
from robot.calibration.solver import SolveOptions, solve
from robot.config import RobotConfig
from robot.localization.localizer import LocalizationResult
from robot.localization.measurements import PlaneMeasurement
from robot.maps.plane_map import DEFAULT_TOLERANCE, PlaneMap

log = logging.getLogger(__name__)

ONLINE_CAMERA_PARAMS = ("depth_scale", "x", "y", "pitch", "yaw")
STATE_VERSION = 1
MAX_ODOMETRY_SAMPLES = 20_000  # wheel reports kept while no window closes (200 s at 100 Hz)


@dataclass(frozen=True)
class OnlineSettings:
    window: float = 2.0  # s of keyframes per update
    min_keyframes: int = 6  # a window closes only with at least this many keyframes
    keyframe_interval: float = 0.15  # s: localizations closer than this to the last keyframe are skipped
    iterations: int = 4  # Gauss-Newton steps per window (the prior is close: the problem is near linear)
    # Random walk of the states per sqrt(second): slow drifts, and a guard against overconfidence.
    walk_scale: float = 2e-5  # 1/sqrt(s)
    walk_position: float = 2e-5  # m/sqrt(s)
    walk_angle: float = math.radians(0.002)  # rad/sqrt(s)
    walk_radius: float = 2e-6  # relative/sqrt(s)
    walk_disparity: float = 2e-5  # px/sqrt(s)
    # Prior of the wheel states (the cameras' come from the localizer config's error model).
    radius_std: float = 0.02  # relative
    radius_diff_std: float = 0.01  # relative
    l_std: float = 0.05  # relative
    # Observed: the data alone gives a standard deviation below these.
    bound_scale: float = 2e-3
    bound_position: float = 0.003  # m
    bound_angle: float = math.radians(0.1)
    bound_radius: float = 2e-3  # relative
    bound_l: float = 1e-2  # relative
    inflate: bool = True  # add the estimate's uncertainty to each corrected measurement's covariance
    # Walls as built: each seen wall's offset, turn and plumb are states kept from window to window
    # (every view of a wall shares them; counted per window they would be counted again each time).
    walls: bool = True
    max_walls: int = 64  # the walls kept; beyond, the one seen longest ago is dropped (marginalised)
    wall_pivot_height: float = 0.5  # m: where a wall's turn and tilt pivot when no map gives its centre


class CalibrationFilter:
    """Online calibration states for one robot config (its values are the prior's mean)."""

    def __init__(self, robot: RobotConfig, settings: Optional[OnlineSettings] = None,
                 plane_map: Optional[PlaneMap] = None):
        self.robot = robot
        self.settings = settings or OnlineSettings()
        self.plane_map = plane_map  # the walls' centres and tolerances (None: the default tolerance)
        self._map_planes = {p.id: p for p in plane_map.planes} if plane_map is not None else {}
        self.reset()
        self._warned: set = set()

    # -- state ------------------------------------------------------------------------------------

    def _set_layout(self, walls: Sequence[str]) -> None:
        cams = [c.name for c in self.robot.cameras]
        self.layout = ParamLayout(cams, walls)
        self.nominal = self.layout.nominal(self.robot)
        self.names = [f"{c}.{p}" for c in cams for p in ONLINE_CAMERA_PARAMS + DISPARITY_PARAMS] + \
                     [f"odometry.{p}" for p in ODOMETRY_PARAMS] + \
                     [f"{WALL_PREFIX}{w}.{p}" for w in walls for p in WALL_PARAMS]
        self.index = [self.layout.index(n) for n in self.names]
        self.prior_std = self._prior_std()
        self.bounds = self._bounds()

    def reset(self) -> None:
        self.wall_pivot: Dict[str, np.ndarray] = {}
        self.wall_std: Dict[str, np.ndarray] = {}
        self._wall_seen: Dict[str, float] = {}
        self._set_layout(())
        self.mean = self.nominal[self.index].copy()
        self.cov = np.diag(self.prior_std ** 2)
        self.info_data = np.zeros((len(self.names), len(self.names)))
        self.windows = 0
        self.t_last: Optional[float] = None
        self._collector = Collector(self.robot)
        self._last_keyframe = -math.inf

    @property
    def walls(self) -> Sequence[str]:
        return self.layout.walls

    def _wall_prior(self, plane_id: str, n_G: np.ndarray, d_G: float, pose: Sequence[float]):
        """(pivot (3,), std (3,)) of a wall's as-built deviation: the map plane's tolerance as the
        offset, the tolerance over its length and height (at least 1 m) as the turn and the tilt,
        like the localizer's integrity model; without a map the default tolerance, pivoting where
        the robot first saw the wall."""
        plane = self._map_planes.get(plane_id)
        if plane is not None:
            return wall_prior(plane)
        p = np.array([pose[0], pose[1], self.settings.wall_pivot_height])
        pivot = p - (float(n_G @ p) + float(d_G)) * n_G
        return pivot, np.array([DEFAULT_TOLERANCE] * 3)

    def _add_walls(self, data, t: float) -> None:
        """States for the walls of this window not yet kept (their prior), and the oldest dropped
        beyond ``max_walls``."""
        new = {}
        for kf in data.keyframes:
            for o in kf.observations:
                n_G = np.asarray(o.n_ground, float)
                if abs(n_G[2]) > 0.3:  # floors and ceilings: no turn or plumb (not modelled)
                    continue
                self._wall_seen[o.plane_id] = t
                if o.plane_id not in self.wall_pivot and o.plane_id not in new:
                    new[o.plane_id] = self._wall_prior(o.plane_id, n_G, o.d_ground, kf.pose)
        walls = list(self.walls)
        if new:
            for w, (pivot, std) in new.items():
                self.wall_pivot[w], self.wall_std[w] = pivot, std
            walls += list(new)
        drop = set()
        if len(walls) > self.settings.max_walls:
            oldest = sorted(walls, key=lambda w: self._wall_seen.get(w, -math.inf))
            drop = set(oldest[:len(walls) - self.settings.max_walls])
        if not new and not drop:
            return
        old_names = list(self.names)
        keep = [w for w in walls if w not in drop]
        mean, cov, info = self.mean, self.cov, self.info_data
        for w in drop:
            del self.wall_pivot[w], self.wall_std[w]
            self._wall_seen.pop(w, None)
        self._set_layout(keep)
        pos = {n: i for i, n in enumerate(old_names)}
        mine = [j for j, n in enumerate(self.names) if n in pos]
        theirs = [pos[self.names[j]] for j in mine]
        self.mean = self.nominal[self.index].copy()
        self.mean[mine] = mean[theirs]
        self.cov = np.diag(self.prior_std ** 2)
        self.cov[np.ix_(mine, mine)] = cov[np.ix_(theirs, theirs)]
        self.info_data = np.zeros((len(self.names), len(self.names)))
        self.info_data[np.ix_(mine, mine)] = info[np.ix_(theirs, theirs)]

    def _prior_std(self) -> np.ndarray:
        loc, s = self.robot.localizer, self.settings
        out = []
        for n in self.names:
            cam, p = n.rsplit(".", 1)
            if is_wall_param(n):
                out.append(float(self.wall_std[cam[len(WALL_PREFIX):]][WALL_PARAMS.index(p)]))
            elif cam == "odometry":
                r0, L0 = self.nominal[self.layout.odometry_slice][[0, 4]]
                out.append({"wheel_radius": s.radius_std * r0, "lx_plus_ly": s.l_std * L0}.get(p, s.radius_diff_std * r0))
            elif p in DISPARITY_PARAMS:  # the camera's disparity error: a nuisance with a physical prior
                out.append(float(disparity_prior_std(loc.depth_systematic_px)[DISPARITY_PARAMS.index(p)]))
            elif p == "depth_scale":
                out.append(max(loc.depth_scale_std, 1e-4))
            elif p in ("x", "y"):
                out.append(max(loc.mount_position_std, 1e-4))
            else:
                out.append(max(math.radians(loc.mount_angle_std_deg), 1e-5))
        return np.array(out)

    def _bounds(self) -> np.ndarray:
        s = self.settings
        r0, L0 = self.nominal[self.layout.odometry_slice][[0, 4]]
        out = []
        for n in self.names:
            cam, p = n.rsplit(".", 1)
            if cam == "odometry":
                out.append(s.bound_l * L0 if p == "lx_plus_ly" else s.bound_radius * r0)
            elif is_nuisance(n):
                out.append(math.inf)
            elif p == "depth_scale":
                out.append(s.bound_scale)
            elif p in ("x", "y"):
                out.append(s.bound_position)
            else:
                out.append(s.bound_angle)
        return np.array(out)

    def theta(self) -> np.ndarray:
        """The full parameter vector the corrections use: the estimates, the rest as configured."""
        th = self.nominal.copy()
        th[self.index] = self.mean
        return th

    def std(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    @property
    def nuisance(self) -> np.ndarray:
        """The camera's disparity error terms and the walls as built: estimated so the calibration
        is not biased, never reported."""
        return np.array([is_nuisance(n) for n in self.names], bool)

    def observed(self) -> np.ndarray:
        """Which states the data so far has observed: its information alone, not the prior's (only
        the disparity terms and the walls keep theirs: physical bounds, not guesses). Nuisances: False."""
        nuis = self.nuisance
        reg = np.diag(np.where(nuis, 1.0, 1e-9) / self.prior_std ** 2)
        try:
            C = np.linalg.inv(self.info_data + reg)
        except np.linalg.LinAlgError:
            return np.zeros(len(self.names), bool)
        sd = np.sqrt(np.maximum(np.diag(C), 0.0))
        ok = (sd <= self.bounds) & ~nuis
        corr = C / np.outer(np.maximum(sd, 1e-300), np.maximum(sd, 1e-300))
        np.fill_diagonal(corr, 0.0)
        corr[:, nuis] = 0.0
        ok &= np.max(np.abs(corr), axis=1) < 0.99
        return ok

    # -- inputs -----------------------------------------------------------------------------------

    def add_odometry(self, odo: WheelOdometry) -> None:
        self._collector.add_odometry(odo)
        track = self._collector.odometry
        if len(track) > MAX_ODOMETRY_SAMPLES:  # no keyframes for a while (vision down): keep only the recent past
            t_keep = min([odo.t - self.settings.window * 4] + self._collector.keyframe_times())
            track.drop_before(t_keep)

    def add_localization(self, result: LocalizationResult, t_capture: float, accepted: Iterable[str],
                         pose: Sequence[float]) -> bool:
        """Keep the accepted planes of an (uncorrected) localization as a keyframe; True when a window
        was solved."""
        if t_capture - self._last_keyframe < self.settings.keyframe_interval:
            return False
        # the fused pose is a better start than the single localization's
        if self._collector.add_localization(result, t_capture, accepted, pose=pose) == 0:
            return False
        self._last_keyframe = t_capture
        kfs = self._collector.keyframe_times()
        if kfs[-1] - kfs[0] >= self.settings.window and len(kfs) >= self.settings.min_keyframes:
            self._update(kfs[-1])
            return True
        return False

    def _update(self, t_end: float) -> None:
        data = self._collector.dataset()
        if self.t_last is not None:
            self._random_walk(max(0.0, data.keyframes[0].t - self.t_last))
        if self.settings.walls:
            self._add_walls(data, t_end)
            data.walls = {w: self.wall_pivot[w] for w in self.walls}
        theta = self.theta()
        try:
            info_prior = np.linalg.inv(self.cov)
        except np.linalg.LinAlgError:
            info_prior = np.diag(1.0 / self.prior_std ** 2)
        options = SolveOptions(free=self.names, prior_mean=theta, prior_info=info_prior,
                               max_iterations=self.settings.iterations, variance_components=False)
        try:
            sol = solve(data, options, self.layout, theta0=theta)
        except (np.linalg.LinAlgError, ValueError) as e:
            log.debug("calibration window skipped: %s", e)
            sol = None
        if sol is not None and np.all(np.isfinite(sol.theta)) and np.all(np.isfinite(sol.cov)):
            order = [sol.free.index(i) for i in self.index]
            self.mean = sol.theta[self.index]
            self.cov = sol.cov[np.ix_(order, order)]
            self.info_data = self.info_data + sol.info_data[np.ix_(order, order)]
            self.windows += 1
            self._check_bounds()
        self.t_last = t_end
        # the next window starts after this one: no keyframe or wheel angle is used twice
        old = self._collector
        self._collector = Collector(self.robot)
        self._collector.odometry = old.odometry
        old.odometry.drop_before(t_end)

    def _random_walk(self, dt: float) -> None:
        s = self.settings
        r0 = self.nominal[self.layout.odometry_slice][0]
        q = []
        for n in self.names:
            cam, p = n.rsplit(".", 1)
            if is_wall_param(n):
                q.append(0.0)  # a wall stays as it was built
            elif cam == "odometry":
                q.append(s.walk_radius * (self.nominal[self.layout.index(n)] if p in ("wheel_radius", "lx_plus_ly") else r0))
            elif p in DISPARITY_PARAMS:
                q.append(s.walk_disparity)
            elif p == "depth_scale":
                q.append(s.walk_scale)
            elif p in ("x", "y"):
                q.append(s.walk_position)
            else:
                q.append(s.walk_angle)
        self.cov = self.cov + np.diag(np.square(q) * dt)

    def _check_bounds(self) -> None:
        bound = 3.0 * self.robot.localizer.depth_scale_std
        for cam in self.layout.cameras:
            i = self.names.index(f"{cam}.depth_scale")
            s0 = self.nominal[self.layout.index(f"{cam}.depth_scale")]
            off = self.mean[i] - s0
            if abs(off) > bound and cam not in self._warned:
                self._warned.add(cam)
                log.warning("camera %s: its depth scale is estimated %.2f %% %s than configured (%.5f, std %.3f %%); "
                            "that is beyond the localizer's bound of %.2f %% (3 x localizer.depth_scale_std): "
                            "recalibrate it (robotctl calibrate)", cam, abs(off) * 100,
                            "larger" if off > 0 else "smaller", self.mean[i], self.std()[i] * 100, bound * 100)

    @property
    def warned(self) -> List[str]:
        return sorted(self._warned)

    # -- corrections ------------------------------------------------------------------------------

    def correct(self, result: LocalizationResult) -> LocalizationResult:
        """``result`` with each plane measurement as the estimated calibration says the camera saw it:
        the plane taken back to the camera frame with the configured mount and scale, then out again
        with the estimated ones; its covariance grows by the estimate's uncertainty."""
        if not result.measurements:
            return result
        reports = {(p.camera, p.id): p for p in result.planes if p.used and p.normal is not None and p.d is not None}
        geometry: Dict[str, tuple] = {}
        out = []
        for m in result.measurements:
            rep = reports.get((m.camera, m.plane_id))
            if rep is None:
                out.append(m)
                continue
            if m.camera not in geometry:
                geometry[m.camera] = self._camera_geometry(m.camera)
            out.append(self._correct_one(m, rep, geometry[m.camera]))
        return dataclasses.replace(result, measurements=out)

    def _camera_geometry(self, cam: str) -> tuple:
        """Configured and estimated mount of a camera, the rotation's derivatives by the estimated
        angles, its disparity terms, and the rows of the states that belong to it."""
        sl = self.layout.camera_slice(cam)
        p0, p1 = self.nominal[sl], self.theta()[sl]
        R1 = camera_rotation(p1[4:7])
        dR = {}
        for k, name in ((1, "pitch"), (2, "yaw")):
            up, dn = p1[4:7].copy(), p1[4:7].copy()
            up[k] += 1e-6
            dn[k] -= 1e-6
            dR[name] = (camera_rotation(up) - camera_rotation(dn)) / 2e-6
        rows = [i for i, n in enumerate(self.names) if n.rsplit(".", 1)[0] == cam]
        cfg = self.robot.camera(cam)
        return (camera_rotation(p0[4:7]), p0[1:4], p0[0], R1, p1[1:4], p1[0], dR, rows, p1[len(CAMERA_PARAMS):],
                cfg, intrinsics_of(cfg))

    def _correct_one(self, m: PlaneMeasurement, rep, geo: tuple) -> PlaneMeasurement:
        R0, t0, S0, R1, t1, S1, dR, rows, e, cfg, intr = geo
        n_R = np.asarray(rep.normal, float)
        n_m = R0.T @ n_R  # as measured, in the camera frame
        d_m = float(rep.d) + float(t0 @ n_R)
        # the camera's disparity error out, then its scale, then the estimated mount
        center, _ = image_center(cfg, rep.centroid, n_m, d_m)
        dd, dn_e = disparity_effect(n_m, d_m, center, intr)
        n_C = n_m - dn_e @ e
        n_C /= np.linalg.norm(n_C)
        d0 = d_m - float(dd @ e)
        d_C = d0 * S1 / S0
        n1 = R1 @ n_C
        z = np.array([d_C - float(t1 @ n1), m.z[1] + math.remainder(math.atan2(n1[1], n1[0]) - m.z[1], 2.0 * math.pi)])
        R = np.asarray(m.R, float)
        if self.settings.inflate:
            h2 = max(n1[0] ** 2 + n1[1] ** 2, 1e-12)
            J = np.zeros((2, len(rows)))
            for j, i in enumerate(rows):
                p = self.names[i].rsplit(".", 1)[1]
                if p == "depth_scale":
                    J[0, j] = d_C / S1
                elif p in ("x", "y"):
                    J[0, j] = -n1["xy".index(p)]
                elif p in DISPARITY_PARAMS:
                    k = DISPARITY_PARAMS.index(p)
                    dn = -R1 @ dn_e[:, k]
                    J[0, j] = -dd[k] * S1 / S0 - float(t1 @ dn)
                    J[1, j] = (n1[0] * dn[1] - n1[1] * dn[0]) / h2
                else:
                    dn = dR[p] @ n_C
                    J[0, j] = -float(t1 @ dn)
                    J[1, j] = (n1[0] * dn[1] - n1[1] * dn[0]) / h2
            R = R + J @ self.cov[np.ix_(rows, rows)] @ J.T
        return dataclasses.replace(m, z=z, R=0.5 * (R + R.T))

    # -- reporting and persistence ----------------------------------------------------------------

    def estimates(self) -> List[Dict[str, object]]:
        """Every reported state (the disparity nuisances left out) with its estimate, std and whether observed."""
        std, obs = self.std(), self.observed()
        out = []
        for i, n in enumerate(self.names):
            p = n.rsplit(".", 1)[1]
            if is_nuisance(n):
                continue
            angle = p in ("roll", "pitch", "yaw")
            k = math.degrees(1.0) if angle else 1.0
            out.append({"name": n, "value": float(self.mean[i]) * k, "std": float(std[i]) * k,
                        "nominal": float(self.nominal[self.index[i]]) * k, "observed": bool(obs[i]),
                        "unit": "deg" if angle else ("" if p == "depth_scale" else "m")})
        return out

    def status(self) -> Dict[str, object]:
        """JSON-able: every state with its estimate, std and whether the data has observed it yet."""
        ests = self.estimates()
        return {"windows": self.windows, "observed": [e["name"] for e in ests if e["observed"]],
                "not_observed_yet": [e["name"] for e in ests if not e["observed"]],
                "estimates": {e["name"]: {"value": e["value"], "std": e["std"], "observed": e["observed"]} for e in ests},
                "scale_warnings": self.warned}

    def to_json(self) -> Dict[str, object]:
        """The state to persist: per camera (by serial number where the config has one, else by name).
        The walls' states are left out (marginalised): they belong to a map, not to the robot."""
        cams: Dict[str, object] = {}
        for cfg in self.robot.cameras:
            key = _camera_key(cfg)
            cams[key] = {"camera": cfg.name, "nominal": [float(v) for v in self._camera_nominal(cfg.name)]}
        k = [i for i, n in enumerate(self.names) if not is_wall_param(n)]
        w = [i for i, n in enumerate(self.names) if is_wall_param(n)]
        cov, info = self.cov[np.ix_(k, k)], self.info_data[np.ix_(k, k)]
        if w:  # the data's information with the walls marginalised (at their prior), not held known
            I_kw = self.info_data[np.ix_(k, w)]
            I_ww = self.info_data[np.ix_(w, w)] + np.diag(1.0 / self.prior_std[w] ** 2)
            info = info - I_kw @ np.linalg.solve(I_ww, I_kw.T)
            info = 0.5 * (info + info.T)
        return {"version": STATE_VERSION, "names": [self._persist_name(self.names[i]) for i in k],
                "mean": [float(self.mean[i]) for i in k], "cov": [[float(v) for v in row] for row in cov],
                "info_data": [[float(v) for v in row] for row in info],
                "odometry_nominal": [float(v) for v in self.nominal[self.layout.odometry_slice]],
                "cameras": cams, "windows": self.windows}

    def _camera_nominal(self, cam: str) -> np.ndarray:
        """The configured depth scale and mount of a camera: a saved state is for these values only."""
        return self.nominal[self.layout.camera_slice(cam)][:len(CAMERA_PARAMS)]

    def _persist_name(self, name: str) -> str:
        cam, p = name.rsplit(".", 1)
        if cam == "odometry":
            return name
        return f"{_camera_key(self.robot.camera(cam))}.{p}"

    def load_json(self, data: object) -> List[str]:
        """Start from a persisted state; what was not taken and why (a camera replaced, a config
        changed since). Never raises on a malformed state: it is ignored with a note."""
        notes: List[str] = []
        try:
            if not isinstance(data, dict) or data.get("version") != STATE_VERSION:
                return ["saved calibration state ignored: unknown version"]
            names = [str(n) for n in data["names"]]
            mean = np.array(data["mean"], float)
            cov = np.array(data["cov"], float)
            info = np.array(data["info_data"], float)
            n = len(names)
            if mean.shape != (n,) or cov.shape != (n, n) or info.shape != (n, n) or not (
                    np.all(np.isfinite(mean)) and np.all(np.isfinite(cov)) and np.all(np.isfinite(info))):
                return ["saved calibration state ignored: malformed arrays"]
            if np.linalg.eigvalsh(0.5 * (cov + cov.T))[0] <= 0:
                return ["saved calibration state ignored: covariance not positive definite"]
            saved_cams = data.get("cameras", {})
        except (KeyError, TypeError, ValueError, np.linalg.LinAlgError):
            return ["saved calibration state ignored: malformed"]
        # Which saved states still describe this robot: same camera (serial) and same configured values.
        usable: Dict[str, int] = {}
        for i, pname in enumerate(names):
            key, p = pname.rsplit(".", 1) if "." in pname else ("", pname)
            if key == "odometry":
                nominal = np.array(data.get("odometry_nominal", []), float)
                if nominal.shape == (len(ODOMETRY_PARAMS),) and np.allclose(nominal, self.nominal[self.layout.odometry_slice]):
                    usable[f"odometry.{p}"] = i
                continue
            saved = saved_cams.get(key) if isinstance(saved_cams, dict) else None
            cam = next((c for c in self.robot.cameras if _camera_key(c) == key), None)
            if cam is None or not isinstance(saved, dict):
                continue
            nominal = np.array(saved.get("nominal", []), float)
            mine = self._camera_nominal(cam.name)
            if nominal.shape != mine.shape or not np.allclose(nominal, mine):
                continue
            usable[f"{cam.name}.{p}"] = i
        take = [(j, usable[name]) for j, name in enumerate(self.names) if name in usable]
        for cfg in self.robot.cameras:
            if not any(self.names[j].startswith(cfg.name + ".") for j, _ in take):
                notes.append(f"camera {cfg.name}: no saved calibration state for it (new camera, new config or "
                             "first run): starting from the configured values")
        if not any(self.names[j].startswith("odometry.") for j, _ in take):
            notes.append("odometry: no saved calibration state for this chassis config: starting from the configured values")
        if not take:
            return notes
        mine, theirs = [j for j, _ in take], [i for _, i in take]
        self.mean[mine] = mean[theirs]
        C = self.cov.copy()
        C[np.ix_(mine, mine)] = cov[np.ix_(theirs, theirs)]
        self.cov = C
        I = self.info_data.copy()
        I[np.ix_(mine, mine)] = info[np.ix_(theirs, theirs)]
        self.info_data = I
        self.windows = int(data.get("windows", 0)) if isinstance(data.get("windows", 0), int) else 0
        self._check_bounds()
        return notes


def _camera_key(cam) -> str:
    return f"serial:{cam.serial}" if cam.serial else f"name:{cam.name}"
