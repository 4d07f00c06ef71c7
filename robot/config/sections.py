"""Every section of the robot config as a frozen dataclass, with its default and meaning.

This module stands below everything it configures: it imports only the shared base, so that
loading the config (for example in the serial driver) never pulls in the filter or the
localizer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

import numpy as np

from robot.base.geometry import mount_to_T_robot_camera
from robot.config.realsense import RealSenseConfig


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
class QualityConfig:
    localized_within: float = 1.0  # s since the last accepted plane
    localized_pos_std: float = 0.02  # m
    localized_heading_std_deg: float = 1.0
    lost_after: float = 10.0  # s without an accepted plane
    lost_pos_std: float = 0.10  # m
    lost_heading_std_deg: float = 5.0
    rejection_window: float = 3.0  # s of gate decisions behind the rejection ratio
    min_decisions: int = 5  # fewer decisions in the window: ratio not judged
    degraded_rejection_ratio: float = 0.5
    lost_rejection_ratio: float = 0.9
    hysteresis: float = 0.8  # leave a worse state below this fraction of its threshold


@dataclass(frozen=True)
class HealthConfig:
    slow_after: float = 1.0  # s without a successful localization before slowing down
    stop_after: float = 3.0  # s without one before stopping
    slow_scale: float = 0.3  # fraction of the planned speed while degraded
    max_command_age: float = 0.5  # s: older commands are dropped, never sent (cmd_vel_timeout)
    vision_required: bool = True  # False: odometry-only driving is allowed (experiments, teleop)


@dataclass(frozen=True)
class ControlConfig:
    """Limits and gains; the ``control:`` section of the robot config. Limits are per axis."""

    rate: float = 50.0  # Hz control loop
    max_speed: float = 0.30  # m/s, |vx|, |vy| and the norm of the translation target
    max_accel: float = 0.50  # m/s^2 per axis
    max_jerk: float = 2.0  # m/s^3 per axis
    max_yaw_rate: float = 1.0  # rad/s
    max_yaw_accel: float = 2.0  # rad/s^2
    max_yaw_jerk: float = 10.0  # rad/s^3
    kp_position: float = 1.5  # 1/s, final approach along the segment
    kp_cross_track: float = 2.0  # 1/s, pull back onto the segment
    kp_heading: float = 2.0  # 1/s
    brake_fraction: float = 0.5  # share of max accel the approach profile plans with (rest: jerk margin)
    require_settled: bool = True  # arrival also needs the command below the settle speeds
    settle_speed: float = 0.02  # m/s
    settle_yaw_rate: float = 0.05  # rad/s
    max_dt: float = 0.1  # s: a longer gap between ticks is treated as this long

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, bool):
                continue
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"control.{name} must be finite and > 0, got {v}")
        if self.brake_fraction > 1.0:
            raise ValueError(f"control.brake_fraction must be <= 1, got {self.brake_fraction}")


@dataclass(frozen=True)
class FilterConfig:
    """Tuning of :class:`PoseFilter`. Variances are per unit of what drives them."""

    gate_probability: float = 0.997  # chi-square gate; 2 dof at 0.997 is d^2 < 11.6
    history: float = 2.0  # s of inputs kept for lagged measurements
    hold: float = 0.25  # s the last twist is extrapolated past the last odometry input
    max_future: float = 1.0  # s a measurement may be ahead of the newest input (clock sanity)
    pos_noise_density: float = 1e-7  # m^2/s: floor even when standing still (1 mm after 10 s)
    heading_noise_density: float = 1e-7  # rad^2/s
    slip_per_metre: float = 1e-4  # m^2 per m travelled (1 cm std after 1 m)
    heading_slip_per_rad: float = 3e-4  # rad^2 per rad turned (1 deg std per rad)
    heading_slip_per_metre: float = 7.6e-5  # rad^2 per m travelled (0.5 deg std per m)
    gyro_mode: str = "combine"  # "combine" (inverse variance with the wheels' wz) or "replace"
    min_wall_normal: float = 0.7  # |n_G,xy| below this: not a wall, its heading is meaningless
    max_events: int = 5000  # hard bound on the history when odometry is missing

    def __post_init__(self):
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if self.gyro_mode not in ("combine", "replace"):
            raise ValueError(f"gyro_mode must be 'combine' or 'replace', got {self.gyro_mode!r}")
        for name in ("history", "hold", "max_future", "pos_noise_density", "heading_noise_density",
                     "slip_per_metre", "heading_slip_per_rad", "heading_slip_per_metre"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")


