"""The app under a fake systemd: READY=1 once up, STATUS= lines, WATCHDOG=1 only from a live
control loop. A stalled control loop stops the pings, so systemd's WatchdogSec restarts it."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time

import pytest

from robot.app import sd_notify
from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.sim.realtime import RealtimeSimSettings, sim_rig

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")


@pytest.fixture
def systemd(tmp_path, monkeypatch):
    """A fake systemd's notify socket (NOTIFY_SOCKET): the (arrival time, message) list it fills."""
    path = str(tmp_path / "notify.sock")
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(path)
    server.settimeout(0.05)
    got = []
    done = threading.Event()

    def listen():
        while not done.is_set():
            try:
                data = server.recv(4096)
            except socket.timeout:
                continue
            got.append((time.monotonic(), data.decode()))

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    sd_notify._reset_for_tests()
    try:
        yield got
    finally:
        done.set()
        listener.join()
        server.close()
        sd_notify._reset_for_tests()


def _run_app(rig, script) -> int:
    """The app's run() with ``script`` (a coroutine function) beside it on the same loop."""
    async def main():
        task = asyncio.ensure_future(script())
        try:
            return await rig.app.run()
        finally:
            task.cancel()

    return asyncio.run(main())


def _first(messages, text: str) -> int:
    """Index of the first message containing ``text``, or the list's length."""
    return next((i for i, m in enumerate(messages) if text in m), len(messages))


def test_ready_status_and_watchdog_stop_when_the_control_loop_stalls(systemd, monkeypatch):
    got = systemd
    monkeypatch.setenv("WATCHDOG_USEC", "400000")  # 0.4 s: pings due every 0.2 s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    plan = parse_path({"start": {"x": 0.5, "y": 0.6, "heading": 0.0}, "waypoints": [{"x": 0.7, "y": 0.6}]})
    marks = {}
    with sim_rig(ROBOT, ARENA, (0.5, 0.6, 0.0), RealtimeSimSettings(fps=5), AppOptions(install_signal_handlers=False,
                 status_period=0.3, stop_when_done=False), plan=plan) as rig:
        def pings_after(t):
            return [tp for tp, m in list(got) if m == "WATCHDOG=1" and tp > t]

        async def script():
            # By the app's state, not by the clock: start-up may take seconds (the first start
            # compiles the kernels), so the stall comes after READY and five healthy pings.
            guard = time.monotonic() + 120.0
            while time.monotonic() < guard:
                ready = [t for t, m in list(got) if "READY=1" in m]
                if ready and len(pings_after(ready[0])) >= 5:
                    break
                await asyncio.sleep(0.05)
            marks["stall"] = time.monotonic()
            rig.app.stall_control_loop(1.5)
            while time.monotonic() < guard and not pings_after(marks["stall"] + 1.6):
                await asyncio.sleep(0.05)
            rig.app.request_stop("test done")

        assert _run_app(rig, script) == 0
    got = list(got)
    ready = [t for t, m in got if "READY=1" in m]
    assert len(ready) == 1
    assert any(m.startswith("STATUS=") and "localized" in m for _, m in got)
    pings = [t for t, m in got if m == "WATCHDOG=1"]
    before = [t for t in pings if ready[0] < t < marks["stall"]]
    # Pinged every 0.2 s (half of WATCHDOG_USEC) while healthy: judged by the median gap, since on a
    # starved machine any one ping can be late without the schedule being wrong.
    assert len(before) >= 4
    gaps = sorted(b - a for a, b in zip(before, before[1:]))
    assert 0.1 < gaps[len(gaps) // 2] < 0.3, gaps
    t0 = marks["stall"]
    assert not [t for t in pings if t0 + 0.05 < t < t0 + 1.45], "a hung control loop must not ping"
    assert [t for t in pings if t > t0 + 1.6], "pings resume when the loop runs again"
    assert any("STOPPING=1" in m for _, m in got)


def test_a_start_that_compiles_the_kernels_asks_systemd_for_more_time_until_it_is_ready(systemd, monkeypatch):
    """Without the ahead-of-time build a first start compiles the kernels (minutes on a Nano, far
    beyond TimeoutStartSec): while it does, the app renews EXTEND_TIMEOUT_USEC; once the kernels
    are in, it stops asking and reports READY=1 as usual."""
    from robot.localization import fit_kernels

    compiling = threading.Event()  # the stand-in compile runs until the test has seen the asks
    release = threading.Event()

    def slow_warm_up():
        compiling.set()
        assert release.wait(120.0), "hang guard: the test never released the stand-in compile"
        return 0.0

    def messages():
        return [m for _, m in list(systemd)]

    monkeypatch.setattr(fit_kernels, "warm_up", slow_warm_up)
    options = AppOptions(install_signal_handlers=False, stop_when_done=False, start_extend_period=0.05,
                         status_period=0.3)
    with sim_rig(ROBOT, ARENA, (0.5, 0.6, 0.0), RealtimeSimSettings(fps=5), options,
                 initial_pose=(0.5, 0.6, 0.0)) as rig:
        async def script():
            guard = time.monotonic() + 120.0
            while not (compiling.is_set() and sum(m.startswith("EXTEND_TIMEOUT_USEC=") for m in messages()) >= 3):
                assert time.monotonic() < guard, f"hang guard: no extension asked while compiling; got {messages()}"
                await asyncio.sleep(0.02)
            release.set()
            # Ready, then running long enough for several periods of asks: a STATUS= line after READY.
            while not any(m.startswith("STATUS=") for m in messages()[_first(messages(), "READY=1") + 1:]):
                assert time.monotonic() < guard, f"hang guard: never ready and running; got {messages()}"
                await asyncio.sleep(0.02)
            rig.app.request_stop("test done")

        try:
            assert _run_app(rig, script) == 0
        finally:
            release.set()
    got = messages()
    asks = [i for i, m in enumerate(got) if m.startswith("EXTEND_TIMEOUT_USEC=")]
    ready = [i for i, m in enumerate(got) if "READY=1" in m]
    assert len(asks) >= 3 and len(ready) == 1
    assert all(got[i] == "EXTEND_TIMEOUT_USEC=150000" for i in asks)  # three periods past each ask
    assert asks[-1] < ready[0], "no extension is asked once the kernels are in"
    assert any(m.startswith("STATUS=") and "kernels" in m for m in got[:ready[0]])
