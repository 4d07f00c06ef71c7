"""What calibration data is, and the equations that tie it to the parameters (docs/calibration.md).

Parameters, per camera (in the camera's config order): ``depth_scale`` S (multiplies the depth the
camera reports), the mount ``x, y, z`` (m) and ``roll, pitch, yaw`` (rad, URDF R = Rz Ry Rx, as
``mount_rpy_deg``); for the wheels: the mean rolling radius ``wheel_radius``, three differences
between the wheels (``wheel_diff_crab``, ``wheel_diff_turn``, ``wheel_diff_axle``: unequal wheels
make a Mecanum robot crab and turn while it drives, which would otherwise be read as a mount yaw)
and ``lx_plus_ly``. The robot pose of each keyframe is a parameter too, solved for and dropped.

Plane equation. A camera that reads k times the true depth sees a plane with the true normal and
k times its offset: n . p' + k d = 0 in its optical frame C. With S = 1 / k the calibration,
S_a the scale the localizer already applied, the pose (x, y, phi) and the mount T_RC = (R, t)::

    n_R    = Rz(-phi) n_G                       the map plane's normal in the robot frame
    n_C    = R^T n_R                            its normal in the camera frame
    d_C    = n_Gx x + n_Gy y + n_R . t + d_G    the camera's distance to it
    r_d    = d_meas - (S_a / S) d_C             one scalar per fitted wall
    r_n    = B n_C                              B: two unit vectors orthogonal to the measured normal

Odometry equation. Between keyframes a and b the wheel angles advance by dtheta_k (100 Hz
reports); wheel i rolls u_i = r_i dtheta_i, and the body moves (sum u / 4, (-u1 + u2 + u3 - u4) /
4) while turning (-u1 + u2 - u3 + u4) / (4 L), integrated step by step at the mid-step heading::

    r_o = [Rz(-phi_a) (p_b - p_a) - dp_odo(r, L),  wrap(phi_b - phi_a - dphi_odo(r, L))]
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import R_BODY_OPTICAL, rpy_to_matrix, wrap_angle
from robot.config import RobotConfig
from robot.maps.plane_map import MapPlane

CAMERA_PARAMS = ("depth_scale", "x", "y", "z", "roll", "pitch", "yaw")
# The camera's smooth disparity error over its image, up to fourth order (px): every monomial
# u^i v^j with i + j <= 4 (15 terms), u and v from the image centre in half-widths and
# half-heights. A D435i has such an error (its stereo calibration); it biases depth like a scale
# error that depends on where the wall is in the image, so it is estimated beside the scale, with
# the localizer's systematic disparity error as its prior, and never written: a nuisance. Why
# fourth order: a field of up to 1.5 cycles per image width (the D435's) is not followed by a
# cubic; on simulated cameras other than the one the third order was tried on, the batch depth
# scale came out 0.07 % off (7 of its standard deviations); with the quartic terms within 0.035 %
# for every camera tried, and a fifth order changed nothing (docs/calibration.md).
DISPARITY_ORDER = 4
_FIELD_LOW = ((0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2))  # (power of u, power of v), the first six
# every monomial u^i v^j up to DISPARITY_ORDER, the first six in the order they always had
FIELD_POWERS = _FIELD_LOW + tuple((n - j, j) for n in range(3, DISPARITY_ORDER + 1) for j in range(n + 1))
DISPARITY_PARAMS = tuple("disparity_" + ("u" * i + "v" * j or "0") for i, j in FIELD_POWERS)
CAMERA_BLOCK = CAMERA_PARAMS + DISPARITY_PARAMS
# A map wall as built (docs/calibration.md, "Walls as built"): its offset along its normal (m, the
# change of the plane's d), a turn about the vertical and an out-of-plumb tilt about the wall's
# horizontal line (rad), both through the wall's pivot point. Every view of a wall shares them, so
# the online estimator keeps them as states from window to window; never written: nuisances.
WALL_PARAMS = ("offset", "turn", "plumb")
WALL_PREFIX = "plane:"
ODOMETRY_PARAMS = ("wheel_radius", "wheel_diff_crab", "wheel_diff_turn", "wheel_diff_axle", "lx_plus_ly")
# r_i = r + H[i] . (crab, turn, axle): FL, FR, RL, RR. Orthogonal columns, each summing to zero,
# so r stays the mean radius.
WHEEL_DIFFS = np.array([[-1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0]])
ANGLE_PARAMS = ("roll", "pitch", "yaw")
D435_BASELINE = 0.050  # m, the stereo baseline behind the systematic depth error
CONSIDER_TERMS = len(DISPARITY_PARAMS)  # terms of the disparity error field, up to DISPARITY_ORDER
# Prior std of each term in units of the field's RMS (``LocalizerConfig.depth_systematic_px``): the
# offset is the field's RMS; a smooth field of about one cycle per image width changes by about
# 2.5 times its RMS over a half-width, so the slopes and the higher-order terms get that. Tighter,
# the walls' tilt from a slope is taken for a mount pitch. The third-order terms are there because
# a field of up to 1.5 cycles per image width (the D435's, docs/simulator.md) still has a local
# slope that second order cannot follow, and that slope is the same in every view from the same
# place in the image: left out, it does not average away and the mount pitch learnt online became
# several of its own standard deviations wrong.
DISPARITY_PRIOR_FACTORS = (1.0,) + (2.5,) * (len(FIELD_POWERS) - 1)


def disparity_prior_std(systematic_px: float) -> np.ndarray:
    """(CONSIDER_TERMS,) prior standard deviations (px) of the disparity terms for a field of ``systematic_px`` RMS."""
    return np.maximum(np.asarray(DISPARITY_PRIOR_FACTORS) * float(systematic_px), 1e-6)


@dataclass
class PlaneObservation:
    """One fitted wall in one camera frame, as the localizer saw it."""

    camera: str
    plane_id: str
    n_ground: np.ndarray  # (3,) map plane in G
    d_ground: float
    n_camera: np.ndarray  # (3,) fitted unit normal in the optical frame, towards the camera
    d_camera: float  # m, fitted offset in the optical frame (the camera's distance to the wall)
    applied_scale: float  # the depth scale the frame already carried (the config's), S_a
    sigma: Tuple[float, float, float]  # (d m, heading rad, tilt rad) standard deviations
    center: Tuple[float, float] = (0.0, 0.0)  # where the fitted points lie in the image: (u, v) from the
    # centre in half-widths and half-heights (-1 .. 1)


@dataclass
class Keyframe:
    """The frames taken at one instant (one robot pose) and what they saw."""

    t: float
    pose: Tuple[float, float, float]  # initial guess (x, y, phi) in G
    observations: List[PlaneObservation] = field(default_factory=list)
    truth: Optional[Tuple[float, float, float]] = None  # simulation only: evaluation, never the solve


class OdometryTrack:
    """Cumulative wheel angles over time (the encoder reports), to integrate between keyframes."""

    def __init__(self, max_gap: float = 0.25):
        self.max_gap = float(max_gap)  # s: a longer gap between reports breaks the chain there
        self._t: List[float] = []
        self._angles: List[Tuple[float, float, float, float]] = []
        self._arrays: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t: float, angles: Sequence[float]) -> None:
        if self._t and t <= self._t[-1]:
            return  # a repeated or reordered report adds nothing
        self._t.append(float(t))
        self._angles.append(tuple(float(a) for a in angles))  # type: ignore[arg-type]
        self._arrays = None

    def drop_before(self, t: float) -> None:
        i = int(np.searchsorted(np.asarray(self._t), t, side="right")) - 1
        if i > 0:
            del self._t[:i]
            del self._angles[:i]
            self._arrays = None

    @property
    def span(self) -> Tuple[float, float]:
        return (self._t[0], self._t[-1]) if self._t else (math.inf, -math.inf)

    def _as_arrays(self) -> Tuple[np.ndarray, np.ndarray]:
        if self._arrays is None:
            self._arrays = (np.asarray(self._t, float), np.asarray(self._angles, float).reshape(-1, 4))
        return self._arrays

    def steps(self, t0: float, t1: float) -> Optional[np.ndarray]:
        """(M, 4) wheel-angle increments from t0 to t1 (ends interpolated), or None if the reports
        do not cover the interval without a gap."""
        if not self._t or t0 < self._t[0] or t1 > self._t[-1] or t1 <= t0:
            return None
        t, a = self._as_arrays()
        i0 = int(np.searchsorted(t, t0, side="right"))  # first report after t0 (t[i0 - 1] <= t0)
        i1 = int(np.searchsorted(t, t1, side="left"))  # first report at or after t1
        if np.max(np.diff(t[max(i0 - 1, 0):i1 + 1])) > self.max_gap:
            return None
        times = np.concatenate([[t0], t[i0:i1], [t1]])
        lo, hi = max(i0 - 1, 0), min(i1 + 1, len(t))
        ang = np.stack([np.interp(times, t[lo:hi], a[lo:hi, w]) for w in range(4)], axis=1)
        return np.diff(ang, axis=0)


@dataclass
class Dataset:
    """Everything one solve looks at."""

    cameras: Tuple[str, ...]
    keyframes: List[Keyframe]
    odometry: OdometryTrack
    nominal: np.ndarray  # the parameter vector the data was taken with (``ParamLayout`` order)
    # Per camera (f_x, f_y, width, height) at full resolution, and the RMS (px) of the matcher's
    # systematic disparity error over a wall: an error the solve cannot remove, whose effect it
    # adds to the covariance (the solver's "consider" terms).
    intrinsics: Dict[str, Tuple[float, float, float, float]] = field(default_factory=dict)
    systematic_px: float = 0.0
    # (3,) pivot in G of each wall whose as-built deviation is a parameter (``ParamLayout.walls``)
    walls: Dict[str, np.ndarray] = field(default_factory=dict)

    def observation_count(self) -> int:
        return sum(len(k.observations) for k in self.keyframes)


class ParamLayout:
    """Names and order of the calibration parameters for a robot's cameras."""

    def __init__(self, cameras: Sequence[str], walls: Sequence[str] = ()):
        self.cameras = tuple(cameras)
        self.walls = tuple(walls)  # plane ids whose as-built deviation (WALL_PARAMS) is a parameter
        self.names: List[str] = [f"{c}.{p}" for c in self.cameras for p in CAMERA_BLOCK]
        self.names += [f"odometry.{p}" for p in ODOMETRY_PARAMS]
        self.names += [f"{WALL_PREFIX}{w}.{p}" for w in self.walls for p in WALL_PARAMS]
        self._index = {n: i for i, n in enumerate(self.names)}

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self._index[name]

    def camera_slice(self, camera: str) -> slice:
        i = self.cameras.index(camera) * len(CAMERA_BLOCK)
        return slice(i, i + len(CAMERA_BLOCK))

    def wall_slice(self, wall: str) -> slice:
        i = self.odometry_slice.stop + self.walls.index(wall) * len(WALL_PARAMS)
        return slice(i, i + len(WALL_PARAMS))

    @property
    def nuisance(self) -> List[int]:
        """The disparity error terms and the walls as built: estimated, never reported as calibration or written."""
        return [i for i, n in enumerate(self.names) if is_nuisance(n)]

    @property
    def odometry_slice(self) -> slice:
        i = len(self.cameras) * len(CAMERA_BLOCK)
        return slice(i, i + len(ODOMETRY_PARAMS))

    def nominal(self, robot: RobotConfig) -> np.ndarray:
        """The parameter vector a robot config stands for (its cameras' depth scales and mounts, its chassis)."""
        theta = np.zeros(len(self))
        for cam_name in self.cameras:
            cam = robot.camera(cam_name)
            theta[self.camera_slice(cam_name)] = [cam.depth_scale, *cam.mount_xyz,
                                                  *(math.radians(a) for a in cam.mount_rpy_deg),
                                                  *(0.0 for _ in DISPARITY_PARAMS)]
        ch = robot.chassis
        theta[self.odometry_slice] = [ch.wheel_radius, 0.0, 0.0, 0.0, ch.half_wheelbase + ch.half_track]
        return theta


def wall_prior(plane: MapPlane) -> Tuple[np.ndarray, np.ndarray]:
    """(pivot (3,) in G, std (3,) of ``WALL_PARAMS``) of a map wall's as-built deviation: the
    plane's ``tolerance`` as the offset, the tolerance over the wall's length and over its height
    (each at least 1 m) as the turn and the out-of-plumb tilt, as the localizer's integrity model
    takes them. The tilt is what bounds a mount's roll and pitch: a wall's lean is read as the
    camera's unless the map says how plumb it was built."""
    v = np.concatenate([np.asarray(poly, float).reshape(-1, 3) for poly in plane.polygons])
    extent = v.max(axis=0) - v.min(axis=0)
    length, height = math.hypot(float(extent[0]), float(extent[1])), float(extent[2])
    tol = float(plane.tolerance)
    return v.mean(axis=0), np.array([tol, tol / max(length, 1.0), tol / max(height, 1.0)])


def with_walls_as_built(data: Dataset, planes: Mapping[str, MapPlane]) -> Tuple[Dataset, Dict[str, np.ndarray]]:
    """The dataset with every observed wall that ``planes`` holds as a parameter (its pivot in
    ``data.walls``, zeros appended to the nominal vector), and each such wall's prior std.

    A batch solve that took the walls as drawn would turn their builders' tolerances into the
    calibration: a few millimetres of offset read as a depth scale, a lean as a mount's roll or
    pitch, each with a standard deviation from the pixel noise alone."""
    base = len(ParamLayout(data.cameras))
    seen = sorted({o.plane_id for kf in data.keyframes for o in kf.observations if o.plane_id in planes})
    pivots: Dict[str, np.ndarray] = {}
    stds: Dict[str, np.ndarray] = {}
    for w in seen:
        pivots[w], stds[w] = wall_prior(planes[w])
    nominal = np.concatenate([np.asarray(data.nominal, float)[:base], np.zeros(len(WALL_PARAMS) * len(seen))])
    return replace(data, nominal=nominal, walls=pivots), stds


def is_wall_param(name: str) -> bool:
    return name.startswith(WALL_PREFIX)


def is_nuisance(name: str) -> bool:
    """A parameter estimated only so the others are not biased: never reported or written."""
    return is_wall_param(name) or name.rsplit(".", 1)[1] in DISPARITY_PARAMS


def camera_rotation(rpy: Sequence[float]) -> np.ndarray:
    """R_RC of the optical frame for a body roll, pitch, yaw (rad)."""
    return rpy_to_matrix(*rpy) @ R_BODY_OPTICAL


def wheel_radii(odo: np.ndarray) -> np.ndarray:
    """(4,) radii FL, FR, RL, RR from the odometry parameters (r, crab, turn, axle, L)."""
    return odo[0] + WHEEL_DIFFS @ odo[1:4]


def integrate_wheels(steps: np.ndarray, segment: np.ndarray, n_segments: int, odo: np.ndarray) -> np.ndarray:
    """(n_segments, 3) body motion (dx, dy in the segment's start frame, dphi) of each segment's
    wheel-angle steps (``steps`` (M, 4), ``segment`` (M,) its index, segments contiguous)."""
    u = steps * wheel_radii(odo)[None, :]
    du = u.sum(axis=1) / 4.0
    dv = (-u[:, 0] + u[:, 1] + u[:, 2] - u[:, 3]) / 4.0
    dphi = (-u[:, 0] + u[:, 1] - u[:, 2] + u[:, 3]) / (4.0 * odo[4])
    before = np.cumsum(dphi) - dphi  # heading turned before each step, counted over all segments
    first = np.searchsorted(segment, np.arange(n_segments))
    first = np.minimum(first, len(segment) - 1)
    h = before - before[first][segment] + 0.5 * dphi  # mid-step heading in the segment's start frame
    c, s = np.cos(h), np.sin(h)
    out = np.zeros((n_segments, 3))
    out[:, 0] = np.bincount(segment, c * du - s * dv, n_segments)
    out[:, 1] = np.bincount(segment, s * du + c * dv, n_segments)
    out[:, 2] = np.bincount(segment, dphi, n_segments)
    return out


def field_terms(u0: np.ndarray, v0: np.ndarray) -> np.ndarray:
    """(N, 3, CONSIDER_TERMS): the disparity field's terms (``DISPARITY_PARAMS``) as the affine field
    they look like near image points (u0, v0) (half-widths and half-heights from the centre): its
    slope along u, its slope along v and its value extrapolated to the optical axis, per unit term."""
    u0, v0 = np.asarray(u0, float), np.asarray(v0, float)
    # Each term f(u, v) with its gradient (f_u, f_v); the axis value is f - u0 f_u - v0 f_v.
    zero = np.zeros_like(u0)
    f = [u0 ** i * v0 ** j for i, j in FIELD_POWERS]
    f_u = [i * u0 ** (i - 1) * v0 ** j if i else zero for i, j in FIELD_POWERS]
    f_v = [j * u0 ** i * v0 ** (j - 1) if j else zero for i, j in FIELD_POWERS]
    T = np.empty((len(u0), 3, CONSIDER_TERMS))
    T[:, 0, :] = np.stack(f_u, axis=-1)
    T[:, 1, :] = np.stack(f_v, axis=-1)
    T[:, 2, :] = np.stack(f, axis=-1) - u0[:, None] * T[:, 0, :] - v0[:, None] * T[:, 1, :]
    return T


def disparity_effect(n_C: np.ndarray, d: float, center: Sequence[float],
                     intrinsics: Tuple[float, float, float, float]) -> Tuple[np.ndarray, np.ndarray]:
    """What the camera's disparity error terms (``DISPARITY_PARAMS``, px) do to a wall it fits:
    (CONSIDER_TERMS,) to its offset and (3, CONSIDER_TERMS) to its normal, to first order (d' = d + dd . e, n' = n + dn e).

    Near the wall's points (u0, v0) the error field is affine; an affine disparity error e adds
    e / (f_x b) to the plane's inverse depth q = -n / d along each ray (x/z, y/z, 1), so
    dq = A (slope_u, slope_v, offset at the optical axis), d' = d + d^2 n . dq and
    n' = n - d (I - n n^T) dq."""
    fx, fy, w, h = intrinsics
    u0, v0 = center
    T = field_terms(np.array([u0], float), np.array([v0], float))[0]
    dq = np.diag([fx / (w / 2.0), fy / (h / 2.0), 1.0]) @ T / (fx * D435_BASELINE)
    n = np.asarray(n_C, float)
    return d * d * (n @ dq), -d * (np.eye(3) - np.outer(n, n)) @ dq


@dataclass
class PlaneArrays:
    """The plane observations of a dataset as arrays (one row per observation)."""

    keyframe: np.ndarray  # (N,) keyframe index
    camera: np.ndarray  # (N,) camera index
    n_ground: np.ndarray  # (N, 3)
    d_ground: np.ndarray
    d_meas: np.ndarray
    applied: np.ndarray
    basis: np.ndarray  # (N, 2, 3): heading and tilt directions orthogonal to the measured normal
    sigma: np.ndarray  # (N, 3)
    # (N, 3, CONSIDER_TERMS): d residual / d (DISPARITY_PARAMS) of the camera's disparity error, seen by each
    # wall as its local offset and slopes where its points are
    consider: np.ndarray
    wall: Optional[np.ndarray] = None  # (N,) index into ``ParamLayout.walls`` of the observed wall, -1: none
    pivot: Optional[np.ndarray] = None  # (N, 3) that wall's pivot in G

    @classmethod
    def build(cls, data: Dataset, layout: ParamLayout) -> PlaneArrays:
        obs = [o for kf in data.keyframes for o in kf.observations]
        n = len(obs)
        keyframe = np.array([k for k, kf in enumerate(data.keyframes) for _ in kf.observations], int)
        camera = np.array([layout.cameras.index(o.camera) for o in obs], int)
        n_C = np.array([o.n_camera for o in obs], float).reshape(n, 3)
        d = np.array([o.d_camera for o in obs], float)
        # The heading direction is horizontal in the robot frame (nominal mount), the tilt one is
        # orthogonal to it and the normal: errors of the pose heading move the first only.
        R0 = np.stack([camera_rotation(data.nominal[layout.camera_slice(c)][4:7]) for c in layout.cameras])
        n_R = np.einsum("nij,nj->ni", R0[camera], n_C) if n else np.zeros((0, 3))
        e_h = np.stack([-n_R[:, 1], n_R[:, 0], np.zeros(n)], axis=1)
        h = np.linalg.norm(e_h, axis=1)
        e_h = np.where(h[:, None] > 1e-6, e_h / np.maximum(h, 1e-12)[:, None], np.array([1.0, 0.0, 0.0]))
        e_h_C = np.einsum("nji,nj->ni", R0[camera], e_h) if n else np.zeros((0, 3))
        e_t_C = np.cross(n_C, e_h_C)
        e_t_C /= np.maximum(np.linalg.norm(e_t_C, axis=1), 1e-12)[:, None]
        basis = np.stack([e_h_C, e_t_C], axis=1) if n else np.zeros((0, 2, 3))
        sigma = np.array([o.sigma for o in obs], float).reshape(n, 3)
        sigma[:, 1] *= np.maximum(h, 0.05)
        # A disparity error e (px), affine near the wall's points (u0, v0), adds e / (f_x b) to the
        # plane's inverse depth q = -n / d along each ray (x/z, y/z, 1): dq = A (slope_u, slope_v,
        # offset at the optical axis). Then d' = d + d^2 n . dq and n' = n - d (I - n n^T) dq.
        consider = np.zeros((n, 3, CONSIDER_TERMS))
        uv = np.array([o.center for o in obs], float).reshape(n, 2)
        u0, v0 = uv[:, 0], uv[:, 1]
        T = field_terms(u0, v0)
        for ci, c in enumerate(layout.cameras):
            if c not in data.intrinsics:
                continue
            fx, fy, w, hgt = data.intrinsics[c]
            A = np.diag([fx / (w / 2.0), fy / (hgt / 2.0), 1.0]) / (fx * D435_BASELINE)
            m = camera == ci
            dq = np.einsum("ij,njk->nik", A, T[m])  # (n, 3, terms)
            consider[m, 0, :] = np.einsum("ni,nik->nk", d[m, None] ** 2 * n_C[m], dq)
            consider[m, 1:, :] = d[m, None, None] * np.einsum("nai,nik->nak", basis[m], dq)
        wall = np.array([layout.walls.index(o.plane_id) if o.plane_id in layout.walls else -1 for o in obs], int)
        pivot = np.array([np.asarray(data.walls.get(o.plane_id, np.zeros(3)), float) for o in obs]).reshape(n, 3)
        return cls(keyframe, camera, np.array([o.n_ground for o in obs], float).reshape(n, 3),
                   np.array([o.d_ground for o in obs], float), d, np.array([o.applied_scale for o in obs], float),
                   basis, sigma, consider, wall, pivot)


def wall_directions(n_ground: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(N, 3) each: how a wall's normal moves by its turn about the vertical (up x n) and by its out
    of plumb tilt (-up: the top leans towards the side the normal faces)."""
    a = np.cross(np.array([0.0, 0.0, 1.0]), n_ground)
    b = np.zeros_like(n_ground)
    b[:, 2] = -1.0
    return a, b


def plane_residuals(planes: PlaneArrays, poses: np.ndarray, cams: np.ndarray, jacobian: bool = False,
                    walls: Optional[np.ndarray] = None) -> Tuple[np.ndarray, Optional[Tuple[np.ndarray, ...]]]:
    """Residuals (N, 3) = (r_d, r_heading, r_tilt), unwhitened, and with ``jacobian`` their
    derivatives: (N, 3, 3) by the keyframe pose (x, y, phi), (N, 3, 13) by the camera's own
    parameters (S, x, y, z, roll, pitch, yaw, then the disparity terms) and (N, 3, 3) by the
    observed wall's as-built deviation (WALL_PARAMS; zero for a wall without). ``cams``: (C, 13);
    ``walls``: (W, 3), one row per ``ParamLayout.walls``."""
    k, c = planes.keyframe, planes.camera
    phi = poses[k, 2]
    co, si = np.cos(phi), np.sin(phi)
    nG = planes.n_ground
    dG = planes.d_ground
    has_wall = planes.wall is not None and walls is not None and len(walls) > 0 and bool(np.any(planes.wall >= 0))
    if has_wall:
        # the wall as built: turned and tilted about its pivot, then moved along its normal
        wi = np.maximum(planes.wall, 0)
        on = (planes.wall >= 0)[:, None]
        w = np.where(on, walls[wi], 0.0)
        a_dir, b_dir = wall_directions(nG)
        n_built = nG + w[:, 1:2] * a_dir + w[:, 2:3] * b_dir
        n_built /= np.linalg.norm(n_built, axis=1)[:, None]
        dG = dG + w[:, 0] - np.einsum("oi,oi->o", n_built - nG, planes.pivot)
        nG = n_built
    n_R = np.stack([nG[:, 0] * co + nG[:, 1] * si, -nG[:, 0] * si + nG[:, 1] * co, nG[:, 2]], axis=1)
    R = np.stack([camera_rotation(p[4:7]) for p in cams])  # (C, 3, 3)
    t = cams[:, 1:4]
    n_C = np.einsum("oji,oj->oi", R[c], n_R)
    S = cams[c, 0]
    d_pred = nG[:, 0] * poses[k, 0] + nG[:, 1] * poses[k, 1] + np.einsum("oi,oi->o", n_R, t[c]) + dG
    res = np.zeros((len(k), 3))
    # measured = scale x model, not model / scale = measured: the noisy measurement must not be a
    # lever of the scale (errors in variables would give the scale information it does not have)
    gain = planes.applied / S
    res[:, 0] = planes.d_meas - gain * d_pred
    res[:, 1:] = np.einsum("oai,oi->oa", planes.basis, n_C)
    # what the camera's disparity error put into the measurement, taken out again
    res -= np.einsum("ork,ok->or", planes.consider, cams[c, len(CAMERA_PARAMS):])
    if not jacobian:
        return res, None
    dn_R = np.stack([n_R[:, 1], -n_R[:, 0], np.zeros(len(k))], axis=1)  # d n_R / d phi
    Jp = np.zeros((len(k), 3, 3))
    Jp[:, 0, 0], Jp[:, 0, 1] = -gain * nG[:, 0], -gain * nG[:, 1]
    Jp[:, 0, 2] = -gain * np.einsum("oi,oi->o", dn_R, t[c])
    Jp[:, 1:, 2] = np.einsum("oai,oji,oj->oa", planes.basis, R[c], dn_R)
    Jc = np.zeros((len(k), 3, len(CAMERA_BLOCK)))
    Jc[:, 0, 0] = gain / S * d_pred
    Jc[:, :, len(CAMERA_PARAMS):] = -planes.consider
    Jc[:, 0, 1:4] = -gain[:, None] * n_R
    h = 1e-6
    for j in range(3):  # the rotation's derivatives, per camera, by central differences
        dR = []
        for p in cams:
            up, dn = p[4:7].copy(), p[4:7].copy()
            up[j] += h
            dn[j] -= h
            dR.append((camera_rotation(up) - camera_rotation(dn)) / (2 * h))
        dR = np.stack(dR)
        Jc[:, 1:, 4 + j] = np.einsum("oai,oji,oj->oa", planes.basis, dR[c], n_R)
    Jw = np.zeros((len(k), 3, len(WALL_PARAMS)))
    if has_wall:
        # through the map plane: d r_d / d d_G = -gain; d r_d / d n_G = -gain (p + Rz(phi) t) (p the
        # robot's position at z = 0); d r_angles / d n_G = B R^T Rz(-phi)
        zero, one = np.zeros(len(k)), np.ones(len(k))
        Rzm = np.stack([np.stack([co, si, zero], 1), np.stack([-si, co, zero], 1), np.stack([zero, zero, one], 1)], 1)
        t_G = np.einsum("oji,oj->oi", Rzm, t[c])  # Rz(phi) t
        p = np.stack([poses[k, 0], poses[k, 1], zero], axis=1)
        dn = np.zeros((len(k), 3, 3))
        dn[:, 0, :] = -gain[:, None] * (p + t_G)
        dn[:, 1:, :] = np.einsum("oai,oji,ojk->oak", planes.basis, R[c], Rzm)
        dd = np.zeros((len(k), 3))
        dd[:, 0] = -gain
        Jw[:, :, 0] = dd
        Jw[:, :, 1] = np.einsum("ork,ok->or", dn, a_dir) - dd * np.einsum("oi,oi->o", a_dir, planes.pivot)[:, None]
        Jw[:, :, 2] = np.einsum("ork,ok->or", dn, b_dir) - dd * np.einsum("oi,oi->o", b_dir, planes.pivot)[:, None]
        Jw[planes.wall < 0] = 0.0
    return res, (Jp, Jc, Jw)


@dataclass
class OdometryArrays:
    """The wheel motion between consecutive keyframes that odometry covers."""

    a: np.ndarray  # (M,) keyframe index at the start of each interval
    b: np.ndarray  # (M,) keyframe index at its end
    steps: np.ndarray  # (S, 4) wheel-angle steps of all intervals
    segment: np.ndarray  # (S,) interval index of each step
    travel: np.ndarray  # (M,) m a wheel rolled (nominal radius), for the noise model
    turn: np.ndarray  # (M,) rad turned (nominal)

    @classmethod
    def build(cls, data: Dataset, layout: ParamLayout) -> OdometryArrays:
        a, b, steps, seg = [], [], [], []
        order = sorted(range(len(data.keyframes)), key=lambda i: data.keyframes[i].t)
        for i, j in zip(order, order[1:]):
            ti, tj = data.keyframes[i].t, data.keyframes[j].t
            s = data.odometry.steps(ti, tj) if tj > ti else None
            if s is None:
                continue
            seg.append(np.full(len(s), len(a)))
            a.append(i)
            b.append(j)
            steps.append(s)
        if not a:
            return cls(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4)), np.zeros(0, int), np.zeros(0), np.zeros(0))
        steps_all, seg_all = np.concatenate(steps), np.concatenate(seg)
        odo0 = data.nominal[layout.odometry_slice]
        motion = integrate_wheels(steps_all, seg_all, len(a), odo0)
        return cls(np.array(a), np.array(b), steps_all, seg_all, np.hypot(motion[:, 0], motion[:, 1]),
                   np.abs(motion[:, 2]))


def odometry_residuals(odo: OdometryArrays, poses: np.ndarray, odo_params: np.ndarray,
                       jacobian: bool = False):
    """Residuals (M, 3) of vision motion against wheel motion and, with ``jacobian``, their
    derivatives by the start pose, the end pose (M, 3, 3 each) and the odometry parameters (M, 3, 5)."""
    m = len(odo.a)
    motion = integrate_wheels(odo.steps, odo.segment, m, odo_params)
    pa, pb = poses[odo.a], poses[odo.b]
    c, s = np.cos(pa[:, 2]), np.sin(pa[:, 2])
    dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
    res = np.zeros((m, 3))
    res[:, 0] = c * dx + s * dy - motion[:, 0]
    res[:, 1] = -s * dx + c * dy - motion[:, 1]
    res[:, 2] = wrap_angle(pb[:, 2] - pa[:, 2] - motion[:, 2])
    if not jacobian:
        return res, None
    Ja, Jb = np.zeros((m, 3, 3)), np.zeros((m, 3, 3))
    Jb[:, 0, 0], Jb[:, 0, 1], Jb[:, 1, 0], Jb[:, 1, 1] = c, s, -s, c
    Ja[:, :2, :2] = -Jb[:, :2, :2]
    Ja[:, 0, 2] = -s * dx + c * dy
    Ja[:, 1, 2] = -c * dx - s * dy
    Ja[:, 2, 2], Jb[:, 2, 2] = -1.0, 1.0
    Jo = np.zeros((m, 3, len(odo_params)))
    for j in range(len(odo_params)):
        h = 1e-7 * max(abs(odo_params[j]), 1e-2)
        up, dn = odo_params.copy(), odo_params.copy()
        up[j] += h
        dn[j] -= h
        d = (integrate_wheels(odo.steps, odo.segment, m, up) - integrate_wheels(odo.steps, odo.segment, m, dn)) / (2 * h)
        Jo[:, :, j] = -d
    return res, (Ja, Jb, Jo)
