"""The bench tools ask before the wheels turn, check that the wheels are off the floor, and fail
when a required device is missing.

The motor board is the firmware emulator on a real pseudo-terminal, given to the tools with
``--port`` like a real board (``--emulate`` has no wheels to ask about). Whether a wheel was
commanded is read from what the emulated board received, not from timing.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import io
import json
import time

import pytest

from drivers.chassis.emulator import FirmwareEmulator
from firmware_protocol import SetWheelSpeeds
from robot.app import bench_checks as bc
from robot.app.bench_checks import FAIL, OFF_GROUND, PASS, SKIP, BenchOptions
from robot.cli import bench as cli_bench
from robot.cli import chassis as cli_chassis
from robot.cli.common import confirm_motion
from robot.config import ChassisConfig

CFG = ChassisConfig(link_timeout=0.5, reconnect_backoff_max=0.2)  # a loaded test machine stalls the emulator
QUICK = functools.partial(BenchOptions, wheel_hold=0.6, handshake_listen=0.3)
MOTION_ROWS = [OFF_GROUND, "wheel FL", "wheel FR", "wheel RL", "wheel RR", "chassis: watchdog"]


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def wheel_commands(emulator: FirmwareEmulator):
    return [m for _, m in emulator.received() if isinstance(m, SetWheelSpeeds) and any(m.speeds_mrad_s)]


@pytest.fixture
def no_cameras(monkeypatch):
    monkeypatch.setattr(bc, "connected_cameras", lambda: ([], None))


@pytest.fixture
def quick_bench(monkeypatch):
    monkeypatch.setattr(cli_bench, "BenchOptions", QUICK)


@pytest.fixture
def board(tmp_path):
    emu = FirmwareEmulator(CFG)
    emu.start()
    config = tmp_path / "robot.yaml"
    config.write_text("cameras:\n  - {name: front, width: 848, height: 480, fps: 30, hfov_deg: 87, vfov_deg: 58,\n"
                      "     mount: {xyz: [0.1, 0, 0.12], rpy_deg: [0, 0, 0]}}\n"
                      "chassis: {link_timeout: 0.5, reconnect_backoff_max: 0.2}\n")
    yield emu, str(config)
    emu.close()


def run_cli(module, command, argv, capsys, stdin=None, monkeypatch=None):
    parser = argparse.ArgumentParser()
    module.register(parser.add_subparsers())
    args = parser.parse_args([command] + argv)
    if stdin is not None:
        monkeypatch.setattr("sys.stdin", stdin)
    rc = args.func(args)
    return rc, capsys.readouterr()


# The question  -----------------------------------------------------------------------------------

def test_confirmation_needs_yes_or_a_y_on_a_terminal():
    err = io.StringIO()
    assert confirm_motion(True, "t", stdin=io.StringIO(), stderr=err) is None and err.getvalue() == ""
    assert "no terminal to ask and no --yes" in confirm_motion(False, "t", stdin=io.StringIO("y\n"), stderr=err)
    assert confirm_motion(False, "t", stdin=FakeTerminal("y\n"), stderr=err) is None
    assert "ON BLOCKS" in err.getvalue() and "[y/N]" in err.getvalue()
    for answer in ("\n", "n\n", "no\n", "yess\n", ""):
        assert "not confirmed at the prompt" in confirm_motion(False, "t", stdin=FakeTerminal(answer), stderr=err)


def test_bench_without_a_terminal_and_without_yes_never_turns_a_wheel(board, capsys, no_cameras, quick_bench):
    emu, config = board
    rc, out = run_cli(cli_bench, "bench", ["--config", config, "--port", emu.port, "--skip-cameras", "--json"], capsys)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert checks["chassis: handshake"]["status"] == PASS
    for name in MOTION_ROWS:
        assert checks[name]["status"] == SKIP and "no terminal to ask and no --yes" in checks[name]["detail"]
    assert "the wheels stay still" in out.err and "--yes" in out.err
    assert wheel_commands(emu) == [] and rc == 0


def test_bench_asks_on_a_terminal_and_a_no_keeps_the_wheels_still(board, capsys, monkeypatch, no_cameras, quick_bench):
    emu, config = board
    rc, out = run_cli(cli_bench, "bench", ["--config", config, "--port", emu.port, "--skip-cameras", "--json"], capsys,
                      stdin=FakeTerminal("n\n"), monkeypatch=monkeypatch)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert "[y/N]" in out.err
    assert all(checks[n]["status"] == SKIP and "not confirmed at the prompt" in checks[n]["detail"] for n in MOTION_ROWS)
    assert wheel_commands(emu) == []


def test_bench_with_a_yes_at_the_prompt_runs_the_motion_checks(board, capsys, monkeypatch, no_cameras, quick_bench):
    emu, config = board
    rc, out = run_cli(cli_bench, "bench", ["--config", config, "--port", emu.port, "--skip-cameras", "--json"], capsys,
                      stdin=FakeTerminal("y\n"), monkeypatch=monkeypatch)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert rc == 0, {n: c for n, c in checks.items() if c["status"] not in (PASS, SKIP)}
    assert all(checks[n]["status"] == PASS for n in MOTION_ROWS), checks
    lifted = checks[OFF_GROUND]["data"]
    assert lifted["command"] == [1.5, 1.5, -1.5, -1.5] and min(lifted["ratios"]) > 0.9  # free wheels follow
    assert wheel_commands(emu)


def test_a_host_stall_during_a_wheel_measurement_is_measured_again_not_blamed_on_the_board(monkeypatch, no_cameras):
    """The host blocks its loop for 0.4 s while the first wheel turns (longer than the board's
    0.25 s watchdog, which stops the wheel): that window measures the host, so it is repeated."""
    from drivers.chassis.serial_chassis import SerialChassis

    emu = FirmwareEmulator(CFG)
    send = SerialChassis.send_wheel_speeds
    calls = {"FL": 0}

    def stalling_send(self, wheels):
        if wheels[0] != 0.0 and not any(wheels[1:]):  # the front-left wheel alone
            calls["FL"] += 1
            if calls["FL"] == 10:
                time.sleep(0.4)  # a stalled host: nothing else on this loop runs meanwhile
        return send(self, wheels)

    monkeypatch.setattr(SerialChassis, "send_wheel_speeds", stalling_send)

    async def main():
        return await bc.chassis_checks(CFG, emu.port, QUICK(), emu, port_required=True)

    with emu:
        res = {r.name: r for r in asyncio.run(asyncio.wait_for(main(), 60.0))}
        trips = emu.events("watchdog")
    assert calls["FL"] >= 10 and trips, "the stall did not happen or did not trip the board's watchdog"
    fl = res["wheel FL"]
    assert fl.status == PASS and fl.data["host_stall_repeats"] >= 1, (fl.detail, fl.data)
    assert all(res[n].status == PASS for n in MOTION_ROWS), {n: res[n].detail for n in MOTION_ROWS}


# Off the ground  ----------------------------------------------------------------------------------

def test_wheels_that_lag_under_load_stop_the_motion_checks(no_cameras):
    """A slow motor response (time constant 3 s instead of 30 ms) is what a wheel pressed on the
    floor looks like to its encoder: the pulse fails and no single-wheel test follows."""
    emu = FirmwareEmulator(CFG, motor_tau=3.0)

    async def main():
        return await bc.chassis_checks(CFG, emu.port, QUICK(), emu, port_required=True)

    with emu:
        res = {r.name: r for r in asyncio.run(asyncio.wait_for(main(), 60.0))}
        pulses = len(wheel_commands(emu))
        patterns = {tuple(m.speeds_mrad_s) for m in wheel_commands(emu)}
    assert res[OFF_GROUND].status == FAIL and "put the robot on blocks" in res[OFF_GROUND].detail
    assert all(res[n].status == SKIP and "on the floor" in res[n].detail for n in MOTION_ROWS[1:])
    assert pulses > 0 and patterns == {(1500, 1500, -1500, -1500)}  # only the pulse, which moves no robot


def test_the_pulse_moves_no_robot_on_the_floor():
    from robot.control.kinematics import make_kinematics

    twist = make_kinematics(CFG).forward([1.5, 1.5, -1.5, -1.5])
    assert max(abs(v) for v in twist) < 1e-12


# Required devices  --------------------------------------------------------------------------------

def test_bench_with_nothing_connected_exits_non_zero(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(bc, "connected_cameras", lambda: ([], "pyrealsense2 is not usable (no module)"))
    config = tmp_path / "robot.yaml"
    config.write_text("cameras:\n  - {name: front, width: 848, height: 480, fps: 30, hfov_deg: 87, vfov_deg: 58,\n"
                      "     mount: {xyz: [0.1, 0, 0.12], rpy_deg: [0, 0, 0]}}\n"
                      f"chassis:\n  port: {tmp_path / 'no-board'}\n")
    rc, out = run_cli(cli_bench, "bench", ["--config", str(config), "--json"], capsys)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert rc == 1 and json.loads(out.out)["ok"] is False
    assert checks["camera front: stream"]["status"] == FAIL and checks["chassis: handshake"]["status"] == FAIL


# robotctl chassis  --------------------------------------------------------------------------------

def test_chassis_motion_without_yes_reports_the_board_and_turns_nothing(board, capsys):
    emu, config = board
    rc, out = run_cli(cli_chassis, "chassis", ["--config", config, "--port", emu.port, "--motion", "--duration", "0.3",
                                               "--json"], capsys)
    report = json.loads(out.out)
    assert "no terminal to ask" in report["motion_skipped"] and "no test motion" in out.err
    assert "motion" not in report and "off_ground" not in report and rc == 0
    assert wheel_commands(emu) == []


def test_chassis_motion_with_yes_pulses_first_then_tests_each_wheel(board, capsys):
    emu, config = board
    rc, out = run_cli(cli_chassis, "chassis", ["--config", config, "--port", emu.port, "--motion", "--yes",
                                               "--duration", "0.3", "--hold", "0.4", "--json"], capsys)
    report = json.loads(out.out)
    assert rc == 0 and report["ok"] is True, report
    assert report["off_ground"]["ok"] is True and len(report["motion"]) == 4
    first = wheel_commands(emu)[0]
    assert tuple(first.speeds_mrad_s) == (1500, 1500, -1500, -1500)  # the pulse comes before any single wheel
