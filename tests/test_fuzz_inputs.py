"""Property-based fuzzing of every loader and every command that takes a file.

The contract, whatever the bytes: a loader returns a valid object or raises one ``RobotError``
whose message is a single short line; a command exits 0, 1 or 2, and on 2 writes exactly one
line to stderr and no traceback; nothing hangs (each example runs under a generous alarm, a hang
guard only); and no wheel is ever commanded, because a bad file must stop everything before it
starts. Inputs: random bytes, mutated valid files (byte flips, cuts, splices), YAML trees of
hostile values (NaN, inf, 1e308, huge integers, wrong types, deep nesting, alias bombs), and
for recordings, valid MCAP containers around hostile JSON.

Examples per loader: a few dozen by default (a few hundred in all); ``ROBOT_FUZZ_LONG=1`` runs
10,000 per loader (``scripts/bench_fuzz.py`` times that). The default run is derandomized so a
failure in CI reproduces; the long run explores.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import dataclasses
import importlib.util
import io
import json
import math
import os
import signal
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any, Callable, List, Tuple

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robot.base.errors import RobotError
from robot.config import load_robot_config
from robot.config.ranges import check_fields
from robot.config.schema import load_yaml_file, parse_yaml
from robot.config.sections import CameraConfig, ChassisConfig, ControlConfig, LocalizerConfig
from robot.control.path_file import load_path
from robot.maps.plane_map import COORDINATE_RANGE, load_plane_map

ROOT = Path(__file__).resolve().parents[1]
ROBOT_YAML = ROOT / "config" / "robot.yaml"
ARENA_YAML = ROOT / "config" / "maps" / "paper_arena.yaml"
PATH_YAML = ROOT / "config" / "paths" / "paper_4_3.yaml"

LONG = os.environ.get("ROBOT_FUZZ_LONG") == "1"
LOADER_EXAMPLES = int(os.environ.get("ROBOT_FUZZ_EXAMPLES", 10_000 if LONG else 40))
CLI_EXAMPLES = int(os.environ.get("ROBOT_FUZZ_CLI_EXAMPLES", 300 if LONG else 12))
HANG_GUARD = 120.0  # s per example: only there to turn a hang into a failure
MESSAGE_LIMIT = 600  # characters of one error line

FUZZ = settings(max_examples=LOADER_EXAMPLES, deadline=None, derandomize=not LONG, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture, HealthCheck.filter_too_much])
FUZZ_CLI = settings(FUZZ, max_examples=CLI_EXAMPLES)


class Hang(Exception):
    pass


@contextlib.contextmanager
def hang_guard(seconds: float = HANG_GUARD):
    def on_alarm(signum, frame):
        raise Hang(f"no result within {seconds:.0f} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def holds_contract(load: Callable[[Path], Any], path: Path) -> Any:
    """``load(path)``: a result, or None after one RobotError with a one-line message."""
    with hang_guard():
        try:
            return load(path)
        except RobotError as e:
            msg = str(e)
            assert msg and "\n" not in msg and len(msg) <= MESSAGE_LIMIT, msg[:2000]
            return None


# ------------------------------------------------------------------ strategies

HOSTILE_NUMBERS = [0, -1, 1, 0.5, -0.0, 1e308, -1e308, 1e-320, float("nan"), float("inf"), -float("inf"),
                   10**30, -(2**63), 2**64, 848, 1920, 10**11, 0.02, 0.5, 200.0]
KEYS = sorted({f.name for cls in (CameraConfig, ChassisConfig, ControlConfig, LocalizerConfig)
               for f in dataclasses.fields(cls)}
              | {"cameras", "mount", "xyz", "rpy_deg", "realsense", "map", "planes", "id", "vertices", "polygons",
                 "source", "waypoints", "start", "defaults", "x", "y", "heading", "speed", "tolerance", "dwell",
                 "description", "<<"})

numbers = st.sampled_from(HOSTILE_NUMBERS) | st.floats(allow_nan=True, allow_infinity=True) | st.integers()
scalars = numbers | st.text(max_size=30) | st.booleans() | st.none()
trees = st.recursive(scalars, lambda inner: st.lists(inner, max_size=5)
                     | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=8), inner, max_size=5),
                     max_leaves=30)


@st.composite
def mutated_bytes(draw, original: bytes) -> bytes:
    """Byte flips, a cut, a spliced or repeated slice, or an insertion of random bytes."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["flip", "cut", "splice", "insert", "repeat"]))
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        if op == "flip":
            data[i] = draw(st.integers(0, 255))
        elif op == "cut":
            del data[i:]
        elif op == "splice":
            j = draw(st.integers(i, len(data)))
            del data[i:j]
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=64))
        else:
            j = draw(st.integers(i, min(len(data), i + 256)))
            data[i:i] = data[i:j] * draw(st.integers(1, 8))
    return bytes(data)


def alias_bomb(levels: int, width: int) -> str:
    lines = ["a0: &a0 [" + ", ".join(["x"] * width) + "]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


special_yaml = st.one_of(
    st.builds(lambda n: "[" * n + "]" * n, st.integers(1, 30_000)),
    st.builds(lambda n: "a:\n" + "".join("  " * (k + 1) + "b:\n" for k in range(n)) + "  " * (n + 1) + "1\n",
              st.integers(1, 200)),
    st.builds(alias_bomb, st.integers(2, 12), st.integers(2, 12)),
    st.sampled_from(["a: &x [1, *x]\n", "a: *nothing\n", "a: 2024-13-45\n", "a: " + "9" * 5000 + "\n",
                     "!!python/object/apply:os.system ['true']\n", "a: !!binary '!!!'\n", "--- 1\n--- 2\n",
                     "\ufeffcameras: []\n", "a: 1\n\x00\n", "? [1, 2]\n: 3\n", "a: {b: 1, b: 2}\n"]),
)


def yaml_text_from(base: Any):
    """YAML text: a mutated valid document, a hostile tree, a special construct, or mutated bytes of the base."""
    base_text = yaml.safe_dump(base, sort_keys=False)

    @st.composite
    def edited(draw):
        doc = copy.deepcopy(base)
        for _ in range(draw(st.integers(1, 4))):
            node = doc
            for _ in range(draw(st.integers(0, 3))):  # walk down a little
                if isinstance(node, dict) and node:
                    node = node[draw(st.sampled_from(sorted(node, key=str)))]
                elif isinstance(node, list) and node:
                    node = node[draw(st.integers(0, len(node) - 1))]
            if isinstance(node, dict):
                key = draw(st.sampled_from(sorted(node, key=str)) | st.sampled_from(KEYS)) if node else draw(
                    st.sampled_from(KEYS))
                if draw(st.booleans()) and key in node:
                    del node[key]
                else:
                    node[key] = draw(trees)
            elif isinstance(node, list):
                node.append(draw(trees))
        return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)

    return st.one_of(
        edited(),
        trees.map(lambda t: yaml.safe_dump(t, allow_unicode=True)),
        special_yaml,
        mutated_bytes(base_text.encode()).map(lambda b: b.decode("utf-8", "replace")),
        st.text(max_size=300),
    )


def write(tmp: Path, name: str, content) -> Path:
    p = tmp / name
    if isinstance(content, str):
        p.write_text(content, encoding="utf-8", errors="surrogatepass")
    else:
        p.write_bytes(content)
    return p


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# ------------------------------------------------------------------ YAML loaders

ROBOT_DATA = yaml.safe_load(ROBOT_YAML.read_text())
ARENA_DATA = yaml.safe_load(ARENA_YAML.read_text())
PATH_DATA = yaml.safe_load(PATH_YAML.read_text())


@FUZZ
@given(text=st.one_of(special_yaml, st.text(max_size=500), trees.map(yaml.safe_dump)))
def test_yaml_parsing_is_bounded(text):
    with hang_guard():
        try:
            parse_yaml(text, "fuzz.yaml")
        except RobotError as e:
            assert "\n" not in str(e) and len(str(e)) <= MESSAGE_LIMIT


@FUZZ
@given(text=yaml_text_from(ROBOT_DATA))
def test_robot_config_loader(scratch, text):
    robot = holds_contract(load_robot_config, write(scratch, "robot.yaml", text))
    if robot is not None:  # accepted: then every value lies in its declared range
        for name in ("chassis", "localizer", "control", "health", "fusion", "quality"):
            check_fields(getattr(robot, name), name)
        for cam in robot.cameras:
            check_fields(cam, cam.name)
            cam.realsense.validate()


@FUZZ
@given(text=yaml_text_from(PATH_DATA))
def test_path_loader(scratch, text):
    plan = holds_contract(load_path, write(scratch, "path.yaml", text))
    if plan is not None:
        for w in plan.waypoints:
            assert abs(w.x) <= 1000 and abs(w.y) <= 1000 and 0 < w.speed <= 2.0 and math.isfinite(w.dwell)


@FUZZ
@given(text=yaml_text_from(ARENA_DATA))
def test_map_loader(scratch, text):
    pm = holds_contract(load_plane_map, write(scratch, "map.yaml", text))
    if pm is not None:
        lo, hi = pm.bounds()
        assert COORDINATE_RANGE.lo <= lo.min() and hi.max() <= COORDINATE_RANGE.hi
        assert np.all(np.isfinite(pm.plane_array))


@FUZZ
@given(text=yaml_text_from(ARENA_DATA))
def test_map_check(scratch, text):
    from robot.base.files import MAP
    from robot.maps.tools import check_map_data

    def check(p):
        data = load_yaml_file(p, MAP)
        return check_map_data(data, source=str(p))

    holds_contract(check, write(scratch, "check.yaml", text))


@FUZZ
@given(data=st.binary(max_size=2048))
def test_yaml_loaders_on_random_bytes(scratch, data):
    p = write(scratch, "bytes.yaml", data)
    for load in (load_robot_config, load_path, load_plane_map):
        holds_contract(load, p)


# ------------------------------------------------------------------ depth snapshots

K = np.array([[300.0, 0.0, 31.5], [0.0, 300.0, 23.5], [0.0, 0.0, 1.0]])


def npz_bytes(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


VALID_NPZ = npz_bytes(depth=np.full((48, 64), 1000, np.uint16), depth_scale=np.float64(0.001), K=K,
                      camera=np.str_("front"))

arrays = st.one_of(
    st.builds(lambda shape, dtype, fill: np.full(shape, fill).astype(dtype),
              st.lists(st.integers(0, 70), min_size=0, max_size=3).map(tuple),
              st.sampled_from([np.uint16, np.float32, np.int64, np.uint8, np.bool_, np.complex64]),
              st.sampled_from([0, 1, 1000, 65535, -1])),
    st.sampled_from([np.float64(np.nan), np.float64(np.inf), np.float64(-1.0), np.float64(1e308), np.str_("x" * 100),
                     np.bytes_(b"\xff\xfe"), np.array([]), np.array(["a", "b"]), np.array([[np.nan] * 3] * 3),
                     np.array([[1e308, 0, 0], [0, 1, 0], [0, 0, 1]]), np.array([0.0, 0.0, np.inf])]),
)


@st.composite
def snapshot_bytes(draw) -> bytes:
    if draw(st.booleans()):
        return draw(mutated_bytes(VALID_NPZ))
    fields = {"depth": np.full((48, 64), 1000, np.uint16), "depth_scale": np.float64(0.001), "K": K,
              "camera": np.str_("front")}
    for key in draw(st.lists(st.sampled_from(["depth", "depth_scale", "K", "camera", "truth", "extra"]),
                             max_size=3, unique=True)):
        if draw(st.booleans()) and key in fields:
            del fields[key]
        else:
            fields[key] = draw(arrays)
    return npz_bytes(**fields)


@FUZZ
@given(data=st.one_of(snapshot_bytes(), st.binary(max_size=1024)))
def test_snapshot_loader(scratch, data):
    from robot.recording.snapshot import load_snapshot

    frame = holds_contract(load_snapshot, write(scratch, "snap.npz", data))
    if frame is not None:
        assert frame.depth.dtype == np.uint16 and frame.depth.ndim == 2 and np.all(np.isfinite(frame.K))


# ------------------------------------------------------------------ recordings

def write_mcap(path: Path, records: List[Tuple[str, int, bytes, str]]) -> None:
    """An MCAP container (valid framing, CRCs) around any message bytes: what a hostile tool could write."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("any", "jsonschema", b"{}")
        channels = {}
        for topic, log_ns, data, encoding in records:
            key = (topic, encoding)
            if key not in channels:
                channels[key] = w.register_channel(topic, encoding, schema)
            log_ns = min(max(0, log_ns), 2**64 - 1)  # the field is a uint64
            w.add_message(channels[key], log_time=log_ns, data=data, publish_time=log_ns)
        w.finish()


@pytest.fixture(scope="module")
def app_recording(tmp_path_factory) -> Path:
    """A short recording of the simulated app (config, odometry, depth, planes, poses), made once."""
    pytest.importorskip("mcap")
    from robot.app.controller import AppOptions
    from robot.control.path_file import parse_path
    from robot.recording.recorder import BackgroundRecorder, Recorder
    from robot.sim.realtime import RealtimeSimSettings, sim_rig

    counts = {"/planes": 0, "/pose": 0, "/odometry": 0}

    class Counting(BackgroundRecorder):
        def write(self, topic, t, message):
            if topic in counts:
                counts[topic] += 1
            return super().write(topic, t, message)

    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    robot = load_robot_config(ROBOT_YAML)
    arena = load_plane_map(ARENA_YAML)
    plan = parse_path({"start": {"x": 0.4, "y": 0.6, "heading": 0.0}, "waypoints": [{"x": 0.6, "y": 0.6}]})
    rec = Counting(Recorder(str(path)), max_queue=1 << 20)
    opts = AppOptions(install_signal_handlers=False, status_period=0.25, stop_when_done=False)

    def on_tick(app, t):
        if counts["/planes"] >= 3 and counts["/pose"] >= 2 and counts["/odometry"] >= 60:
            app.request_stop("enough recorded")

    with sim_rig(robot, arena, (0.4, 0.6, 0.0), RealtimeSimSettings(fps=8, decimation=4), opts, plan=plan,
                 recorder=rec, on_tick=on_tick) as rig:
        assert asyncio.run(asyncio.wait_for(rig.app.run(), HANG_GUARD)) == 0
    return path


@pytest.fixture(scope="module")
def recorded(app_recording) -> List[Tuple[str, int, bytes]]:
    """(topic, log time ns, JSON bytes) of every message, read with the mcap package itself."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    channels, out = {}, []
    with open(app_recording, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Channel):
                channels[record.id] = record.topic
            elif isinstance(record, Message):
                out.append((channels[record.channel_id], record.log_time, bytes(record.data)))
    assert {"/config", "/odometry", "/pose"} <= {t for t, _, _ in out}
    return out


hostile_json = st.one_of(
    trees.map(lambda t: json.dumps(t, allow_nan=True).encode()),
    st.builds(lambda n: ("[" * n + "]" * n).encode(), st.integers(1, 200_000)),
    st.binary(max_size=200),
    st.sampled_from([b"NaN", b"{}", b"[]", b"null", b'{"data": 5}', b'{"format": "png", "data": "!!!"}']),
)


@st.composite
def hostile_recording(draw, recorded):
    records = [(t, ns, data, "json") for t, ns, data in recorded]
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(records) - 1))
        topic, ns, data, enc = records[i]
        op = draw(st.sampled_from(["json", "field", "drop", "time", "encoding", "topic"]))
        if op == "json":
            data = draw(hostile_json)
        elif op == "field":
            try:
                msg = json.loads(data)
            except (ValueError, RecursionError):  # an earlier step may have put 200,000 nested brackets here
                msg = {}
            if isinstance(msg, dict) and msg:
                key = draw(st.sampled_from(sorted(msg)))
                if draw(st.booleans()):
                    msg[key] = draw(trees)
                else:
                    del msg[key]
            data = json.dumps(msg, allow_nan=True).encode()
        elif op == "drop":
            del records[i]
            continue
        elif op == "time":
            ns = draw(st.sampled_from([0, 2**63 - 1, ns // 2, ns * 1000]))
        elif op == "encoding":
            enc = draw(st.sampled_from(["protobuf", "", "json"]))
        else:
            topic = draw(st.sampled_from(["/depth/rear", "/odometry", "/pose", "/planes", "/config", "/nope"]))
        records[i] = (topic, ns, data, enc)
    return records


@settings(FUZZ, max_examples=max(10, LOADER_EXAMPLES // 4))
@given(data=st.data())
def test_recording_reader_on_hostile_content(scratch, recorded, data):
    from robot.recording.reader import RecordingReader

    path = scratch / "hostile.mcap"
    write_mcap(path, data.draw(hostile_recording(recorded)))
    holds_contract(lambda p: list(RecordingReader(p).messages()), path)


@FUZZ
@given(data=st.data())
def test_recording_reader_on_mutated_bytes(scratch, app_recording, data):
    from robot.recording.reader import RecordingReader

    original = app_recording.read_bytes()
    path = write(scratch, "mutated.mcap", data.draw(mutated_bytes(original) | st.binary(max_size=512)))
    holds_contract(lambda p: list(RecordingReader(p, follow_segments=False).messages()), path)


# ------------------------------------------------------------------ IFC models

def _room_ifc() -> str:
    spec = importlib.util.spec_from_file_location("_ifc_fixture", ROOT / "tests" / "test_ifc_import.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.ifc_text(mod.ROOM_WALLS, mod.ROOM_OPENINGS)


@pytest.mark.skipif(importlib.util.find_spec("ifcopenshell") is None, reason="ifcopenshell not installed")
@settings(FUZZ, max_examples=max(10, LOADER_EXAMPLES // 4))
@given(data=st.data())
def test_ifc_open_model(scratch, data):
    """Opening; what a model's entities then say is judged by the import (see test_import_ifc_command)."""
    from robot.maps.ifc_import import open_model

    room = _room_ifc().encode()
    content = data.draw(mutated_bytes(room) | st.binary(max_size=512))
    holds_contract(open_model, write(scratch, "model.ifc", content))


# ------------------------------------------------------------------ the commands, in process

class Started(Exception):
    """Raised where the app or the experiment would start: the inputs were accepted."""


@pytest.fixture
def no_motion(monkeypatch):
    """Every way a command could move a wheel records the attempt, and starting the app stops the test."""
    from drivers.chassis import serial_chassis
    from robot.app import controller
    from robot.sim import experiment

    commands = []
    monkeypatch.setattr(serial_chassis.SerialChassis, "send_wheel_speeds",
                        lambda self, *a, **k: commands.append(a) or False)

    def started(*a, **k):
        raise Started()

    monkeypatch.setattr(controller.RobotApp, "run", started)
    monkeypatch.setattr(experiment, "run_experiment", started)
    return commands


def run_cli(argv: List[str]) -> Tuple[Any, str]:
    """``robotctl argv`` in this process; stderr as a terminal would show it, log lines included."""
    import logging

    from robot.cli.main import main

    err = io.StringIO()
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    root.handlers = []  # so that main's logging.basicConfig writes to this stderr, as in a real run
    try:
        with hang_guard(), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                rc = main(argv)
            except Started:
                rc = "started"
    finally:
        root.handlers, _ = saved
        root.setLevel(saved[1])
    return rc, err.getvalue()


def assert_cli_contract(rc, err: str, commands) -> None:
    assert rc in (0, 1, 2, "started"), (rc, err)
    if rc == 2:
        lines = err.splitlines()
        assert err.endswith("\n") and "Traceback" not in err, err[:2000]
        assert len(lines) == 1 and lines[0].startswith("robotctl ") and len(lines[0]) <= MESSAGE_LIMIT + 100, \
            err[:2000]
    assert commands == [], "a wheel was commanded"


CLI_FILE_COMMANDS = {
    "run-config": (lambda f: ["run", "--config", str(f), "--map", str(ARENA_YAML)], ROBOT_DATA, "robot.yaml"),
    "run-path": (lambda f: ["run", "--config", str(ROBOT_YAML), "--path", str(f)], PATH_DATA, "path.yaml"),
    "sim-path": (lambda f: ["sim", "--path", str(f), "--runs", "1"], PATH_DATA, "path.yaml"),
    "sim-robot": (lambda f: ["sim", "--path", str(PATH_YAML), "--robot", str(f), "--runs", "1"], ROBOT_DATA, "r.yaml"),
    "visible-map": (lambda f: ["visible", "--map", str(f), "--pose", "0.5", "0.5", "0"], ARENA_DATA, "map.yaml"),
    "map-info": (lambda f: ["map", "info", str(f)], ARENA_DATA, "map.yaml"),
    "map-check": (lambda f: ["map", "check", str(f)], ARENA_DATA, "map.yaml"),
}


@pytest.mark.parametrize("name", sorted(CLI_FILE_COMMANDS))
def test_commands_taking_yaml_files(scratch, no_motion, name):
    argv_for, base, filename = CLI_FILE_COMMANDS[name]

    @FUZZ_CLI
    @given(text=yaml_text_from(base))
    def check(text):
        f = write(scratch, filename, text)
        assert_cli_contract(*run_cli(argv_for(f)), no_motion)

    check()


def test_a_key_holding_a_line_break_is_quoted_on_one_line(scratch, no_motion):
    """Found by the long fuzz run: an unknown key "\\r" split the error into two lines."""
    f = write(scratch, "map.yaml", '"\\r":\n0:\nplanes:')
    rc, err = run_cli(["visible", "--map", str(f), "--pose", "0.5", "0.5", "0"])
    assert rc == 2 and "unknown key(s): '\\r', 0" in err, err
    assert_cli_contract(rc, err, no_motion)


@FUZZ_CLI
@given(data=st.one_of(snapshot_bytes(), st.binary(max_size=512)))
def test_localize_command(scratch, no_motion, data):
    f = write(scratch, "cli.npz", data)
    assert_cli_contract(*run_cli(["localize", "--init", "0.5", "0.5", "0", str(f)]), no_motion)


@settings(FUZZ, max_examples=max(CLI_EXAMPLES, LOADER_EXAMPLES // 4))
@given(data=st.data())
def test_replay_command(scratch, recorded, no_motion, data):
    """The replay itself trusts each message's fields; the command turns a message that does not
    hold them into one line (robot.cli.replay)."""
    path = scratch / "cli.mcap"
    write_mcap(path, data.draw(hostile_recording(recorded)))
    assert_cli_contract(*run_cli(["replay", str(path)]), no_motion)


@pytest.mark.skipif(importlib.util.find_spec("ifcopenshell") is None, reason="ifcopenshell not installed")
@FUZZ_CLI
@given(data=st.data())
def test_import_ifc_command(scratch, no_motion, data):
    content = data.draw(mutated_bytes(_room_ifc().encode()))
    f = write(scratch, "cli.ifc", content)
    out = scratch / "cli-map.yaml"
    storey = ["--storey", "Level 0", "--out", str(out)] if data.draw(st.booleans()) else []  # import, or list
    assert_cli_contract(*run_cli(["map", "import-ifc", str(f), *storey]), no_motion)


# ------------------------------------------------------------------ the commands, as processes

def robotctl(*argv: str, timeout: float = HANG_GUARD) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robot.cli.main", *argv], capture_output=True, text=True,
                          timeout=timeout, cwd=str(ROOT))


def hostile_files(tmp: Path):
    fifo = tmp / "fifo.yaml"
    os.mkfifo(str(fifo))
    bomb = write(tmp, "bomb.yaml", alias_bomb(9, 9))
    deep = write(tmp, "deep.yaml", "[" * 20_000 + "]" * 20_000)
    cut = tmp / "cut.mcap"
    return fifo, bomb, deep, cut


@pytest.mark.parametrize("case", ["fifo-config", "dev-zero-map", "alias-bomb-robot", "deep-map", "cut-mcap",
                                  "directory-snapshot", "zip-bomb-snapshot", "cut-ifc"])
def test_real_processes_exit_2_with_one_line(tmp_path, case, app_recording):
    fifo, bomb, deep, cut = hostile_files(tmp_path)
    if case == "fifo-config":
        argv = ["run", "--config", str(fifo)]
    elif case == "dev-zero-map":
        argv = ["map", "info", "/dev/zero"]
    elif case == "alias-bomb-robot":
        argv = ["sim", "--path", str(PATH_YAML), "--robot", str(bomb), "--runs", "1"]
    elif case == "deep-map":
        argv = ["visible", "--map", str(deep), "--pose", "0.5", "0.5", "0"]
    elif case == "cut-mcap":
        cut.write_bytes(app_recording.read_bytes()[:10])
        argv = ["replay", str(cut)]
    elif case == "directory-snapshot":
        argv = ["localize", "--init", "0.5", "0.5", "0", str(tmp_path)]
    elif case == "zip-bomb-snapshot":
        big = tmp_path / "bomb.npz"
        with zipfile.ZipFile(big, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("depth.npy", b"\0" * (80 << 20))  # more than a depth frame can unpack to
        argv = ["localize", "--init", "0.5", "0.5", "0", str(big)]
    else:
        if importlib.util.find_spec("ifcopenshell") is None:
            pytest.skip("ifcopenshell not installed")
        text = _room_ifc()
        half = write(tmp_path, "half.ifc", text[:len(text) // 2])
        argv = ["map", "import-ifc", str(half), "--storey", "Level 0"]
    p = robotctl(*argv)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, (p.returncode, p.stderr[-3000:])
    assert lines[0].startswith("robotctl ") and len(lines[0]) <= MESSAGE_LIMIT + 100
