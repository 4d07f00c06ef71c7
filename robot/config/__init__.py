"""Configuration: every section of the robot config, the strict YAML loader, and the calibration.

The package stands below everything it configures (it imports only ``robot.base``), so any
part of the robot, a driver included, can read its settings without loading the parts it does
not use.
"""

from robot.config.control_api import ControlApiConfig
from robot.config.fleet import FleetConfig
from robot.config.loader import RobotConfig, load_robot_config, parse_robot_config
from robot.config.realsense import RealSenseConfig
from robot.config.sections import (
    CameraConfig,
    ChassisConfig,
    ControlConfig,
    FilterConfig,
    HealthConfig,
    LocalizerConfig,
    QualityConfig,
)

__all__ = [
    "CameraConfig",
    "ChassisConfig",
    "ControlApiConfig",
    "ControlConfig",
    "FilterConfig",
    "FleetConfig",
    "HealthConfig",
    "LocalizerConfig",
    "QualityConfig",
    "RealSenseConfig",
    "RobotConfig",
    "load_robot_config",
    "parse_robot_config",
]
