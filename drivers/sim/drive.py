"""A simulated drive seen by one camera, as depth frames and D435i IMU samples (for .bag recordings)."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import numpy as np

from drivers.sim.render import render_depth_frame, resolve_noise
from robot.base.samples import ImuSample

GRAVITY = 9.80665  # m/s^2


def simulate_run(robot, scene, camera: str, start_pose: Sequence[float], velocity: Sequence[float] = (0.0, 0.0, 0.0),
                 frames: int = 30, fps: Optional[float] = None, imu_rate: float = 0.0, noise="default",
                 rng: Optional[np.random.Generator] = None, depth_scale: float = 0.001, K=None):
    """A simulated drive seen by one camera: depth frames and, if ``imu_rate`` > 0, D435i IMU samples.

    The robot moves from ``start_pose`` (x, y, phi) at constant ground-frame velocity
    (vx, vy, omega). IMU samples are in the camera's IMU frame, whose axes librealsense aligns
    with the depth optical frame (x right, y down, z forward; ``drivers.camera.realsense_imu``), as it
    reports a D435i's motion data: the gyro sees the yaw rate, the accelerometer
    the specific force of gravity (a level camera at rest reads about (0, -9.8, 0)). Returns
    (frames, imu_samples), times in seconds from 0.
    """
    cam = robot.camera(camera)
    fps = float(cam.fps if fps is None else fps)
    rng = rng if rng is not None else np.random.default_rng()
    if isinstance(noise, str):
        noise = resolve_noise(noise)  # "default" / "realistic", "simple", "none"
    x0, y0, phi0 = (float(v) for v in start_pose)
    vx, vy, om = (float(v) for v in velocity)

    def pose(t: float) -> Tuple[float, float, float]:
        return (x0 + vx * t, y0 + vy * t, phi0 + om * t)

    out = []
    for i in range(frames):
        t = i / fps
        out.append(render_depth_frame(robot, scene, camera, pose(t), rng=rng, noise=noise, depth_scale=depth_scale,
                                      K=K, t_capture=t, frame_number=i))
    imu: List[ImuSample] = []
    if imu_rate > 0:
        R_robot_camera = cam.T_robot_camera[:3, :3]
        gyro = tuple(float(v) for v in R_robot_camera.T @ np.array([0.0, 0.0, om]))
        accel = tuple(float(v) for v in R_robot_camera.T @ np.array([0.0, 0.0, GRAVITY]))
        n = int(np.floor((frames - 1) / fps * imu_rate)) + 1
        for j in range(n):
            imu.append(ImuSample(t=j / imu_rate, gyro=gyro, accel=accel))
    return out, imu
