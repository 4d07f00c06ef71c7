"""The whole controller in simulation: the simulated-clock runner and the real-time asyncio app
with the pty firmware emulator and fake cameras, including a camera stall, a serial link loss and operator signals."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import subprocess
import sys
from dataclasses import replace

import pytest

from drivers.sim.world import WorldSettings
from firmware_protocol import SetWheelSpeeds, Stop
from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.control.path_file import load_path, parse_path
from robot.maps.plane_map import load_plane_map
from robot.sim.realtime import RealtimeSimSettings, sim_rig
from robot.sim.runner import RunSettings, run_path

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
# A short out-and-back run in the arena; both cameras face walls 0.6 m or more away.
SHORT = parse_path({"start": {"x": 0.3, "y": 0.6, "heading": 0.0},
                    "defaults": {"speed": 0.15, "tolerance": 0.005, "dwell": 0.3},
                    "waypoints": [{"x": 0.8, "y": 0.6, "heading": 0.0}, {"x": 0.4, "y": 0.5, "heading": 0.0}]},
                   source="<short path>")


def test_sim_clock_paper_path_vision_stays_within_10_mm_and_odometry_drifts():
    plan = load_path("config/paths/paper_4_3.yaml")
    world = WorldSettings(seed=3)
    vis = run_path(ROBOT, ARENA, plan, RunSettings(vision=True, vision_rate=3.0, world=world))
    odo = run_path(ROBOT, ARENA, plan, RunSettings(vision=False, world=world))
    assert vis.finished and odo.finished
    assert [t.index for t in vis.targets] == list(range(len(plan.waypoints)))
    assert max(t.error for t in vis.targets) < 0.010
    # odometry alone: the same wheels, the error accumulates along the path
    assert odo.targets[-1].error > 3 * max(t.error for t in vis.targets)
    assert max(t.error for t in odo.targets[4:]) > 0.02
    # the fused covariance is honest: mean NEES near its 3 dof expectation, not wildly above
    assert 0.2 < sum(vis.nees) / len(vis.nees) < 6.0


def _run(rig, seconds_max, actions=()):
    """Run the app until it stops, with (delay, callable) actions scheduled on its loop."""
    async def main():
        loop = asyncio.get_running_loop()
        for delay, fn in actions:
            loop.call_later(delay, fn)
        loop.call_later(seconds_max, rig.app.request_stop, "test timeout")
        return await rig.app.run()
    return asyncio.run(main())


def _watch(samples):
    def on_tick(app, t):
        out = app.last_output
        samples.append((t, app.core.status(t)["quality"], out.speed_scale, out.wheels is not None,
                        app.chassis.link_state.value, app.core.trajectory.state))
    return on_tick


def test_realtime_app_survives_a_2_s_camera_stall_and_finishes_the_path():
    samples = []
    opts = AppOptions(install_signal_handlers=False)
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=_watch(samples)) as rig:
        stall = [lambda: [c.stall(2.0) for c in rig.cameras]]
        rc = _run(rig, 40.0, [(1.5, stall[0])])
        truth = rig.emulator.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    t0 = samples[0][0]
    during = [s for s in samples if 1.5 + 1.3 < s[0] - t0 < 1.5 + 1.9]
    assert during and all(s[1] != "localized" for s in during)  # quality reports the missing vision
    assert all(s[2] < 1.0 for s in during)  # and health slows the robot down
    after = [s for s in samples if s[0] - t0 > 1.5 + 3.5]
    assert any(s[1] == "localized" for s in after)
    assert math.hypot(truth[0] - 0.4, truth[1] - 0.5) < 0.010


def test_realtime_app_stops_commanding_while_the_serial_link_is_down_then_resumes():
    samples = []
    opts = AppOptions(install_signal_handlers=False)
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=_watch(samples)) as rig:
        emu = rig.emulator
        marks = {}

        def drop():
            marks["t_drop"] = emu.t_board
            emu.go_silent(True)

        def restore():
            marks["t_back"] = emu.t_board
            emu.go_silent(False)

        def probe():
            marks["speeds_during"] = emu.true_wheel_speeds
            marks["moving_before"] = marks.get("moving_before", 0.0)

        def before():
            marks["moving_before"] = max(abs(w) for w in emu.true_wheel_speeds)

        rc = _run(rig, 40.0, [(1.4, before), (1.5, drop), (2.3, probe), (2.5, restore)])
        received = emu.received()
        truth = emu.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert any(s[4] == "lost" for s in samples) and samples[-1][4] == "ready"
    # once the driver noticed the loss (link_timeout + a tick), no speed command reached the board
    t_lost = marks["t_drop"] + ROBOT.chassis.link_timeout + 0.1
    sent = [t for t, m in received if isinstance(m, SetWheelSpeeds) and t_lost < t < marks["t_back"]]
    assert sent == []
    # the wheels were turning, and stood still while the host was cut off (STOP or board watchdog)
    assert marks["moving_before"] > 1.0
    assert max(abs(w) for w in marks["speeds_during"]) < 0.05
    assert math.hypot(truth[0] - 0.4, truth[1] - 0.5) < 0.010


def test_sigterm_during_motion_stops_the_wheels():
    opts = AppOptions(install_signal_handlers=True)
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT) as rig:
        emu = rig.emulator
        moving = {}

        def term():
            moving["speeds"] = emu.true_wheel_speeds
            os.kill(os.getpid(), signal.SIGTERM)

        rc = _run(rig, 20.0, [(2.0, term)])
        import time as _time

        _time.sleep(0.3)
        stops = [m for _, m in emu.received() if isinstance(m, Stop)]
        after = emu.true_wheel_speeds
        setpoints = emu.setpoints
    assert rc == 0 and rig.app.exit_reason == "signal SIGTERM"
    assert max(abs(w) for w in moving["speeds"]) > 1.0  # it was driving when the signal came
    assert stops, "the board received STOP"
    assert max(abs(w) for w in setpoints) == 0.0 and max(abs(w) for w in after) < 0.05


def test_sigusr1_pauses_and_sigusr2_resumes_the_path():
    samples = []
    opts = AppOptions(install_signal_handlers=True)
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=_watch(samples)) as rig:
        emu = rig.emulator
        marks = {}

        def probe():
            marks["paused_speeds"] = emu.true_wheel_speeds
            marks["paused_pose"] = emu.pose

        def later():
            marks["still_pose"] = emu.pose

        rc = _run(rig, 40.0, [(1.5, lambda: os.kill(os.getpid(), signal.SIGUSR1)), (3.0, probe), (4.0, later),
                              (4.1, lambda: os.kill(os.getpid(), signal.SIGUSR2))])
        truth = emu.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert any(s[5] == "paused" for s in samples)
    assert max(abs(w) for w in marks["paused_speeds"]) < 0.05  # braked and holding
    assert math.hypot(marks["still_pose"][0] - marks["paused_pose"][0], marks["still_pose"][1] - marks["paused_pose"][1]) < 1e-3
    assert math.hypot(truth[0] - 0.4, truth[1] - 0.5) < 0.010  # resumed and finished


def test_malformed_path_file_is_refused_before_anything_starts(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("start: {x: 0, y: 0}\nwaypoints:\n  - {x: 0.5, y: 0.5, speed: fast}\n")
    for cmd in (["sim", "--path", str(bad), "--runs", "1"], ["sim", "--realtime", "--path", str(bad)],
                ["run", "--config", "config/robot.yaml", "--path", str(bad)]):
        p = subprocess.run([sys.executable, "-m", "robot.cli.main", *cmd], capture_output=True, text=True, timeout=60)
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and "bad.yaml" in lines[0] and "speed" in lines[0] and "Traceback" not in p.stderr


def test_world_seed_decides_the_wheels_so_modes_compare_fairly():
    a = replace(WorldSettings(), seed=5)
    from drivers.sim.world import SimWorld

    w1 = SimWorld(ROBOT, ARENA, (0, 0, 0), a)
    w2 = SimWorld(ROBOT, ARENA, (0, 0, 0), a)
    assert w1.board.rolling == w2.board.rolling
    assert w1.board.rolling != SimWorld(ROBOT, ARENA, (0, 0, 0), replace(a, seed=6)).board.rolling


@pytest.mark.parametrize("value", ["0", "-3"])
def test_sim_refuses_bad_run_counts(value):
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "sim", "--path", "config/paths/paper_4_3.yaml", "--runs", value],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "--runs" in p.stderr
