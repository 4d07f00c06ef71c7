"""Data that crosses from drivers into the robot core: depth frames, IMU samples, wheel odometry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np


@dataclass
class DepthFrame:
    """One depth image, owned by the core (drivers hand over a copy, never a driver buffer).

    ``t_capture`` is the exposure time on the host's monotonic clock (seconds), so the EKF can
    apply the measurement at the instant it describes rather than when it was processed.
    """

    camera: str
    depth: np.ndarray  # (H, W) uint16, 0 = no data
    depth_scale: float  # metres per depth unit
    K: np.ndarray  # (3, 3) intrinsics of this frame's stream
    t_capture: float = 0.0
    frame_number: int = 0
    timestamp_domain: str = "simulated"
    truth: Optional[Tuple[float, float, float]] = None  # ground-truth pose (x, y, phi), simulation only

    def depth_m(self) -> np.ndarray:
        return self.depth.astype(np.float32) * np.float32(self.depth_scale)


@dataclass
class ImuSample:
    """A D435i motion sample in the camera's IMU frame; host monotonic time in seconds."""

    t: float
    gyro: Optional[Tuple[float, float, float]] = None  # rad/s
    accel: Optional[Tuple[float, float, float]] = None  # m/s^2


@dataclass(frozen=True)
class WheelOdometry:
    """One encoder report turned into wheel motion. Wheel order FL, FR, RL, RR."""

    t: float  # host monotonic time (s) the board sampled the encoders at
    angles: Tuple[float, float, float, float]  # cumulative wheel angles (rad), continuous across reconnects
    speeds: Tuple[float, float, float, float]  # mean wheel speeds (rad/s) over dt
    dt: float  # s since the previous sample, on the board's clock
    t_board: float  # board time (s), unwrapped
