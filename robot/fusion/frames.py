"""The robot's coordinate frames as ROS REP-105 names them: ``map -> odom -> base_link``, plus the cameras.

- ``map``: the plane map's ground frame G. The fused pose (EKF) is ``T_map_base``.
- ``odom``: a frame in which the robot moves continuously, by its wheels alone. It drifts, but it
  never jumps, so anything that needs smooth motion (a controller's derivative, a plot of the
  robot's track) reads ``T_odom_base``.
- ``base_link``: the robot frame R (x forward, y left, z up, on the floor).
- ``<camera>_link``: a camera's body frame (x forward, y left, z up) at its mount, and
  ``<camera>_optical_frame`` under it (x right, y down, z forward), where depth images live.

Keeping ``map -> odom`` separate from ``odom -> base_link`` is what lets a localization jump
show up where it belongs: the fused pose corrects ``T_map_odom = T_map_base * T_odom_base^-1``,
and the robot's odometry is untouched.

Poses here are planar ``(x, y, phi)`` tuples (SE(2)); ``camera_mounts`` gives 4x4 transforms.
Pure math: no clock, no I/O.
"""

from __future__ import annotations

import math
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import (
    R_BODY_OPTICAL,
    compose_se2,
    integrate_twist,
    invert_se2,
    make_transform,
    rpy_to_matrix,
)
from robot.base.samples import WheelOdometry
from robot.config import CameraConfig

MAP = "map"
ODOM = "odom"
BASE_LINK = "base_link"

Pose2 = Tuple[float, float, float]
IDENTITY: Pose2 = (0.0, 0.0, 0.0)

# A longer gap between two odometry samples is an outage (a lost link, a restarted board): the
# mean speed of the sample after it says nothing about how the robot moved during it.
DEFAULT_MAX_GAP = 0.5  # s


def camera_link(camera: str) -> str:
    """The body frame of a camera's mount (x forward, y left, z up)."""
    return f"{camera}_link"


def camera_optical_frame(camera: str) -> str:
    """A camera's optical frame (x right, y down, z forward): the frame of its depth images."""
    return f"{camera}_optical_frame"


compose = compose_se2  # T_a * T_b on SE(2)
invert = invert_se2  # T_a^-1 on SE(2)


class OdomFrame:
    """``odom -> base_link`` from the wheels alone, and ``map -> odom`` from the fused pose.

    ``forward`` maps the four wheel speeds (rad/s) to the body twist (vx, vy, wz), e.g.
    ``MecanumKinematics.forward``. Each sample's mean twist is integrated exactly on SE(2) over
    the host-time interval it ends (the interval the EKF's prediction uses too), so with no
    vision the fused pose and the odometry move alike and ``map -> odom`` stays still. The first
    sample, which has no predecessor, spans its own board interval ``dt``. A sample that is not
    finite or not later than the previous one is refused (False) and changes nothing.
    """

    def __init__(self, forward: Callable[[Sequence[float]], Sequence[float]], max_gap: float = DEFAULT_MAX_GAP):
        self._forward = forward
        self.max_gap = float(max_gap)
        self._pose: Pose2 = IDENTITY
        self._t: Optional[float] = None
        self.refused = 0

    @property
    def t(self) -> Optional[float]:
        """Host time of the newest sample integrated (None before the first one)."""
        return self._t

    @property
    def pose(self) -> Pose2:
        """T_odom_base: the robot in the odom frame, starting at the origin."""
        return self._pose

    def update(self, odo: WheelOdometry) -> bool:
        """Integrate one wheel odometry sample; False (and nothing changes) if it is refused."""
        t = float(odo.t)
        vx, vy, wz = self._forward(odo.speeds)
        vx, vy, wz = float(vx), float(vy), float(wz)
        isfinite = math.isfinite  # (a hundred samples a second, on the event loop)
        if not (isfinite(t) and isfinite(vx) and isfinite(vy) and isfinite(wz)) or (self._t is not None and t <= self._t):
            self.refused += 1
            return False
        dt = t - self._t if self._t is not None else float(odo.dt)
        if not (math.isfinite(dt) and 0.0 < dt <= self.max_gap):
            # an outage, or a first sample without a usable interval: the robot's motion over it
            # is unknown; the frame stays continuous and picks up from here
            board_dt = float(odo.dt)
            dt = board_dt if math.isfinite(board_dt) and 0.0 < board_dt <= self.max_gap else 0.0
        self._pose = integrate_twist(*self._pose, vx, vy, wz, dt)
        self._t = t
        return True

    def map_to_odom(self, T_map_base: Pose2) -> Pose2:
        """T_map_odom = T_map_base * T_odom_base^-1, for the fused pose at ``self.t`` (the time of
        the odometry the frame holds), so that map -> odom -> base_link is the fused pose."""
        return compose(tuple(float(v) for v in T_map_base), invert(self._pose))  # type: ignore[arg-type]


def planar_to_T(pose: Pose2) -> np.ndarray:
    """4x4 transform of a planar pose (z = 0, rotation about z)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, 0.0, pose[0]], [s, c, 0.0, pose[1]], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def camera_mounts(cameras: Sequence[CameraConfig]) -> List[Tuple[str, str, np.ndarray]]:
    """The fixed transforms of the cameras: (parent, child, T_parent_child) for ``base_link ->
    <camera>_link`` (the configured mount) and ``<camera>_link -> <camera>_optical_frame``."""
    out: List[Tuple[str, str, np.ndarray]] = []
    for cam in cameras:
        rpy = tuple(math.radians(a) for a in cam.mount_rpy_deg)
        out.append((BASE_LINK, camera_link(cam.name), make_transform(rpy_to_matrix(*rpy), cam.mount_xyz)))
        out.append((camera_link(cam.name), camera_optical_frame(cam.name), make_transform(R_BODY_OPTICAL, (0, 0, 0))))
    return out


__all__ = ["MAP", "ODOM", "BASE_LINK", "OdomFrame", "camera_link", "camera_optical_frame", "camera_mounts",
           "compose", "invert", "planar_to_T"]
