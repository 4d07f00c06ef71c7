"""Fusion that stays honest through faults: host stalls, serial dropouts and corruption, board
resets and bad live frames.

Most runs use the simulated-clock runner (deterministic, no dependence on machine speed): a host
stall is a window in which the host runs nothing while the board and the world go on, line
faults act on the real protocol bytes, bad frames are rendered frames made bad. Each run asserts
that no target is declared reached outside its tolerance, that the fused pose's error stays
within its reported covariance over the whole run (NEES), and, after a fault, that the robot
came back stopped and its first commands ramp from rest. The frozen-and-continued host runs in
real time through the real asyncio app and serial driver, blocked by a known sleep; it asserts
only on events (what the board received after the freeze), never on timing.
"""

from __future__ import annotations

import asyncio
import math
import threading
from dataclasses import replace
from typing import List

import numpy as np
import pytest

from drivers.camera.base import CameraDriver, CameraState
from drivers.chassis.base import OdometryQueue
from drivers.chassis.emulator import BoardModel
from drivers.chassis.encoders import EncoderOdometry, merge_odometry
from drivers.chassis.loopback import LoopbackChassis
from drivers.sim.render import SimScene, render_depth_frame
from drivers.sim.world import WorldSettings
from firmware_protocol import SetWheelSpeeds
from robot.app.controller import AppOptions, RobotApp
from robot.base import frames as base_frames
from robot.base.frames import FrameCheck, frame_problem
from robot.base.samples import DepthFrame, WheelOdometry
from robot.base.stats import chi2_quantile as chi2_threshold
from robot.config import load_robot_config
from robot.control.core import ControllerCore
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.recording import snapshot
from robot.sim.faults import FUTURE_FRAME, NAN_FRAME, FaultPlan
from robot.sim.realtime import RealtimeSimSettings, sim_rig
from robot.sim.runner import RunSettings, run_path

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
# Out 0.4 m and back at 0.15 m/s, 5 mm tolerance; both cameras face walls 0.6 m or more away.
PATH = parse_path({"start": {"x": 0.3, "y": 0.6, "heading": 0.0},
                   "defaults": {"speed": 0.15, "tolerance": 0.005, "dwell": 0.3},
                   "waypoints": [{"x": 0.7, "y": 0.6, "heading": 0.0}, {"x": 0.5, "y": 0.55, "heading": 0.0}]},
                  source="<fault path>")
SETTINGS = RunSettings(vision=True, vision_rate=3.0, world=WorldSettings(seed=3), max_time=90.0)
FAULT_AT = 2.5  # s: the robot is driving along the first segment at cruise speed
DT = 1.0 / ROBOT.control.rate
CHI2_3 = chi2_threshold(0.999, 3)  # 16.3
# The estimate's own error at arrival: the truth may miss the tolerance by about that much, never
# by the 15 to 40 mm a pose that lost its odometry did.
ESTIMATE_ALLOWANCE = 0.002  # m


def _run(faults: FaultPlan):
    return run_path(ROBOT, ARENA, PATH, replace(SETTINGS, faults=faults))


def assert_honest(r) -> None:
    """Every target reached in order within its tolerance, and the covariance covers the error."""
    assert r.finished, r.reason
    assert [t.index for t in r.targets] == list(range(len(PATH.waypoints)))
    for tr in r.targets:
        wp = PATH.waypoints[tr.index]
        assert tr.estimate_error <= ESTIMATE_ALLOWANCE, tr
        assert tr.error <= wp.tolerance + ESTIMATE_ALLOWANCE, tr
    nees = np.array(r.nees)
    assert len(nees) > 50 and 0.2 < nees.mean() < 6.0  # 3 dof: 3 on average when honest
    assert np.mean(nees > CHI2_3) <= 0.01 and nees.max() < 2.0 * CHI2_3, np.sort(nees)[-5:]


def assert_comes_back_stopped_and_ramps(r, t_back: float) -> None:
    """From the first tick at or after ``t_back``: a zero command, then speeds that grow from rest
    within the jerk and acceleration limits (never the speed held before the fault)."""
    c = ROBOT.control
    before = [cmd for cmd in r.commands if cmd[0] < FAULT_AT]
    assert max(math.hypot(cmd[1], cmd[2]) for cmd in before) > 0.05  # it was driving when the fault came
    after = [cmd for cmd in r.commands if cmd[0] >= t_back - 1e-9]
    assert after and after[0][1:4] == (0.0, 0.0, 0.0)
    moving = [cmd for cmd in after if cmd[1:4] != (0.0, 0.0, 0.0)]
    assert moving, "the mission never resumed"
    first = moving[0]
    assert abs(first[1]) <= 1.01 * c.max_jerk * DT * DT and abs(first[2]) <= 1.01 * c.max_jerk * DT * DT
    assert abs(first[3]) <= 1.01 * c.max_yaw_jerk * DT * DT
    ramp = [cmd for cmd in after if cmd[0] <= first[0] + 1.0]
    for a, b in zip(ramp, ramp[1:]):
        assert abs(b[1] - a[1]) <= c.max_accel * DT * 1.01 + 1e-9 and abs(b[2] - a[2]) <= c.max_accel * DT * 1.01 + 1e-9


# ---- the simulated clock -------------------------------------------------------------------------


@pytest.mark.parametrize("seconds", [3.0, 10.0])
def test_a_host_stall_loses_no_odometry_and_the_robot_comes_back_stopped(seconds):
    r = _run(FaultPlan(host_stalls=((FAULT_AT, seconds),)))
    # The queue filled while nobody read it (256 samples are 2.56 s) and merged, never dropped:
    # the estimate kept what the robot rolled while the board braked.
    assert r.counters["odometry_coalesced"] > 0 and r.counters.get("odometry_gaps", 0) == 0
    assert r.counters["faults"] >= 1
    assert_honest(r)
    assert_comes_back_stopped_and_ramps(r, FAULT_AT + seconds)


def test_a_1_s_serial_dropout_is_bridged_by_the_cumulative_ticks():
    r = _run(FaultPlan(line_cuts=((FAULT_AT, 1.0),)))
    assert r.counters["link_losses"] >= 1 and r.counters["reconnects"] >= 1
    # once the loss was noticed (link timeout and a tick), nothing went out until the link was back
    cut = [cmd for cmd in r.commands if FAULT_AT + ROBOT.chassis.link_timeout + 2 * DT < cmd[0] < FAULT_AT + 1.0]
    assert cut and not any(cmd[4] for cmd in cut)
    assert_honest(r)
    assert_comes_back_stopped_and_ramps(r, min(cmd[0] for cmd in r.commands if cmd[0] > FAULT_AT + 1.0 and cmd[4]))


def test_3_percent_of_bytes_corrupted_both_ways_no_corrupted_frame_and_no_dishonest_pose():
    r = _run(FaultPlan(corrupt=0.03, seed=11))
    # most encoder reports died on the line (a 30-byte report survives 3 % per byte 40 % of the time)
    assert r.counters["odometry"] < 0.7 * r.sim_time * 100
    assert_honest(r)


def test_a_board_reset_is_an_odometry_gap_the_covariance_covers():
    r = _run(FaultPlan(board_resets=(FAULT_AT,)))
    assert r.counters["reconnects"] >= 1 and r.counters["odometry_gaps"] >= 1
    assert_honest(r)
    assert_comes_back_stopped_and_ramps(r, min(cmd[0] for cmd in r.commands if cmd[0] >= FAULT_AT + DT))


def test_nan_and_future_stamped_frames_are_refused_and_never_fused():
    bad = ((1.55, 3.55, NAN_FRAME), (4.55, 6.55, FUTURE_FRAME))
    r = _run(FaultPlan(bad_frames=bad))
    period_us = int(round(1e6 / SETTINGS.vision_rate))  # the runner's schedule, in integer microseconds
    captures = [(period_us // 2 + k * period_us) / 1e6 for k in range(int(r.sim_time * SETTINGS.vision_rate) + 2)]
    in_windows = sum(1 for t in captures for start, end, _ in bad if start <= t < end and t <= r.sim_time)
    assert in_windows >= 10
    assert r.counters["frames_refused"] == len(ROBOT.cameras) * in_windows  # every bad frame, nothing else
    assert_honest(r)


# ---- the pieces ------------------------------------------------------------------------------------


def test_the_frame_validator_is_the_snapshots_and_names_each_problem():
    assert snapshot.validate_frame_arrays is base_frames.validate_frame_arrays  # one check for files and live frames
    good = render_depth_frame(ROBOT, SimScene(ARENA), "front", (0.5, 0.6, 0.0), t_capture=10.0, decimation=4)
    assert frame_problem(good, 10.02, 0.05, 1.0) is None
    holes = good.depth.astype(np.float32) * np.float32(good.depth_scale)
    holes[::9, ::9] = np.nan
    holes[1::13, ::7] = np.inf
    why = frame_problem(replace(good, depth=holes, depth_scale=1.0), 10.02, 0.05, 1.0)
    assert "must be uint16" in why and "non-finite" in why and "camera 'front'" in why
    assert "in the future" in frame_problem(replace(good, t_capture=10.8), 10.0, 0.05, 1.0)
    assert "ago" in frame_problem(good, 11.5, 0.05, 1.0)
    assert "not a finite number" in frame_problem(replace(good, t_capture=math.nan), 10.0, 0.05, 1.0)
    assert "depth_scale" in frame_problem(replace(good, depth_scale=-0.001), 10.0, 0.05, 1.0)
    assert "pinhole" in frame_problem(replace(good, K=np.eye(3) * [1.0, -1.0, 1.0]), 10.0, 0.05, 1.0)
    check = FrameCheck(0.05, 1.0)
    assert check.admit(good, 10.0) and not check.admit(replace(good, t_capture=12.0), 10.0)
    assert check.refused == {"front": 1} and "future" in check.last_reason["front"]


def test_a_full_odometry_queue_merges_its_oldest_samples_exactly():
    enc = EncoderOdometry(ROBOT.chassis.ticks_per_rev, ROBOT.chassis.max_wheel_speed)
    rng = np.random.default_rng(1)
    ticks = np.zeros(4)
    samples = []
    for k in range(600):  # 6 s of reports at 100 Hz while a stalled consumer reads nothing
        ticks += rng.uniform(0, 60, 4)
        s = enc.update(tuple(int(v) for v in ticks), 0.01 * k, 100.0 + 0.01 * k)
        if s is not None:
            samples.append(s)
    q = OdometryQueue(256)
    for s in samples:
        q.put_nowait(s)
    got = [q.get_nowait() for _ in range(q.qsize())]
    assert len(got) == 256 and q.coalesced == len(samples) - 256
    assert got[-1] == samples[-1] and got[0].dt == pytest.approx(sum(s.dt for s in samples[:len(samples) - 255]))
    # every tick is still there: the merged sample's speeds times its dt give the angle it spans
    start = np.array(samples[0].angles) - np.array(samples[0].speeds) * samples[0].dt
    spanned = np.array(got[0].speeds) * got[0].dt
    np.testing.assert_allclose(start + spanned, got[0].angles, atol=1e-9)
    m = merge_odometry(samples[0], samples[1])
    assert m.angles == samples[1].angles and m.dt == pytest.approx(samples[0].dt + samples[1].dt)


def _odo(t: float, dt: float = 0.01) -> WheelOdometry:
    return WheelOdometry(t=t, angles=(0.0,) * 4, speeds=(0.0,) * 4, dt=dt, t_board=t)


def test_an_odometry_queue_listener_takes_every_sample_in_order_and_queued_ones_first():
    samples = [_odo(0.01 * k) for k in range(1, 7)]
    q = OdometryQueue(4)
    q.put_nowait(samples[0])
    q.put_nowait(samples[1])
    got = []
    q.set_listener(got.append)
    assert got == samples[:2] and q.empty()  # what waited is handed over first
    for s in samples[2:4]:
        q.put_nowait(s)
    assert got == samples[:4] and q.empty() and q.coalesced == 0
    q.set_listener(None)  # queueing again
    for s in samples[4:]:
        q.put_nowait(s)
    assert got == samples[:4] and [q.get_nowait() for _ in range(q.qsize())] == samples[4:]


def test_a_listener_that_detaches_itself_leaves_the_rest_queued():
    samples = [_odo(0.01 * k) for k in range(1, 4)]
    q = OdometryQueue(8)
    for s in samples:
        q.put_nowait(s)
    got = []

    def once(s):
        got.append(s)
        q.set_listener(None)

    q.set_listener(once)
    assert got == samples[:1] and [q.get_nowait() for _ in range(q.qsize())] == samples[1:]


def test_the_app_fuses_odometry_as_the_driver_hands_it_over_and_stops_on_an_error(caplog):
    """The app's odometry is the queue's listener (no task per sample); a sample whose handling
    fails ends the fusion of odometry, as the task it replaces did when it died, and never
    reaches into the driver's message handling."""
    from robot.app.controller import AppOptions, RobotApp
    from robot.maps.plane_map import load_plane_map

    q = OdometryQueue(16)

    class Chassis:
        def odometry_queue(self, maxsize: int = 256) -> OdometryQueue:
            return q

    app = RobotApp(ROBOT, load_plane_map("config/maps/paper_arena.yaml"), [], Chassis(),
                   options=AppOptions(vision=False))
    app.core.set_pose(0.0, 0.5, 0.5, 0.0, np.diag([1e-4, 1e-4, 1e-4]))
    app._odometry_queue = app.chassis.odometry_queue()
    app._odometry_queue.set_listener(app._odometry)
    q.put_nowait(_odo(0.01))
    assert app.stats.odometry == 1 and app.core.counters["odometry"] == 1 and app.odom.t == 0.01

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    app.core.on_odometry = broken
    q.put_nowait(_odo(0.02))  # does not raise into the feeder
    assert app._odometry_queue is None and "odometry is no longer fused" in caplog.text
    q.put_nowait(_odo(0.03))
    assert app.stats.odometry == 2 and q.qsize() == 1  # queued, no longer fused


@pytest.mark.parametrize("mode", ["auto", "command"])
def test_after_a_stall_the_mission_waits_for_the_pose_and_in_command_mode_for_the_operator(mode):
    robot = replace(ROBOT, health=replace(ROBOT.health, resume_after_fault=mode, vision_required=False),
                    safety=replace(ROBOT.safety, enabled=False))
    core = ControllerCore(robot, vision=False, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, np.diag([1e-6, 1e-6, 1e-6]))
    core.set_chassis_link(True)
    core.follow(parse_path({"start": {"x": 0.0, "y": 0.0, "heading": 0.0}, "waypoints": [{"x": 1.0, "y": 0.0}]}))
    t = 0.0
    for _ in range(50):
        t += DT
        core.on_odometry(_odo(t, DT))
        out = core.control_step(t)
    assert out.command.vx > 0.05  # cruising
    t += 1.0  # the host stalled for a second: no tick, no odometry read
    out = core.control_step(t)
    assert out.command.vx == 0.0 and core.health.fault and "stalled" in core.health.fault
    assert core.trajectory.state == "paused" and "fresh wheel odometry" in out.reason
    core.on_odometry(_odo(t + 0.005, 1.005))  # the bridging sample: fresh odometry confirms an odometry-only pose
    for _ in range(5):
        t += DT
        core.on_odometry(_odo(t, DT))
        out = core.control_step(t)
    if mode == "auto":
        assert core.health.fault is None and 0.0 < out.command.vx <= 5 * ROBOT.control.max_accel * DT
    else:
        assert out.command.vx == 0.0 and "operator" in out.reason
        core.resume()
        t += DT
        core.on_odometry(_odo(t, DT))
        out = core.control_step(t)
        assert core.health.fault is None and 0.0 < out.command.vx <= 1.01 * ROBOT.control.max_jerk * DT * DT


# ---- the real asyncio app --------------------------------------------------------------------------


class ScriptedCamera(CameraDriver):
    """Hands the app a fixed list of frames from its own thread, stamped relative to the host clock."""

    def __init__(self, robot, name: str, make_frames):
        super().__init__(robot.camera(name))
        self._make = make_frames
        self._thread = None

    def start(self, on_frame, on_imu=None) -> None:
        def run():
            import time

            for frame in self._make(time.monotonic()):
                on_frame(frame)
                time.sleep(0.05)

        self._set_state(CameraState.STREAMING)
        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._set_state(CameraState.STOPPED)


def test_the_app_refuses_bad_live_frames_and_counts_them():
    pose = (0.5, 0.6, 0.0)
    robot = replace(ROBOT, safety=replace(ROBOT.safety, enabled=False))

    def frames(now: float) -> List[DepthFrame]:
        good = render_depth_frame(robot, SimScene(ARENA), "front", pose, t_capture=now, frame_number=4, decimation=4)
        holes = good.depth.astype(np.float32) * np.float32(good.depth_scale)
        holes[::5, ::3] = np.nan
        holes[2::7, ::4] = np.inf
        return [replace(good, depth=holes, depth_scale=1.0, frame_number=1),
                replace(good, t_capture=now + 0.8, frame_number=2),
                replace(good, t_capture=now - 5.0, frame_number=3),
                good]

    cam = ScriptedCamera(robot, "front", frames)
    chassis = LoopbackChassis(BoardModel(robot.chassis), robot.chassis)
    done = {}

    def on_tick(app, t):
        if app.stats.localizations >= 1 and app.frame_check.total >= 3:
            done["status"] = app.status(t)
            app.request_stop("test done")

    app = RobotApp(robot, ARENA, [cam], chassis, AppOptions(install_signal_handlers=False), initial_pose=pose,
                   on_tick=on_tick)

    async def main():
        asyncio.get_running_loop().call_later(60.0, app.request_stop, "hang guard")
        return await app.run()

    assert asyncio.run(main()) == 0 and app.exit_reason == "test done"
    assert app.frame_check.refused == {"front": 3} and app.stats.localizations == 1  # only the good frame
    assert done["status"]["frames_refused"] == {"front": 3} and "front" in done["status"]["frame_refusal"]


def test_a_frozen_and_continued_host_comes_back_stopped_and_ramps_from_rest():
    """The real app, serial driver and pty board; the event loop is blocked for 3 s by a known sleep.
    Judged on what the board received after the freeze, not on when."""
    c = ROBOT.control
    ticks = []
    marks = {}
    opts = AppOptions(install_signal_handlers=False)

    def on_tick(app, t):
        ticks.append(t)
        if len(ticks) > 1 and ticks[-1] - ticks[-2] > 2.0 and "thawed" not in marks:
            marks["thawed"] = rig.emulator.t_board
            marks["thawed_tick"] = len(ticks) - 1
        speed = max(abs(w) for w in rig.emulator.true_wheel_speeds)
        if "frozen" not in marks and speed > 2.0:  # cruising: freeze now (an event, not a time)
            marks["moving"] = speed
            marks["frozen"] = rig.emulator.t_board
            app.stall_control_loop(3.0)

    with sim_rig(ROBOT, ARENA, (0.3, 0.6, 0.0), RealtimeSimSettings(fps=10, decimation=4), opts, plan=PATH,
                 on_tick=on_tick) as rig:
        async def main():
            loop = asyncio.get_running_loop()
            loop.call_later(90.0, rig.app.request_stop, "hang guard")
            return await rig.app.run()

        rc = asyncio.run(main())
        received = rig.emulator.received()
        truth = rig.emulator.pose
        faults = rig.app.core.counters.get("faults", 0)
    assert rc == 0 and rig.app.exit_reason == "path complete"
    assert "frozen" in marks and "thawed" in marks and faults >= 1
    after = [m.rad_s for t, m in received if isinstance(m, SetWheelSpeeds) and t >= marks["frozen"] + 2.0]
    assert len(after) > 20
    # A wheel at 0.15 m/s turns 5 rad/s; from rest the limiters allow at most this much per tick.
    # Their step is per second (the tick's own dt, at most max_dt): on a busy machine a late tick
    # may step further, so the bound takes the longest tick interval of the ramp (never less than DT).
    k = marks["thawed_tick"]
    dt = min(max([DT] + [b - a for a, b in zip(ticks[k:k + 40], ticks[k + 1:k + 41])]), c.max_dt)
    r = ROBOT.chassis.wheel_radius
    L = ROBOT.chassis.half_wheelbase + ROBOT.chassis.half_track
    first_step = (2 * c.max_jerk * dt * dt + L * c.max_yaw_jerk * dt * dt) / r
    assert max(abs(w) for w in after[0]) <= 1e-3  # stopped first
    nonzero = [w for w in after if max(abs(v) for v in w) > 1e-3]
    assert nonzero and max(abs(v) for v in nonzero[0]) <= 1.05 * first_step + 2e-3
    per_tick = (2 * c.max_accel * dt + L * c.max_yaw_accel * dt) / r
    for a, b in zip(nonzero[:25], nonzero[1:25]):
        assert max(abs(x - y) for x, y in zip(a, b)) <= 1.05 * per_tick + 2e-3
    wp = PATH.waypoints[-1]
    assert math.hypot(truth[0] - wp.x, truth[1] - wp.y) < wp.tolerance + ESTIMATE_ALLOWANCE
