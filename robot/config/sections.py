"""Every section of the robot config as a frozen dataclass, with its default, range and meaning.

Each number is declared with its physical range (``robot.config.ranges``): the loader refuses a
value outside it naming the file, the key and the range, ``__post_init__`` refuses it for a
config built in code, and ``docs/configuration.md`` is generated from the same declarations
(``python -m robot.config.reference --write``). Safety limits (timeouts, the control rate,
speeds) are bounded on both sides: a value that would switch a safety function off in effect
(a watchdog of 1e308 s) is not a setting.

This module stands below everything it configures: it imports only the shared base, so that
loading the config (for example in the serial driver) never pulls in the filter or the
localizer.
"""

from __future__ import annotations

import functools
import math
from dataclasses import MISSING, dataclass, field
from typing import Optional, Tuple

import numpy as np

from robot.base.errors import ConfigError
from robot.base.geometry import mount_to_T_robot_camera
from robot.config.ranges import check_fields, choice, flag, integer, number, text
from robot.config.realsense import RealSenseConfig

# Real depth cameras: the D435i streams depth up to 1280x720 and colour up to 1920x1080.
MAX_IMAGE_WIDTH = 1920  # px
MAX_IMAGE_HEIGHT = 1080  # px
MAX_MOUNT_OFFSET = 2.0  # m: a camera further than this from the robot origin is not on this robot


@dataclass(frozen=True)
class CameraConfig:
    name: str = text(doc="camera name, unique in the config (front, left, ...)")
    width: int = integer(MISSING, 16, MAX_IMAGE_WIDTH, "px", "depth image width")
    height: int = integer(MISSING, 16, MAX_IMAGE_HEIGHT, "px", "depth image height")
    fps: float = number(MISSING, 1.0, 90.0, "Hz", "depth frame rate (the D435i offers 6 to 90)")
    hfov_deg: float = number(MISSING, 1.0, 170.0, "deg", "horizontal field of view of the depth image")
    vfov_deg: float = number(MISSING, 1.0, 170.0, "deg", "vertical field of view of the depth image")
    mount_xyz: Tuple[float, float, float] = number(
        MISSING, -MAX_MOUNT_OFFSET, MAX_MOUNT_OFFSET, "m", "`mount.xyz`: camera body position in the robot frame")
    mount_rpy_deg: Tuple[float, float, float] = number(
        MISSING, -360.0, 360.0, "deg", "`mount.rpy_deg`: camera body roll, pitch, yaw, R = Rz Ry Rx")
    serial: Optional[str] = text(None, "RealSense serial number; absent: the only device present")
    depth_scale: float = number(1.0, 0.9, 1.1, "x", "factor on the depth the camera reports (its calibration, "
                                "docs/calibration.md: reads 1 % long -> 1 / 1.01)")
    realsense: RealSenseConfig = field(default_factory=RealSenseConfig)  # optional 'realsense:' section

    def __post_init__(self):
        check_fields(self, f"camera '{self.name}'")

    @functools.cached_property
    def T_robot_camera(self) -> np.ndarray:
        """T_RC: optical frame (z forward, x right, y down) to robot frame. Built once per camera
        (the config is frozen; a recalibrated camera is a new object) and read-only: the per-frame
        path reads it many times."""
        T = mount_to_T_robot_camera(self.mount_xyz, tuple(math.radians(a) for a in self.mount_rpy_deg))
        T.flags.writeable = False
        return T

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

    wheel_radius: float = number(0.03, 0.005, 0.5, "m", "wheel radius")
    half_wheelbase: float = number(0.075, 0.01, 2.0, "m", "lx: centre to front axle")
    half_track: float = number(0.085, 0.01, 2.0, "m", "ly: centre to left wheel contact")
    ticks_per_rev: int = integer(1320, 1, 1_000_000, "ticks", "encoder ticks per wheel revolution (after the gearbox)")
    port: str = text("/dev/robot-motor-board", "serial port or pyserial URL (the stable udev symlink on the robot)")
    baud: int = integer(115200, 1200, 4_000_000, "baud", "serial line speed")
    max_wheel_speed: float = number(20.0, 0.0, 50.0, "rad/s", "wheel speed limit, also enforced by the board",
                                    lo_open=True)
    max_wheel_accel: float = number(40.0, 0.0, 1000.0, "rad/s^2", "wheel acceleration limit, also enforced by "
                                    "the board", lo_open=True)
    # Safety: bounded above so that a lost link or a hung host stops the wheels within half a second.
    link_timeout: float = number(0.1, 0.02, 0.5, "s", "without an encoder report for this long the link counts "
                                 "as lost")
    watchdog_timeout: float = number(0.2, 0.05, 0.5, "s", "without a fresh speed command for this long the board "
                                     "ramps the wheels to zero")
    reconnect_backoff_max: float = number(2.0, 0.01, 60.0, "s", "cap of the doubling delay between reconnect "
                                          "attempts")

    def __post_init__(self):
        check_fields(self, "chassis")


@dataclass(frozen=True)
class LocalizerConfig:
    """Tuning of the per-frame plane localizer."""

    pixel_stride: int = integer(4, 1, 64, "px", "use every n-th ROI pixel in rows and columns: the main CPU knob")
    ransac_iterations: int = integer(60, 1, 10_000, "", "RANSAC hypotheses per plane")
    ransac_sample: int = integer(600, 3, 100_000, "points", "points RANSAC scores each hypothesis on")
    inlier_threshold: float = number(0.012, 0.0005, 0.5, "m", "point-to-plane inlier distance at 1 m; grows with "
                                     "the depth noise model")
    min_inliers: int = integer(300, 3, 2_073_600, "points", "fewer inliers: the plane is not used")
    min_roi_pixels: int = integer(400, 3, 2_073_600, "px", "smaller predicted regions are not fitted")
    min_inlier_fraction: float = number(0.25, 0.0, 1.0, "", "a fit must explain this share of its ROI's points "
                                        "(rejects corner and strip fits)")
    angle_gate_deg: float = number(8.0, 0.1, 90.0, "deg", "base normal gate; 3 sigma of the coarse heading is "
                                   "added")
    offset_gate: float = number(0.05, 0.001, 2.0, "m", "base offset gate; 3 sigma of the coarse position is added")
    margin_px: float = number(4.0, 0.0, 500.0, "px", "base ROI shrink; grows with the coarse pose's uncertainty")
    max_margin_px: float = number(40.0, 0.0, 1000.0, "px", "largest ROI shrink")
    min_range: float = number(0.2, 0.05, 10.0, "m", "nearer depth is not used (D435i minimum depth at 848x480)")
    max_range: float = number(6.0, 0.1, 20.0, "m", "farther depth is not used (the D435i's noise grows with "
                              "range squared)")
    max_passes: int = integer(2, 1, 10, "", "re-predict ROIs from the refined pose when the first correction is "
                              "large")
    unobservable_std: float = number(0.05, 1e-4, 10.0, "m", "weaker information than this std (m, and rad at "
                                     "1 m) marks a direction unobservable")
    # Systematic errors (docs/localization-integrity.md): they do not average down with the number of
    # pixels, so every plane measurement, gate and protection level carries them.
    depth_scale_std: float = number(0.01, 0.0, 0.1, "", "1-sigma depth scale error of each camera (0.01: 1 %); "
                                    "an uncalibrated D435i is 0.5 to 2 % off (a calibration file replaces it)")
    depth_systematic_px: float = number(0.02, 0.0, 1.0, "px", "RMS of the matcher's systematic disparity error "
                                        "(low-frequency wave, subpixel non-linearity), full-resolution pixels")
    noise_correlation_px: float = number(1.5, 0.0, 50.0, "px", "correlation length (Gaussian std) of the per-pixel "
                                         "depth noise, full-resolution pixels")
    mount_position_std: float = number(0.003, 0.0, 0.1, "m", "1-sigma error of each camera mount position, per axis")
    mount_angle_std_deg: float = number(0.3, 0.0, 10.0, "deg", "1-sigma error of each camera mount angle, per axis")
    # A calibration file (docs/calibration.md) measures the scales and mount angles: once it gives
    # them for every camera, these (or the file's own std, where larger) replace
    # depth_scale_std and mount_angle_std_deg.
    calibrated_depth_scale_std: float = number(0.0025, 0.0, 0.1, "", "1-sigma depth scale error once the "
                                               "calibration file gives every camera's scale: what temperature and "
                                               "knocks move it by between calibrations")
    calibrated_mount_angle_std_deg: float = number(0.05, 0.0, 10.0, "deg", "1-sigma mount angle error once the "
                                                   "calibration file gives every camera's mount angles")
    integrity_risk: float = number(1e-3, 1e-9, 0.1, "", "probability that the error exceeds a protection level")
    false_alarm: float = number(1e-3, 1e-9, 0.1, "", "probability that walls which agree fail the consistency test")

    def __post_init__(self):
        check_fields(self, "localizer")
        if self.min_range >= self.max_range:
            raise ConfigError(f"localizer: 'min_range' ({self.min_range} m) must be below 'max_range' "
                              f"({self.max_range} m)")


@dataclass(frozen=True)
class QualityConfig:
    """When the localization counts as localized, degraded or lost."""

    localized_within: float = number(1.0, 0.01, 60.0, "s", "since the last accepted plane, to count as localized")
    localized_pos_std: float = number(0.02, 1e-4, 10.0, "m", "position std to count as localized")
    localized_heading_std_deg: float = number(1.0, 0.01, 180.0, "deg", "heading std to count as localized")
    lost_after: float = number(10.0, 0.1, 3600.0, "s", "without an accepted plane: lost")
    lost_pos_std: float = number(0.10, 1e-4, 10.0, "m", "position std beyond which the robot is lost")
    lost_heading_std_deg: float = number(5.0, 0.01, 180.0, "deg", "heading std beyond which the robot is lost")
    rejection_window: float = number(3.0, 0.1, 600.0, "s", "of gate decisions behind the rejection ratio")
    min_decisions: int = integer(5, 1, 10_000, "", "fewer decisions in the window: the ratio is not judged")
    degraded_rejection_ratio: float = number(0.5, 0.0, 1.0, "", "share of rejected planes that means degraded")
    lost_rejection_ratio: float = number(0.9, 0.0, 1.0, "", "share of rejected planes that means lost")
    hysteresis: float = number(0.8, 0.0, 1.0, "", "leave a worse state below this fraction of its threshold",
                               lo_open=True)
    # Protection levels over these mean the pose cannot be vouched for at the risk it is computed for:
    # degraded, and the controller slows down.
    horizontal_alert_limit: float = number(0.10, 0.001, 10.0, "m", "horizontal protection level above which the "
                                           "pose is degraded")
    heading_alert_limit_deg: float = number(3.0, 0.01, 180.0, "deg", "heading protection level above which the "
                                            "pose is degraded")

    def __post_init__(self):
        check_fields(self, "quality")


@dataclass(frozen=True)
class HealthConfig:
    """What the controller does when localization fails. Safety: bounded so it cannot be switched off."""

    slow_after: float = number(1.0, 0.05, 10.0, "s", "without a successful localization before slowing down")
    stop_after: float = number(3.0, 0.1, 30.0, "s", "without one before stopping")
    slow_scale: float = number(0.3, 0.0, 1.0, "", "fraction of the planned speed while degraded")
    max_command_age: float = number(0.5, 0.01, 0.5, "s", "older commands are dropped, never sent (cmd_vel timeout)")
    vision_required: bool = flag(True, "false: odometry-only driving is allowed (experiments, teleop)")
    # After a fault (a control tick this late, a lost link, a board reset) the robot is stopped,
    # its command limiters start from rest, and the mission waits until the pose is confirmed.
    stall_after: float = number(0.15, 0.03, 0.5, "s", "a control tick this long after the previous one is a "
                                "host stall (keep it below the board watchdog; at least 2.5 control periods "
                                "are used)")
    resume_after_fault: str = choice("auto", ("auto", "command"), "after a fault: auto resumes the mission once "
                                     "the pose is confirmed, command also waits for the operator's resume")
    confirm_planes: int = integer(2, 1, 100, "", "accepted plane fixes captured after a fault that confirm the pose")
    confirm_pos_std: float = number(0.005, 0.0005, 0.1, "m", "position std at or below which the pose counts as "
                                    "confirmed after a fault")
    # Live depth frames are checked like snapshot files, and for their time stamp on the host clock.
    frame_max_ahead: float = number(0.05, 0.0, 1.0, "s", "a depth frame stamped further in the future is refused "
                                    "(camera clock mapping fault)")
    frame_max_age: float = number(1.0, 0.05, 10.0, "s", "an older depth frame is refused, never fused")

    def __post_init__(self):
        check_fields(self, "health")
        if self.slow_after > self.stop_after:
            raise ConfigError(f"health: 'slow_after' ({self.slow_after} s) must not be after 'stop_after' "
                              f"({self.stop_after} s)")


@dataclass(frozen=True)
class ControlConfig:
    """Limits and gains; the ``control:`` section of the robot config. Limits are per axis."""

    rate: float = number(50.0, 10.0, 200.0, "Hz", "control loop rate")
    max_speed: float = number(0.30, 0.0, 2.0, "m/s", "|vx|, |vy| and the norm of the translation target",
                              lo_open=True)
    max_accel: float = number(0.50, 0.0, 5.0, "m/s^2", "per axis", lo_open=True)
    max_jerk: float = number(2.0, 0.0, 50.0, "m/s^3", "per axis", lo_open=True)
    max_yaw_rate: float = number(1.0, 0.0, 10.0, "rad/s", "turn rate limit", lo_open=True)
    max_yaw_accel: float = number(2.0, 0.0, 50.0, "rad/s^2", "turn acceleration limit", lo_open=True)
    max_yaw_jerk: float = number(10.0, 0.0, 500.0, "rad/s^3", "turn jerk limit", lo_open=True)
    kp_position: float = number(1.5, 0.0, 20.0, "1/s", "final approach along the segment", lo_open=True)
    kp_cross_track: float = number(2.0, 0.0, 20.0, "1/s", "pull back onto the segment", lo_open=True)
    kp_heading: float = number(2.0, 0.0, 20.0, "1/s", "heading gain", lo_open=True)
    brake_fraction: float = number(0.5, 0.0, 1.0, "", "share of max accel the approach profile plans with (rest: "
                                   "jerk margin)", lo_open=True)
    require_settled: bool = flag(True, "arrival also needs the command below the settle speeds")
    settle_speed: float = number(0.02, 0.0, 0.5, "m/s", "translation below this counts as settled", lo_open=True)
    settle_yaw_rate: float = number(0.05, 0.0, 1.0, "rad/s", "rotation below this counts as settled", lo_open=True)
    max_dt: float = number(0.1, 0.0, 1.0, "s", "a longer gap between ticks is treated as this long", lo_open=True)

    def __post_init__(self):
        check_fields(self, "control")


@dataclass(frozen=True)
class FilterConfig:
    """Tuning of :class:`PoseFilter`. Variances are per unit of what drives them."""

    gate_probability: float = number(0.997, 0.5, 0.999999, "", "chi-square gate; 2 dof at 0.997 is d^2 < 11.6")
    history: float = number(2.0, 0.1, 60.0, "s", "of inputs kept for lagged measurements")
    hold: float = number(0.25, 0.0, 5.0, "s", "the last twist is extrapolated past the last odometry input")
    max_future: float = number(1.0, 0.0, 10.0, "s", "a measurement may be ahead of the newest input (clock sanity)")
    pos_noise_density: float = number(1e-7, 0.0, 1.0, "m^2/s", "floor even when standing still (1 mm after 10 s)")
    heading_noise_density: float = number(1e-7, 0.0, 1.0, "rad^2/s", "heading noise floor")
    slip_per_metre: float = number(1e-4, 0.0, 1.0, "m^2/m", "position variance per metre travelled (1 cm std "
                                   "after 1 m)")
    heading_slip_per_rad: float = number(3e-4, 0.0, 1.0, "rad^2/rad", "heading variance per radian turned (1 deg "
                                         "std per rad)")
    heading_slip_per_metre: float = number(7.6e-5, 0.0, 1.0, "rad^2/m", "heading variance per metre travelled "
                                           "(0.5 deg std per m)")
    gyro_mode: str = choice("combine", ("combine", "replace"), "combine: inverse variance with the wheels' wz; "
                            "replace: the gyro alone")
    min_wall_normal: float = number(0.7, 0.0, 1.0, "", "|n_G,xy| below this: not a wall, its heading is "
                                    "meaningless")
    max_events: int = integer(5000, 10, 1_000_000, "", "hard bound on the history when odometry is missing")
    # The board reports every 10 ms; an interval this much longer came from a dropout or a stall.
    max_odom_interval: float = number(0.1, 0.01, 5.0, "s", "a longer odometry interval is a gap: a fix inside "
                                      "it is not placed on a constant-velocity path, its covariance covers the "
                                      "gap's unknown timing")

    def __post_init__(self):
        check_fields(self, "fusion")


@dataclass(frozen=True)
class RecordingConfig:
    """What the MCAP recording and the Foxglove live view may spend on depth images (the other channels are small)."""

    # A 848x480 16UC1 frame is 1.1 MB as JSON; over this, whole frames are skipped (replay fuses their recorded planes).
    depth_max_mbit_s: float = number(40.0, 0.0, 2000.0, "Mbit/s", "depth images written to a recording; 0: none")
    # Shared by all live clients; the live view also sends every n-th pixel only (at most 424 px wide).
    live_depth_max_mbit_s: float = number(8.0, 0.0, 1000.0, "Mbit/s", "depth images sent to the live view; 0: none")

    def __post_init__(self):
        check_fields(self, "recording")
