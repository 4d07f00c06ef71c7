"""Simulated D435i depth frames: the fake camera's renderer (DESIGN.md section 6 noise model).

The scene is the map's polygons plus what a real site adds and the map does not know: the
floor, a backdrop beyond the walls (a room around the arena) and clutter boxes. Each polygon is
clipped to the frustum, rasterized, and its exact depth along each pixel ray written through a
z-buffer, so occlusion and partial views are exact. Noise follows the stereo model
sigma_z = z^2 s / (f_x b), drawn where a stereo camera makes it: a Gaussian error of s pixels in
disparity (so Gaussian in 1/z, slightly skewed in z), with dropouts and flying pixels at depth
edges.

Map polygons are one-sided (DESIGN.md section 3: a face is seen from its normal's side; a real
wall is two faces in an imported map), so a map face seen from behind is not drawn: otherwise a
camera looking through a door would see the back of the wall's far face, a surface one wall
thickness behind the opening that no real camera sees. Clutter boxes, floor and backdrop are
closed or enclosing surfaces and stay double-sided.

``decimation`` renders what librealsense's decimation filter delivers: a frame of W/d x H/d
pixels with the intrinsics scaled to it. The noise model keeps the full-resolution f_x: stereo
noise is set by the matcher, which works at full resolution, and the filter's combination of
d x d neighbouring depths (median or mean) removes little of it, since that noise is correlated
over neighbouring pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

from robot.base.geometry import invert_transform, pose_to_T_ground_robot, transform_plane, transform_points
from robot.base.samples import DepthFrame
from robot.config import RobotConfig
from robot.maps.plane_map import PlaneMap
from robot.maps.visibility import clip_polygon, frustum_planes, project

_SUBPIXEL_BITS = 4  # fillPoly fixed-point: vertices placed to 1/16 pixel


@dataclass(frozen=True)
class DepthNoise:
    """Stereo depth noise of a D435i (DESIGN.md section 6)."""

    baseline: float = 0.050  # m
    subpixel: float = 0.08  # disparity noise, pixels
    dropout: float = 0.01  # fraction of valid pixels returned as 0
    flying_pixels: float = 0.5  # fraction of depth-edge pixels given a depth between the two sides
    edge_jump: float = 0.05  # relative depth jump that counts as an edge
    min_range: float = 0.2  # m, closer returns 0 (D435i minimum z at 848x480)
    max_range: float = 10.0  # m, farther returns 0

    def sigma(self, z: np.ndarray, fx: float) -> np.ndarray:
        """Depth standard deviation at depth z (first order): z^2 s / (f_x b)."""
        return z * z * self.subpixel / (fx * self.baseline)

    def inverse_depth_sigma(self, fx: float) -> float:
        """Standard deviation of 1/z (1/m): the matcher's disparity error s over f_x b, the same everywhere."""
        return self.subpixel / (fx * self.baseline)


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
    """Everything the fake cameras see, in the ground frame."""

    plane_map: PlaneMap
    clutter: Sequence[Box] = ()
    floor: bool = True
    backdrop: bool = True
    backdrop_margin: float = 3.0  # m beyond the map's extent
    backdrop_height: float = 3.0  # m, with a ceiling on top
    _polys: Optional[List[np.ndarray]] = field(default=None, repr=False)
    _sides: Optional[List[Optional[np.ndarray]]] = field(default=None, repr=False)

    def polygons(self) -> List[np.ndarray]:
        if self._polys is None:
            polys = [poly for p in self.plane_map.planes for poly in p.polygons]
            # The map plane (n, d) of each one-sided polygon; None: drawn from both sides.
            self._sides = [p.pi for p in self.plane_map.planes for _ in p.polygons]
            for box in self.clutter:
                polys.extend(box.faces())
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


def render_depth_metres(scene: SimScene, T_ground_camera: np.ndarray, K: np.ndarray, width: int,
                        height: int) -> np.ndarray:
    """Noise-free depth (z along the optical axis, metres; 0 where nothing is hit)."""
    T_camera_ground = invert_transform(T_ground_camera)
    frustum = frustum_planes(K, width, height)
    zbuf = np.full((height, width), np.inf, dtype=np.float64)
    cols = (np.arange(width) - K[0, 2]) / K[0, 0]
    rows = (np.arange(height) - K[1, 2]) / K[1, 1]
    cam_G = T_ground_camera[:3, 3]
    for poly_G, pi_G in zip(scene.polygons(), scene.one_sided_planes()):
        if pi_G is not None and pi_G[:3] @ cam_G + pi_G[3] <= 0:
            continue  # the back of a one-sided map face
        poly_C = clip_polygon(transform_points(T_camera_ground, poly_G), frustum)
        if poly_C is None:
            continue
        # Plane of the polygon in C, from its (unclipped) vertices.
        n = np.cross(poly_G[1] - poly_G[0], poly_G[2] - poly_G[0])
        if np.linalg.norm(n) < 1e-12:
            continue
        n = n / np.linalg.norm(n)
        pi_C = transform_plane(T_ground_camera, np.array([*n, -n @ poly_G[0]]))
        px = project(K, poly_C)
        c0, r0 = np.floor(px.min(axis=0)).astype(int)
        c1, r1 = np.ceil(px.max(axis=0)).astype(int)
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, width - 1), min(r1, height - 1)
        if c1 < c0 or r1 < r0:
            continue
        mask = np.zeros((r1 - r0 + 1, c1 - c0 + 1), np.uint8)
        pts = np.round((px - (c0, r0)) * (1 << _SUBPIXEL_BITS)).astype(np.int32)
        cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=_SUBPIXEL_BITS)
        denom = pi_C[0] * cols[None, c0:c1 + 1] + pi_C[1] * rows[r0:r1 + 1, None] + pi_C[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = -pi_C[3] / denom
        sub = zbuf[r0:r1 + 1, c0:c1 + 1]
        upd = (mask > 0) & (z > 0) & (z < sub)
        sub[upd] = z[upd]
    zbuf[~np.isfinite(zbuf)] = 0.0
    return zbuf


def add_depth_noise(z: np.ndarray, fx: float, noise: DepthNoise, rng: np.random.Generator) -> np.ndarray:
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
                       rng: Optional[np.random.Generator] = None, noise: Optional[DepthNoise] = DepthNoise(),
                       depth_scale: float = 0.001, K: Optional[np.ndarray] = None, t_capture: float = 0.0,
                       frame_number: int = 0, decimation: int = 1) -> DepthFrame:
    """A simulated frame of ``camera`` with the robot at ``pose`` (ground truth attached).

    ``K`` is the full-resolution intrinsics (default: from the field of view). With
    ``decimation`` d > 1 the frame is (W // d) x (H // d) with K scaled to it, as the D435i's
    decimation filter gives; the depth noise keeps the full-resolution f_x (the stereo matcher's)."""
    cam = robot.camera(camera)
    K_full = cam.intrinsics_from_fov() if K is None else np.asarray(K, float)
    K, width, height = decimated_intrinsics(K_full, cam.width, cam.height, decimation)
    T_ground_camera = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    z = render_depth_metres(scene, T_ground_camera, K, width, height)
    if noise is not None:
        z = add_depth_noise(z, K_full[0, 0], noise, rng if rng is not None else np.random.default_rng())
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
