"""The control socket: the core's operator entry points on explicit time, the wire format, the
server's bounds and access rules, and the whole thing end to end against the real-time
simulation (the real app, the pty board emulator, fake cameras) and ``robotctl``.

Nothing here depends on the machine's speed: the simulated-clock tests step time themselves,
and the real-time tests wait for replies and states, with long timeouts only as hang guards.
"""

from __future__ import annotations

import asyncio
import atexit
import json
import math
import os
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivers.chassis.loopback import LoopbackChassis
from drivers.sim.world import SimWorld, WorldSettings
from firmware_protocol import SetWheelSpeeds
from robot.app import control_protocol as proto
from robot.app.control_client import ControlClient, ControlError
from robot.app.control_server import ControlServer, bind_socket
from robot.app.controller import AppOptions
from robot.base.errors import ConfigError
from robot.config import load_robot_config
from robot.control.core import CommandRefused, ControllerCore
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.sim.realtime import RealtimeSimSettings, sim_rig

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
START = (0.3, 0.6, 0.0)
HANG = 90.0  # s: only a guard against a hang, never a performance figure
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
SYSTEM_PYTHON = "/usr/bin/python3"  # readable by nobody (the venv may live under /root)


# -- the core's entry points, on explicit time -------------------------------------------------------

# Odometry only and no protective stop: these tests are about the mission logic, which must not
# wait for depth scans that a simulated-clock run without cameras never produces.
CORE_ROBOT = replace(ROBOT, safety=replace(ROBOT.safety, enabled=False))


class ClockRig:
    """The core on a simulated clock with the emulated board (real protocol bytes, no threads)."""

    def __init__(self, start=START):
        self.world = SimWorld(CORE_ROBOT, ARENA, start, WorldSettings(seed=1))
        self.chassis = LoopbackChassis(self.world.board, CORE_ROBOT.chassis)
        self.chassis.connect_now()
        self.core = ControllerCore(CORE_ROBOT, vision=False, t_start=0.0, plane_map=ARENA)
        self.core.set_pose(0.0, *start, np.diag([1e-6, 1e-6, 1e-6]))
        self.core.set_chassis_link(True)
        self.dt = 1.0 / CORE_ROBOT.control.rate
        self.log = []  # (t, vx, vy, wz, state)

    def run(self, seconds: float, until=None):
        for _ in range(int(round(seconds / self.dt))):
            self.world.step(self.dt)
            t = self.world.t
            for odo in self.chassis.poll():
                self.core.on_odometry(odo, self.chassis.encoders.speed_variance(odo.dt))
            out = self.core.control_step(t)
            if out.wheels is not None:
                self.chassis.send_wheel_speeds(out.wheels)
            c = out.command
            self.log.append((t, c.vx, c.vy, c.wz, self.core.trajectory.state if self.core.trajectory else "idle"))
            if until is not None and until(self):
                return True
        return until is None


def _plan(*targets, speed=0.15):
    return parse_path({"defaults": {"speed": speed, "tolerance": 0.005},
                       "waypoints": [{"x": x, "y": y, "heading": 0.0} for x, y in targets]}, source="<test>")


def _accel_ok(log, start_index=0):
    """Every tick's change of the commanded translation is within control.max_accel (plus rounding)."""
    a = CORE_ROBOT.control.max_accel
    for (t0, vx0, vy0, *_), (t1, vx1, vy1, *_) in zip(log[start_index:], log[start_index + 1:]):
        dt = min(t1 - t0, CORE_ROBOT.control.max_dt)
        if abs(vx1 - vx0) > a * dt + 1e-9 or abs(vy1 - vy0) > a * dt + 1e-9:
            return False
    return True


def test_core_go_refuses_a_second_mission_and_replace_brakes_within_the_limits_first():
    rig = ClockRig()
    rig.core.go(_plan((0.9, 0.6)))
    rig.run(2.0)
    assert rig.core.mission_active and rig.log[-1][1] > 0.1  # cruising towards x = 0.9
    with pytest.raises(CommandRefused, match="mission is running"):
        rig.core.go(_plan((0.3, 0.9)))
    i = len(rig.log)
    rig.core.go(_plan((0.5, 0.8)), replace=True)
    assert rig.run(30.0, until=lambda r: r.core.finished)
    assert _accel_ok(rig.log, i - 1)  # the switch is a braking ramp, never a jump in speed
    x, y, _ = rig.world.truth
    assert math.hypot(x - 0.5, y - 0.8) < 0.01
    assert rig.core.trajectory.plan.waypoints[0].x == 0.5 and not rig.core.mission_active


def test_core_extend_runs_after_the_current_plan_and_finished_waits_for_it():
    rig = ClockRig()
    first, second = _plan((0.5, 0.6)), _plan((0.5, 0.8))
    rig.core.go(first)
    rig.core.extend(second)
    assert rig.run(40.0, until=lambda r: r.core.finished)
    assert rig.core.trajectory.plan is second
    x, y, _ = rig.world.truth
    assert math.hypot(x - 0.5, y - 0.8) < 0.01
    rig.core.extend(_plan((0.3, 0.8)))  # nothing running: starts at once
    assert rig.core.mission_active


def test_core_pause_holds_also_a_plan_started_later_and_abort_clears_the_queue():
    rig = ClockRig()
    rig.core.pause()
    rig.core.go(_plan((0.8, 0.6)))
    rig.run(2.0)
    assert rig.core.trajectory.state == "paused" and max(abs(v) for v in rig.log[-1][1:4]) < 1e-9
    assert math.hypot(rig.world.truth[0] - START[0], rig.world.truth[1] - START[1]) < 1e-3
    rig.core.resume()
    rig.run(2.0)
    assert rig.log[-1][1] > 0.1
    rig.core.extend(_plan((0.8, 0.9)))
    i = len(rig.log)
    assert rig.core.abort("test")
    assert rig.run(10.0, until=lambda r: r.core.finished)
    assert _accel_ok(rig.log, i - 1) and rig.core.trajectory.state == "aborted"
    assert not rig.core.mission_active and rig.world.truth[1] < 0.65  # the queued plan never started
    assert not rig.core.abort("again")


def test_core_speed_limit_slows_smoothly_and_is_never_above_the_configured_one():
    rig = ClockRig()
    cap = CORE_ROBOT.control.max_speed
    with pytest.raises(CommandRefused, match="above the configured"):
        rig.core.set_speed_limit(cap + 0.01)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(CommandRefused):
            rig.core.set_speed_limit(bad)
    rig.core.go(_plan((1.1, 0.6), speed=0.25))
    rig.run(1.5)
    assert rig.log[-1][1] > 0.2
    i = len(rig.log)
    assert rig.core.set_speed_limit(0.08) == 0.08
    rig.run(1.5)
    assert _accel_ok(rig.log, i - 1)  # lowered through the limiters: a ramp down
    assert all(math.hypot(vx, vy) <= 0.08 + 1e-6 for _, vx, vy, *_ in rig.log[-25:])
    assert rig.core.set_speed_limit(None) == cap
    rig.run(0.8)
    assert rig.log[-1][1] > 0.15


def test_core_teleop_takes_no_mission_and_obeys_the_limit():
    rig = ClockRig()
    rig.core.teleoperate()
    with pytest.raises(CommandRefused, match="teleoperated"):
        rig.core.go(_plan((0.5, 0.6)))
    rig.core.set_speed_limit(0.05)
    for _ in range(150):
        rig.core.set_teleop_twist(rig.world.t, 0.3, 0.0, 0.0)
        rig.run(rig.dt)
    assert 0.04 < rig.log[-1][1] <= 0.05 + 1e-9


# -- the wire format ---------------------------------------------------------------------------------


@pytest.mark.parametrize("line, code", [
    (b"not json", proto.BAD_JSON),
    (b"\xff\xfe", proto.BAD_JSON),
    (b'{"v": 1, "cmd": "goto", "args": {"x": NaN, "y": 0, "phi": 0}}', proto.BAD_JSON),
    (b'{"v": 1, "cmd": "goto", "args": {"x": Infinity, "y": 0, "phi": 0}}', proto.BAD_JSON),
    (b"[" * 5000 + b"]" * 5000, proto.BAD_JSON),
    (b'{"v": 1, "cmd": "goto", "args": {"x": 1' + b"0" * 5000 + b', "y": 0, "phi": 0}}', proto.BAD_JSON),
    (b"[1, 2]", proto.BAD_REQUEST),
    (b'{"cmd": "status"}', proto.BAD_REQUEST),
    (b'{"v": 2, "cmd": "status"}', proto.UNSUPPORTED_VERSION),
    (b'{"v": true, "cmd": "status"}', proto.UNSUPPORTED_VERSION),
    (b'{"v": 1, "cmd": "status", "extra": 1}', proto.BAD_REQUEST),
    (b'{"v": 1, "id": [1], "cmd": "status"}', proto.BAD_REQUEST),
    (b'{"v": 1, "cmd": 5}', proto.BAD_REQUEST),
    (b'{"v": 1, "cmd": "fly"}', proto.UNKNOWN_COMMAND),
    (b'{"v": 1, "cmd": "status", "args": [1]}', proto.BAD_REQUEST),
    (b'{"v": 1, "cmd": "status", "args": {"x": 1}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"x": 0.5, "y": 0.5}}', None),
    (b'{"v": 1, "cmd": "goto", "args": {"x": true, "y": 0.5, "phi": 0}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"x": "0.5", "y": 0.5, "phi": 0}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"x": 5000, "y": 0.5, "phi": 0}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"y": 0.5, "phi": 0}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"x": 0.5, "y": 0.5, "phi": 90}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "goto", "args": {"x": 0.5, "y": 0.5, "phi": 0, "speed": 0}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "set-pose", "args": {"x": 0.5, "y": 0.5, "phi": 0, "force": 1}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "relocalize", "args": {"region": [0, 0, 1]}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "limits", "args": {"speed": -0.1}}', proto.BAD_ARGS),
    (b'{"v": 1, "cmd": "watch", "args": {"period": 0}}', proto.BAD_ARGS),
])
def test_protocol_refuses_malformed_requests_with_one_code(line, code):
    try:
        req = proto.parse_request(proto.decode_json(line))
    except proto.ProtocolError as e:
        assert e.code == code and e.message and "\n" not in e.message and len(e.message) < 400
    else:
        assert code is None and req.cmd == "goto" and req.motion  # phi may be left out: keep the heading


def test_protocol_marks_what_needs_the_right_to_move():
    def motion(cmd, args=None):
        return proto.parse_request({"v": 1, "cmd": cmd, "args": args or {}}).motion
    assert not motion("status") and not motion("pause") and not motion("abort") and not motion("watch")
    assert motion("resume") and motion("go", {"path": "x"}) and motion("goto", {"x": 0, "y": 0, "phi": 0})
    assert motion("set-pose", {"x": 0, "y": 0, "phi": 0}) and motion("relocalize")
    assert not motion("relocalize", {"apply": False}) and not motion("limits") and motion("limits", {"speed": 0.1})
    assert motion("recover")


# -- the server's bounds, with a stand-in operator ---------------------------------------------------


class _Options:
    initial_cov = (0.02, 0.02, 0.035)


class _App:
    options = _Options()


class FakeOperator:
    """Records what reached it; ``set-pose`` at x = 99 never finishes (a request that hangs)."""

    def __init__(self):
        self.app = _App()
        self.calls = []

    def status(self):
        return {"ok": True, "nan": float("nan")}

    async def set_pose(self, pose, std, force, source):
        self.calls.append(("set-pose", pose, source))
        if pose[0] == 99.0:
            await asyncio.Event().wait()
        return {"pose": list(pose)}

    def goto(self, *args):
        self.calls.append(("goto",) + args)
        if args[0] == -1.0:
            raise RuntimeError("a defect")
        return {"waypoints": 1}

    def pause(self):
        self.calls.append(("pause",))
        return {"paused": True}

    def abort(self, reason):
        self.calls.append(("abort", reason))
        return {"aborted": True}

    def limits(self, speed, reset):
        return {"speed": speed}


class LoopThread:
    """An event loop in a thread, for servers the test talks to with the blocking client."""

    def __init__(self):
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()

    def call(self, coro, timeout=HANG):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self):
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(HANG)
        self.loop.close()


def _socket_dir() -> Path:
    """A directory others may traverse (pytest's tmp_path is 0700), under /tmp."""
    d = Path(tempfile.mkdtemp(prefix="ctl-"))
    d.chmod(0o755)
    atexit.register(shutil.rmtree, d, True)
    return d


@pytest.fixture
def fake_server():
    d = _socket_dir()
    loop = LoopThread()
    servers = []

    def start(**cfg):
        config = replace(ROBOT.control_api, socket=str(d / f"s{len(servers)}.sock"), **cfg)
        op = FakeOperator()
        server = ControlServer(op, config)
        loop.call(server.start())
        servers.append(server)
        return server, op

    yield start
    for s in servers:
        loop.call(s.stop())
    loop.close()


def test_server_bounds_line_length_clients_timeouts_and_leaving_clients(fake_server):
    server, op = fake_server(max_request_bytes=2048, max_clients=3, request_timeout=0.3)
    path = server.path
    with ControlClient(path) as c:
        r = c.exchange_bytes(b'{"v": 1, "cmd": "status"}\n\n')
        assert r["ok"] and r["result"]["nan"] is None  # never NaN on the wire
        too_long = c.exchange_bytes(b'{"v": 1, "cmd": "go", "args": {"path": "' + b"x" * 5000 + b'"}}\n')
        assert too_long["error"]["code"] == proto.TOO_LONG
    with ControlClient(path) as c:  # pipelined requests are answered in order
        c.connect()
        c._sock.sendall(b'{"v":1,"id":"a","cmd":"pause"}\n{"v":1,"id":"b","cmd":"abort"}\n')
        assert [c.read_reply()["id"], c.read_reply()["id"]] == ["a", "b"]
        hung = c.exchange({"v": 1, "id": 9, "cmd": "set-pose", "args": {"x": 99.0, "y": 0, "phi": 0}})
        assert hung == {"v": 1, "id": 9, "ok": False, "error": {"code": proto.TIMEOUT, "message": hung["error"]["message"]}}
        defect = c.exchange({"v": 1, "cmd": "goto", "args": {"x": -1.0, "y": 0, "phi": 0}})
        assert defect["error"]["code"] == proto.INTERNAL and "RuntimeError" in defect["error"]["message"]
    # A client that sends half a request, or a whole one, and leaves: nothing breaks.
    for data in (b'{"v": 1, "cmd": "set-pose", "args": {"x": 99.0, "y": 0, "phi": 0}}\n', b'{"v": 1, "cm'):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(path)
        try:
            s.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass  # refused as BUSY (the earlier clients' slots not yet freed) and closed: leaving anyway
        s.close()
    deadline = time.monotonic() + HANG
    while server._clients:  # the leavers' handlers end (their replies have nowhere to go)
        assert time.monotonic() < deadline
        time.sleep(0.02)
    held = []
    deadline = time.monotonic() + HANG
    while len(held) < 3:  # fill every slot (a slot frees only once the server has seen its client go)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(HANG)
        s.connect(path)
        try:
            s.sendall(b'{"v":1,"cmd":"status"}\n')
        except (BrokenPipeError, ConnectionResetError):
            pass  # a full server answers BUSY and closes before the request arrives: read its answer
        line = s.makefile().readline()
        reply = json.loads(line) if line else {"ok": False, "error": {"code": proto.BUSY}}
        # Taken: any answer but BUSY (on a starved machine the short request timeout of this
        # server may answer TIMEOUT instead of the status).
        if not reply.get("ok") and reply["error"]["code"] == proto.BUSY:
            s.close()
            assert time.monotonic() < deadline, "a slot never freed"
            time.sleep(0.05)
            continue
        held.append(s)
    with ControlClient(path) as c:
        busy = c.read_reply() if c.connect() is None else None
        assert busy["error"]["code"] == proto.BUSY
    for s in held:
        s.close()
    deadline = time.monotonic() + HANG
    while True:  # the slots free as the server notices the closed connections
        try:
            with ControlClient(path) as c:
                assert c.request("status")["ok"]
            break
        except ControlError as e:
            assert e.code in (proto.BUSY, proto.TIMEOUT, "unreachable") and time.monotonic() < deadline
            time.sleep(0.05)
    assert server.stats["errors"] >= 3


def test_socket_file_is_created_with_its_mode_and_group_and_stale_sockets_are_replaced(fake_server, tmp_path):
    server, _ = fake_server(mode=0o640, group="65534")
    st = os.stat(server.path)
    assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o640 and st.st_gid == 65534
    assert not [p for p in Path(server.path).parent.iterdir() if p.name.startswith(".ctl-")]  # no temporary left
    # a second controller on the same socket is refused, a stale socket replaced, a file never touched
    with pytest.raises(ConfigError, match="another process listens"):
        bind_socket(server.config)
    stale = _socket_dir() / "stale.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(stale))
    s.close()  # bound, never listening: what a killed controller leaves
    fresh = bind_socket(replace(server.config, socket=str(stale)))
    # Its name appears only once it listens: a client that finds the path before the event loop
    # serves it is queued, not refused (a refusal here failed the live tests on a starved machine).
    early = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    early.settimeout(HANG)
    early.connect(str(stale))
    fresh.setblocking(True)
    conn, _ = fresh.accept()
    conn.close()
    early.close()
    fresh.close()
    regular = tmp_path / "not-a-socket"
    regular.write_text("precious")
    with pytest.raises(ConfigError, match="not a socket"):
        bind_socket(replace(server.config, socket=str(regular)))
    assert regular.read_text() == "precious"
    with pytest.raises(ConfigError, match="no group"):
        bind_socket(replace(server.config, socket=str(tmp_path / "x.sock"), group="no-such-group-here"))


def _as_nobody(path: str, lines):
    """Send request lines as uid/gid 65534 from a separate process; its replies (or the error)."""
    script = ("import json, socket, sys\n"
              "s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)\n"
              "try:\n    s.connect(sys.argv[1])\n"
              "except OSError as e:\n    print(json.dumps({'connect': type(e).__name__})); sys.exit(0)\n"
              "f = s.makefile('rwb')\n"
              "for line in sys.argv[2:]:\n"
              "    f.write(line.encode() + b'\\n'); f.flush(); print(f.readline().decode().strip())\n")

    def drop():
        os.setgid(65534)
        os.setgroups([])
        os.setuid(65534)

    p = subprocess.run([SYSTEM_PYTHON, "-c", script, path, *lines], capture_output=True, text=True, timeout=HANG,
                       preexec_fn=drop, cwd="/")
    assert p.returncode == 0, p.stderr
    return [json.loads(x) for x in p.stdout.splitlines()]


needs_root = pytest.mark.skipif(not IS_ROOT or not os.path.exists(SYSTEM_PYTHON),
                                reason="needs root (to run a client as another user) and /usr/bin/python3")


@needs_root
def test_the_socket_mode_keeps_other_users_out(fake_server):
    server, op = fake_server(mode=0o660)
    assert _as_nobody(server.path, ['{"v":1,"cmd":"status"}']) == [{"connect": "PermissionError"}]
    assert op.calls == []


@needs_root
def test_peer_credentials_decide_who_may_move_the_robot(fake_server):
    goto = '{"v":1,"cmd":"goto","args":{"x":0.5,"y":0.5,"phi":0}}'
    server, op = fake_server(mode=0o666)  # anyone may connect; nobody is not in motion_groups
    status, moved, paused = _as_nobody(server.path, ['{"v":1,"cmd":"status"}', goto, '{"v":1,"cmd":"pause"}'])
    assert status["ok"] and paused["ok"]  # reading and stopping are for everybody who may connect
    assert moved["error"]["code"] == proto.FORBIDDEN and "nobody" in moved["error"]["message"]
    assert op.calls == [("pause",)]
    server2, op2 = fake_server(mode=0o666, motion_groups=("nogroup",))
    (moved,) = _as_nobody(server2.path, [goto])
    assert moved["ok"] and op2.calls and op2.calls[0][0] == "goto"


# -- end to end: the real app in real time ------------------------------------------------------------


class LiveRobot:
    """The real-time simulated robot with its control socket, run in a background thread."""

    def __init__(self, rig, path):
        self.rig = rig
        self.path = path
        self.ticks = []  # (t, vx, vy, wz) commanded each control tick
        self.rc = []

    def client(self, timeout=HANG) -> ControlClient:
        return ControlClient(self.path, timeout=timeout)

    def request(self, cmd, args=None, timeout=HANG):
        with self.client(timeout) as c:
            return c.request(cmd, args)

    def wait(self, predicate, what, guard=HANG):
        """Poll the status until ``predicate(status)``; the guard only catches a hang."""
        deadline = time.monotonic() + guard
        while True:
            s = self.request("status")
            if predicate(s):
                return s
            assert time.monotonic() < deadline, f"hang guard: never saw {what}; last status {s}"
            time.sleep(0.1)

    def at_rest(self):
        return self.wait(lambda s: not s["mission"]["active"] and _still(s), "the robot at rest")

    def settle(self):
        """Back to a known state: no mission, not paused, the configured speed limit, at rest."""
        self.request("abort")
        self.request("resume")
        self.request("limits", {"reset": True})
        # On a starved machine the board emulator's reports can pause long enough for the driver to
        # call the link lost and reconnect: the robot is only settled once it is back and localized.
        self.wait(lambda s: s["chassis"]["link"] == "ready" and s["quality"]["state"] == "localized",
                  "the link ready and the pose localized")
        return self.at_rest()

    def moving_commands(self):
        return sum(1 for _, m in self.rig.emulator.received() if isinstance(m, SetWheelSpeeds)
                   and max(abs(w) for w in m.rad_s) > 0.0)


def _still(s):
    c = s.get("command") or {}
    return max(abs(c.get("vx", 0.0)), abs(c.get("vy", 0.0)), abs(c.get("wz", 0.0))) < 1e-3


@pytest.fixture(scope="module")
def live():
    d = _socket_dir()
    robot = replace(ROBOT, control_api=replace(ROBOT.control_api, socket=str(d / "control.sock")))
    opts = AppOptions(install_signal_handlers=False, stop_when_done=False, remote=True)
    holder = {}

    def on_tick(app, t):
        c = app.last_output.command
        holder["live"].ticks.append((t, c.vx, c.vy, c.wz))
        del holder["live"].ticks[:-20000]

    with sim_rig(robot, ARENA, START, RealtimeSimSettings(fps=10, decimation=4), opts, initial_pose=START,
                 on_tick=on_tick) as rig:
        lr = holder["live"] = LiveRobot(rig, robot.control_api.socket)
        thread = threading.Thread(target=lambda: lr.rc.append(asyncio.run(rig.app.run())), daemon=True)
        thread.start()
        deadline = time.monotonic() + HANG
        while not os.path.exists(lr.path):
            assert time.monotonic() < deadline and thread.is_alive(), "the app never opened its socket"
            time.sleep(0.05)
        lr.wait(lambda s: s["quality"]["state"] == "localized" and set(s["cameras"].values()) == {"streaming"},
                "a localized robot with streaming cameras")
        try:
            yield lr
        finally:
            rig.app.request_stop("test end")
            thread.join(HANG)
    assert lr.rc == [0] and not os.path.exists(lr.path)  # the socket goes with the controller


def _truth(live):
    return live.rig.emulator.pose


def _near(p, q, tol):
    return math.hypot(p[0] - q[0], p[1] - q[1]) < tol


def test_status_reports_pose_quality_mission_chassis_battery_and_cameras(live):
    s = live.settle()
    assert _near((s["pose"]["x"], s["pose"]["y"]), _truth(live), 0.01)
    assert len(s["pose"]["cov"]) == 3 and s["quality"]["state"] == "localized"
    assert s["mission"] == {**s["mission"], "mode": s["mission"]["mode"], "active": False, "paused": False}
    assert s["mission"]["speed_limit"] == ROBOT.control.max_speed
    assert s["chassis"]["link"] == "ready" and s["chassis"]["estop"] is False
    assert s["battery"]["voltage"] == pytest.approx(12.0)  # the emulator's battery
    assert s["cameras"] == {"front": "streaming", "left": "streaming"}


def test_set_pose_is_checked_against_what_the_cameras_see(live):
    live.settle()
    x, y, phi = _truth(live)
    ok = live.request("set-pose", {"x": x, "y": y, "phi": phi})
    assert ok["check"]["checked"] and ok["check"]["offset_m"] < 0.01 and ok["check"]["walls"]
    with pytest.raises(ControlError) as e:  # 20 cm off: the cameras see the walls elsewhere
        live.request("set-pose", {"x": x + 0.2, "y": y, "phi": phi})
    assert e.value.code == "refused" and "cameras" in e.value.message
    with pytest.raises(ControlError) as e:
        live.request("set-pose", {"x": 5.0, "y": y, "phi": phi})
    assert e.value.code == "refused" and "outside the map" in e.value.message
    s = live.request("status")
    assert _near((s["pose"]["x"], s["pose"]["y"]), (x, y), 0.01)  # refused means untouched
    forced = live.request("set-pose", {"x": x + 0.05, "y": y, "phi": phi, "force": True, "std_xy": 0.05})
    assert forced["forced"] and not forced["check"]["checked"]
    s = live.request("status")
    assert abs(s["pose"]["x"] - (x + 0.05)) < 0.02
    live.request("set-pose", {"x": x, "y": y, "phi": phi, "std_xy": 0.06})  # a wider std admits the 5 cm
    # The robot standing here sees two walls at right angles: had one been a panel, only the given
    # pose would bound the error, and 6 cm given is 22 cm at the integrity risk. It says so. (The
    # status holds the quality of the last control tick: the first one after the request may
    # still show the state before it, so the test waits for the tick that has seen the new pose.)
    live.wait(lambda s: _near((s["pose"]["x"], s["pose"]["y"]), (x, y), 0.005) and s["quality"]["state"] == "degraded"
              and "horizontal protection level" in s["quality"]["reason"], "the pose back on the truth, degraded by its bound")
    live.request("set-pose", {"x": x, "y": y, "phi": phi})  # the default 2 cm: vouched for again
    live.wait(lambda s: s["quality"]["state"] == "localized", "the pose localized")


def test_goto_go_refusal_replace_pause_and_abort_on_the_real_app(live):
    live.settle()
    r = live.request("goto", {"x": 0.55, "y": 0.6, "phi": 0.0})
    assert r["waypoints"] == 1 and not r["replaced"]
    live.at_rest()
    assert _near(_truth(live), (0.55, 0.6), 0.01)
    path = "defaults: {speed: 0.15, tolerance: 0.005}\nwaypoints:\n  - {x: 0.85, y: 0.6, heading: 0.0}\n"
    live.request("go", {"path": path, "name": "east.yaml"})
    live.wait(lambda s: not _still(s), "the robot driving")
    with pytest.raises(ControlError) as e:
        live.request("go", {"path": path})
    assert e.value.code == "refused" and "mission is running" in e.value.message
    back = "waypoints:\n  - {x: 0.4, y: 0.7, heading: 0.0}\n"
    assert live.request("go", {"path": back, "name": "back.yaml", "replace": True})["replaced"]
    s = live.at_rest()
    assert s["mission"]["source"] == "back.yaml" and s["mission"]["state"] == "done"
    assert _near(_truth(live), (0.4, 0.7), 0.01)
    # pause holds the robot where it braked to; resume finishes the target
    live.request("goto", {"x": 0.8, "y": 0.7, "phi": 0.0})
    live.wait(lambda s: not _still(s) and _truth(live)[0] > 0.45, "the robot on its way")
    live.request("pause")
    s = live.wait(lambda s: _still(s) and s["mission"]["state"] == "paused", "the robot paused and still")
    assert s["mission"]["active"] and s["mission"]["paused"]
    live.wait(lambda s: max(abs(w) for w in live.rig.emulator.true_wheel_speeds) < 0.05, "the wheels at rest")
    held = _truth(live)
    for _ in range(10):  # still held a while later (ten status round trips)
        assert live.request("status")["mission"]["state"] == "paused"
    assert _near(_truth(live), held, 2e-3)
    live.request("resume")
    live.at_rest()
    assert _near(_truth(live), (0.8, 0.7), 0.01) and not _near(held, (0.8, 0.7), 0.05)
    # abort mid-way: brakes to rest short of the target
    live.request("goto", {"x": 0.2, "y": 0.7, "phi": 0.0})
    live.wait(lambda s: not _still(s) and _truth(live)[0] < 0.7, "the robot on its way back")
    assert live.request("abort")["aborted"]
    s = live.at_rest()
    assert s["mission"]["state"] == "aborted" and _truth(live)[0] > 0.25


def test_bad_paths_and_arguments_are_refused_and_never_move_the_robot(live):
    live.settle()
    before = live.moving_commands()
    for args, code, words in [
        ({"path": "waypoints:\n  - {x: 0.5, y: 0.5, speed: fast}\n", "name": "bad.yaml"}, "bad_args", ("bad.yaml", "speed")),
        ({"path": "waypoints: [\n", "name": "broken.yaml"}, "bad_args", ("broken.yaml", "malformed YAML")),
        ({"path": "waypoints:\n  - {x: 9.0, y: 0.5}\n", "name": "far.yaml"}, "bad_args", ("outside the map",)),
        ({"path": "{}", "name": "empty.yaml"}, "bad_args", ("waypoints",)),
    ]:
        with pytest.raises(ControlError) as e:
            live.request("go", args)
        assert e.value.code == code and all(w in e.value.message for w in words), e.value.message
    with pytest.raises(ControlError) as e:
        live.request("goto", {"x": 0.5, "y": 0.5, "phi": 0.0, "tolerance": 5.0})
    assert e.value.code == "bad_args"
    s = live.request("status")
    assert not s["mission"]["active"] and _still(s) and live.moving_commands() == before


def test_limits_lower_the_cruise_speed_and_never_rise_above_the_config(live):
    live.settle()
    with pytest.raises(ControlError) as e:
        live.request("limits", {"speed": ROBOT.control.max_speed + 0.1})
    assert e.value.code == "refused" and "configured" in e.value.message
    assert live.request("limits", {"speed": 0.05})["speed"] == 0.05
    n = len(live.ticks)
    target = 0.85 if _truth(live)[0] < 0.55 else 0.25  # a trip long enough to reach the limit
    live.request("goto", {"x": target, "y": 0.7, "phi": 0.0, "speed": 0.25})
    live.at_rest()
    # Like control.max_speed, the limit bounds the target: along the way exactly, and the norm with
    # the cross-track pull only within the per-axis limiters' lag.
    along = [abs(vx) for _, vx, _, _ in live.ticks[n:]]
    assert 0.04 < max(along) <= 0.05 + 1e-3
    assert max(math.hypot(vx, vy) for _, vx, vy, _ in live.ticks[n:]) <= 0.06
    assert _near(_truth(live), (target, 0.7), 0.01)
    assert live.request("limits", {"reset": True})["speed"] == ROBOT.control.max_speed


def test_relocalize_runs_off_the_loop_and_reports_the_square_arenas_ambiguity(live):
    live.settle()
    truth = _truth(live)
    n = len(live.ticks)
    r = live.request("relocalize", {"apply": True})
    # The arena is a square: four poses explain the views equally, so nothing is applied.
    assert r["verdict"] in ("ambiguous", "unique") and r["hypotheses"]
    assert any(_near((h["x"], h["y"]), truth, 0.05) for h in r["hypotheses"])
    if r["verdict"] == "ambiguous":
        assert not r["applied"]
    assert len(live.ticks) > n  # the control loop kept ticking while the search ran
    s = live.request("status")
    assert _near((s["pose"]["x"], s["pose"]["y"]), truth, 0.02)


def test_recover_restarts_the_relocalization_and_is_refused_while_the_robot_moves(live):
    live.settle()
    live.request("goto", {"x": 0.85, "y": 0.6, "phi": 0.0})
    live.wait(lambda s: not _still(s), "the robot driving")
    with pytest.raises(ControlError) as e:
        live.request("recover")
    assert e.value.code == "refused" and "moving" in e.value.message
    live.request("abort")
    s = live.at_rest()
    assert s["recovery"]["state"] == "tracking"
    r = live.request("recover")
    assert r["state"] == "relocalizing" and "control socket" in r["reason"]
    # The square arena: several places explain the views, so it holds and reports them; a unique
    # answer (the clutter-free arena's views are not exactly alike) confirms and tracks.
    s = live.wait(lambda s: s["recovery"]["state"] in ("ambiguous", "tracking"), "a verdict")
    truth = _truth(live)
    if s["recovery"]["state"] == "ambiguous":
        hyps = s["recovery"]["hypotheses"]
        assert len(hyps) >= 2 and any(_near((h["x"], h["y"]), truth, 0.05) for h in hyps), hyps
        assert _still(s)
        live.request("set-pose", {"x": truth[0], "y": truth[1], "phi": truth[2]})
    s = live.wait(lambda s: s["recovery"]["state"] == "tracking" and s["quality"]["state"] == "localized",
                  "tracking again")
    assert _near((s["pose"]["x"], s["pose"]["y"]), truth, 0.02)


def test_robotctl_talks_to_the_running_controller(live, tmp_path):
    live.settle()

    def robotctl(*args):
        env = dict(os.environ, ROBOT_CONTROL_SOCKET=live.path)
        return subprocess.run([sys.executable, "-m", "robot.cli.main", *args], capture_output=True, text=True,
                              timeout=HANG, env=env)

    def until(args, ok):
        """robotctl until its answer shows ``ok`` (a starved board emulator can drop the link for a
        moment; the guard only catches a hang)."""
        deadline = time.monotonic() + HANG
        while True:
            p = robotctl(*args)
            assert p.returncode == 0, p.stderr
            if ok(p.stdout):
                return p
            assert time.monotonic() < deadline, p.stdout
            time.sleep(0.2)

    until(("status", "--json"), lambda out: json.loads(out)["chassis"]["link"] == "ready")
    p = until(("status",), lambda out: "quality   localized" in out)
    assert "battery 12.00 V" in p.stdout, p.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("waypoints:\n  - {x: 0.5, y: 0.5, speed: fast}\n")
    p = robotctl("go", str(bad))
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and "bad.yaml" in lines[0] and "Traceback" not in p.stderr, p.stderr
    p = robotctl("limits", "--speed", "5")
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, (p.stdout, p.stderr)
    p = robotctl("limits", "--speed", "0.2")
    assert p.returncode == 0 and "0.200 m/s" in p.stdout, (p.stdout, p.stderr)
    good = tmp_path / "good.yaml"
    good.write_text("waypoints:\n  - {x: 0.55, y: 0.7, heading: 0.0}\n")
    p = robotctl("go", str(good))
    assert p.returncode == 0 and "1 waypoints" in p.stdout, p.stderr
    s = live.at_rest()
    assert _near(_truth(live), (0.55, 0.7), 0.01), (_truth(live), s)
    # recover, as the test above asks over the socket: it relocalizes; the status line says so.
    p = robotctl("recover")
    assert p.returncode == 0 and p.stdout.startswith("recovery: relocalizing"), (p.stdout, p.stderr)
    s = live.wait(lambda s: s["recovery"]["state"] in ("ambiguous", "tracking"), "a verdict")
    if s["recovery"]["state"] == "ambiguous":  # it holds there until the pose is set
        p = robotctl("status")
        assert p.returncode == 0 and "recovery  ambiguous" in p.stdout and "hypotheses" in p.stdout, p.stdout
    truth = _truth(live)
    live.request("set-pose", {"x": truth[0], "y": truth[1], "phi": truth[2]})
    live.wait(lambda s: s["recovery"]["state"] == "tracking" and s["quality"]["state"] == "localized", "tracking again")
    p = robotctl("status", "--socket", str(tmp_path / "none.sock"))
    assert p.returncode == 2 and "no controller socket" in p.stderr
