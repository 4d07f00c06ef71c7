"""The robot config (``config/robot.yaml``): cameras, chassis, localizer and control sections.

Every key is documented with its default and range in ``robot.config.sections`` (and, generated
from there, in ``docs/configuration.md``). Unknown keys are an error so a typo never silently
falls back to a default on a robot; a value outside its range is one error naming the file, the
key and the range.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from robot.base.errors import ConfigError
from robot.base.files import CONFIG
from robot.config.calibration import apply_calibration, load_calibration
from robot.config.control_api import ControlApiConfig, parse_control_api
from robot.config.fleet import FleetConfig, parse_fleet
from robot.config.ranges import field_choices, field_range
from robot.config.realsense import parse_realsense_config
from robot.config.recovery import RecoveryConfig
from robot.config.safety import SafetyConfig
from robot.config.schema import Section, check_number, load_yaml_file
from robot.config.sections import (
    CameraConfig,
    ChassisConfig,
    ControlConfig,
    FilterConfig,
    HealthConfig,
    LocalizerConfig,
    QualityConfig,
    RecordingConfig,
)


@dataclass(frozen=True)
class RobotConfig:
    cameras: Tuple[CameraConfig, ...]
    chassis: ChassisConfig = field(default_factory=ChassisConfig)
    localizer: LocalizerConfig = field(default_factory=LocalizerConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    health: HealthConfig = field(default_factory=HealthConfig)
    fusion: FilterConfig = field(default_factory=FilterConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    control_api: ControlApiConfig = field(default_factory=ControlApiConfig)  # the local control socket
    fleet: FleetConfig = field(default_factory=FleetConfig)  # VDA 5050 over MQTT (off by default)
    recording: RecordingConfig = field(default_factory=RecordingConfig)  # depth bandwidth of recording and live view
    map_path: Optional[str] = None  # `map:` the robot's plane map, relative to the config file
    source: str = "<built-in>"

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        from robot.base.errors import ConfigError

        names = ", ".join(c.name for c in self.cameras)
        raise ConfigError(f"{self.source}: unknown camera '{name}' (cameras: {names})")


MAX_CAMERAS = 8  # a Jetson's USB 3 bandwidth carries two or three D435i streams, not more
MAX_SERIAL_CHARS = 64


def _parse_camera(sec: Section) -> CameraConfig:
    ranges = {f.name: field_range(f) for f in dataclasses.fields(CameraConfig)}
    mount = sec.sub("mount", required=True)
    serial = None
    if sec.has("serial"):
        raw = sec.raw("serial")
        # a serial of digits only reads as a YAML int; quoting it keeps leading zeros
        if isinstance(raw, bool) or not isinstance(raw, (str, int)) or not 0 < len(str(raw)) <= MAX_SERIAL_CHARS:
            sec.fail(f"'serial' must be a RealSense serial number (a string of up to {MAX_SERIAL_CHARS} characters)")
        serial = str(raw)
    name = sec.string("name")
    if len(name) > 64:
        sec.fail("'name' must be at most 64 characters")
    cam = CameraConfig(
        name=name,
        width=sec.ranged("width", ranges["width"]),
        height=sec.ranged("height", ranges["height"]),
        fps=sec.ranged("fps", ranges["fps"]),
        hfov_deg=sec.ranged("hfov_deg", ranges["hfov_deg"]),
        vfov_deg=sec.ranged("vfov_deg", ranges["vfov_deg"]),
        mount_xyz=mount.vector("xyz", 3, rng=ranges["mount_xyz"]),
        mount_rpy_deg=mount.vector("rpy_deg", 3, rng=ranges["mount_rpy_deg"]),
        serial=serial,
        realsense=parse_realsense_config(sec.sub("realsense")),
        depth_scale=sec.ranged("depth_scale", ranges["depth_scale"], 1.0),
    )
    mount.done()
    sec.done()
    return cam


def _parse_safety(sec: Section) -> SafetyConfig:
    """The ``safety:`` section: flat numbers, plus ``guarded_sectors_deg`` (a list of [lo, hi] pairs)."""
    sectors = []
    raw = sec.raw("guarded_sectors_deg", [])
    if not isinstance(raw, list) or len(raw) > 8:
        sec.fail("'guarded_sectors_deg' must be a list of at most 8 [lo, hi] bearings in degrees")
    for i, pair in enumerate(raw):
        if not isinstance(pair, list) or len(pair) != 2:
            sec.fail(f"'guarded_sectors_deg[{i}]' must be [lo, hi] in degrees")
        lo, hi = (check_number(v, f"guarded_sectors_deg[{i}]", sec, lo=-360.0, hi=720.0) for v in pair)
        sectors.append((lo, hi))
    return _parse_dataclass(sec, SafetyConfig, skip=("guarded_sectors_deg",),
                            extra={"guarded_sectors_deg": tuple(sectors)})


def _parse_dataclass(sec: Section, cls, skip: Tuple[str, ...] = (), extra: Optional[dict] = None):
    """Read a flat section whose keys are the dataclass's fields.

    A field declared with a range (``robot.config.ranges``) is checked against it; a field
    without one is typed by its default (numbers then only need to be finite and >= 0).
    """
    defaults = cls()
    values = dict(extra or {})
    for f in dataclasses.fields(cls):
        name = f.name
        if name in skip:
            continue
        default = getattr(defaults, name)
        rng, choices = field_range(f), field_choices(f)
        if rng is not None:
            values[name] = sec.ranged(name, rng, default)
        elif choices is not None:
            values[name] = sec.string(name, default, choices=choices)
        elif isinstance(default, bool):
            values[name] = sec.boolean(name, default)
        elif isinstance(default, int):
            values[name] = sec.integer(name, default, lo=0)
        elif isinstance(default, float):
            values[name] = sec.number(name, default, lo=0.0)
        else:
            values[name] = sec.string(name, default)
    sec.done()
    try:
        return cls(**values)
    except ValueError as e:  # a dataclass's own cross-field check (__post_init__)
        msg = str(e)
        prefix = f"{sec.where}: "
        sec.fail(msg[len(prefix):] if msg.startswith(prefix) else msg)


def check_cross_section(robot: RobotConfig) -> None:
    """Limits that tie two sections together; ConfigError naming both keys."""
    period = 1.0 / robot.control.rate
    if robot.chassis.watchdog_timeout < 2.0 * period:
        raise ConfigError(
            f"{robot.source}: chassis.watchdog_timeout ({robot.chassis.watchdog_timeout} s) must cover at least two "
            f"control periods (control.rate {robot.control.rate} Hz: {2.0 * period:.3f} s), or the board stops "
            f"the wheels between commands")
    if robot.health.max_command_age < period:
        raise ConfigError(
            f"{robot.source}: health.max_command_age ({robot.health.max_command_age} s) is shorter than one control "
            f"period (control.rate {robot.control.rate} Hz): every command would be dropped")


def parse_robot_config(data, source: str = "<robot config>", calibration=None) -> RobotConfig:
    """The robot config in ``data``, with its calibration applied (``calibration``: a calibration
    file that replaces the config's own ``calibration:``, "" for none at all; robot.config.calibration)."""
    top = Section(data, "", source)
    raw_cams = top.raw("cameras")
    if not isinstance(raw_cams, list) or not raw_cams:
        top.fail("'cameras' must be a non-empty list")
    if len(raw_cams) > MAX_CAMERAS:
        top.fail(f"'cameras' lists {len(raw_cams)} cameras, at most {MAX_CAMERAS} are supported")
    cams: List[CameraConfig] = []
    for i, c in enumerate(raw_cams):
        cams.append(_parse_camera(Section(c, f"cameras[{i}]", source)))
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        top.fail(f"duplicate camera name(s): {', '.join(dup)}")
    chassis = _parse_dataclass(top.sub("chassis"), ChassisConfig)
    localizer = _parse_dataclass(top.sub("localizer"), LocalizerConfig)
    control = _parse_dataclass(top.sub("control"), ControlConfig)
    health = _parse_dataclass(top.sub("health"), HealthConfig)
    fusion = _parse_dataclass(top.sub("fusion"), FilterConfig)
    quality = _parse_dataclass(top.sub("quality"), QualityConfig)
    safety = _parse_safety(top.sub("safety"))
    recovery = _parse_dataclass(top.sub("recovery"), RecoveryConfig)
    control_api = parse_control_api(top.sub("control_api"))
    fleet = parse_fleet(top.sub("fleet"))
    recording = _parse_dataclass(top.sub("recording"), RecordingConfig)
    map_path = None
    if top.has("map"):
        rel = top.string("map")
        base = os.path.dirname(os.path.abspath(source)) if not source.startswith("<") else os.getcwd()
        map_path = os.path.normpath(os.path.join(base, os.path.expanduser(rel)))
    if top.has("calibration"):
        rel = top.string("calibration")
        base = os.path.dirname(os.path.abspath(source)) if not source.startswith("<") else os.getcwd()
        if calibration is None:
            calibration = os.path.normpath(os.path.join(base, os.path.expanduser(rel)))
    top.done()
    robot = RobotConfig(cameras=tuple(cams), chassis=chassis, localizer=localizer, control=control, health=health,
                        fusion=fusion, quality=quality, safety=safety, recovery=recovery, control_api=control_api,
                        fleet=fleet, recording=recording, map_path=map_path, source=source)
    check_cross_section(robot)
    if calibration:
        robot = apply_calibration(robot, load_calibration(calibration))
    return robot


def load_robot_config(path, calibration=None) -> RobotConfig:
    return parse_robot_config(load_yaml_file(path, CONFIG), source=str(path), calibration=calibration)
