"""The D435i's IMU frame, and the robot-frame yaw rate from its gyro. Pure numpy, no pyrealsense2.

Frames (librealsense doc/d435i.md, "Sensor origin and coordinate system"; PRs #2843 and #3901):

- The BMI055 sits on the camera board at its own angle, but librealsense rotates every gyro and
  accel sample into the depth sensor's axes before handing it over: x right, y down, z forward,
  like the depth optical frame C. The IMU frame I keeps its own origin, a few millimetres from the
  depth origin. So ``T_camera_imu`` (I -> C) is a pure translation on every D435i, and the stream
  extrinsics librealsense reports between gyro and depth have an identity rotation
  (``rs-enumerate-devices -c``: "Extrinsic from Depth To Gyro", translation
  (-0.00552, 0.0051, 0.01174) m, from the mechanical drawings, not calibrated per unit).
- The driver takes ``T_camera_imu`` from the device's gyro-to-depth extrinsics when it reports
  them (a camera does) and otherwise uses ``D435I_T_CAMERA_IMU`` below (a recording made by
  ``rs.recorder`` from a ``software_device`` does not carry motion-stream extrinsics).
- ``T_robot_imu = T_robot_camera @ T_camera_imu``. A rotation rate is the same at every point
  of a rigid body, so only the rotation part matters for the gyro; the translation is kept for
  the accelerometer's lever arm.

Sign: librealsense's gyro is right-handed about its axes (rad/s). A level camera looking forward
on a robot turning left (counter-clockwise seen from above, +z in R) reads about -wz on its y
axis, because y points down.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from robot.base.samples import ImuSample

# librealsense's depth -> gyro extrinsics of a D435i (identity rotation, translation in metres),
# inverted: the IMU origin expressed in the depth optical frame.
_DEPTH_TO_GYRO_TRANSLATION = (-0.00552, 0.0051, 0.01174)
D435I_T_CAMERA_IMU = np.eye(4)
D435I_T_CAMERA_IMU[:3, 3] = [-v for v in _DEPTH_TO_GYRO_TRANSLATION]
D435I_T_CAMERA_IMU.setflags(write=False)


def T_from_rs_extrinsics(rotation: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """4x4 transform of librealsense extrinsics ``a.get_extrinsics_to(b)``: it maps points of a to b.

    librealsense stores the rotation column-major (rs_sensor.h), and applies it as
    ``p_b[i] = sum_j rotation[3*j + i] * p_a[j] + translation[i]`` (rs2_transform_point_to_point).
    """
    r = np.asarray(rotation, dtype=float)
    t = np.asarray(translation, dtype=float)
    if r.shape != (9,) or t.shape != (3,) or not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise ValueError(f"extrinsics need 9 finite rotation and 3 finite translation values, "
                         f"got {r.tolist()} / {t.tolist()}")
    T = np.eye(4)
    T[:3, :3] = r.reshape(3, 3).T
    T[:3, 3] = t
    return T


def yaw_rate_robot(sample: ImuSample, T_robot_camera_imu: np.ndarray) -> float:
    """Yaw rate (rad/s, counter-clockwise seen from above, about R's z axis) of a gyro sample.

    ``T_robot_camera_imu`` is the camera IMU frame -> robot frame transform
    (``RealSenseCamera.T_robot_imu``). The robot drives on a level floor, so its yaw rate is the
    z component of the angular velocity in R; the gyro's bias is not removed here.
    """
    if sample.gyro is None:
        raise ValueError("the IMU sample has no gyro reading (an accelerometer sample?)")
    w = np.asarray(sample.gyro, dtype=float)
    T = np.asarray(T_robot_camera_imu, dtype=float)
    if w.shape != (3,) or not np.all(np.isfinite(w)):
        raise ValueError(f"gyro reading must be 3 finite numbers, got {sample.gyro!r}")
    if T.shape != (4, 4):
        raise ValueError(f"T_robot_camera_imu must be 4x4, got shape {T.shape}")
    wz = float(T[2, :3] @ w)
    if not math.isfinite(wz):
        raise ValueError("T_robot_camera_imu is not finite")
    return wz
