"""The assembly module: drivers by name, the one place the command line's backend choices go through."""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from drivers.camera.base import CameraDriver
from drivers.chassis.base import Chassis, LinkState
from robot.app import assemble
from robot.base.errors import InputError
from robot.config import ChassisConfig, load_robot_config
from robot.maps.plane_map import load_plane_map

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
CFG = ChassisConfig(link_timeout=0.5)


@pytest.mark.parametrize("build,kinds", [
    (lambda: assemble.build_chassis("usb", CFG), "serial, emulator"),
    (lambda: assemble.build_cameras("kinect", ROBOT), "realsense, sim, bag"),
    (lambda: assemble.build_rig("robot", ROBOT), "hardware, sim"),
])
def test_an_unknown_kind_names_the_choices(build, kinds):
    with pytest.raises(InputError, match=f"choose from {kinds}"):
        build()


def test_hardware_rig_is_the_serial_board_and_the_realsense_cameras_without_opening_them():
    from drivers.camera.realsense import RealSenseCamera
    from drivers.chassis.serial_chassis import SerialChassis

    rig = assemble.build_rig("hardware", ROBOT)
    assert isinstance(rig.chassis, SerialChassis) and rig.chassis.port == ROBOT.chassis.port
    assert rig.chassis.link_state is LinkState.CLOSED  # nothing opened until the app connects
    assert [type(c) for c in rig.cameras] == [RealSenseCamera] * len(ROBOT.cameras)
    assert [c.name for c in rig.cameras] == [c.name for c in ROBOT.cameras] and rig.emulator is None


def test_emulated_chassis_drives_its_emulator_and_closes_it():
    chassis = assemble.build_chassis("emulator", CFG, pose=(0.5, 0.4, 0.0))
    emulator = chassis.emulator
    assert isinstance(chassis, Chassis) and emulator.pose == (0.5, 0.4, 0.0)

    async def main():
        await chassis.connect()
        state = chassis.link_state
        await chassis.close()
        return state

    assert asyncio.run(asyncio.wait_for(main(), 30.0)) is LinkState.READY
    assert emulator._master is None  # the pty went with the chassis


def test_a_port_and_the_emulator_exclude_each_other():
    with pytest.raises(InputError, match="exclude each other"):
        assemble.build_chassis("emulator", CFG, port="/dev/ttyUSB0")
    with pytest.raises(InputError, match="exclude each other"):
        with assemble.board_port("emulator", CFG, "/dev/ttyUSB0"):
            pass


def test_board_port_gives_the_emulator_slack_and_a_named_port_as_is():
    tight = dataclasses.replace(CFG, link_timeout=0.1)
    with assemble.board_port("emulator", tight) as board:
        assert board.emulator is not None and board.port == board.emulator.port
        assert board.config.link_timeout == assemble.EMULATOR_LINK_TIMEOUT
    assert board.emulator._master is None  # closed with the block
    with assemble.board_port("serial", tight, "/dev/ttyACM3") as board:
        assert (board.port, board.config, board.emulator) == ("/dev/ttyACM3", tight, None)


def test_sim_rig_cameras_render_the_emulators_true_pose():
    robot = dataclasses.replace(ROBOT, cameras=(dataclasses.replace(
        ROBOT.cameras[0], realsense=dataclasses.replace(ROBOT.cameras[0].realsense, imu_enabled=True)),
        ROBOT.cameras[1]))
    rig = assemble.build_rig("sim", robot, ARENA, (0.5, 0.5, 0.3), fps=5.0, seed=2)
    try:
        # approx: once the emulator's physics has stepped (on a loaded machine, before these lines
        # run) the heading has been wrapped, which moves 0.3 by an ulp
        assert rig.emulator is not None and rig.emulator.pose == pytest.approx((0.5, 0.5, 0.3), abs=1e-12)
        assert rig.chassis.port == rig.emulator.port
        front, left = rig.cameras
        assert all(isinstance(c, CameraDriver) for c in rig.cameras)
        assert front.pose_source() == pytest.approx(rig.emulator.pose, abs=1e-12)
        assert front.fps == 5.0 and front.decimation == 4
        assert front.imu_rate == float(robot.cameras[0].realsense.gyro_fps) and left.imu_rate == 0.0
    finally:
        rig.close()


def test_sim_cameras_need_a_scene_and_a_pose():
    with pytest.raises(TypeError, match="scene"):
        assemble.build_cameras("sim", ROBOT)


def test_bag_cameras_need_one_recording_per_configured_camera(tmp_path):
    with pytest.raises(InputError, match="no recording for camera\\(s\\) left"):
        assemble.build_cameras("bag", ROBOT, recordings={"front": tmp_path / "front.bag"})
    with pytest.raises(InputError, match="unknown camera\\(s\\) rear"):
        assemble.build_cameras("bag", ROBOT, recordings={"front": "f.bag", "left": "l.bag", "rear": "r.bag"})
    with pytest.raises(InputError, match="camera 'front': recording .*front.bag not found"):
        assemble.build_cameras("bag", ROBOT, recordings={"front": tmp_path / "front.bag", "left": tmp_path / "l.bag"})
