"""REP-105 frames: odom -> base_link is the wheels alone and never jumps; map -> odom takes the
localization's corrections; the camera mounts and the FrameTransform messages put things where
they are."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.base.geometry import integrate_twist, transform_points
from robot.base.samples import WheelOdometry
from robot.config import load_robot_config
from robot.control.core import ControllerCore
from robot.control.kinematics import MecanumKinematics
from robot.fusion import frames
from robot.localization.localizer import LocalizationResult
from robot.localization.measurements import PlaneMeasurement
from robot.recording import schema as ms

ROBOT = load_robot_config("config/robot.yaml")
KIN = MecanumKinematics.from_config(ROBOT.chassis)
DT = 0.01  # s: the motor board reports at 100 Hz
R_PLANE = np.diag([0.003 ** 2, math.radians(0.5) ** 2])


def drive(t0: float, n: int, twist=(0.2, 0.05, 0.4)):
    """n odometry samples of a constant body twist (an arc with sideways drift), from t0 + DT on."""
    wheels = tuple(float(w) for w in KIN.inverse(*twist))
    return [WheelOdometry(t=t0 + (k + 1) * DT, angles=(0.0,) * 4, speeds=wheels, dt=DT, t_board=t0 + (k + 1) * DT)
            for k in range(n)]


def close(a, b, tol=1e-9) -> bool:
    return abs(a[0] - b[0]) < tol and abs(a[1] - b[1]) < tol and abs(math.remainder(a[2] - b[2], 2 * math.pi)) < tol


def test_odom_is_the_exact_se2_integral_of_the_wheel_twist():
    odom = frames.OdomFrame(KIN.forward)
    assert odom.pose == (0.0, 0.0, 0.0) and odom.t is None
    expected = (0.0, 0.0, 0.0)
    for odo in drive(10.0, 300):
        assert odom.update(odo)
        expected = integrate_twist(*expected, 0.2, 0.05, 0.4, DT)
    assert odom.t == pytest.approx(13.0)
    assert close(odom.pose, expected)
    # 3 s of a 0.4 rad/s turn: 1.2 rad, on an arc (not a straight line)
    assert odom.pose[2] == pytest.approx(1.2) and math.hypot(*odom.pose[:2]) < 0.2 * 3.0


def test_bad_samples_change_nothing_and_an_outage_is_not_guessed():
    odom = frames.OdomFrame(KIN.forward)
    samples = drive(0.0, 10)
    for odo in samples:
        odom.update(odo)
    before = odom.pose
    nan = WheelOdometry(t=0.2, angles=(0.0,) * 4, speeds=(math.nan, 0.0, 0.0, 0.0), dt=DT, t_board=0.2)
    late = samples[3]  # older than the newest: a reordered report
    assert not odom.update(nan) and not odom.update(late)
    assert odom.pose == before and odom.refused == 2
    # the link was down for 3 s: the sample after it spans its own board interval, not the gap
    after = WheelOdometry(t=samples[-1].t + 3.0, angles=(0.0,) * 4, speeds=samples[0].speeds, dt=DT, t_board=3.0)
    assert odom.update(after)
    assert close(odom.pose, integrate_twist(*before, 0.2, 0.05, 0.4, DT))


def test_without_vision_map_to_odom_stays_where_the_pose_was_set():
    """The odom frame and the EKF's prediction integrate the same twists over the same intervals."""
    core = ControllerCore(ROBOT, vision=False, t_start=0.0)
    start = (0.5, 0.6, 0.3)
    core.set_pose(5.0, *start, np.diag([1e-4, 1e-4, 1e-4]))
    odom = frames.OdomFrame(KIN.forward)
    for i, odo in enumerate(drive(5.0, 200) + drive(7.0, 200, twist=(-0.1, 0.2, -0.8))):
        core.on_odometry(odo)
        odom.update(odo)
        (x, y, phi), _ = core.pose(odom.t)
        assert close(odom.map_to_odom((x, y, phi)), start, 1e-9), i


def _measurement(wall_n, wall_d, true_pose, t):
    x, y, phi = true_pose
    z = np.array([wall_n[0] * x + wall_n[1] * y + wall_d, math.remainder(math.atan2(wall_n[1], wall_n[0]) - phi,
                                                                         2 * math.pi)])
    return PlaneMeasurement("wall", "front", t, np.asarray(wall_n, float), wall_d, z, R_PLANE.copy(), 5000)


def test_a_localization_jump_moves_map_to_odom_and_never_the_odometry():
    core = ControllerCore(ROBOT, vision=True, t_start=0.0)
    core.set_pose(0.0, 0.5, 0.5, 0.0, np.diag([0.05 ** 2, 0.05 ** 2, math.radians(3) ** 2]))
    odom = frames.OdomFrame(KIN.forward)
    track = []
    for odo in drive(0.0, 100, twist=(0.1, 0.0, 0.0)):
        core.on_odometry(odo)
        odom.update(odo)
        track.append(odom.pose)
    t = odom.t
    (x0, y0, phi0), _ = core.pose(t)
    map_odom_before = odom.map_to_odom((x0, y0, phi0))
    # the wheels slipped: the robot is really 4 cm further along x than odometry says; walls tell
    truth = (x0 + 0.04, y0, phi0)
    meas = [_measurement((1.0, 0.0, 0.0), 0.25, truth, t), _measurement((0.0, 1.0, 0.0), 0.25, truth, t)]
    report = core.on_localization(LocalizationResult(0, 0, 0, np.eye(3), "ok", [], [], meas), t, "front")
    assert sorted(report.accepted) == ["wall", "wall"]
    (x1, y1, phi1), _ = core.pose(t)
    assert x1 - x0 > 0.02  # the fused pose jumped towards the truth
    assert odom.pose == track[-1]  # odometry untouched
    map_odom_after = odom.map_to_odom((x1, y1, phi1))
    assert map_odom_after[0] - map_odom_before[0] == pytest.approx(x1 - x0, abs=1e-9)  # the jump, all of it
    assert close(frames.compose(map_odom_after, odom.pose), (x1, y1, phi1))
    # and the odometry track itself is smooth: no step larger than 0.1 m/s for one report interval
    steps = [math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(track, track[1:])]
    assert max(steps) <= 0.1 * DT + 1e-12


def test_se2_compose_and_invert():
    a, b = (1.0, 2.0, 0.7), (-0.3, 0.4, -2.9)
    assert close(frames.compose(a, frames.invert(a)), (0.0, 0.0, 0.0))
    T = frames.planar_to_T(a) @ frames.planar_to_T(b)
    assert close(frames.compose(a, b), (T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])))


def test_camera_mounts_put_the_optical_axis_where_the_camera_looks():
    mounts = {child: (parent, T) for parent, child, T in frames.camera_mounts(ROBOT.cameras)}
    assert mounts["front_link"][0] == "base_link" and mounts["front_optical_frame"][0] == "front_link"
    left = ROBOT.camera("left")  # mounted at (0, 0.10, 0.12), yaw 90 deg: looks along the robot's +y
    T_base_optical = mounts["left_link"][1] @ mounts["left_optical_frame"][1]
    np.testing.assert_allclose(T_base_optical, left.T_robot_camera, atol=1e-12)  # the localizer's own mount
    ahead = transform_points(T_base_optical, np.array([[0.0, 0.0, 1.0]]))[0]  # 1 m along the optical z axis
    np.testing.assert_allclose(ahead, [0.0, 1.10, 0.12], atol=1e-12)


def test_frame_transform_messages_hold_the_same_transforms():
    msg = ms.transforms_message(3.0, frames.camera_mounts(ROBOT.cameras))
    assert {(f["parent_frame_id"], f["child_frame_id"]) for f in msg["transforms"]} == {
        ("base_link", "front_link"), ("front_link", "front_optical_frame"),
        ("base_link", "left_link"), ("left_link", "left_optical_frame")}
    for f, (_, _, T) in zip(msg["transforms"], frames.camera_mounts(ROBOT.cameras)):
        q = f["rotation"]
        x, y, z, w = q["x"], q["y"], q["z"], q["w"]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
        assert [f["translation"][k] for k in "xyz"] == pytest.approx(T[:3, 3].tolist())
    tf = ms.odometry_transforms(4.0, (1.0, 2.0, 0.5), (0.3, -0.1, 1.0))
    (map_odom, odom_base) = tf["transforms"]
    assert (map_odom["parent_frame_id"], map_odom["child_frame_id"]) == ("map", "odom")
    assert (odom_base["parent_frame_id"], odom_base["child_frame_id"]) == ("odom", "base_link")
    assert 2 * math.atan2(odom_base["rotation"]["z"], odom_base["rotation"]["w"]) == pytest.approx(1.0)
    assert tf["t"] == 4.0 and map_odom["timestamp"] == ms.stamp(4.0)
