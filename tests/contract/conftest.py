"""What the contract suites need from the robot when they run on its hardware (``--hil``).

Environment, as for tests/hil: ``ROBOT_CONFIG`` (default /etc/robot-controller/robot.yaml when
installed, else config/robot.yaml) and ``ROBOT_CHASSIS_PORT`` (default: the config's
``chassis.port``). The hardware backends are marked ``hil``: without ``--hil`` tests/conftest.py
skips them; with it, each skips naming what is missing.
"""

from __future__ import annotations

import os

import pytest

from robot.config import RobotConfig, load_robot_config


@pytest.fixture(scope="session")
def hil_robot() -> RobotConfig:
    from robot.cli.bench import default_config

    return load_robot_config(os.environ.get("ROBOT_CONFIG") or default_config())
