"""The robot config (``config/robot.yaml``): cameras, chassis, localizer and control sections.

Every key is documented here with its default. Unknown keys are an error so a typo never
silently falls back to a default on a robot.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

import numpy as np

from robot.config_schema import Section, load_yaml_file
from robot.ekf import FilterConfig
from robot.geometry import mount_to_T_robot_camera
from robot.health import HealthConfig
from robot.quality import QualityConfig
from robot.realsense_config import RealSenseConfig, parse_realsense_config
from robot.trajectory import ControlConfig


@dataclass(frozen=True)
class CameraConfig:
    name: str
    width: int
    height: int
    fps: float
    hfov_deg: float
    vfov_deg: float
    mount_xyz: Tuple[float, float, float]
    mount_rpy_deg: Tuple[float, float, float]
    serial: Optional[str] = None  # RealSense serial number; None = the only device present
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)  # optional 'realsense:' section

    @property
    def T_robot_camera(self) -> np.ndarray:
        """T_RC: optical frame (z forward, x right, y down) to robot frame."""
        return mount_to_T_robot_camera(self.mount_xyz, tuple(math.radians(a) for a in self.mount_rpy_deg))

    def intrinsics_from_fov(self) -> np.ndarray:
        """Pinhole K from the field of view, principal point at the image centre.

        Pixel centres sit at integer coordinates, so the centre of a W-wide image is (W-1)/2.
        """
        fx = (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        fy = (self.height / 2.0) / math.tan(math.radians(self.vfov_deg) / 2.0)
        return np.array([[fx, 0.0, (self.width - 1) / 2.0], [0.0, fy, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ChassisConfig:
    """Mecanum chassis. Wheel order everywhere: front-left, front-right, rear-left, rear-right."""

    wheel_radius: float = 0.03  # m
    half_wheelbase: float = 0.075  # lx: centre to front axle, m
    half_track: float = 0.085  # ly: centre to left wheel contact, m
    ticks_per_rev: int = 1320  # encoder ticks per wheel revolution (after the gearbox)
    port: str = "/dev/robot-motor-board"  # stable udev symlink on the robot
    baud: int = 115200
    max_wheel_speed: float = 20.0  # rad/s, also enforced by the board
    max_wheel_accel: float = 40.0  # rad/s^2, also enforced by the board
    link_timeout: float = 0.1  # s without an encoder report before the link counts as lost
    watchdog_timeout: float = 0.2  # s without a fresh speed command before the board ramps to zero
    reconnect_backoff_max: float = 2.0  # s, cap of the doubling delay between reconnect attempts


@dataclass(frozen=True)
class LocalizerConfig:
    """Tuning of the per-frame plane localizer (DESIGN.md section 4)."""

    pixel_stride: int = 4  # use every n-th ROI pixel in rows and columns: the main CPU knob
    ransac_iterations: int = 60
    ransac_sample: int = 600  # points RANSAC scores each hypothesis on
    inlier_threshold: float = 0.012  # m, point-to-plane, at 1 m; grows with the depth noise model
    min_inliers: int = 300
    min_roi_pixels: int = 400
    min_inlier_fraction: float = 0.25  # a fit must explain this share of its ROI's points (rejects corner/strip fits)
    angle_gate_deg: float = 8.0  # base normal gate; 3 sigma of the coarse heading is added
    offset_gate: float = 0.05  # m, base offset gate; 3 sigma of the coarse position is added
    margin_px: float = 4.0  # base ROI shrink; grows with the coarse pose's uncertainty
    max_margin_px: float = 40.0
    min_range: float = 0.2  # m, D435i minimum depth at 848x480
    max_range: float = 6.0  # m, beyond this the D435i's depth noise makes points useless
    max_passes: int = 2  # re-predict ROIs from the refined pose when the first correction is large
    unobservable_std: float = 0.05  # m (and rad at 1 m): weaker information marks a direction unobservable


@dataclass(frozen=True)
class RobotConfig:
    cameras: Tuple[CameraConfig, ...]
    chassis: ChassisConfig = field(default_factory=ChassisConfig)
    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    fusion: FilterConfig = field(default_factory=FilterConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    map_path: Optional[str] = None  # `map:` the robot's plane map, relative to the config file
    source: str = "<built-in>"

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        from robot.errors import ConfigError

        names = ", ".join(c.name for c in self.cameras)
        raise ConfigError(f"{self.source}: unknown camera '{name}' (cameras: {names})")


def _parse_camera(sec: Section) -> CameraConfig:
    mount = sec.sub("mount", required=True)
    cam = CameraConfig(
        name=sec.string("name"),
        width=sec.integer("width", lo=16),
        height=sec.integer("height", lo=16),
        fps=sec.number("fps", positive=True),
        hfov_deg=sec.number("hfov_deg", lo=1.0, hi=170.0),
        vfov_deg=sec.number("vfov_deg", lo=1.0, hi=170.0),
        mount_xyz=mount.vector("xyz", 3),
        mount_rpy_deg=mount.vector("rpy_deg", 3),
        serial=str(sec.raw("serial")) if sec.has("serial") else None,
        realsense=parse_realsense_config(sec.sub("realsense")),
    )
    mount.done()
    sec.done()
    return cam


def _parse_dataclass(sec: Section, cls):
    """Read a flat section whose keys are the dataclass's fields, typed by their defaults."""
    defaults = cls()
    values = {}
    for name in cls.__dataclass_fields__:
        default = getattr(defaults, name)
        if isinstance(default, bool):
            values[name] = sec.boolean(name, default)
        elif isinstance(default, int):
            values[name] = sec.integer(name, default, lo=0)
        elif isinstance(default, float):
            values[name] = sec.number(name, default, lo=0.0)
        else:
            values[name] = sec.string(name, default)
    sec.done()
    try:
        return cls(**values)
    except ValueError as e:  # a dataclass's own cross-field check (__post_init__)
        sec.fail(str(e))


def parse_robot_config(data, source: str = "<robot config>") -> RobotConfig:
    top = Section(data, "", source)
    raw_cams = top.raw("cameras")
    if not isinstance(raw_cams, list) or not raw_cams:
        top.fail("'cameras' must be a non-empty list")
    cams: List[CameraConfig] = []
    for i, c in enumerate(raw_cams):
        cams.append(_parse_camera(Section(c, f"cameras[{i}]", source)))
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        top.fail(f"duplicate camera name(s): {', '.join(dup)}")
    chassis = _parse_dataclass(top.sub("chassis"), ChassisConfig)
    localizer = _parse_dataclass(top.sub("localizer"), LocalizerConfig)
    control = _parse_dataclass(top.sub("control"), ControlConfig)
    health = _parse_dataclass(top.sub("health"), HealthConfig)
    fusion = _parse_dataclass(top.sub("fusion"), FilterConfig)
    quality = _parse_dataclass(top.sub("quality"), QualityConfig)
    map_path = None
    if top.has("map"):
        rel = top.string("map")
        base = os.path.dirname(os.path.abspath(source)) if not source.startswith("<") else os.getcwd()
        map_path = os.path.normpath(os.path.join(base, os.path.expanduser(rel)))
    top.done()
    return RobotConfig(cameras=tuple(cams), chassis=chassis, localizer=localizer, control=control, health=health,
                       fusion=fusion, quality=quality, map_path=map_path, source=source)


def load_robot_config(path) -> RobotConfig:
    return parse_robot_config(load_yaml_file(path), source=str(path))
