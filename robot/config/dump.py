"""The effective robot config as plain data: what the app really ran with, defaults filled in.

A recording carries this next to the YAML text the app loaded, so a run can be understood (and
replayed) even after the defaults in the code have changed. The dict uses only JSON/YAML types
(dict, list, str, int, float, bool) and is exactly what ``parse_robot_config`` reads, so
``parse_robot_config(effective_config_dict(robot), robot.source) == robot``.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Dict, Optional

from robot.config.loader import RobotConfig
from robot.config.sections import CameraConfig


def _plain(value: Any) -> Any:
    """Tuples become lists (YAML's safe dumper and JSON know no tuples); the rest stays as it is."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value


def _flat_section(section: Any) -> Dict[str, Any]:
    return {f.name: _plain(getattr(section, f.name)) for f in dataclasses.fields(section)}


def _camera(cam: CameraConfig) -> Dict[str, Any]:
    out: Dict[str, Any] = {
        "name": cam.name, "width": cam.width, "height": cam.height, "fps": cam.fps,
        "hfov_deg": cam.hfov_deg, "vfov_deg": cam.vfov_deg,
        "mount": {"xyz": _plain(cam.mount_xyz), "rpy_deg": _plain(cam.mount_rpy_deg)},
    }
    if cam.serial is not None:  # absent means "the only device present"; YAML null would not parse
        out["serial"] = cam.serial
    out["realsense"] = _flat_section(cam.realsense)
    out["depth_scale"] = cam.depth_scale  # a calibrated camera: replay scales its recorded depth the same way
    return out


def effective_config_dict(robot: RobotConfig, map_path: Optional[str] = None) -> Dict[str, Any]:
    """Every section of ``robot`` with every key, and ``map``: ``map_path`` when given (the map the
    app loaded, which ``--map`` may have chosen), else the config's own ``map:``. The map path is
    absolute, so the dict means the same wherever it is parsed."""
    out: Dict[str, Any] = {"cameras": [_camera(c) for c in robot.cameras]}
    for f in dataclasses.fields(robot):  # every flat section, also one added later
        value = getattr(robot, f.name)
        if dataclasses.is_dataclass(value):
            out[f.name] = _flat_section(value)
    chosen = map_path if map_path is not None else robot.map_path
    if chosen is not None and not str(chosen).startswith("<"):  # "<map>": built in memory, no file
        out["map"] = os.path.abspath(str(chosen))
    return out


__all__ = ["effective_config_dict"]
