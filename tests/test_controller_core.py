"""ControllerCore: the decisions that keep the robot safe, with explicit times (no threads)."""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import replace

import numpy as np
import pytest

from drivers.chassis.encoders import EncoderOdometry
from firmware_protocol.counters import delta_i32 as wrap_delta_i32
from robot.base.samples import WheelOdometry
from robot.config import load_robot_config
from robot.config.safety import SafetyConfig
from robot.control.core import ControllerCore
from robot.control.path_file import parse_path

# These tests feed no depth frames: the protective stop (which then holds the robot, see the last
# test here and tests/test_protective_stop*.py) is off for them.
ROBOT_WITH_SAFETY = load_robot_config("config/robot.yaml")
ROBOT = replace(ROBOT_WITH_SAFETY, safety=SafetyConfig(enabled=False))
COV = np.diag([1e-4, 1e-4, 1e-4])


def _plan():
    return parse_path({"start": {"x": 0.0, "y": 0.0, "heading": 0.0}, "waypoints": [{"x": 1.0, "y": 0.0}]})


def _odo(t, speeds=(0.0, 0.0, 0.0, 0.0), dt=0.01):
    return WheelOdometry(t=t, angles=(0.0,) * 4, speeds=tuple(speeds), dt=dt, t_board=t)


def _driving_core(vision=False):
    core = ControllerCore(ROBOT, vision=vision, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, COV)
    core.set_chassis_link(True)
    core.follow(_plan())
    t = 0.0
    for _ in range(100):  # 1 s of odometry and control: the robot accelerates along x
        t += 0.01
        core.on_odometry(_odo(t))
        out = core.control_step(t)
    return core, t, out



class _NoChassis:
    """The app's tests of the loop's machinery need no board, only the poll every tick and set makes."""

    def poll(self) -> None:
        pass

def test_path_command_moves_towards_the_waypoint_within_limits():
    core, t, out = _driving_core()
    assert out.wheels is not None
    assert out.command.vx > 0.05 and abs(out.command.vy) < 1e-6
    assert out.command.vx <= ROBOT.control.max_speed + 1e-9


def test_no_command_is_sent_while_the_chassis_link_is_down():
    core, t, _ = _driving_core()
    core.set_chassis_link(False, "chassis link lost")
    out = core.control_step(t + 0.02)
    assert out.wheels is None and "lost" in out.reason


def test_stale_odometry_brings_the_speed_target_to_zero():
    core, t, out = _driving_core()
    v0 = out.command.vx
    # odometry stops while the ticks go on: after max_command_age the pose is stale and the target is zero
    t2 = t + ROBOT.health.max_command_age + 0.05
    while t < t2:
        t = min(t + 0.02, t2)
        out = core.control_step(t)
    assert out.speed_scale == 0.0 and "stale" in out.reason
    for k in range(100):  # the limiter brakes within its limits, never a jump
        out = core.control_step(t2 + 0.02 * (k + 1))
    assert out.command.vx == pytest.approx(0.0, abs=1e-9) and v0 > 0.0


def test_without_vision_required_localization_age_does_not_stop_odometry_runs():
    core, t, out = _driving_core(vision=False)
    assert out.speed_scale == 1.0


def test_with_vision_no_localization_slows_then_stops():
    core = ControllerCore(ROBOT, vision=True, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, COV)
    core.set_chassis_link(True)
    core.follow(_plan())
    scales = {}
    t = 0.0
    while t < ROBOT.health.stop_after + 0.5:
        t = round(t + 0.01, 6)
        core.on_odometry(_odo(t))
        out = core.control_step(t)
        scales[round(t, 2)] = out.speed_scale
    assert scales[0.5] == 1.0
    assert scales[round(ROBOT.health.slow_after + 0.2, 2)] == ROBOT.health.slow_scale
    assert scales[round(ROBOT.health.stop_after + 0.2, 2)] == 0.0


def test_teleop_deadman_zeroes_an_old_operator_twist():
    core = ControllerCore(ROBOT, vision=False, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, COV)
    core.set_chassis_link(True)
    core.teleoperate()
    core.set_teleop_twist(0.0, 0.2, 0.0, 0.0)
    t = 0.0
    for _ in range(25):
        t += 0.02
        core.on_odometry(_odo(t, dt=0.02))  # each sample spans the time since the previous one
        out = core.control_step(t)
    assert out.command.vx > 0.05
    for _ in range(100):  # no new key for 2 s: the deadman brings it to rest
        t += 0.02
        core.on_odometry(_odo(t, dt=0.02))
        out = core.control_step(t)
    assert out.command.vx == pytest.approx(0.0, abs=1e-9)
    core.set_teleop_twist(t, math.nan, 0.0, 0.0)  # a NaN from a broken input never becomes motion
    out = core.control_step(t + 0.02)
    assert out.wheels is not None and all(math.isfinite(w) for w in out.wheels)


def test_no_command_before_a_pose_is_known():
    core = ControllerCore(ROBOT, vision=True, t_start=0.0)
    core.set_chassis_link(True)
    core.follow(_plan())
    out = core.control_step(0.1)
    assert out.wheels is None and "no pose" in out.reason


def test_encoder_odometry_unwraps_int32_and_refuses_impossible_jumps():
    enc = EncoderOdometry(1320, 20.0)
    assert enc.update((2**31 - 10, 0, 0, 0), 0.0, 0.0) is None  # baseline
    s = enc.update((-(2**31) + 10, 0, 0, 0), 0.01, 0.01)  # wrapped: +20 ticks
    assert s is not None and s.angles[0] == pytest.approx(20 * 2 * math.pi / 1320)
    assert wrap_delta_i32(-(2**31) + 10, 2**31 - 10) == 20
    assert enc.update((100000, 0, 0, 0), 0.02, 0.02) is None and enc.implausible == 1


def test_without_fresh_depth_the_protective_stop_holds_the_robot():
    core = ControllerCore(ROBOT_WITH_SAFETY, vision=False, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, COV)
    core.set_chassis_link(True)
    core.follow(_plan())
    t = 0.0
    for _ in range(100):
        t += 0.01
        core.on_odometry(_odo(t))
        out = core.control_step(t)
    assert out.wheels is not None and max(abs(w) for w in out.wheels) == 0.0
    assert "no fresh depth" in out.reason


def test_one_fusion_step_for_the_frames_of_both_cameras_fuses_what_one_at_a_time_would():
    """The app fuses the frames of all cameras in one filter update (one replay of the history):
    the pose and the accepted walls are those of fusing them one after the other."""
    from drivers.sim.render import SimScene, render_depth_frame
    from robot.localization.localizer import Localizer
    from robot.maps.plane_map import load_plane_map

    arena = load_plane_map("config/maps/paper_arena.yaml")
    truth = (0.5, 0.5, 0.3)
    scene, rng = SimScene(arena), np.random.default_rng(3)
    loc = Localizer(ROBOT, arena)
    cores = [ControllerCore(ROBOT, vision=True, t_start=0.0) for _ in range(2)]
    start = (truth[0] + 0.01, truth[1] - 0.008, truth[2] + 0.01)
    for core in cores:
        core.set_pose(0.0, *start, np.diag([0.02**2, 0.02**2, math.radians(1.0) ** 2]))
        for k in range(1, 11):
            core.on_odometry(_odo(0.01 * k))
    items = []
    for i, cam in enumerate(ROBOT.cameras):
        frame = replace(render_depth_frame(ROBOT, scene, cam.name, truth, rng=rng), t_capture=0.05 + 0.01 * i)
        (x, y, phi), P = cores[0].coarse_pose(frame.t_capture)
        items.append((loc.localize([frame], (x, y, phi), P), frame.t_capture, cam.name))
    together = cores[0].on_localizations(items)
    alone = [cores[1].on_localization(*item) for item in items]
    assert [sorted(r.accepted) for r in together] == [sorted(r.accepted) for r in alone]
    assert sum(len(r.accepted) for r in together) >= 3
    (pa, Pa), (pb, Pb) = cores[0].pose(0.1), cores[1].pose(0.1)
    assert np.allclose(pa, pb, atol=1e-9) and np.allclose(Pa, Pb, rtol=1e-6, atol=1e-15)
    assert math.hypot(pa[0] - truth[0], pa[1] - truth[1]) < 0.003  # and both did correct the 13 mm start error


def _pipeline_app():
    """A RobotApp whose localization pipeline runs on the current loop with a scripted worker:
    ``worker.sets`` holds (the cameras of each set sent, its future), completed by the test."""
    import concurrent.futures

    from drivers.camera.base import CameraState
    from robot.app.controller import RobotApp
    from robot.maps.plane_map import load_plane_map

    class Worker:
        def __init__(self):
            self.sets = []

        def submit(self, fn, frames, coarse, localize, walls):
            self.sets.append(([f.camera for f in frames], concurrent.futures.Future()))
            return self.sets[-1][1]

    app = RobotApp(ROBOT, load_plane_map("config/maps/paper_arena.yaml"), [], _NoChassis())
    app._executor = Worker()
    app._loop = asyncio.get_running_loop()
    app._slots = {c.name: None for c in ROBOT.cameras}
    app.camera_states = {c.name: CameraState.STREAMING.value for c in ROBOT.cameras}
    app._start_localization()
    return app, app._executor


def _frame(name):
    from robot.base.samples import DepthFrame

    K = np.array([[400.0, 0.0, 8.0], [0.0, 400.0, 8.0], [0.0, 0.0, 1.0]])
    return DepthFrame(name, np.zeros((16, 16), np.uint16), 0.001, K, t_capture=time.monotonic(), frame_number=1)


async def _settle():
    for _ in range(3):
        await asyncio.sleep(0)


def test_the_app_takes_the_frames_of_all_streaming_cameras_as_one_set():
    """After a camera's frame the pipeline waits for the other streaming cameras' (at most half a
    frame period), never for a camera that is not streaming, and sends the set to the worker once."""
    from drivers.camera.base import CameraState

    front, left = (c.name for c in ROBOT.cameras)

    async def both():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        assert worker.sets == [] and app._set_timer is not None  # waits for the left camera
        app._frame_arrived(_frame(left))
        assert [names for names, _ in worker.sets] == [[front, left]] and app._set_timer is None
        assert app._slots == {front: None, left: None}

    async def stalled():
        app, worker = _pipeline_app()
        app.camera_states[left] = CameraState.STALLED.value
        app._frame_arrived(_frame(front))
        assert [names for names, _ in worker.sets] == [[front]]  # not waited for

    async def never():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        for _ in range(500):  # the guard only: half a period is 17 ms
            if worker.sets:
                break
            await asyncio.sleep(0.01)
        assert [names for names, _ in worker.sets] == [[front]]  # waited, then alone

    for scenario in (both, stalled, never):
        asyncio.run(scenario())


def test_frames_that_come_while_the_worker_is_busy_make_the_next_set_once_it_is_free():
    """One set at a time in the worker: frames arriving meanwhile wait in their slots (a newer one
    replaces an older), and the next set is judged when the worker's result is back, complete or
    with the wait for the rest starting then."""
    front, left = (c.name for c in ROBOT.cameras)

    async def scenario():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        app._frame_arrived(_frame(left))
        app._frame_arrived(_frame(front))  # the worker has the first set
        app._frame_arrived(_frame(front))  # replaces the one before
        assert len(worker.sets) == 1 and app._set_timer is None and app.stats.frames_dropped[front] == 1
        worker.sets[0][1].set_result([])
        await _settle()
        assert len(worker.sets) == 1 and app._set_timer is not None  # the left frame is waited for from now
        app._frame_arrived(_frame(left))
        assert [names for names, _ in worker.sets] == [[front, left], [front, left]]
        worker.sets[1][1].set_result([])
        await _settle()
        assert not app._set_in_worker and app._set_timer is None and len(worker.sets) == 2  # nothing waiting

    asyncio.run(scenario())


def test_the_pipeline_stops_with_the_app_and_after_an_error(caplog):
    """Stopped (shutdown), the wait for the rest of a set ends and a set in the worker is not
    fused; an error in handling a set ends the pipeline as it ended the task it replaces (the
    protective stop's scans then age out)."""
    front, left = (c.name for c in ROBOT.cameras)

    async def stop_while_waiting():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        timer = app._set_timer
        app._stop_localization()
        assert timer.cancelled() and app._set_timer is None
        app._frame_arrived(_frame(left))
        assert worker.sets == []

    async def stop_while_in_worker():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        app._frame_arrived(_frame(left))
        app._stop_localization()
        fused = []
        app._fuse_set = lambda *args: fused.append(args)
        worker.sets[0][1].set_result([])
        await _settle()
        assert fused == [] and not app._set_in_worker

    async def error():
        app, worker = _pipeline_app()
        app._frame_arrived(_frame(front))
        app._frame_arrived(_frame(left))
        worker.sets[0][1].set_exception(RuntimeError("boom"))
        await _settle()
        assert not app._sets_running and "no more frames are localized" in caplog.text
        app._frame_arrived(_frame(front))
        app._frame_arrived(_frame(left))
        assert len(worker.sets) == 1

    for scenario in (stop_while_waiting, stop_while_in_worker, error):
        asyncio.run(scenario())


def test_the_ticks_wheel_speeds_are_the_kinematics_limit_bit_for_bit():
    """The control tick turns the command into wheel speeds in floats after the kinematics'
    inverse: the same speeds as ``MecanumKinematics.limit`` gives, scaled or not, and None
    where those are not finite (the tick then refuses the command)."""
    core = ControllerCore(ROBOT, vision=False)
    kin, limit = core.kinematics, ROBOT.chassis.max_wheel_speed
    rng = np.random.default_rng(5)
    twists = [tuple(v) for v in rng.normal(0.0, 0.6, (2000, 3)).tolist()]
    twists += [(0.0, 0.0, 0.0), (5.0, -5.0, 9.0), (-0.0, 0.0, -0.0)]
    scaled = 0
    for vx, vy, wz in twists:
        ref, s = kin.limit(kin.inverse(vx, vy, wz), limit)
        scaled += s < 1.0
        assert core._wheels(vx, vy, wz) == tuple(float(w) for w in ref)
    assert scaled > 100  # the scaling branch is covered
    for bad in ((math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, -math.inf)):
        with np.errstate(invalid="ignore"):
            assert not np.isfinite(kin.limit(kin.inverse(*bad), limit)[0]).all()
        assert core._wheels(*bad) is None


def test_the_control_tick_keeps_absolute_deadlines_without_bursts_and_stops_with_an_error():
    """The control tick is a timer callback that schedules the next one: on absolute deadlines
    at control.rate, at once (never in a burst) after falling behind, and no more once a tick
    raised (the board's watchdog then stops the wheels) or the app stopped it."""
    from robot.app.controller import RobotApp
    from robot.maps.plane_map import load_plane_map

    class Handle:
        def __init__(self, when, cb):
            self.when, self.cb, self.cancelled = when, cb, False

        def cancel(self):
            self.cancelled = True

    class Loop:
        def __init__(self):
            self.now, self.handles = 100.0, []

        def time(self):
            return self.now

        def call_at(self, when, cb):
            self.handles.append(Handle(when, cb))
            return self.handles[-1]

        def call_soon(self, cb):
            return self.call_at(None, cb)

        def run_next(self, late=0.0):
            h = self.handles.pop(0)
            assert not h.cancelled and not self.handles
            self.now = max(self.now, h.when or self.now) + late
            h.cb()
            return h.when

    app = RobotApp(ROBOT, load_plane_map("config/maps/paper_arena.yaml"), [], _NoChassis())
    period = 1.0 / ROBOT.control.rate
    ticks = []
    app._tick = ticks.append
    loop = app._loop = Loop()
    app._start_control()
    whens = [loop.run_next() for _ in range(3)]
    assert whens == pytest.approx([100.0 + period * k for k in (1, 2, 3)], abs=1e-12) and len(ticks) == 3
    assert loop.run_next(late=2.5 * period) == pytest.approx(100.0 + 4 * period)  # this tick ran late ...
    assert loop.run_next() is None  # ... the next goes at once, once ...
    # ... then a period after the moment it fell behind (100 + 6.5 periods), no catching up
    assert loop.run_next() == pytest.approx(100.0 + 7.5 * period, abs=1e-12)
    assert len(ticks) == 6
    app._stop_control()
    assert not loop.handles or loop.handles[0].cancelled

    def broken(t):
        raise RuntimeError("boom")

    loop.handles.clear()
    app._tick = broken
    app._start_control()
    with pytest.raises(RuntimeError):
        loop.run_next()
    assert loop.handles == []  # no tick after one that raised


def test_four_wheel_reports_are_differenced_as_by_the_general_path():
    """``EncoderOdometry`` writes out the usual four-wheel report (a tuple): same samples bit for
    bit as the general path (any sequence), across counter wraps, a backwards board clock and
    implausible jumps."""
    rng = np.random.default_rng(8)
    fast = EncoderOdometry(ROBOT.chassis.ticks_per_rev, ROBOT.chassis.max_wheel_speed)
    general = EncoderOdometry(ROBOT.chassis.ticks_per_rev, ROBOT.chassis.max_wheel_speed)
    ticks = np.array([2**31 - 500, -2**31 + 300, 17, -5], dtype=np.int64)
    board = 0.0
    outs = 0
    for k in range(3000):
        ticks += rng.integers(-60, 61, 4)
        if k % 500 == 250:
            ticks[rng.integers(0, 4)] += 10**6  # faster than any wheel: refused
        board += -0.004 if k % 700 == 350 else 0.01  # the odd clock step backwards
        wrapped = tuple(int((v + 2**31) % 2**32 - 2**31) for v in ticks)
        a = fast.update(wrapped, board, 100.0 + board)
        b = general.update(list(wrapped), board, 100.0 + board)
        assert a == b
        outs += a is not None
    assert fast.implausible == general.implausible >= 5 and outs > 2900
