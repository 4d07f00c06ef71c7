"""Fuzzing the robot's two command channels on the running real-time simulation: the control
socket (random bytes, random and malformed JSON, wrong types, out-of-range numbers, huge lines)
and VDA 5050 ``order`` / ``instantActions`` messages over MQTT (garbage, type-mutated and
semantically broken orders, oversized payloads).

The properties: the controller keeps running and answers each bad request with an error (a
socket reply, a ``state.errors`` entry), and the robot never moves because of one: the
emulated board receives no nonzero wheel speed while the fuzz runs, and no mission starts.

Each generated request is bad by construction (an unknown key, a value of the wrong type or out
of its range, a path text without waypoints, a schema-breaking field), never by a filter that
asks the code under test. ``ROBOT_FUZZ_LONG=1`` runs many more examples.
"""

from __future__ import annotations

import asyncio
import copy
import json
import os
import shutil
import socket
import threading
import time
from dataclasses import replace

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from firmware_protocol import SetWheelSpeeds
from robot.app import control_protocol as proto
from robot.app.control_client import ControlClient
from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.maps.plane_map import load_plane_map
from robot.sim.realtime import RealtimeSimSettings, sim_rig

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
START = (0.3, 0.6, 0.0)
HANG = 120.0  # s: hang guard only
LONG = os.environ.get("ROBOT_FUZZ_LONG") == "1"
FUZZ = settings(max_examples=2000 if LONG else 120, deadline=None, derandomize=not LONG, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture, HealthCheck.filter_too_much])
MQTT_FUZZ = settings(FUZZ, max_examples=500 if LONG else 50)
MAX_REQUEST = 8192  # the fuzzed controller's line limit (small, so that "huge" is cheap to send)
MAX_ORDER = 16384

MOSQUITTO = shutil.which("mosquitto", path=os.environ.get("PATH", "") + os.pathsep + "/usr/sbin" + os.pathsep + "/sbin")
try:
    import jsonschema  # noqa: F401
    import paho.mqtt.client as mqtt
except ImportError:
    mqtt = None
FLEET_REASON = ("mosquitto is not installed" if MOSQUITTO is None else
                "paho-mqtt / jsonschema (the 'fleet' extra) are not installed" if mqtt is None else "")


class Fuzzed:
    def __init__(self, rig, socket_path):
        self.rig = rig
        self.socket_path = socket_path
        self.master = None
        self.port = None

    def moving_commands(self):
        return sum(1 for _, m in self.rig.emulator.received()
                   if isinstance(m, SetWheelSpeeds) and max(abs(w) for w in m.rad_s) > 0.0)

    def status(self):
        with ControlClient(self.socket_path, timeout=HANG) as c:
            return c.request("status")

    def fleet(self):
        from robot.app.fleet.link import FleetLink

        return next(s for s in self.rig.app.services if isinstance(s, FleetLink))


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    fleet = ROBOT.fleet
    broker = None
    if not FLEET_REASON:
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        conf = d / "mosquitto.conf"
        conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        broker = __import__("subprocess").Popen([MOSQUITTO, "-c", str(conf)], stdout=-3, stderr=-3)
        deadline = time.monotonic() + HANG
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                assert time.monotonic() < deadline and broker.poll() is None, "mosquitto never listened"
                time.sleep(0.05)
        fleet = replace(fleet, enabled=True, port=port, state_period=2.0, max_message_bytes=MAX_ORDER)
    robot = replace(ROBOT, fleet=fleet, control_api=replace(ROBOT.control_api, socket=str(d / "control.sock"),
                                                            max_request_bytes=MAX_REQUEST))
    opts = AppOptions(install_signal_handlers=False, stop_when_done=False, remote=True)
    with sim_rig(robot, ARENA, START, RealtimeSimSettings(fps=10, decimation=4), opts, initial_pose=START) as rig:
        f = Fuzzed(rig, robot.control_api.socket)
        rc = []
        thread = threading.Thread(target=lambda: rc.append(asyncio.run(rig.app.run())), daemon=True)
        thread.start()
        deadline = time.monotonic() + HANG
        while True:
            try:
                if f.status()["quality"]["state"] == "localized":
                    break
            except Exception:  # noqa: BLE001 - not up yet
                pass
            assert time.monotonic() < deadline and thread.is_alive(), "the app never came up"
            time.sleep(0.1)
        if broker is not None:
            f.master = MqttMaster(fleet.port)
            f.master.state(lambda s: True)
        try:
            yield f
        finally:
            if f.master is not None:
                f.master.close()
            rig.app.request_stop("test end")
            thread.join(HANG)
            if broker is not None:
                broker.terminate()
                broker.wait(HANG)
    assert rc == [0]


# -- the control socket ------------------------------------------------------------------------------

SENTINEL = b'{"v":1,"id":"sentinel","cmd":"status"}\n'


def exchange(path, line: bytes):
    """Send one fuzz line and a sentinel; every reply before the sentinel's (or the one reply when
    the server closes on a too-long line)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(HANG)
    s.connect(path)
    try:
        try:
            s.sendall(line + SENTINEL)
        except (BrokenPipeError, ConnectionResetError):
            pass
        f = s.makefile("rb")
        replies = []
        while True:
            raw = f.readline()
            if not raw:
                return replies, False
            reply = json.loads(raw)
            if reply.get("id") == "sentinel":
                return replies, True
            replies.append(reply)
    finally:
        s.close()


json_leaf = st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=20)
json_value = st.recursive(json_leaf, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
                          max_leaves=12)


def _wrong_for(check_name: str):
    """Values no argument of that kind accepts."""
    not_number = st.none() | st.text(max_size=10) | st.booleans() | st.lists(json_leaf, max_size=3) | \
        st.dictionaries(st.text(max_size=4), json_leaf, max_size=2)
    return {"number": not_number | st.sampled_from([1e6, -1e6, 10 ** 400, -(10 ** 400)]),
            "bool": st.none() | st.integers() | st.text(max_size=5) | st.floats(allow_nan=False) | st.lists(json_leaf, max_size=2),
            "string": st.none() | st.integers() | st.booleans() | st.lists(json_leaf, max_size=2) | st.just(""),
            "region": st.none() | st.lists(st.floats(allow_nan=False), max_size=3) | st.text(max_size=5) |
            st.lists(st.text(max_size=3), min_size=4, max_size=4)}[check_name]


ARG_KINDS = {"x": "number", "y": "number", "phi": "number", "std_xy": "number", "std_phi": "number", "speed": "number",
             "tolerance": "number", "period": "number", "force": "bool", "replace": "bool", "apply": "bool",
             "reset": "bool", "path": "string", "name": "string", "reason": "string", "region": "region"}


@st.composite
def bad_request(draw):
    """A request for a real command that is wrong in at least one place, by construction."""
    cmd = draw(st.sampled_from(sorted(proto.COMMANDS)))
    spec = proto.COMMANDS[cmd]
    args = {}
    for key in spec.args:  # plausible values for the rest, so that only the planted fault is wrong
        if draw(st.booleans()):
            kind = ARG_KINDS[key]
            args[key] = draw({"number": st.floats(-0.5, 0.5), "bool": st.booleans(), "string": st.just("label"),
                              "region": st.just([0.0, 0.0, 1.0, 1.0])}[kind])
    fault = draw(st.sampled_from(["unknown key", "wrong value", "path without waypoints"] if spec.args else
                                 ["unknown key"]))
    if fault == "unknown key":
        key = draw(st.text(min_size=1, max_size=12))
        assume(key not in spec.args)
        args[key] = draw(json_value)
    elif fault == "wrong value":
        key = draw(st.sampled_from(sorted(spec.args)))
        args[key] = draw(_wrong_for(ARG_KINDS[key]))
    else:
        if "path" not in spec.args:
            key = draw(st.text(min_size=1, max_size=12))
            assume(key not in spec.args)
            args[key] = 1
        else:
            text = draw(st.text(max_size=300))
            assume("waypoints" not in text)
            args["path"] = text
    req = {"v": 1, "id": draw(st.integers(0, 1000) | st.text(max_size=10)), "cmd": cmd, "args": args}
    return json.dumps(req).encode()


garbage_line = st.binary(max_size=600).map(lambda b: b.replace(b"\n", b" ") + b"\n")
malformed_json = st.sampled_from([b"{", b'{"v": 1', b"[]", b"null", b'"status"', b'{"v": 1, "cmd": "status"',
                                  b'{"v": NaN, "cmd": "status"}', b'{"v": 1, "cmd": "goto", "args": {"x": -Infinity}}',
                                  b"{" * 3000, b'{"v": 1, "cmd": "go", "args": {"path": "' + b"w" * 20000 + b'"}}',
                                  b"\x00" * 100, b'{"v": 1, "cmd": "status"}' * 400]).map(lambda b: b + b"\n")
random_json = json_value.map(lambda v: json.dumps(v).encode() + b"\n")
huge = st.integers(MAX_REQUEST + 1, 4 * MAX_REQUEST).map(lambda n: b'{"v":1,"cmd":"status","args":{"x":"' + b"a" * n +
                                                         b'"}}\n')


@FUZZ
@given(line=garbage_line | malformed_json | random_json | bad_request().map(lambda b: b + b"\n") | huge)
def test_the_control_socket_answers_every_bad_request_with_an_error_and_never_moves(fuzzed, line):
    before = fuzzed.moving_commands()
    replies, served_on = exchange(fuzzed.socket_path, line)
    for r in replies:
        assert r.get("ok") is False and r["error"]["code"] in proto.ERROR_CODES, r
        assert isinstance(r["error"]["message"], str) and "\n" not in r["error"]["message"]
    if not served_on:  # a too-long line: one error, and the connection closed
        assert [r["error"]["code"] for r in replies] == [proto.TOO_LONG]
    assert fuzzed.moving_commands() == before
    s = fuzzed.status()
    assert not s["mission"]["active"] and s["chassis"]["link"] in ("ready", "lost", "connecting")


def test_after_the_socket_fuzz_the_robot_stood_still_and_serves_normally(fuzzed):
    s = fuzzed.status()
    x, y, _ = fuzzed.rig.emulator.pose
    assert abs(x - START[0]) < 2e-3 and abs(y - START[1]) < 2e-3  # it never moved
    assert s["quality"]["state"] == "localized" and s["mission"]["speed_limit"] == ROBOT.control.max_speed


# -- VDA 5050 over MQTT ------------------------------------------------------------------------------


class MqttMaster:
    def __init__(self, port):
        self.cond = threading.Condition()
        self.states = []
        self.header = 0
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"fuzz-master-{os.getpid()}")
        c.on_connect = lambda client, *a: client.subscribe("uagv/v2/planeloc/robot-1/state")
        c.on_message = self._on_message
        c.connect("127.0.0.1", port)
        c.loop_start()
        self.client = c

    def _on_message(self, client, userdata, msg):
        with self.cond:
            self.states.append(json.loads(msg.payload))
            self.cond.notify_all()

    def close(self):
        self.client.loop_stop()
        self.client.disconnect()

    def state(self, predicate, since=0):
        deadline = time.monotonic() + HANG
        i = since
        with self.cond:
            while True:
                while i < len(self.states):
                    i += 1
                    if predicate(self.states[i - 1]):
                        return self.states[i - 1]
                assert time.monotonic() < deadline, "hang guard: no such state"
                self.cond.wait(1.0)

    def publish(self, subtopic, payload: bytes):
        self.client.publish(f"uagv/v2/planeloc/robot-1/{subtopic}", payload).wait_for_publish(HANG)

    def sync(self) -> dict:
        """A stateRequest behind whatever was sent before: the state that answers it."""
        self.header += 1
        aid = f"sync-{self.header}"
        with self.cond:
            since = len(self.states)
        self.publish("instantActions", json.dumps(
            {"headerId": self.header, "timestamp": "2024-05-01T12:00:00.00Z", "version": "2.0.0",
             "manufacturer": "planeloc", "serialNumber": "robot-1",
             "actions": [{"actionName": "stateRequest", "actionId": aid, "blockingType": "NONE"}]}).encode())
        return self.state(lambda s: any(a["actionId"] == aid for a in s["actionStates"]), since)


def _valid_order(x, y):
    return {"headerId": 1, "timestamp": "2024-05-01T12:00:00.00Z", "version": "2.0.0", "manufacturer": "planeloc",
            "serialNumber": "robot-1", "orderId": "fuzz", "orderUpdateId": 0,
            "nodes": [{"nodeId": "f0", "sequenceId": 0, "released": True, "actions": [],
                       "nodePosition": {"x": x, "y": y, "theta": 0.0, "mapId": "paper_arena", "allowedDeviationXy": 0.1}},
                      {"nodeId": "f1", "sequenceId": 2, "released": True, "actions": [],
                       "nodePosition": {"x": x + 0.2, "y": y, "theta": 0.0, "mapId": "paper_arena"}}],
            "edges": [{"edgeId": "e", "sequenceId": 1, "released": True, "startNodeId": "f0", "endNodeId": "f1",
                       "actions": [], "maxSpeed": 0.2}]}


# (path in the order, the JSON type the schema wants there)
TYPED_PATHS = [(("orderId",), "string"), (("orderUpdateId",), "integer"), (("nodes",), "array"), (("edges",), "array"),
               (("headerId",), "integer"), (("version",), "string"), (("manufacturer",), "string"),
               (("nodes", 0, "nodeId"), "string"), (("nodes", 1, "sequenceId"), "integer"),
               (("nodes", 1, "released"), "boolean"), (("nodes", 1, "nodePosition"), "object"),
               (("nodes", 1, "nodePosition", "x"), "number"), (("nodes", 1, "nodePosition", "mapId"), "string"),
               (("nodes", 1, "actions"), "array"), (("edges", 0, "startNodeId"), "string"),
               (("edges", 0, "maxSpeed"), "number"), (("edges", 0, "released"), "boolean"),
               (("nodes", 0), "object"), (("edges", 0), "object")]
SEMANTIC = [(("nodes", 1, "nodePosition", "x"), 1e6), (("nodes", 1, "nodePosition", "mapId"), "another-map"),
            (("nodes", 1, "sequenceId"), 4), (("edges", 0, "endNodeId"), "nowhere"), (("serialNumber",), "robot-9"),
            (("nodes", 0, "nodePosition", "x"), 1.2), (("edges", 0, "maxSpeed"), -1.0), (("version",), "3.0.0"),
            (("nodes", 1, "nodePosition", "x"), 10 ** 400), (("edges", 0, "maxSpeed"), 10 ** 30)]


def _json_type(v):
    if isinstance(v, bool):
        return "boolean"
    if isinstance(v, int):
        return "integer"
    if isinstance(v, float):
        return "integer" if v.is_integer() else "number"
    return {str: "string", list: "array", dict: "object", type(None): "null"}[type(v)]


def _fits(v, wanted):
    t = _json_type(v)
    return t == wanted or (wanted == "number" and t == "integer")


@st.composite
def bad_order(draw):
    kind = draw(st.sampled_from(["garbage", "json", "typed", "semantic", "missing", "huge"]))
    if kind == "garbage":
        return draw(st.binary(max_size=400))
    if kind == "json":
        v = draw(json_value)
        assume(not isinstance(v, dict) or "nodes" not in v)
        return json.dumps(v).encode()
    order = _valid_order(*draw(st.sampled_from([(0.3, 0.6)])))
    if kind == "huge":
        return json.dumps(order).encode() + b" " * draw(st.integers(MAX_ORDER, 3 * MAX_ORDER))
    if kind == "missing":
        key = draw(st.sampled_from(["orderId", "orderUpdateId", "nodes", "edges", "headerId", "serialNumber"]))
        del order[key]
        return json.dumps(order).encode()
    if kind == "typed":
        path, wanted = draw(st.sampled_from(TYPED_PATHS))
        value = draw(json_value)
        assume(not _fits(value, wanted))
    else:
        path, value = draw(st.sampled_from(SEMANTIC))
    target = order
    for p in path[:-1]:
        target = target[p]
    target[path[-1]] = copy.deepcopy(value)
    return json.dumps(order).encode()


@pytest.mark.skipif(bool(FLEET_REASON), reason=FLEET_REASON or "ok")
@MQTT_FUZZ
@given(payload=bad_order(), topic=st.sampled_from(["order", "order", "order", "instantActions"]))
def test_bad_order_and_instant_action_messages_are_errors_in_the_state_and_never_move(fuzzed, payload, topic):
    m = fuzzed.master
    before = fuzzed.moving_commands()
    rejected = fuzzed.fleet().agv.stats["rejected"]
    m.publish(topic, payload)
    s = m.sync()
    assert s["orderId"] != "fuzz" and not s["driving"]  # never taken
    if topic == "order" or len(payload) > MAX_ORDER:  # (an instantActions message without actions is valid)
        assert fuzzed.fleet().agv.stats["rejected"] > rejected
        reported = [e for e in s["errors"] if any(r["referenceKey"] == "topic" for r in e["errorReferences"])]
        assert reported and all(e["errorLevel"] == "WARNING" and e["errorDescription"] for e in reported)
    assert fuzzed.moving_commands() == before


@pytest.mark.skipif(bool(FLEET_REASON), reason=FLEET_REASON or "ok")
def test_after_the_order_fuzz_the_robot_still_takes_a_good_order(fuzzed):
    m = fuzzed.master
    x, y, _ = fuzzed.rig.emulator.pose
    assert abs(x - START[0]) < 2e-3 and abs(y - START[1]) < 2e-3  # nothing moved it
    order = _valid_order(x, y)
    order["nodes"][1]["nodePosition"].update(x=x + 0.05)
    m.publish("order", json.dumps(order).encode())
    done = m.state(lambda s: s["orderId"] == "fuzz" and s["lastNodeId"] == "f1" and not s["driving"])
    assert not [e for e in done["errors"] if e["errorType"] in ("validationError", "orderError")]
    assert abs(fuzzed.rig.emulator.pose[0] - (x + 0.05)) < 0.015
