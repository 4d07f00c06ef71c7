"""``robotctl bench`` off the robot: the chassis checks against the firmware emulator (the real
driver on a real pty), with and without injected faults; the camera judgements on measurements
shaped like a D435i's; the command's table, JSON and exit status.

The emulator runs in real time: wheel speeds are measured on the board's clock and the watchdog
judged on the emulator's, so a loaded machine slows these tests down but does not change them.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest

from drivers.chassis.emulator import BoardModel, FirmwareEmulator
from robot.app import bench_checks as bc
from robot.app.bench_checks import FAIL, PASS, SKIP, BenchOptions, CameraMeasurement
from robot.base.errors import ConfigError, InputError
from robot.cli import bench as cli_bench
from robot.config import CameraConfig, ChassisConfig

# a loaded test machine can stall the emulator thread for 100 ms (as in test_chassis_driver.py)
CFG = ChassisConfig(link_timeout=0.5, reconnect_backoff_max=0.2)
QUICK = BenchOptions(wheel_hold=0.6, handshake_listen=0.3)
WHEEL_NAMES = ["wheel FL", "wheel FR", "wheel RL", "wheel RR"]


def bench_cli(argv, capsys):
    parser = argparse.ArgumentParser()
    cli_bench.register(parser.add_subparsers())
    args = parser.parse_args(["bench"] + argv)
    rc = args.func(args)
    return rc, capsys.readouterr()


@pytest.fixture
def no_cameras(monkeypatch):
    """Hermetic: the machine's RealSense devices (if any) are not part of these tests."""
    monkeypatch.setattr(bc, "connected_cameras", lambda: ([], None))


def run_chassis(emulator: FirmwareEmulator, opts: BenchOptions = QUICK, config: ChassisConfig = CFG):
    async def main():
        return await bc.chassis_checks(config, emulator.port, opts, emulator, port_required=True)

    with emulator:
        return {r.name: r for r in asyncio.run(asyncio.wait_for(main(), 60.0))}


class EncoderFault(BoardModel):
    """A board whose encoder for one wheel reads ``gain`` of the true angle, or whose FL/FR
    encoder cables are swapped (``swap``): what a slipping belt or a wiring mistake looks like."""

    def __init__(self, *args, wheel: int = 2, gain: float = 1.0, swap: bool = False, **kwargs):
        self.fault_wheel, self.gain, self.swap = wheel, gain, swap
        super().__init__(*args, **kwargs)

    def ticks(self):
        true = self.theta
        seen = list(true)
        seen[self.fault_wheel] = true[self.fault_wheel] * self.gain
        if self.swap:
            seen[0], seen[1] = true[1], true[0]
        self.theta = seen
        try:
            return super().ticks()
        finally:
            self.theta = true


def faulty_emulator(**fault) -> FirmwareEmulator:
    emu = FirmwareEmulator(CFG)
    emu.board = EncoderFault(CFG, **fault)
    return emu


# Against the emulator  ---------------------------------------------------------------------------

def test_bench_on_the_emulator_passes_the_chassis_and_skips_the_cameras(capsys, no_cameras):
    """The command as shipped: default config, 2 s per wheel, table then JSON."""
    rc, out = bench_cli(["--emulate", "--skip-cameras", "--json"], capsys)
    report = json.loads(out.out)
    checks = {c["name"]: c for c in report["checks"]}
    assert rc == 0 and report["ok"] is True
    assert [c["name"] for c in report["checks"]] == [
        "camera front: stream", "camera front: intrinsics", "camera left: stream", "camera left: intrinsics",
        "chassis: handshake", "wheels: off the ground"] + WHEEL_NAMES + ["chassis: watchdog"]
    for name, c in checks.items():
        if name.startswith("camera"):
            assert c["status"] == SKIP and c["detail"] == "--skip-cameras"
        else:
            assert c["status"] == PASS, c
    assert report["summary"] == {"pass": 7, "fail": 0, "skip": 4}
    hs = checks["chassis: handshake"]["data"]
    assert hs["ticks_per_rev"] == 1320 and hs["watchdog_ms"] == 200 and hs["report_hz"] == 100.0
    for w in WHEEL_NAMES:
        d = checks[w]["data"]
        assert d["command"] == 3.0 and abs(d["error_pct"]) < 5.0 and d["others_max"] < 0.15
    wd = checks["chassis: watchdog"]["data"]
    assert wd["board_trip_s"] == pytest.approx(0.2, abs=0.002)  # the emulator's 200 ms, on its clock
    assert math.isfinite(wd["stopped_s"])


def test_the_table_says_what_ran_and_the_motion_can_be_skipped(capsys, no_cameras):
    rc, out = bench_cli(["--emulate", "--skip-cameras", "--skip-motion"], capsys)
    lines = out.out.splitlines()
    assert rc == 0
    assert lines[0].split() == ["check", "result", "detail"]
    rows = {ln[:25].strip(): ln[25:].split(None, 1) for ln in lines[1:-1]}
    assert rows["chassis: handshake"][0] == "pass"
    assert all(rows[w] == ["skip", "--skip-motion"] for w in ["wheels: off the ground"] + WHEEL_NAMES + ["chassis: watchdog"])
    assert lines[-1] == "1 passed, 0 failed, 10 skipped"
    assert "ON BLOCKS" not in out.err  # nothing turns, nothing to warn about


def test_a_motor_fault_fails_the_handshake_and_every_wheel_without_spinning(no_cameras):
    emu = FirmwareEmulator(CFG)
    emu.board.set_motor_fault(1, True)  # the FR driver reports a fault from power-up
    res = run_chassis(emu)
    assert res["chassis: handshake"].status == FAIL and "motor fault on FR" in res["chassis: handshake"].detail
    for w in WHEEL_NAMES:
        assert res[w].status == FAIL and "refuses speed commands: motor fault on FR" in res[w].detail
    assert res["chassis: watchdog"].status == SKIP
    assert not [e for e in emu.events("command")]  # nothing was commanded


@pytest.mark.parametrize("fault, failing, why", [
    ({"wheel": 2, "gain": 0.9}, ["wheel RL"], "off by more than 5 %"),
    ({"swap": True}, ["wheel FL", "wheel FR"], "another wheel turned"),
], ids=["slow-RL-encoder", "FL-FR-swapped"])
def test_a_wheel_that_does_not_follow_its_command_fails_by_its_encoder(fault, failing, why, no_cameras):
    res = run_chassis(faulty_emulator(**fault))
    assert res["chassis: handshake"].status == PASS
    for w in WHEEL_NAMES:
        assert res[w].status == (FAIL if w in failing else PASS), res[w]
    for w in failing:
        assert why in res[w].detail
    if "gain" in fault:
        assert res["wheel RL"].data["error_pct"] == pytest.approx(-10.0, abs=1.0)
    assert res["chassis: watchdog"].status == PASS


def test_a_slow_board_watchdog_fails(no_cameras):
    emu = FirmwareEmulator(ChassisConfig(watchdog_timeout=0.4))  # the board's own period: 400 ms
    res = run_chassis(emu, BenchOptions(wheel_hold=0.4, handshake_listen=0.3))
    assert res["chassis: handshake"].status == FAIL and "board watchdog 400 ms > 250 ms" in res["chassis: handshake"].detail
    wd = res["chassis: watchdog"]
    assert wd.status == FAIL and wd.data["board_trip_s"] == pytest.approx(0.4, abs=0.002)
    assert all(res[w].status == PASS for w in WHEEL_NAMES)


def test_a_board_clamping_below_the_test_speed_fails_every_wheel(no_cameras):
    res = run_chassis(FirmwareEmulator(CFG, max_wheel_speed=2.7), BenchOptions(wheel_hold=0.6, handshake_listen=0.3))
    for w in WHEEL_NAMES:
        assert res[w].status == FAIL and res[w].data["error_pct"] == pytest.approx(-10.0, abs=1.0)


# Ports and bad input  ----------------------------------------------------------------------------

def test_an_absent_port_fails_the_chassis_named_or_not(tmp_path, capsys, no_cameras):
    config = tmp_path / "robot.yaml"
    config.write_text("cameras:\n  - {name: front, width: 848, height: 480, fps: 30, hfov_deg: 87, vfov_deg: 58,\n"
                      "     mount: {xyz: [0.1, 0, 0.12], rpy_deg: [0, 0, 0]}}\n"
                      f"chassis:\n  port: {tmp_path / 'absent-default'}\n")
    rc, out = bench_cli(["--config", str(config), "--json"], capsys)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert rc == 1 and checks["chassis: handshake"]["status"] == FAIL  # the motor board is required
    assert checks["chassis: handshake"]["detail"] == f"motor board port {tmp_path / 'absent-default'} is absent"

    rc, out = bench_cli(["--config", str(config), "--port", str(tmp_path / "named"), "--json"], capsys)
    checks = {c["name"]: c for c in json.loads(out.out)["checks"]}
    assert rc == 1 and checks["chassis: handshake"]["status"] == FAIL
    assert all(checks[w]["status"] == SKIP for w in WHEEL_NAMES)


def test_a_port_that_does_not_answer_fails_the_handshake(no_cameras):
    emu = FirmwareEmulator(CFG)
    emu.go_silent()
    res = run_chassis(emu)
    assert res["chassis: handshake"].status == FAIL and "no answer to HELLO" in res["chassis: handshake"].detail
    assert all(res[w].status == SKIP and res[w].detail == "no handshake" for w in WHEEL_NAMES)


def test_bad_input_is_a_robot_error_and_exit_status_2(tmp_path, capsys):
    with pytest.raises(InputError, match="exclude each other"):
        bench_cli(["--emulate", "--port", "/dev/ttyUSB0"], capsys)
    with pytest.raises(ConfigError):
        bench_cli(["--config", str(tmp_path / "missing.yaml")], capsys)
    from robot.cli import main as cli

    assert cli_bench in cli.COMMAND_MODULES
    assert cli.main(["bench", "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "robotctl bench: error:" in capsys.readouterr().err


# Camera judgements  ------------------------------------------------------------------------------

FRONT = CameraConfig("front", 848, 480, 30.0, 87.0, 58.0, (0.1, 0.0, 0.12), (0.0, 0.0, 0.0), serial="036522070001")
# A D435i's depth stream at 848x480 as librealsense reports it: about 90 x 59 deg.
D435_K = np.array([[424.23, 0.0, 423.43], [0.0, 424.23, 239.86], [0.0, 0.0, 1.0]])


def measurement(fps: float = 30.0, seconds: float = 5.0, K=D435_K, shape=(480, 848), stats=None) -> CameraMeasurement:
    n = int(round(fps * seconds))
    frames = [(100.0 + i / fps, 99.99 + i / fps, 1000 + i, 0.62, "hardware_clock") for i in range(n)]
    return CameraMeasurement(FRONT, frames=frames, K=np.array(K, float), shape=shape, depth_scale=0.001,
                             stats=stats or {"frames": n, "timeouts": 0, "reconnects": 0, "drops": 0},
                             window=(100.0, 100.0 + seconds))


def test_a_camera_at_its_rate_passes_and_a_slow_or_stalling_one_fails():
    ok = bc.judge_stream(measurement())
    assert ok.status == PASS and ok.data["fps"] == pytest.approx(30.0) and ok.data["valid_depth_fraction"] == 0.62
    slow = bc.judge_stream(measurement(fps=27.0))
    assert slow.status == FAIL and "27.0 fps, configured 30" in slow.detail
    stalled = bc.judge_stream(measurement(stats={"frames": 150, "timeouts": 1, "reconnects": 0}))
    assert stalled.status == FAIL and "1 timeouts" in stalled.detail
    nothing = bc.judge_stream(CameraMeasurement(FRONT, window=(0.0, 5.0), last_error="RealSense 0365 is not connected"))
    assert nothing.status == FAIL and "no frame in 5 s (RealSense 0365 is not connected)" == nothing.detail


def test_a_d435i_matches_the_nominal_field_of_view_and_a_wrong_mode_does_not():
    ok = bc.judge_intrinsics(measurement())
    assert ok.status == PASS, ok.detail
    assert ok.data["hfov_deg"] == pytest.approx(89.97, abs=0.01) and ok.data["vfov_deg"] == pytest.approx(58.99, abs=0.01)
    # 640x480 is a cropped 4:3 mode (about 80 x 64 deg): a config written for it is wrong here
    K640 = np.array([[384.2, 0.0, 319.5], [0.0, 384.2, 236.4], [0.0, 0.0, 1.0]])
    bad = bc.judge_intrinsics(measurement(K=K640, shape=(480, 640)))
    assert bad.status == FAIL
    assert "depth is 640x480, config says 848x480" in bad.detail and "horizontal field of view" in bad.detail
    off_centre = bc.judge_intrinsics(measurement(K=[[424.23, 0, 380.0], [0, 424.23, 239.86], [0, 0, 1]]))
    assert off_centre.status == FAIL and "ppx 380.0 px is far from the image centre" in off_centre.detail


def test_configured_cameras_are_matched_to_devices_by_serial():
    left = CameraConfig("left", 848, 480, 30.0, 87.0, 58.0, (0, 0.1, 0.12), (0, 0, 90), serial="036522070002")
    m = dict((c.name, why) for c, why in bc.match_cameras([FRONT, left], ["036522070001"]))
    assert m["front"] is None and "serial 036522070002 is not connected (connected: 036522070001)" == m["left"]
    a, b = (CameraConfig(n, 848, 480, 30.0, 87.0, 58.0, (0, 0, 0), (0, 0, 0)) for n in ("a", "b"))
    m = dict((c.name, why) for c, why in bc.match_cameras([a, b], ["X1"]))
    assert m["a"] is None and "set 'serial'" in m["b"]  # one device cannot be two cameras
    m = dict((c.name, why) for c, why in bc.match_cameras([a], ["X1", "X2"]))
    assert "2 unclaimed devices" in m["a"]


def test_camera_checks_skip_without_a_device_and_fail_a_missing_one(monkeypatch):
    from robot.config import RobotConfig

    robot = RobotConfig(cameras=(FRONT,))
    monkeypatch.setattr(bc, "connected_cameras", lambda: ([], "pyrealsense2 is not usable (no module)"))
    assert {(r.status, r.detail) for r in bc.camera_checks(robot, BenchOptions())} == {
        (FAIL, "pyrealsense2 is not usable (no module)"), (SKIP, "camera not connected")}  # cameras are required
    assert {r.status for r in bc.camera_checks(robot, BenchOptions(cameras=False))} == {SKIP}
    monkeypatch.setattr(bc, "connected_cameras", lambda: (["999"], None))
    stream, intr = bc.camera_checks(robot, BenchOptions())
    assert stream.status == FAIL and "036522070001 is not connected (connected: 999)" in stream.detail
    assert intr.status == SKIP

def test_the_camera_measurement_reads_frames_through_the_real_driver(tmp_path):
    """A simulated D435i recording played through pyrealsense2 and the unmodified driver: the bench
    sees its frames, intrinsics and identity the way it would see a camera's."""
    pytest.importorskip("pyrealsense2")
    from drivers.camera.bag import write_recording
    from drivers.camera.realsense import PlaybackFile
    from drivers.sim.drive import simulate_run
    from drivers.sim.render import SimScene
    from robot.config import load_robot_config
    from robot.maps.plane_map import load_plane_map

    root = Path(__file__).resolve().parents[1]
    robot = load_robot_config(root / "config" / "robot.yaml")
    scene = SimScene(load_plane_map(root / "config" / "maps" / "paper_arena.yaml"))
    frames, _ = simulate_run(robot, scene, "front", (0.5, 0.5, math.pi), frames=8, rng=np.random.default_rng(3))
    path = tmp_path / "front.bag"
    write_recording(path, frames, serial="SIM-front")
    cam = robot.camera("front")
    m = bc.measure_cameras([cam], seconds=3.0, settle=0.0, source_for=lambda c: PlaybackFile(path))["front"]
    assert m.frames, (m.stats, m.last_error)
    numbers = [f[2] for f in m.frames]
    assert numbers == sorted(numbers) and set(numbers) <= set(range(8))
    assert m.device_info.get("serial") == "SIM-front" and m.shape == (480, 848)
    assert m.depth_scale == pytest.approx(0.001)
    np.testing.assert_allclose(m.K, frames[0].K, atol=1e-3)
    assert m.frames[0][3] > 0.2  # the west wall fills much of the image
    verdict = bc.judge_intrinsics(m)
    assert verdict.status == PASS, verdict.detail
