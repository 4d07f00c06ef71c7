"""The app turns a camera's gyro samples into robot-frame yaw rate for the EKF's prediction."""

from __future__ import annotations

import math

import numpy as np

from robot.app.controller import RobotApp
from robot.base.samples import ImuSample
from robot.config import load_robot_config
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")


class _Cam:
    name = "left"

    def __init__(self, T_robot_imu):
        self.T_robot_imu = T_robot_imu


class _Chassis:
    pass


def test_gyro_samples_become_yaw_rate_about_the_robot_z_axis():
    written = []

    class _Recorder:
        active = True

        def write(self, topic, t, message):
            written.append((topic, dict(message)))

    app = RobotApp(ROBOT, load_plane_map("config/maps/paper_arena.yaml"), [], _Chassis(), recorder=_Recorder())
    seen = []
    app.core.on_gyro = lambda t, wz, var: seen.append((t, wz, var))
    # IMU axes as librealsense gives them (the depth optical frame: x right, y down, z forward),
    # camera looking along the robot's +y (the left camera): robot z (up) is optical -y.
    T = np.eye(4)
    T[:3, :3] = ROBOT.camera("left").T_robot_camera[:3, :3]
    app._imu(_Cam(T), ImuSample(t=1.0, gyro=(0.0, -0.5, 0.0)))  # spinning about optical -y = robot +z
    app._imu(_Cam(T), ImuSample(t=1.1, gyro=(float("nan"), 0.0, 0.0)))  # refused, never fused
    assert len(seen) == 1 and seen[0][0] == 1.0 and math.isclose(seen[0][1], 0.5, abs_tol=1e-9)
    assert app.stats.imu_rejected == 1
    # recorded for replay, in the order fused
    assert [(topic, m["gyro_wz"]) for topic, m in written] == [("/odometry", seen[0][1])]
