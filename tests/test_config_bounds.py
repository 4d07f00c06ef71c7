"""Bounded configuration and hostile files: every number has a physical range, every file is
opened as a regular file of bounded size, YAML is parsed with bounds, and each refusal is one
short error naming the file, the key and the range.

The hostile values are the ones that got through before: a link or watchdog timeout of 1e308 s
(safety off in effect), a control rate of 1e308 Hz (the run hangs), a wheel speed of 1e308
(OverflowError in the simulator), a pixel stride of 0, a camera 1e11 pixels wide.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib.util
import math
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from robot.base import files
from robot.base.errors import ConfigError, InputError, RobotError
from robot.cli.main import main as cli_main
from robot.config import load_robot_config, parse_robot_config
from robot.config.ranges import field_range
from robot.config.realsense import RealSenseConfig
from robot.config.schema import MAX_ALIAS_NODES, MAX_YAML_DEPTH, load_yaml_file, parse_yaml
from robot.config.sections import (
    CameraConfig,
    ChassisConfig,
    ControlConfig,
    FilterConfig,
    HealthConfig,
    LocalizerConfig,
    QualityConfig,
)
from robot.control.path_file import StartPose, Waypoint, load_path, parse_path
from robot.maps.plane_map import load_plane_map, parse_plane_map

ROOT = Path(__file__).resolve().parents[1]
ROBOT_YAML = ROOT / "config" / "robot.yaml"
ARENA = ROOT / "config" / "maps" / "paper_arena.yaml"
PATH = ROOT / "config" / "paths" / "paper_4_3.yaml"
SECTIONS = {"chassis": ChassisConfig, "localizer": LocalizerConfig, "control": ControlConfig, "health": HealthConfig,
            "fusion": FilterConfig, "quality": QualityConfig}
MESSAGE_LIMIT = 400  # characters: a refusal is one readable line, never the rejected document


def robot_data():
    return yaml.safe_load(ROBOT_YAML.read_text())


def refusal(fn, *args, kind=RobotError) -> str:
    with pytest.raises(kind) as e:
        fn(*args)
    msg = str(e.value)
    assert "\n" not in msg and len(msg) <= MESSAGE_LIMIT, msg
    return msg


# ------------------------------------------------------------------ every number has a range

NUMERIC_CLASSES = [CameraConfig, RealSenseConfig, *SECTIONS.values(), Waypoint, StartPose]


@pytest.mark.parametrize("cls", NUMERIC_CLASSES, ids=lambda c: c.__name__)
def test_every_number_has_a_finite_documented_range_holding_its_default(cls):
    for f in dataclasses.fields(cls):
        if f.type not in ("float", "int", "Optional[float]", "Tuple[float, float, float]") and f.type not in (float, int):
            continue
        rng = field_range(f)
        assert rng is not None, f"{cls.__name__}.{f.name} has no declared range"
        assert math.isfinite(rng.lo) and math.isfinite(rng.hi) and rng.lo < rng.hi, (cls.__name__, f.name)
        assert f.metadata.get("doc"), f"{cls.__name__}.{f.name} has no meaning in the docs"
        if f.default is not dataclasses.MISSING and f.default is not None:
            assert rng.problem(f.default) is None, (cls.__name__, f.name, f.default)


def test_the_shipped_config_and_files_load():
    robot = load_robot_config(ROBOT_YAML)
    assert robot.control.rate == 50.0 and robot.cameras[0].width == 848
    assert len(load_plane_map(ARENA)) > 0 and load_path(PATH).start is not None


# ------------------------------------------------------------------ the values that got through before

@pytest.mark.parametrize("section, key, value, allowed", [
    ("chassis", "link_timeout", 1e308, "[0.02, 0.5] s"),
    ("chassis", "watchdog_timeout", 1e308, "[0.05, 0.5] s"),
    ("control", "rate", 1e308, "[10.0, 200.0] Hz"),
    ("chassis", "max_wheel_speed", 1e308, "(0.0, 50.0] rad/s"),
    ("localizer", "pixel_stride", 0, "[1, 64] px"),
    ("health", "stop_after", 1e9, "[0.1, 30.0] s"),
    ("health", "max_command_age", 60.0, "[0.01, 0.5] s"),
    ("fusion", "max_events", 10**12, "[10, 1000000]"),
])
def test_safety_and_resource_values_out_of_range_are_one_error_naming_file_key_and_range(section, key, value, allowed):
    data = robot_data()
    data[section] = {key: value}
    msg = refusal(parse_robot_config, data, "robot.yaml", kind=ConfigError)
    assert msg.startswith(f"robot.yaml: {section}: '{key}' must be ") and f"allowed: {allowed}" in msg


@pytest.mark.parametrize("key, value, expect", [
    ("width", 10**11, "'width' must be <= 1920 px (allowed: [16, 1920] px)"),
    ("height", 4, "'height' must be >= 16 px"),
    ("fps", 0, "'fps' must be >= 1.0 Hz"),
    ("fps", float("nan"), "'fps' must be finite"),
    ("hfov_deg", "wide", "'hfov_deg' must be a number, got 'wide'"),
    ("width", 848.5, "'width' must be an integer"),
])
def test_camera_values_out_of_range(key, value, expect):
    data = robot_data()
    data["cameras"][0][key] = value
    msg = refusal(parse_robot_config, data, "robot.yaml", kind=ConfigError)
    assert "robot.yaml: cameras[0]: " in msg and expect in msg


def test_camera_mount_and_count_are_bounded():
    data = robot_data()
    data["cameras"][0]["mount"]["xyz"] = [0.1, 1e300, 0.1]
    assert "'xyz[1]' must be <= 2.0 m" in refusal(parse_robot_config, data, "r.yaml")
    data = robot_data()
    data["cameras"] = [dict(data["cameras"][0], name=f"c{i}") for i in range(9)]
    assert "at most 8 are supported" in refusal(parse_robot_config, data, "r.yaml")


@pytest.mark.parametrize("section", sorted(SECTIONS))
def test_each_key_is_refused_just_outside_its_range_and_taken_at_its_ends(section):
    cls = SECTIONS[section]
    for f in dataclasses.fields(cls):
        rng = field_range(f)
        if rng is None:
            continue
        step = 1 if rng.integer else max(1e-9, 1e-6 * (rng.hi - rng.lo))
        for bad in (rng.lo - step, rng.hi + step, rng.hi * 1e6 + 1, -1e308):
            if rng.lo <= bad <= rng.hi:
                continue
            data = robot_data()
            data[section] = {f.name: int(bad) if rng.integer and abs(bad) < 1e18 else bad}
            msg = refusal(parse_robot_config, data, "robot.yaml", kind=ConfigError)
            assert f"robot.yaml: {section}: '{f.name}'" in msg and rng.describe() in msg, msg
        for good in ([] if rng.lo_open else [rng.lo]) + ([] if rng.hi_open else [rng.hi]):
            data = robot_data()
            data[section] = {f.name: int(good) if rng.integer else good}
            try:
                parse_robot_config(data, "robot.yaml")
            except ConfigError as e:  # only a rule across keys may refuse a value at its own range's end
                assert "must" in str(e) and f"'{f.name}'" in str(e) or "control period" in str(e), str(e)


def test_realsense_values_out_of_range():
    data = robot_data()
    data["cameras"][0]["realsense"] = {"laser_power": 1e308}
    assert "'laser_power' must be <= 360.0 mW" in refusal(parse_robot_config, data, "robot.yaml")
    data["cameras"][0]["realsense"] = {"gyro_fps": 0}
    assert "'gyro_fps' must be >= 1 Hz" in refusal(parse_robot_config, data, "robot.yaml")


def test_rules_across_sections():
    data = robot_data()
    data["control"] = {"rate": 10.0}
    data["chassis"] = {"watchdog_timeout": 0.1}
    assert "must cover at least two control periods" in refusal(parse_robot_config, data, "robot.yaml")
    data = robot_data()
    data["health"] = {"slow_after": 5.0, "stop_after": 2.0}
    assert "'slow_after' (5.0 s) must not be after 'stop_after'" in refusal(parse_robot_config, data, "robot.yaml")
    data = robot_data()
    data["localizer"] = {"min_range": 5.0, "max_range": 4.0}
    assert "'min_range' (5.0 m) must be below 'max_range'" in refusal(parse_robot_config, data, "robot.yaml")


def test_configs_built_in_code_are_checked_too():
    for build, text in ((lambda: ControlConfig(rate=1e308), "control: 'rate'"),
                        (lambda: ChassisConfig(link_timeout=math.inf), "chassis: 'link_timeout' must be finite"),
                        (lambda: LocalizerConfig(pixel_stride=0), "localizer: 'pixel_stride'"),
                        (lambda: FilterConfig(gyro_mode="both"), "fusion: 'gyro_mode' must be one of"),
                        (lambda: CameraConfig("c", 10**11, 480, 30.0, 87.0, 58.0, (0, 0, 0), (0, 0, 0)),
                         "camera 'c': 'width'")):
        with pytest.raises(ConfigError, match=text.replace("(", r"\(")):
            build()
    with pytest.raises(ConfigError, match="realsense: 'decimation' must be 1 \\(off\\) to 8"):
        RealSenseConfig(decimation=9).validate()


# ------------------------------------------------------------------ path files and maps

@pytest.mark.parametrize("text, expect", [
    ("waypoints: [{x: 1e308, y: 0}]", "waypoints[0]: 'x' must be <= 1000.0 m"),
    ("start: {x: -2000, y: 0}\nwaypoints: [{x: 0, y: 0}]", "start: 'x' must be >= -1000.0 m"),
    ("waypoints: [{x: 0, y: 0, dwell: 1e308}]", "'dwell' must be <= 3600.0 s"),
    ("waypoints: [{x: 0, y: 0, speed: 1e-4}]", None),  # 1e-4 is a number (YAML 1.1 says a string)
    ("waypoints: [{x: 0, y: 0, speed: 1E5}]", "'speed' must be <= 2.0 m/s"),
])
def test_path_values_are_bounded(tmp_path, text, expect):
    p = tmp_path / "path.yaml"
    p.write_text(text + "\n")
    if expect is None:
        assert load_path(p).waypoints[0].speed == pytest.approx(1e-4)
    else:
        msg = refusal(load_path, p, kind=ConfigError)
        assert str(p) in msg and expect in msg


def test_path_waypoint_count_is_bounded():
    data = {"waypoints": [{"x": 0.0, "y": 0.0}] * 10_001}
    assert "at most 10000 are allowed" in refusal(parse_path, data, "p.yaml")


def test_map_coordinates_and_counts_are_bounded():
    square = [[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]]
    far = [[1e308, 0, 0], [1, 0, 0], [1, 0, 1]]
    msg = refusal(parse_plane_map, {"planes": [{"id": "w", "vertices": far}]}, "m.yaml", kind=ConfigError)
    assert "m.yaml: plane 'w': polygon 0 vertex 0: a coordinate must be <= 1000.0 m" in msg
    msg = refusal(parse_plane_map, {"planes": [{"id": "x" * 10_000, "vertices": square}]}, "m.yaml")
    assert "'id' must be at most 200 characters" in msg
    msg = refusal(parse_plane_map, {"planes": [{"id": "w", "polygons": [square] * 1001}]}, "m.yaml")
    assert "at most 1000 are allowed per plane" in msg


# ------------------------------------------------------------------ YAML bounds

def alias_bomb(levels: int = 9, width: int = 9) -> str:
    lines = ["a0: &a0 [" + ", ".join(["lol"] * width) + "]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * width) + "]")
    return "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_before_it_expands():
    text = alias_bomb()
    assert len(text) < 1500  # 9^9 = 387 million strings once expanded
    msg = refusal(parse_yaml, text, "bomb.yaml", kind=ConfigError)
    assert f"aliases expand the document by more than {MAX_ALIAS_NODES} nodes" in msg
    assert parse_yaml(alias_bomb(levels=3, width=4), "small.yaml")["a2"][0][0] == ["lol"] * 4  # ordinary aliases work


def test_deep_nesting_and_recursive_aliases_are_refused():
    assert f"nested deeper than {MAX_YAML_DEPTH} levels" in refusal(parse_yaml, "[" * 20_000 + "]" * 20_000, "d.yaml")
    assert "recursive aliases are not allowed" in refusal(parse_yaml, "a: &x [1, *x]\n", "r.yaml")
    assert parse_yaml("[" * (MAX_YAML_DEPTH - 1) + "]" * (MAX_YAML_DEPTH - 1)) is not None


def test_yaml_numbers_in_exponent_form_are_numbers():
    doc = parse_yaml("a: 1e-4\nb: 1E5\nc: -2.5e3\nd: .5\ne: '1e-4'\nf: 1e\ng: 12e\n")
    assert doc == {"a": 1e-4, "b": 1e5, "c": -2500.0, "d": 0.5, "e": "1e-4", "f": "1e", "g": "12e"}


def test_messages_quote_a_short_excerpt_of_a_bad_value():
    data = robot_data()
    data["control"] = {"rate": "x" * 2_000_000}
    msg = refusal(parse_robot_config, data, "robot.yaml")
    assert "'rate' must be a number, got 'xxxx" in msg and len(msg) < 200
    data["control"] = {"r" * 5000: 1}
    assert len(refusal(parse_robot_config, data, "robot.yaml")) < 200


def test_constructor_errors_are_malformed_yaml_not_tracebacks():
    for text in ("a: 2024-13-45\n", "a: " + "9" * 5000 + "\n", "{[1]: 2}\n", "\x00\n", "!!python/object:os.system x\n"):
        assert "malformed YAML" in refusal(parse_yaml, text, "x.yaml", kind=ConfigError)


# ------------------------------------------------------------------ files

def in_thread(fn, *args, hang_guard: float = 60.0):
    """Run fn in a thread; the timeout only turns a hang into a failure instead of a stuck suite."""
    out = {}

    def target():
        try:
            out["value"] = fn(*args)
        except BaseException as e:  # noqa: B902 (the test inspects it)
            out["error"] = e

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(hang_guard)
    assert not t.is_alive(), f"{fn.__name__} blocked on {args}"
    return out


@pytest.mark.parametrize("loader, kind", [
    (load_robot_config, ConfigError), (load_path, ConfigError), (load_plane_map, ConfigError),
    (lambda p: __import__("robot.recording.snapshot", fromlist=["x"]).load_snapshot(p), InputError),
], ids=["robot-config", "path", "map", "snapshot"])
def test_a_fifo_is_refused_at_once_and_never_read(tmp_path, loader, kind):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(str(fifo))
    out = in_thread(loader, fifo)
    assert isinstance(out.get("error"), kind), out
    assert "is a FIFO (named pipe), not a regular file" in str(out["error"])


def test_devices_and_directories_are_refused(tmp_path):
    assert "is a character device" in refusal(load_yaml_file, "/dev/zero", kind=ConfigError)
    assert "is a directory" in refusal(load_robot_config, tmp_path, kind=ConfigError)
    assert "file not found" in refusal(load_plane_map, tmp_path / "none.yaml", kind=ConfigError)


def test_each_kind_of_file_has_a_size_limit(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"# " + b"x" * files.CONFIG.max_bytes + b"\n")
    assert "larger than the 1.0 MiB limit for config files" in refusal(load_robot_config, big)
    assert "limit for path files" in refusal(load_path, big)
    assert load_yaml_file(big, files.MAP) is None  # a comment: within the map's 64 MiB
    assert files.CONFIG.max_bytes < files.MAP.max_bytes < files.SNAPSHOT.max_bytes < files.RECORDING.max_bytes


def test_text_that_is_not_utf8_is_refused(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes(b"name: caf\xe9\n")
    assert "not UTF-8 text (byte 9 is 0xe9)" in refusal(load_robot_config, p, kind=ConfigError)


def test_output_paths_are_checked_before_work_starts(tmp_path):
    assert files.check_writable_file(tmp_path / "out.mcap", "--record") == tmp_path / "out.mcap"
    assert "is a directory, give a file name" in refusal(files.check_writable_file, tmp_path, "--record")
    assert "does not exist" in refusal(files.check_writable_file, tmp_path / "no" / "x.mcap", "--record")
    assert "not a directory" in refusal(files.check_writable_directory, tmp_path / "none", "--record")
    assert not list(tmp_path.glob(".robotctl-write-test-*"))  # the probe file is gone again


@pytest.mark.parametrize("call, err, expect", [
    ("mkstemp", 30, "cannot write there (read-only file system)"),  # EROFS: a read-only mount
    ("write", 28, "cannot write there (No space left on device)"),  # ENOSPC: takes the name, not the data
])
def test_read_only_or_full_places_are_refused(tmp_path, monkeypatch, call, err, expect):
    def fail(*args, **kwargs):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(files.tempfile if call == "mkstemp" else files.os, call, fail)
    assert expect in refusal(files.check_writable_file, tmp_path / "run.mcap", "--record")


def test_sim_record_into_a_directory_exits_2_before_the_run(tmp_path):
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "sim", "--realtime", "--path", str(PATH),
                        "--record", str(tmp_path)], capture_output=True, text=True, timeout=120, cwd=str(ROOT))
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "--record" in lines[0] and "is a directory" in lines[0] and "Traceback" not in p.stderr


def test_snapshot_archives_are_bounded(tmp_path):
    from robot.recording.snapshot import MAX_MEMBER_BYTES, load_snapshot

    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    bomb = tmp_path / "bomb.npz"  # 128 MiB of zeros, a few hundred kB compressed
    np.savez_compressed(bomb, depth=np.zeros((8192, 8192), np.uint16), depth_scale=0.001, K=K, camera="front")
    assert bomb.stat().st_size < MAX_MEMBER_BYTES
    assert "unpacks to 128.0 MiB" in refusal(load_snapshot, bomb, kind=InputError)
    plain = tmp_path / "plain.npz"
    np.save(plain, np.zeros((4, 4)))  # numpy adds .npy: a plain array, not an archive
    os.replace(str(plain) + ".npy", plain)
    assert "not a zip archive" in refusal(load_snapshot, plain, kind=InputError)
    wide = tmp_path / "wide.npz"
    np.savez_compressed(wide, depth=np.zeros((16, 4000), np.uint16), depth_scale=0.001, K=K, camera="front")
    assert "larger than a camera's 1920x1080" in refusal(load_snapshot, wide, kind=InputError)
    # Found by the long fuzz run: a member whose central-directory entry "needs" zip version 6.4,
    # which Python's zipfile does not implement (it raised NotImplementedError).
    future = tmp_path / "future.npz"
    np.savez_compressed(future, depth=np.zeros((16, 16), np.uint16), depth_scale=0.001, K=K, camera="front")
    data = bytearray(future.read_bytes())
    at = data.index(b"PK\x01\x02")  # the first central-directory entry; extract version at +6
    data[at + 6:at + 8] = (64).to_bytes(2, "little")
    future.write_bytes(bytes(data))
    assert "not a readable .npz snapshot (NotImplementedError: zip file version 6.4" in refusal(
        load_snapshot, future, kind=InputError)


# ------------------------------------------------------------------ recordings and IFC models

@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    pytest.importorskip("mcap")
    from robot.base.samples import DepthFrame
    from robot.recording.recorder import Recorder

    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    rng = np.random.default_rng(1)  # noisy depth: PNG cannot shrink it, so the file spans several chunks
    with Recorder(str(path), chunk_bytes=16 * 1024) as rec:
        rec.write_config(0.0, ROBOT_YAML.read_text(), ARENA.read_text())
        for i in range(100):
            rec.write_odometry(i * 0.01, {"t": i * 0.01, "angles": [0.0] * 4, "speeds": [0.0] * 4})
            if i % 10 == 0:
                depth = rng.integers(500, 3000, (60, 80)).astype(np.uint16)
                rec.write_depth(i * 0.01, DepthFrame("front", depth, 0.001, np.eye(3)))
    assert path.stat().st_size > 64 * 1024
    return path


def test_an_mcap_cut_after_10_bytes_is_one_clear_error(tmp_path, small_recording):
    from robot.recording.reader import RecordingReader

    cut = tmp_path / "cut.mcap"
    cut.write_bytes(small_recording.read_bytes()[:10])
    msg = refusal(lambda: list(RecordingReader(cut).messages()), kind=InputError)
    assert msg == f"{cut}: cut short at byte 10, before its first complete message: nothing to read"


def test_a_recording_cut_in_the_middle_yields_what_is_intact(tmp_path, small_recording, caplog):
    from robot.recording.reader import RecordingReader

    data = small_recording.read_bytes()
    full = len(list(RecordingReader(small_recording).messages()))
    cut = tmp_path / "half.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    reader = RecordingReader(cut)
    got = list(reader.messages())
    assert 0 < len(got) < full and reader.truncated == [cut]
    assert any(f"ends early at byte {len(data) * 2 // 3}" in r.getMessage() for r in caplog.records)


def test_a_corrupt_recording_is_one_error_naming_the_byte(tmp_path, small_recording):
    from robot.recording.reader import RecordingReader

    data = bytearray(small_recording.read_bytes())
    data[200:260] = b"\xff" * 60  # inside the first chunk: its CRC no longer matches
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    msg = refusal(lambda: list(RecordingReader(bad).messages()), kind=InputError)
    assert str(bad) in msg and "corrupt recording at byte" in msg


needs_ifc = pytest.mark.skipif(importlib.util.find_spec("ifcopenshell") is None, reason="ifcopenshell not installed")

MINIMAL_IFC = """ISO-10303-21;
HEADER;
FILE_DESCRIPTION(('ViewDefinition [CoordinationView]'),'2;1');
FILE_NAME('x.ifc','2024-01-01T00:00:00',(''),(''),'','test','');
FILE_SCHEMA(('IFC4'));
ENDSEC;
DATA;
#1=IFCPROJECT('0YvctVUKr0kugbFTf53O9L',$,'p',$,$,$,$,$,$);
ENDSEC;
END-ISO-10303-21;
"""


@needs_ifc
def test_an_ifc_file_cut_in_half_is_refused(tmp_path):
    from robot.maps.ifc_import import open_model

    whole = tmp_path / "whole.ifc"
    whole.write_text(MINIMAL_IFC)
    assert open_model(whole).schema == "IFC4"
    half = tmp_path / "half.ifc"
    half.write_text(MINIMAL_IFC[:len(MINIMAL_IFC) // 2])
    assert "the IFC file is cut short" in refusal(open_model, half, kind=ConfigError)
    assert "is a directory" in refusal(open_model, tmp_path, kind=ConfigError)


# ------------------------------------------------------------------ command-line numbers

@pytest.mark.parametrize("argv, option", [
    (["map", "import-ifc", "x.ifc", "--storey", "L0", "--threads", "0"], "--threads"),
    (["sim", "--path", str(PATH), "--workers", "0"], "--workers"),
    (["sim", "--path", str(PATH), "--runs", "1000000"], "--runs"),
    (["sim", "--path", str(PATH), "--vision-rate", "1e308"], "--vision-rate"),
    (["sim", "--path", str(PATH), "--vision-rate", "nan"], "--vision-rate"),
    (["chassis", "--duration", "inf"], "--duration"),
    (["teleop", "--sim", "--deadman", "1e9"], "--deadman"),
    (["run", "--live", "70000"], "--live"),
    (["render", "--pose", "0", "0", "0", "--camera", "front", "--out", "x.npz", "--seed", "-1"], "--seed"),
])
def test_numeric_options_out_of_range_are_one_line_and_exit_2(capsys, argv, option):
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and "must be" in err, err


def test_poses_on_the_command_line_are_bounded(capsys):
    assert cli_main(["visible", "--pose", "1e308", "0", "0"]) == 2
    assert "x and y must be within +-1000 m" in capsys.readouterr().err
    assert cli_main(["visible", "--pose", "0.5", "0.5", "90"]) == 2
    assert "heading is in radians" in capsys.readouterr().err


def test_docs_configuration_md_is_generated_from_the_declared_ranges():
    spec = importlib.util.spec_from_file_location("gen_config_doc", ROOT / "scripts" / "gen_config_doc.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    text = gen.render()
    current = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert current == text, "docs/configuration.md is out of date: run python scripts/gen_config_doc.py --write"
    for section in SECTIONS:
        assert f"### `{section}:`" in text
    assert "| `link_timeout` | `0.1` | [0.02, 0.5] s |" in text
    assert "| `robotctl map import-ifc` | `--threads` | [1, 64] |" in text


def test_the_robot_config_deep_copies_are_still_refused_after_a_roundtrip():
    # parse(effective config dict) is how a recording's config is read back: the same checks apply
    from robot.config.dump import effective_config_dict

    robot = load_robot_config(ROBOT_YAML)
    data = copy.deepcopy(effective_config_dict(robot))
    assert parse_robot_config(data, str(ROBOT_YAML)) == robot
    data["control"]["rate"] = 1e308
    assert "'rate' must be <= 200.0 Hz" in refusal(parse_robot_config, data, "rec.mcap:/config")
