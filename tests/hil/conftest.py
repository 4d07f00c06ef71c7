"""Fixtures of the hardware-in-the-loop tests: the robot config, the cameras that are there, and
a person at the robot for the steps only a person can do (pulling a cable).

Environment:
- ``ROBOT_CONFIG``: the robot config to test against (default: /etc/robot-controller/robot.yaml
  when installed, else config/robot.yaml; as ``robotctl bench``).
- ``HIL_MANUAL``: ``1`` runs the tests that need a person even without a terminal, ``0`` skips
  them; unset, they run when pytest's stdin is a terminal.
- ``HIL_OPERATOR_TIMEOUT``: seconds a person has for each step (default 60).

Without ``--hil`` every test here is skipped by tests/conftest.py; with it, each test skips
with the reason when its hardware is absent.
"""

from __future__ import annotations

import asyncio
import os
import sys
import time
from typing import Callable, List

import pytest

from robot.config import RobotConfig, load_robot_config


@pytest.fixture(scope="session")
def robot() -> RobotConfig:
    from robot.cli.bench import default_config

    return load_robot_config(os.environ.get("ROBOT_CONFIG") or default_config())


@pytest.fixture(scope="session")
def rs():
    from drivers.camera.realsense import load_pyrealsense2

    try:
        return load_pyrealsense2()
    except Exception as e:
        pytest.skip(str(e))


@pytest.fixture(scope="session")
def connected(rs) -> List[str]:
    """Serial numbers of the RealSense devices present; skips when there are none."""
    from robot.app.bench_checks import connected_cameras

    serials, why_not = connected_cameras()
    if why_not or not serials:
        pytest.skip(why_not or "no RealSense device connected")
    return serials


@pytest.fixture
def cameras(robot, connected):
    """Every configured camera; fails naming the ones that are not connected (a robot has them all:
    point ROBOT_CONFIG at a config with fewer cameras to test a subset)."""
    from robot.app.bench_checks import match_cameras

    matches = match_cameras(robot.cameras, connected)
    missing = [f"{c.name}: {why}" for c, why in matches if why]
    if missing:
        pytest.fail(f"configured cameras not available ({robot.source}): " + "; ".join(missing))
    return [c for c, _ in matches]


@pytest.fixture
def camera(robot, connected):
    """One configured camera that is connected (the first); skips when none is."""
    from robot.app.bench_checks import match_cameras

    usable = [c for c, why in match_cameras(robot.cameras, connected) if why is None]
    if not usable:
        pytest.skip(f"none of the configured cameras is connected (connected: {', '.join(connected)})")
    return usable[0]


def interactive() -> bool:
    flag = os.environ.get("HIL_MANUAL")
    if flag is not None:
        return flag == "1"
    stdin = sys.__stdin__
    return bool(stdin is not None and stdin.isatty())


class Operator:
    """Prints an instruction where the person at the robot sees it (past pytest's capture) and
    waits, with a timeout, for the hardware to show it was done."""

    def __init__(self, capsys, timeout: float):
        self._capsys = capsys
        self.timeout = timeout

    def ask(self, instruction: str) -> None:
        bar = "=" * 72
        with self._capsys.disabled():
            sys.stdout.write(f"\n{bar}\n>>> OPERATOR: {instruction} (within {self.timeout:.0f} s)\n{bar}\n")
            sys.stdout.flush()

    def say(self, line: str) -> None:
        with self._capsys.disabled():
            sys.stdout.write(f">>> {line}\n")
            sys.stdout.flush()

    def wait_for(self, pred: Callable[[], bool], what: str) -> float:
        """Seconds until ``pred()``; fails the test naming ``what`` after the timeout."""
        t0 = time.monotonic()
        while not pred():
            if time.monotonic() - t0 > self.timeout:
                pytest.fail(f"timed out after {self.timeout:.0f} s waiting for {what}")
            time.sleep(0.05)
        return time.monotonic() - t0

    async def wait_for_async(self, pred: Callable[[], bool], what: str) -> float:
        t0 = time.monotonic()
        while not pred():
            if time.monotonic() - t0 > self.timeout:
                pytest.fail(f"timed out after {self.timeout:.0f} s waiting for {what}")
            await asyncio.sleep(0.01)
        return time.monotonic() - t0


@pytest.fixture
def operator(capsys) -> Operator:
    """A person at the robot; skips the test when nobody can answer (not a terminal, HIL_MANUAL=0)."""
    if not interactive():
        pytest.skip("needs a person at the robot: run pytest --hil from a terminal (or set HIL_MANUAL=1)")
    return Operator(capsys, float(os.environ.get("HIL_OPERATOR_TIMEOUT", "60")))
