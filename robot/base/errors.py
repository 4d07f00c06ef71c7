"""Exception tree. Every user-facing failure is one of these, with a message that names the problem."""

from __future__ import annotations


class RobotError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(RobotError, ValueError):
    """A robot config, map or path file is missing, malformed or inconsistent."""


class InputError(RobotError, ValueError):
    """A data file (depth snapshot, recording) is missing or malformed."""


class DriverError(RobotError, IOError):
    """A hardware driver (camera, serial chassis) failed."""
