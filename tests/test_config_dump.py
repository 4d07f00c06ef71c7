"""The effective config dict reads back, through YAML or JSON, to the very RobotConfig it came from."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace
from pathlib import Path

import yaml

from robot.config import CameraConfig, load_robot_config, parse_robot_config
from robot.config.dump import effective_config_dict

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = load_robot_config(ROOT / "config" / "robot.yaml")


def _tuned(robot):
    """The shipped config with a value off its default in every section (a robot after field tuning)."""
    front, *others = robot.cameras
    front = replace(front, serial="147122071234", fps=15.0, mount_rpy_deg=(0.5, -1.25, 2.0),
                    realsense=replace(front.realsense, imu_enabled=True, gyro_fps=400, visual_preset="high_density",
                                      laser_power=210.0, spatial_filter=True))
    others = tuple(replace(c, serial=None) for c in others)
    return replace(robot, cameras=(front, *others),
                   chassis=replace(robot.chassis, port="/dev/ttyUSB1", wheel_radius=0.0305, ticks_per_rev=1440),
                   localizer=replace(robot.localizer, pixel_stride=2, inlier_threshold=0.015),
                   control=replace(robot.control, rate=100.0, require_settled=False),
                   health=replace(robot.health, vision_required=False, stop_after=5.0),
                   fusion=replace(robot.fusion, gyro_mode="replace", slip_per_metre=2e-4),
                   quality=replace(robot.quality, min_decisions=7, hysteresis=0.75))


def test_the_shipped_and_a_tuned_config_round_trip_exactly_through_yaml_and_json():
    for robot in (SHIPPED, _tuned(SHIPPED)):
        d = effective_config_dict(robot)
        assert parse_robot_config(d, robot.source) == robot
        assert parse_robot_config(yaml.safe_load(yaml.safe_dump(d)), robot.source) == robot
        assert parse_robot_config(json.loads(json.dumps(d, allow_nan=False)), robot.source) == robot


def test_every_key_is_written_with_its_value_after_defaults():
    robot = _tuned(SHIPPED)
    d = effective_config_dict(robot)
    for section in ("chassis", "localizer", "control", "health", "fusion", "quality"):
        assert set(d[section]) == {f.name for f in dataclasses.fields(getattr(robot, section))}, section
    cam = d["cameras"][0]
    expected = {f.name for f in dataclasses.fields(CameraConfig)} - {"mount_xyz", "mount_rpy_deg"} | {"mount"}
    assert set(cam) == expected  # a camera field added later must be written too
    assert cam["mount"]["rpy_deg"] == [0.5, -1.25, 2.0] and cam["realsense"]["gyro_fps"] == 400
    assert "serial" not in d["cameras"][1]  # no serial: "the only device", never a null that fails to parse
    assert d["fusion"]["gyro_mode"] == "replace" and d["control"]["rate"] == 100.0


def test_the_map_is_the_one_the_app_loaded_as_an_absolute_path(tmp_path, monkeypatch):
    assert effective_config_dict(SHIPPED)["map"] == SHIPPED.map_path
    monkeypatch.chdir(tmp_path)
    d = effective_config_dict(SHIPPED, map_path="maps/site_b.yaml")  # --map given relative to the cwd
    assert d["map"] == str(tmp_path / "maps" / "site_b.yaml")
    assert parse_robot_config(d, "/elsewhere/robot.yaml").map_path == d["map"]
    assert "map" not in effective_config_dict(replace(SHIPPED, map_path=None))
    assert "map" not in effective_config_dict(replace(SHIPPED, map_path=None), map_path="<map>")
