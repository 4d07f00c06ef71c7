"""Simulated D435i depth frames: the fake camera's renderer and its depth error models.

The scene is the map's polygons (or their as-built version, ``drivers.sim.clutter.as_built``)
plus what a real site adds and the map does not know: the floor, a backdrop beyond the walls (a
room around the arena) and clutter. Each polygon is clipped to the frustum, rasterized, and its
exact depth along each pixel ray written through a z-buffer, so occlusion and partial views are
exact.

Map polygons are one-sided (a face is seen from its normal's side; a real wall is two faces in
an imported map), so a map face seen from behind is not drawn: otherwise a camera looking
through a door would see the back of the wall's far face, a surface one wall thickness behind
the opening that no real camera sees. Clutter, floor and backdrop are closed or enclosing
surfaces and stay double-sided.

Depth errors (``DepthNoise``; docs/simulator.md has the figures):

* ``realistic`` (the default): the error is made where a stereo camera makes it, in disparity
  d = f_x b / z. The matcher's subpixel error (0.08 px RMS) is spatially correlated over its
  window; a fixed low-frequency disparity "wave" per camera unit and a periodic subpixel
  non-linearity add systematic error; flying pixels mix the two sides of depth edges; the stereo
  shadow left of near objects, the left border band, dark or shiny blobs, random drop-outs and a
  fill rate falling beyond 4 m leave holes; a per-camera scale error makes depth read long or
  short.
* ``simple``: the earlier, kinder model: the same 0.08 px but independent per pixel, 1 %
  drop-outs and flying pixels on the four-neighbour edge only.
* ``exact`` (``noise=None`` or ``"none"``): no error, except a scale error if one is asked for.

``decimation`` renders what librealsense's decimation filter delivers: a frame of W/d x H/d
pixels with the intrinsics scaled to it. The error models keep the full-resolution f_x and
pixel coordinates: stereo error is made by the matcher, which works at full resolution, and the
filter's averaging of d x d neighbours removes little of it, since it is correlated over
neighbouring pixels (the realistic model draws the d x d block mean of its correlated field).
"""

from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass, field, fields, replace
from statistics import NormalDist
from typing import Any, List, Mapping, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from robot.base.errors import ConfigError
from robot.base.geometry import invert_transform, newell_normal, pose_to_T_ground_robot, transform_plane, transform_points
from robot.base.samples import DepthFrame
from robot.config import RobotConfig
from robot.maps.plane_map import PlaneMap
from robot.maps.visibility import clip_polygon, frustum_planes, project

_SUBPIXEL_BITS = 4  # fillPoly fixed-point: vertices placed to 1/16 pixel
_RIM_KERNEL = np.ones((3, 3), np.uint8)
NOISE_MODELS = ("realistic", "simple", "none")  # what ``noise=`` and the command lines accept by name
_MODELS = ("realistic", "simple", "exact")

ScaleErrors = Union[float, Mapping[str, float]]


@dataclass(frozen=True)
class DepthNoise:
    """How the simulated D435i's depth goes wrong. The defaults are the realistic model.

    Use :meth:`realistic`, :meth:`simple` or :meth:`exact` rather than ``model=``. Disparities
    and pixel sizes are full-resolution (848 x 480) pixels whatever the frame's decimation.
    """

    model: str = "realistic"
    baseline: float = 0.050  # m, D435i
    subpixel: float = 0.08  # disparity error RMS per pixel, px
    dropout: float = 0.005  # fraction of pixels returned as 0 at random (single pixels)
    flying_pixels: float = 0.5  # fraction of the pixels near a depth edge given a mix of its two sides
    edge_jump: float = 0.05  # relative depth jump that counts as an edge
    min_range: float = 0.2  # m, closer returns 0 (D435i minimum z at 848x480)
    max_range: float = 10.0  # m, farther returns 0
    # -- realistic model only --
    correlation_px: float = 1.5  # Gaussian std of the matcher-window smoothing of the subpixel error, px
    wave_px: float = 0.015  # RMS of the fixed low-frequency disparity error over the image, px (beyond a plane)
    wave_cycles: float = 1.5  # its highest spatial frequency, cycles per image width
    nonlinearity_px: float = 0.02  # amplitude of the error periodic in disparity (period 1 px), px
    edge_band_px: float = 2.0  # half-width of the band each side of a depth edge where the window mixes, px
    shadow: bool = True  # stereo occlusion left of near objects and the left border band are invalid
    search_range_px: float = 126.0  # the matcher's disparity search: a larger disparity (too near) is invalid
    blobs: float = 0.02  # fraction of the image lost to blobs of dark or shiny surface
    blob_px: float = 24.0  # their size scale, px
    fill_start: float = 4.0  # m, beyond this the fill rate falls ...
    fill_scale: float = 3.0  # m, ... as exp(-((z - fill_start) / fill_scale)^2): 64 % at 6 m, 2 % at 10 m
    unit_seed: int = 0  # which physical camera: decides its fixed wave (with the camera's name)
    # -- every model --
    scale_error: float = 0.0  # depth_reported = (1 + scale_error) * depth_true, for every camera ...
    camera_scale_errors: Tuple[Tuple[str, float], ...] = ()  # ... except these (camera name, error)

    def __post_init__(self) -> None:
        if self.model not in _MODELS:
            raise ConfigError(f"depth noise model must be one of {', '.join(_MODELS)}, got {self.model!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in ("model", "shadow", "camera_scale_errors", "unit_seed"):
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) or f.name == "fill_start" and v == math.inf):
                raise ConfigError(f"depth noise {f.name} must be a finite number, got {v!r}")
            if f.name != "scale_error" and v < 0:
                raise ConfigError(f"depth noise {f.name} must not be negative, got {v}")
        for name in ("dropout", "flying_pixels", "blobs"):
            if getattr(self, name) > 1:
                raise ConfigError(f"depth noise {name} is a fraction (0 to 1), got {getattr(self, name)}")
        if self.baseline <= 0 or self.max_range <= self.min_range:
            raise ConfigError("depth noise needs a positive baseline and max_range > min_range")
        for cam, e in ((None, self.scale_error), *self.camera_scale_errors):
            if not (math.isfinite(e) and -0.5 < e < 0.5):
                raise ConfigError(f"depth scale error{'' if cam is None else ' of camera ' + repr(cam)} must be "
                                  f"between -0.5 and 0.5 (0.01 reads 1 % long), got {e}")

    # -- constructors ------------------------------------------------------------------------------

    @classmethod
    def realistic(cls, scale_error: ScaleErrors = 0.0, **overrides: Any) -> DepthNoise:
        """The realistic D435i. ``scale_error``: one value for every camera or {camera: value}."""
        return cls(model="realistic", **_scale_kwargs(scale_error), **overrides)

    @classmethod
    def simple(cls, scale_error: ScaleErrors = 0.0, **overrides: Any) -> DepthNoise:
        """The earlier model: independent per-pixel disparity error, 1 % drop-outs, 4-neighbour flying pixels."""
        return cls(model="simple", dropout=overrides.pop("dropout", 0.01), **_scale_kwargs(scale_error), **overrides)

    @classmethod
    def exact(cls, scale_error: ScaleErrors = 0.0) -> DepthNoise:
        """Exact depth, only scaled by the camera's scale error."""
        return cls(model="exact", **_scale_kwargs(scale_error))

    def with_scale_error(self, scale_error: ScaleErrors) -> DepthNoise:
        return replace(self, **_scale_kwargs(scale_error))

    # -- figures -----------------------------------------------------------------------------------

    def scale_error_of(self, camera: str) -> float:
        for name, e in self.camera_scale_errors:
            if name == camera:
                return float(e)
        return float(self.scale_error)

    def sigma(self, z: np.ndarray, fx: float) -> np.ndarray:
        """Per-pixel depth standard deviation at depth z (first order): z^2 s / (f_x b)."""
        return z * z * self.subpixel / (fx * self.baseline)

    def inverse_depth_sigma(self, fx: float) -> float:
        """Standard deviation of 1/z (1/m): the matcher's disparity error s over f_x b, the same everywhere."""
        return self.subpixel / (fx * self.baseline)


def _scale_kwargs(scale_error: ScaleErrors) -> dict:
    if isinstance(scale_error, Mapping):
        return {"scale_error": 0.0,
                "camera_scale_errors": tuple(sorted((str(k), float(v)) for k, v in scale_error.items()))}
    return {"scale_error": float(scale_error), "camera_scale_errors": ()}


def resolve_noise(noise: Union[DepthNoise, str, None], scale_error: Optional[ScaleErrors] = None) -> Optional[DepthNoise]:
    """A ``DepthNoise`` from a model name (``realistic``, ``simple``, ``none``) or an instance; None
    means exact depth. ``scale_error`` (if given) replaces the model's."""
    if isinstance(noise, DepthNoise):
        model = noise
    elif noise is None or noise == "none":
        model = None
    elif noise in ("realistic", "default"):
        model = DepthNoise.realistic()
    elif noise == "simple":
        model = DepthNoise.simple()
    else:
        raise ConfigError(f"unknown depth noise model {noise!r} (choose from {', '.join(NOISE_MODELS)})")
    if scale_error is None:
        return model
    if model is None:
        if not isinstance(scale_error, Mapping) and float(scale_error) == 0.0:
            return None
        return DepthNoise.exact(scale_error)
    return model.with_scale_error(scale_error)


# -- scene ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Box:
    """An axis-aligned-in-yaw box standing on the floor: clutter the map does not contain."""

    x: float
    y: float
    size_x: float
    size_y: float
    height: float
    yaw: float = 0.0

    def faces(self) -> List[np.ndarray]:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        hx, hy = self.size_x / 2, self.size_y / 2
        corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
        xy = [(self.x + c * a - s * b, self.y + s * a + c * b) for a, b in corners]
        faces = []
        for i in range(4):
            (x0, y0), (x1, y1) = xy[i], xy[(i + 1) % 4]
            faces.append(np.array([[x0, y0, 0], [x1, y1, 0], [x1, y1, self.height], [x0, y0, self.height]], float))
        faces.append(np.array([[x, y, self.height] for x, y in xy], float))
        return faces


@dataclass
class SimScene:
    """Everything the fake cameras see, in the ground frame.

    ``clutter``: anything with ``faces() -> [(K, 3) polygon, ...]`` (``Box``, ``clutter.Solid``),
    drawn from both sides. ``walls``: the as-built surfaces (``clutter.BuiltWalls``: ``polygons``
    and, per polygon, the map plane whose front alone is drawn) drawn instead of the map's own
    polygons; the map itself stays what the localizer knows."""

    plane_map: PlaneMap
    clutter: Sequence[Any] = ()
    floor: bool = True
    backdrop: bool = True
    backdrop_margin: float = 3.0  # m beyond the map's extent
    backdrop_height: float = 3.0  # m, with a ceiling on top
    walls: Optional[Any] = None
    _polys: Optional[List[np.ndarray]] = field(default=None, repr=False)
    _sides: Optional[List[Optional[np.ndarray]]] = field(default=None, repr=False)
    _spheres: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default=None, repr=False)

    def polygons(self) -> List[np.ndarray]:
        if self._polys is None:
            if self.walls is not None:
                polys = [np.asarray(p, float) for p in self.walls.polygons]
                self._sides = list(self.walls.sides)
            else:
                polys = [poly for p in self.plane_map.planes for poly in p.polygons]
                # The map plane (n, d) of each one-sided polygon; None: drawn from both sides.
                self._sides = [p.pi for p in self.plane_map.planes for _ in p.polygons]
            for item in self.clutter:
                polys.extend(np.asarray(f, float) for f in item.faces())
            lo, hi = self.plane_map.bounds()
            m = self.backdrop_margin
            x0, y0, x1, y1 = lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m
            if self.floor:
                polys.append(np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], float))
            if self.backdrop:
                h = self.backdrop_height
                ring = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
                for i in range(4):
                    (a, b), (c, d) = ring[i], ring[(i + 1) % 4]
                    polys.append(np.array([[a, b, 0], [c, d, 0], [c, d, h], [a, b, h]], float))
                polys.append(np.array([[x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]], float))
            self._sides += [None] * (len(polys) - len(self._sides))
            self._polys = polys
        return self._polys

    def one_sided_planes(self) -> List[Optional[np.ndarray]]:
        """Per polygon of :meth:`polygons`: the map plane (n, d) whose front alone is drawn, or None."""
        self.polygons()
        return self._sides

    def bounding_spheres(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) centres and (N,) radii enclosing each polygon, for culling before clipping, and
        (N, 4) each polygon's plane (n, d), from all its vertices (a clipped or split polygon may
        start with three collinear ones); n = 0 for a degenerate polygon."""
        if self._spheres is None:
            polys = self.polygons()
            centres = np.array([p.mean(axis=0) for p in polys]).reshape(-1, 3)
            radii = np.array([np.linalg.norm(p - c, axis=1).max() for p, c in zip(polys, centres)])
            planes = np.zeros((len(polys), 4))
            for k, (p, c) in enumerate(zip(polys, centres)):
                n = newell_normal(p)
                norm = np.linalg.norm(n)
                if norm >= 1e-12:
                    planes[k] = [*(n / norm), -(n / norm) @ c]
            self._spheres = (centres, radii, planes)
        return self._spheres


def render_depth_metres(scene: SimScene, T_ground_camera: np.ndarray, K: np.ndarray, width: int,
                        height: int) -> np.ndarray:
    """Noise-free depth (z along the optical axis, metres; 0 where nothing is hit)."""
    T_camera_ground = invert_transform(T_ground_camera)
    frustum = frustum_planes(K, width, height)
    zbuf = np.full((height, width), np.inf, dtype=np.float64)
    cols = (np.arange(width) - K[0, 2]) / K[0, 0]
    rows = (np.arange(height) - K[1, 2]) / K[1, 1]
    cam_G = T_ground_camera[:3, 3]
    polys, sides = scene.polygons(), scene.one_sided_planes()
    # A site has thousands of polygons, most behind the camera or beside the view: one vectorised
    # test of their bounding spheres against the frustum leaves the few worth clipping.
    centres, radii, planes_G = scene.bounding_spheres()
    c_C = transform_points(T_camera_ground, centres)
    maybe = np.all(c_C @ frustum[:, :3].T + frustum[:, 3] >= -radii[:, None], axis=1)
    maybe &= np.any(planes_G[:, :3] != 0, axis=1)
    planes_C = transform_plane(T_ground_camera, planes_G)
    with np.errstate(divide="ignore", invalid="ignore"):  # a ray parallel to a plane
        for k in np.flatnonzero(maybe):
            poly_G, pi_G, pi_C = polys[k], sides[k], planes_C[k]
            if pi_G is not None and pi_G[:3] @ cam_G + pi_G[3] <= 0:
                continue  # the back of a one-sided map face
            poly_C = clip_polygon(transform_points(T_camera_ground, poly_G), frustum)
            if poly_C is None:
                continue
            px = project(K, poly_C)
            box_lo, box_hi = poly_C.min(axis=0), poly_C.max(axis=0)
            c0, r0 = np.floor(px.min(axis=0)).astype(int)
            c1, r1 = np.ceil(px.max(axis=0)).astype(int)
            c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, width - 1), min(r1, height - 1)
            if c1 < c0 or r1 < r0:
                continue
            mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
            pts = np.round((px - (c0, r0)) * (1 << _SUBPIXEL_BITS)).astype(np.int32)
            cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
            denom = pi_C[0] * cols[None, c0:c1 + 1] + pi_C[1] * rows[r0:r1 + 1, None] + pi_C[2]
            z = -pi_C[3] / denom
            sub = zbuf[r0:r1 + 1, c0:c1 + 1]
            upd = (mask > 0) & (z > 0) & (z < sub)
            # fillPoly also marks pixels whose centre lies just outside the polygon; on a face seen at a
            # grazing angle their ray meets its plane far beyond it. Such a pixel (on the mask's rim:
            # inside it the centres are inside) is kept only if that point is within a pixel's
            # footprint of the polygon's bounding box.
            inner = cv2.erode(mask, _RIM_KERNEL, borderType=cv2.BORDER_CONSTANT, borderValue=0)
            er, ec = np.nonzero(upd & (inner == 0))
            if len(er):
                ze = z[er, ec]
                fp = ze * (1.0 / K[0, 0] + 1.0 / K[1, 1])
                xe, ye = ze * cols[c0 + ec], ze * rows[r0 + er]
                off = ((xe < box_lo[0] - fp) | (xe > box_hi[0] + fp) | (ye < box_lo[1] - fp) | (ye > box_hi[1] + fp)
                       | (ze < box_lo[2] - fp) | (ze > box_hi[2] + fp))
                upd[er[off], ec[off]] = False
            sub[upd] = z[upd]
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf


# -- depth errors ---------------------------------------------------------------------------------


def add_depth_noise(z: np.ndarray, fx: float, noise: DepthNoise, rng: np.random.Generator, camera: str = "",
                    decimation: int = 1) -> np.ndarray:
    """Measured depth (m, 0 = no value) from true depth ``z`` (0 = nothing hit) under ``noise``.

    ``fx`` is the full-resolution focal length; ``decimation`` the factor the frame was rendered
    at (its pixel c covers full-resolution columns d c .. d c + d - 1); ``camera`` picks the
    per-camera scale error and, with ``noise.unit_seed``, the camera's fixed wave."""
    if noise.model == "simple":
        out = _simple_noise(z, fx, noise, rng)
    elif noise.model == "realistic":
        out = _realistic_noise(z, fx, noise, rng, camera, int(decimation))
    else:
        out = np.where((z >= noise.min_range) & (z <= noise.max_range), z, 0.0)
    e = noise.scale_error_of(camera)
    if e != 0.0:
        out = out * (1.0 + e)
        out[(out < noise.min_range) | (out > noise.max_range)] = 0.0
    return out


def _simple_noise(z: np.ndarray, fx: float, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
    out = z.copy()
    valid = out > 0
    # Flying pixels: stereo matching at a depth discontinuity mixes the two surfaces.
    zp = np.pad(out, 1, mode="edge")
    neigh = np.stack([zp[:-2, 1:-1], zp[2:, 1:-1], zp[1:-1, :-2], zp[1:-1, 2:]])
    far = neigh.max(axis=0)
    edge = valid & (far > out * (1 + noise.edge_jump))
    fly = edge & (rng.random(out.shape) < noise.flying_pixels)
    mix = rng.random(int(fly.sum()))
    out[fly] = out[fly] + mix * (far[fly] - out[fly])
    # The matcher errs in disparity (f_x b / z) by about s pixels, Gaussian: in depth that is
    # sigma_z = z^2 s / (f_x b) to first order, skewed towards far at long range.
    inv = 1.0 / out[valid] + rng.standard_normal(int(valid.sum())) * noise.inverse_depth_sigma(fx)
    out[valid] = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0)
    drop = rng.random(out.shape) < noise.dropout
    out[drop | (out < noise.min_range) | (out > noise.max_range)] = 0.0
    return out


def _realistic_noise(z: np.ndarray, fx: float, noise: DepthNoise, rng: np.random.Generator, camera: str,
                     d: int) -> np.ndarray:
    h, w = z.shape
    fb = fx * noise.baseline
    hit = z > 0
    with np.errstate(divide="ignore"):
        disp = np.where(hit, fb / np.where(hit, z, 1.0), 0.0).astype(np.float32)  # true disparity, full-res px
    invalid = ~hit
    if noise.shadow:
        invalid |= stereo_shadow(disp, d)
    if noise.search_range_px > 0:
        invalid |= disp > noise.search_range_px
    # Flying pixels: near a depth edge the matcher's window holds both surfaces and returns a
    # disparity between theirs.
    if noise.flying_pixels > 0 and noise.edge_band_px > 0:
        k = max(1, int(round(noise.edge_band_px / d)))
        kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
        d_near = cv2.dilate(disp, kernel)
        d_far = cv2.erode(np.where(hit, disp, np.float32(1e9)), kernel)
        edge = np.flatnonzero(hit & (d_near > d_far * (1.0 + noise.edge_jump)))
        fly = edge[rng.random(edge.size) < noise.flying_pixels]
        flat = disp.reshape(-1)
        lo, hi = d_far.reshape(-1)[fly], d_near.reshape(-1)[fly]
        flat[fly] = lo + rng.random(fly.size).astype(np.float32) * (hi - lo)
    meas = disp + np.float32(noise.subpixel) * correlated_normal((h, w), noise.correlation_px, d, rng)
    if noise.wave_px > 0:
        meas += np.float32(noise.wave_px) * _wave_field(noise.unit_seed, camera, h, w, d, noise.wave_cycles)
    if noise.nonlinearity_px > 0:
        meas += np.float32(noise.nonlinearity_px) * np.sin(np.float32(2 * np.pi) * disp)
    invalid |= meas <= 0
    out = np.where(invalid, 0.0, fb / np.where(invalid, 1.0, meas).astype(np.float64))
    # Holes: dark or shiny surfaces (blobs), the fill rate falling with range, single drop-outs.
    if noise.blobs > 0:
        g = smooth_gaussian_field((h, w), noise.blob_px / d, rng)
        invalid |= g < NormalDist().inv_cdf(min(max(noise.blobs, 1e-12), 1 - 1e-12))
    far = hit & (z > noise.fill_start)
    if far.any():
        g = smooth_gaussian_field((h, w), noise.blob_px / d, rng)
        p = np.exp(-np.square((z[far] - noise.fill_start) / max(noise.fill_scale, 1e-9)))
        lost = np.zeros_like(hit)
        lost[far] = _normal_cdf(g[far]) > p  # spatially coherent holes, a fraction 1 - p of the pixels
        invalid |= lost
    if noise.dropout > 0:
        invalid |= rng.random((h, w), dtype=np.float32) < noise.dropout
    out[invalid | (out < noise.min_range) | (out > noise.max_range)] = 0.0
    return out


def stereo_shadow(disp: np.ndarray, decimation: int = 1) -> np.ndarray:
    """Pixels of the left (depth) imager that the right imager cannot see, from the true
    disparity (full-resolution px, 0 where nothing is hit).

    A left pixel at column u is seen by the right imager at u - d(u). It is hidden if some pixel
    to its right lands at or left of that column (a nearer surface: the shadow to the left of a
    near object, as wide as the two disparities differ), and outside the right image if
    u - d(u) < 0 (the band at the left border, as wide as the disparity)."""
    w = disp.shape[1]
    u = (np.arange(w, dtype=np.float32) + 0.5) * decimation - 0.5  # full-resolution column of each pixel centre
    r = u[None, :] - disp
    suffix_min = np.minimum.accumulate(r[:, ::-1], axis=1)[:, ::-1]
    right_min = np.full_like(r, np.inf)
    right_min[:, :-1] = suffix_min[:, 1:]
    return (r >= right_min) | (r < 0)


@functools.lru_cache(maxsize=16)
def _block_kernel(sigma: float, d: int) -> Tuple[np.ndarray, float]:
    """(1-D kernel of unit L2 norm on the frame's grid, std of the d x d block mean) of a field
    with unit variance per full-resolution pixel and Gaussian correlation of std ``sigma`` px."""
    if sigma <= 0:
        return np.ones(1, np.float32), 1.0 / d
    # Autocorrelation of the full-resolution smoothing kernel, then the variance of a d-block mean.
    r = int(math.ceil(4 * sigma))
    g = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    g /= np.linalg.norm(g)
    rho = np.correlate(g, g, mode="full")  # rho[len(g) - 1] = 1 at lag 0
    lags = np.subtract.outer(np.arange(d), np.arange(d)) + len(g) - 1
    gain = float(rho[lags].mean())  # per axis; the 2-D field is separable
    # On the frame's grid the block mean is correlated like a Gaussian of variance sigma^2 + (d^2 - 1) / 12.
    s = math.sqrt(sigma * sigma + (d * d - 1) / 12.0) / d
    rk = max(1, int(math.ceil(3 * s)))
    k = np.exp(-0.5 * (np.arange(-rk, rk + 1) / s) ** 2)
    k /= np.linalg.norm(k)
    return k.astype(np.float32), gain


def correlated_normal(shape: Tuple[int, int], sigma: float, decimation: int, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean Gaussian field (float32): what a full-resolution field of unit variance, correlated
    over a Gaussian window of std ``sigma`` px, gives after averaging d x d blocks."""
    k, gain = _block_kernel(float(sigma), int(decimation))
    white = rng.standard_normal(shape, dtype=np.float32)
    if len(k) == 1:
        return white * np.float32(gain)
    out = cv2.sepFilter2D(white, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT)
    return out * np.float32(gain)


# Bilinear interpolation between grid nodes correlated by rho = exp(-1/4) (the one-cell smoothing)
# lowers the variance between them, on average by 2/3 + rho/3 per axis: by its square in 2-D, so
# the standard deviation by 2/3 + rho/3. Undone on average.
_INTERP_STD = 2.0 / 3.0 + math.exp(-0.25) / 3.0


def smooth_gaussian_field(shape: Tuple[int, int], cell: float, rng: np.random.Generator) -> np.ndarray:
    """About unit-variance Gaussian field (float32) smooth over ``cell`` pixels: white noise on a
    grid of that spacing, smoothed over one cell and interpolated."""
    h, w = shape
    cell = max(float(cell), 1.0)
    gh, gw = int(math.ceil(h / cell)) + 4, int(math.ceil(w / cell)) + 4
    g = rng.standard_normal((gh, gw), dtype=np.float32)
    k = np.exp(-0.5 * np.arange(-3, 4) ** 2).astype(np.float32)
    k /= np.linalg.norm(k)
    g = cv2.sepFilter2D(g, cv2.CV_32F, k, k, borderType=cv2.BORDER_REFLECT) * np.float32(1.0 / _INTERP_STD)
    big = cv2.resize(g, (int(round(gw * cell)), int(round(gh * cell))), interpolation=cv2.INTER_LINEAR)
    o = int(round(2 * cell))
    return big[o:o + h, o:o + w]


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF (Abramowitz and Stegun 7.1.26 for erf, error below 1e-6)."""
    t = np.abs(x) / math.sqrt(2.0)
    k = 1.0 / (1.0 + 0.3275911 * t)
    poly = k * (0.254829592 + k * (-0.284496736 + k * (1.421413741 + k * (-1.453152027 + k * 1.061405429))))
    erf = 1.0 - poly * np.exp(-t * t)
    return 0.5 * (1.0 + np.sign(x) * erf)


_WAVE_TERMS = 6


@functools.lru_cache(maxsize=32)
def _wave_field(unit_seed: int, camera: str, h: int, w: int, d: int, cycles: float) -> np.ndarray:
    """The camera unit's fixed low-frequency disparity error, zero mean and unit RMS over the
    image, at the frame's pixels (evaluated at their full-resolution centres, so a decimated
    frame sees the same wave as a full one)."""
    rng = np.random.default_rng([int(unit_seed), zlib.crc32(camera.encode("utf-8"))])
    freq = rng.uniform(0.4, 1.0, _WAVE_TERMS) * cycles
    ang = rng.uniform(0.0, 2 * np.pi, _WAVE_TERMS)
    phase = rng.uniform(0.0, 2 * np.pi, _WAVE_TERMS)
    amp = rng.standard_normal(_WAVE_TERMS)
    radial = float(rng.standard_normal())  # lens residual: symmetric about the image centre
    W, H = w * d, h * d

    def field(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # x, y: full-resolution pixel centres, scaled by the width so frequencies are per image width
        xs, ys = (x[None, :] + 0.5) / W, (y[:, None] + 0.5) / W
        f = np.zeros((len(y), len(x)))
        for a, fr, th, ph in zip(amp, freq, ang, phase):
            f += a * np.cos(2 * np.pi * fr * (np.cos(th) * xs + np.sin(th) * ys) + ph)
        return f + radial * ((xs - 0.5) ** 2 + (ys - 0.5 * H / W) ** 2) * 4.0

    def affine(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.stack(np.broadcast_arrays(np.ones((len(y), len(x))), x[None, :] / W, y[:, None] / W), axis=-1)

    # A disparity error affine in the pixel coordinates is a plane's (an extrinsic error, not a
    # wave): taken out, and the rest scaled to unit RMS, on a fixed grid so every decimation gets
    # the same wave.
    xr, yr = np.linspace(0, W - 1, 96), np.linspace(0, H - 1, max(2, int(96 * H / W)))
    ref = field(xr, yr)
    A = affine(xr, yr).reshape(-1, 3)
    coef, *_ = np.linalg.lstsq(A, ref.reshape(-1), rcond=None)
    rms = float(np.sqrt(np.mean((ref.reshape(-1) - A @ coef) ** 2)))
    cols = (np.arange(w) + 0.5) * d - 0.5
    rows = (np.arange(h) + 0.5) * d - 0.5
    out = ((field(cols, rows) - affine(cols, rows) @ coef) / max(rms, 1e-12)).astype(np.float32)
    out.setflags(write=False)
    return out


def to_depth_units(z: np.ndarray, depth_scale: float) -> np.ndarray:
    return np.clip(np.round(z / depth_scale), 0, 65535).astype(np.uint16)


def decimated_intrinsics(K: np.ndarray, width: int, height: int, decimation: int) -> Tuple[np.ndarray, int, int]:
    """K, width and height of a frame decimated by ``decimation`` (librealsense's decimation filter:
    each output pixel covers a d x d block, so a pixel centre c maps to (c + 0.5) / d - 0.5)."""
    d = int(decimation)
    if d < 1:
        raise ValueError(f"decimation must be >= 1, got {decimation}")
    Kd = np.array(K, float)
    if d > 1:
        Kd[0, 0] /= d
        Kd[1, 1] /= d
        Kd[0, 2] = (Kd[0, 2] + 0.5) / d - 0.5
        Kd[1, 2] = (Kd[1, 2] + 0.5) / d - 0.5
    return Kd, width // d, height // d


def render_depth_frame(robot: RobotConfig, scene: SimScene, camera: str, pose: Tuple[float, float, float],
                       rng: Optional[np.random.Generator] = None,
                       noise: Union[DepthNoise, str, None] = "realistic",
                       depth_scale: float = 0.001, K: Optional[np.ndarray] = None, t_capture: float = 0.0,
                       frame_number: int = 0, decimation: int = 1) -> DepthFrame:
    """A simulated frame of ``camera`` with the robot at ``pose`` (ground truth attached).

    ``noise``: a ``DepthNoise``, a model name (``realistic``, ``simple``, ``none``) or None
    (exact). ``K`` is the full-resolution intrinsics (default: from the field of view). With
    ``decimation`` d > 1 the frame is (W // d) x (H // d) with K scaled to it, as the D435i's
    decimation filter gives; the depth errors keep the full-resolution f_x (the stereo matcher's)."""
    cam = robot.camera(camera)
    model = resolve_noise(noise)
    K_full = cam.intrinsics_from_fov() if K is None else np.asarray(K, float)
    K, width, height = decimated_intrinsics(K_full, cam.width, cam.height, decimation)
    T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    z = render_depth_metres(scene, T_ground_camera, K, width, height)
    if model is not None:
        z = add_depth_noise(z, K_full[0, 0], model, rng if rng is not None else np.random.default_rng(),
                            camera=camera, decimation=decimation)
    return DepthFrame(camera=camera, depth=to_depth_units(z, depth_scale), depth_scale=depth_scale, K=K,
                      t_capture=t_capture, frame_number=frame_number, timestamp_domain="simulated",
                      truth=tuple(float(v) for v in pose))


def random_clutter(plane_map: PlaneMap, count: int, rng: np.random.Generator,
                   keep_clear: Sequence[Tuple[float, float]] = (), clearance: float = 0.3) -> List[Box]:
    """Boxes (0.05 to 0.25 m) placed inside the map's extent, away from the given points."""
    lo, hi = plane_map.bounds()
    boxes: List[Box] = []
    tries = 0
    while len(boxes) < count and tries < 1000:
        tries += 1
        x, y = rng.uniform(lo[0] + 0.1, hi[0] - 0.1), rng.uniform(lo[1] + 0.1, hi[1] - 0.1)
        if any(np.hypot(x - a, y - b) < clearance for a, b in keep_clear):
            continue
        s = rng.uniform(0.05, 0.25, 3)
        boxes.append(Box(x, y, s[0], s[1], s[2], rng.uniform(0, np.pi)))
    return boxes
