"""The robot config (``config/robot.yaml``): cameras, chassis, localizer and control sections.

Every key is documented here with its default. Unknown keys are an error so a typo never
silently falls back to a default on a robot.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import List, Optional, Tuple

from robot.config.realsense import parse_realsense_config
from robot.config.schema import Section, load_yaml_file
from robot.config.sections import (
    CameraConfig,
    ChassisConfig,
    ControlConfig,
    FilterConfig,
    HealthConfig,
    LocalizerConfig,
    QualityConfig,
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
    map_path: Optional[str] = None  # `map:` the robot's plane map, relative to the config file
    source: str = "<built-in>"

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        from robot.base.errors import ConfigError

        names = ", ".join(c.name for c in self.cameras)
        raise ConfigError(f"{self.source}: unknown camera '{name}' (cameras: {names})")


def _parse_camera(sec: Section) -> CameraConfig:
    mount = sec.sub("mount", required=True)
    cam = CameraConfig(
        name=sec.string("name"),
        width=sec.integer("width", lo=16),
        height=sec.integer("height", lo=16),
        fps=sec.number("fps", positive=True),
        hfov_deg=sec.number("hfov_deg", lo=1.0, hi=170.0),
        vfov_deg=sec.number("vfov_deg", lo=1.0, hi=170.0),
        mount_xyz=mount.vector("xyz", 3),
        mount_rpy_deg=mount.vector("rpy_deg", 3),
        serial=str(sec.raw("serial")) if sec.has("serial") else None,
        realsense=parse_realsense_config(sec.sub("realsense")),
    )
    mount.done()
    sec.done()
    return cam


def _parse_dataclass(sec: Section, cls):
    """Read a flat section whose keys are the dataclass's fields, typed by their defaults."""
    defaults = cls()
    values = {}
    for name in cls.__dataclass_fields__:
        default = getattr(defaults, name)
        if isinstance(default, bool):
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
        sec.fail(str(e))


def parse_robot_config(data, source: str = "<robot config>") -> RobotConfig:
    top = Section(data, "", source)
    raw_cams = top.raw("cameras")
    if not isinstance(raw_cams, list) or not raw_cams:
        top.fail("'cameras' must be a non-empty list")
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
    map_path = None
    if top.has("map"):
        rel = top.string("map")
        base = os.path.dirname(os.path.abspath(source)) if not source.startswith("<") else os.getcwd()
        map_path = os.path.normpath(os.path.join(base, os.path.expanduser(rel)))
    top.done()
    return RobotConfig(cameras=tuple(cams), chassis=chassis, localizer=localizer, control=control, health=health,
                       fusion=fusion, quality=quality, map_path=map_path, source=source)


def load_robot_config(path) -> RobotConfig:
    return parse_robot_config(load_yaml_file(path), source=str(path))
