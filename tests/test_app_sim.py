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
from firmware_protocol import Stop
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


class _Script:
    """Steps run from the app's own ticks, each when its condition first holds: faults are
    injected at a state of the run (the wheels turning, the driver having noticed), never at a
    wall-clock instant, so a slow machine changes when things happen, not what is tested."""

    def __init__(self, samples, steps):
        self.samples, self.steps, self.done = samples, list(steps), []
        self._watch = _watch(samples)

    def on_tick(self, app, t):
        self._watch(app, t)
        if self.steps and self.steps[0][0](app):
            self.steps.pop(0)[1](app)
            self.done.append(t)


HANG_GUARD = 300.0  # s: only against a hung app; a slow machine just takes longer


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
    marks = {}

    def stall(app):
        marks["t0"], marks["n0"] = samples[-1][0], len(samples)
        for c in rig.cameras:
            c.stall(2.0)

    def stall_over(app):
        marks["n1"] = len(samples)

    # the stall starts once the robot is localized and driving, and lasts 2 s of the cameras' clock
    script = _Script(samples, [(lambda app: samples[-1][1] == "localized"
                                and max(abs(w) for w in rig.emulator.true_wheel_speeds) > 0.5, stall),
                               (lambda app: samples[-1][0] - marks["t0"] > 2.0, stall_over)])
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=script.on_tick) as rig:
        rc = _run(rig, HANG_GUARD)
        truth = rig.emulator.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert len(script.done) == 2
    during = samples[marks["n0"]:marks["n1"]]
    blind = [s for s in during if s[1] != "localized"]
    assert blind  # quality reports the missing vision ...
    assert all(s[2] < 1.0 for s in blind)  # ... and health slows the robot down while it does
    assert any(s[1] == "localized" for s in samples[marks["n1"]:])
    assert math.hypot(truth[0] - 0.4, truth[1] - 0.5) < 0.010


def test_realtime_app_stops_commanding_while_the_serial_link_is_down_then_resumes():
    samples = []
    opts = AppOptions(install_signal_handlers=False)
    marks = {}

    def drop(app):
        marks["moving_before"] = max(abs(w) for w in rig.emulator.true_wheel_speeds)
        rig.emulator.go_silent(True)

    def noticed(app):
        marks["sent_at_notice"] = app.stats.commands_sent

    def restore(app):
        marks["speeds_during"] = rig.emulator.true_wheel_speeds
        marks["sent_at_restore"] = app.stats.commands_sent
        rig.emulator.go_silent(False)

    script = _Script(samples, [
        (lambda app: max(abs(w) for w in rig.emulator.true_wheel_speeds) > 1.0, drop),  # cut while driving
        (lambda app: app.chassis.link_state.value == "lost", noticed),  # the driver noticed
        # the wheels stood still while the host was cut off (the host's STOP or the board's watchdog)
        (lambda app: max(abs(w) for w in rig.emulator.true_wheel_speeds) < 0.05, restore),
    ])
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=script.on_tick) as rig:
        rc = _run(rig, HANG_GUARD)
        truth = rig.emulator.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert len(script.done) == 3
    assert any(s[4] == "lost" for s in samples) and samples[-1][4] == "ready"
    # once the driver noticed the loss, no speed command was sent until the link came back
    assert marks["sent_at_restore"] == marks["sent_at_notice"]
    assert marks["moving_before"] > 1.0 and max(abs(w) for w in marks["speeds_during"]) < 0.05
    assert math.hypot(truth[0] - 0.4, truth[1] - 0.5) < 0.010


def _wheels(rig) -> float:
    return max(abs(w) for w in rig.emulator.true_wheel_speeds)


def _wait_for(condition, what: str, guard: float = HANG_GUARD) -> None:
    """Poll until ``condition()`` holds; the guard is against a hang only."""
    import time as _time

    end = _time.monotonic() + guard
    while not condition():
        assert _time.monotonic() < end, f"still waiting for {what} after {guard:.0f} s"
        _time.sleep(0.01)


def test_sigterm_during_motion_stops_the_wheels():
    opts = AppOptions(install_signal_handlers=True)
    moving = {}

    def term(app):
        moving["speeds"] = rig.emulator.true_wheel_speeds
        os.kill(os.getpid(), signal.SIGTERM)

    script = _Script([], [(lambda app: _wheels(rig) > 1.0, term)])  # the signal comes while it drives
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=script.on_tick) as rig:
        emu = rig.emulator
        rc = _run(rig, HANG_GUARD)
        _wait_for(lambda: _wheels(rig) < 0.05, "the wheels to stand still after SIGTERM")
        stops = [m for _, m in emu.received() if isinstance(m, Stop)]
        setpoints = emu.setpoints
    assert rc == 0 and rig.app.exit_reason == "signal SIGTERM"
    assert max(abs(w) for w in moving["speeds"]) > 1.0  # it was driving when the signal came
    assert stops, "the board received STOP"
    assert max(abs(w) for w in setpoints) == 0.0


def test_sigusr1_pauses_and_sigusr2_resumes_the_path():
    samples = []
    opts = AppOptions(install_signal_handlers=True)
    marks = {}

    def probe(app):
        marks["paused_speeds"] = rig.emulator.true_wheel_speeds
        marks["paused_pose"] = rig.emulator.pose
        marks["t_paused"] = samples[-1][0]

    def later(app):
        marks["still_pose"] = rig.emulator.pose
        os.kill(os.getpid(), signal.SIGUSR2)

    script = _Script(samples, [
        (lambda app: _wheels(rig) > 1.0, lambda app: os.kill(os.getpid(), signal.SIGUSR1)),  # pause while driving
        (lambda app: samples[-1][5] == "paused" and _wheels(rig) < 0.05, probe),  # braked and holding ...
        (lambda app: samples[-1][0] - marks["t_paused"] > 1.0, later),  # ... for a second; then resume
    ])
    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=SHORT,
                 on_tick=script.on_tick) as rig:
        rc = _run(rig, HANG_GUARD)
        truth = rig.emulator.pose
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert len(script.done) == 3
    assert max(abs(w) for w in marks["paused_speeds"]) < 0.05
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
