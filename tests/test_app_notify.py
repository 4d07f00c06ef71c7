"""The app under a fake systemd: READY=1 once up, STATUS= lines, WATCHDOG=1 only from a live
control loop. A stalled control loop stops the pings, so systemd's WatchdogSec restarts it."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time

from robot.app import sd_notify
from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.sim.realtime import RealtimeSimSettings, sim_rig

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")


def test_ready_status_and_watchdog_stop_when_the_control_loop_stalls(tmp_path, monkeypatch):
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
    monkeypatch.setenv("WATCHDOG_USEC", "400000")  # 0.4 s: pings due every 0.2 s
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    sd_notify._reset_for_tests()
    plan = parse_path({"start": {"x": 0.5, "y": 0.6, "heading": 0.0}, "waypoints": [{"x": 0.7, "y": 0.6}]})
    marks = {}
    try:
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

            async def main():
                task = asyncio.ensure_future(script())
                try:
                    return await rig.app.run()
                finally:
                    task.cancel()

            assert asyncio.run(main()) == 0
    finally:
        done.set()
        listener.join()
        server.close()
        sd_notify._reset_for_tests()
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
