"""MCAP recording: round trip, rotation, disk budget, and stopping cleanly when the disk fills."""

from __future__ import annotations

import base64
import errno
import inspect
import io
import logging
import math
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")

from mcap.reader import NonSeekingReader, make_reader  # noqa: E402

from robot.base.errors import ConfigError, InputError  # noqa: E402
from robot.base.samples import DepthFrame  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.config.dump import effective_config_dict  # noqa: E402
from robot.localization.localizer import PlaneReport  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402
from robot.recording import schema as ms  # noqa: E402
from robot.recording.reader import RecordingReader, read_recording, recording_segments  # noqa: E402
from robot.recording.recorder import BackgroundRecorder, NullRecorder, Recorder  # noqa: E402

MiB = 1024 * 1024
ROOT = Path(__file__).resolve().parents[1]
CONFIG_YAML = "cameras:\n  - name: front\n    width: 848\n"
MAP_YAML = "planes:\n  - id: wall_n\n    vertices: [[0, 1.5, 0], [1.5, 1.5, 0], [1.5, 1.5, 0.3]]\n"
OFFSET_NS = 1_700_000_000_123_456_789  # wall clock minus monotonic clock, fixed for the tests


@pytest.fixture(autouse=True)
def fixed_wall_clock():
    old = ms.set_wall_clock(ms.WallClock(offset_ns=OFFSET_NS))
    yield
    ms.set_wall_clock(old)


def wall_depth(rng, width=848, height=480, z0=1.8, tilt=0.4, depth_scale=0.001):
    """A D435i-like frame of a tilted wall: stereo noise growing with z^2, ~3 % dropouts."""
    f = 0.5 * width / math.tan(math.radians(87) / 2)
    u = (np.arange(width) - (width - 1) / 2.0) / f
    z = z0 / (1.0 - tilt * u)[None, :] * np.ones((height, 1))
    z += rng.normal(0.0, 1.0, z.shape) * z ** 2 * 0.08 / (f * 0.050)
    depth = np.round(z / depth_scale).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.03] = 0
    K = np.array([[f, 0, (width - 1) / 2.0], [0, f, (height - 1) / 2.0], [0, 0, 1.0]])
    return depth, K


def frame(rng, camera, i, **kw):
    depth, K = wall_depth(rng, **kw)
    return DepthFrame(camera=camera, depth=depth, depth_scale=0.001, K=K,
                      t_capture=10.0 + i / 30 - 0.004, frame_number=1000 + i,
                      timestamp_domain="global_time", truth=(0.5, 0.5 + 0.01 * i, math.pi))


def unlimited(path, **kw):
    return Recorder(str(path), max_file_bytes=kw.pop("max_file_bytes", 1 << 40), max_total_bytes=1 << 41,
                    min_free_bytes=0, **kw)


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    frames = [frame(rng, cam, i) for i in range(3) for cam in ("front", "left")]
    cov = np.array([[4e-6, 1e-7, 0.0], [1e-7, 9e-6, 2e-7], [0.0, 2e-7, 1e-5]])
    path = tmp_path / "run.mcap"
    with unlimited(path) as rec:
        assert rec.write_config(10.0, CONFIG_YAML, MAP_YAML, "/etc/robot-controller/robot.yaml", None)
        for i, f in enumerate(frames):
            t = 10.0 + i / 30
            assert rec.write_odometry(t, {"t": t - 0.002, "wheel_speeds": [1.0, -1.0, 1.0, -1.0],
                                          "ticks": [10, -10, 10, -10]})
            assert rec.write_depth(t, f)
            assert rec.write_planes(t, ms.planes_message(t, f.camera, [
                PlaneReport("wall_n", f.camera, np.int64(5321), np.array([0.0, -0.6, 0.8]), -1.8, True, "ok")],
                frame_number=f.frame_number, coarse=(0.5, 0.25, math.pi), coarse_cov=cov))
            assert rec.write_pose(t, 0.5 + i * 1e-3, 0.25, math.pi - 1e-3 * i, cov, quality="degraded",
                                  reason="heading std 1.2 deg > 1.0 deg")
            assert rec.write_cmd(t, ms.cmd_message(t, 0.1, 0.0, 0.0, [0.5, 0.5, 0.5, 0.5], sent=True))
        assert rec.write_status(t, {"state": "running", "text": "localization good"})
    assert rec.stopped_reason is None and not rec.active

    got = list(read_recording(path))
    assert [m.topic for m in got[:6]] == ["/config", "/odometry", "/depth/front", "/planes", "/pose", "/cmd"]
    assert len(got) == 2 + 5 * len(frames)
    assert all(a.log_time_ns <= b.log_time_ns for a, b in zip(got, got[1:]))
    assert got[0].message["robot_config_yaml"] == CONFIG_YAML and got[0].message["map_yaml"] == MAP_YAML

    depth = [m for m in got if m.topic.startswith("/depth/")]
    assert [m.topic for m in depth] == ["/depth/" + f.camera for f in frames]
    for m, f in zip(depth, frames):
        d = m.message
        assert isinstance(d, DepthFrame) and d.depth.dtype == np.uint16
        assert np.array_equal(d.depth, f.depth), "depth must survive bit-exact"
        assert np.array_equal(d.K, f.K) and d.depth_scale == f.depth_scale
        assert (d.camera, d.t_capture, d.frame_number, d.timestamp_domain, d.truth) == \
            (f.camera, f.t_capture, f.frame_number, f.timestamp_domain, f.truth)

    poses = [m.message for m in got if m.topic == "/pose"]
    assert poses[2]["x"] == 0.5 + 2e-3 and poses[2]["phi"] == math.pi - 2e-3  # floats round-trip exactly
    assert np.array_equal(np.array(poses[0]["cov"]).reshape(3, 3), cov) and poses[0]["quality"] == "degraded"
    assert poses[0]["reason"].startswith("heading std")
    q = poses[0]["pose"]["orientation"]
    assert math.isclose(2 * math.atan2(q["z"], q["w"]), poses[0]["phi"])
    planes = [m.message for m in got if m.topic == "/planes"]
    assert planes[0]["planes"][0]["normal"] == [0.0, -0.6, 0.8] and planes[0]["planes"][0]["inliers"] == 5321
    assert planes[0]["frame_number"] == 1000 and np.array_equal(np.reshape(planes[0]["coarse_cov"], (3, 3)), cov)
    cmds = [m.message for m in got if m.topic == "/cmd"]
    assert cmds[0]["wheel_speeds"] == [0.5] * 4 and cmds[0]["sent"] is True and cmds[0]["vx"] == 0.1


def test_file_is_a_finished_mcap_that_foxglove_can_index(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "run.mcap"
    with unlimited(path) as rec:
        rec.write_config(1.0, CONFIG_YAML, MAP_YAML)
        rec.write_depth(1.0, frame(rng, "front", 0, width=212, height=120))
        rec.write_pose(1.0, 0.0, 0.0, 0.0, np.eye(3))
        label = np.zeros((24, 32), np.int32)
        rec.write("/roi/front", 1.0, ms.roi_message(1.0, "front", label))
        rec.write(ms.TOPIC_TF_STATIC, 1.0, ms.transforms_message(1.0, [("base_link", "front_link", np.eye(4))]))
        rec.write(ms.TOPIC_TF, 1.0, ms.odometry_transforms(1.0, (0.1, 0.2, 0.3), (0.0, 0.0, 0.0)))
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 6
        schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert schemas["/depth/front"].name == "foxglove.RawImage"
        assert schemas["/roi/front"].name == "foxglove.CompressedImage"
        assert schemas["/tf"].name == schemas["/tf_static"].name == "foxglove.FrameTransforms"
        assert schemas["/tf"].id != schemas["/tf_static"].id  # one name, two descriptions
        assert schemas["/pose"].name == "foxglove.PoseInFrame"
        first = summary.statistics.message_start_time
        assert first == OFFSET_NS + 1_000_000_000  # log times are wall-clock: Foxglove shows the date
        assert all(s.encoding == "jsonschema" for s in schemas.values())
        assert all(s.data.decode() == ms.schema_text(topic) for topic, s in schemas.items())
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["recording"]["id"] == rec.recording_id and meta["recording"]["segment"] == "0"
    assert meta["recording"]["clock_offset_ns"] == str(OFFSET_NS)


def test_log_time_never_goes_back_and_nan_becomes_null(tmp_path):
    path = tmp_path / "run.mcap"
    with unlimited(path) as rec:
        rec.write_status(5.0, {"state": "a"})
        rec.write_status(4.9, {"state": "late caller"})
        rec.write_pose(5.1, float("nan"), 0.0, 0.0, np.full((3, 3), np.inf))
    got = list(read_recording(path))
    assert [m.log_time_ns - OFFSET_NS for m in got] == [5_000_000_000, 5_000_000_000, 5_100_000_000]
    assert [m.t for m in got] == [5.0, 5.0, 5.1]  # back on the app's monotonic clock
    assert got[1].message["t"] == 4.9
    assert got[2].message["x"] is None and got[2].message["cov"] == [None] * 9


def test_rotation_keeps_each_segment_under_the_limit_and_self_contained(tmp_path):
    rng = np.random.default_rng(3)
    limit = 600 * 1024
    rec = unlimited(tmp_path / "run.mcap", max_file_bytes=limit)
    rec.write_config(0.0, CONFIG_YAML, MAP_YAML)
    n = 24
    for i in range(n):
        rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
        rec.write_pose(i / 30, float(i), 0.0, 0.0, np.eye(3))
    rec.close()
    files = [Path(p) for p in rec.files]
    assert len(files) >= 3 and files[0].name == "run.mcap" and files[1].name == "run_001.mcap"
    for p in files:
        assert p.stat().st_size <= limit, p
        alone = list(read_recording(p, follow_segments=False))
        assert alone[0].topic == "/config", f"{p.name} does not start with the config"
    # Any segment leads to the whole run, in order, with the repeated config given once.
    whole = list(read_recording(files[1]))
    assert recording_segments(files[-1]) == files
    assert [m.topic for m in whole].count("/config") == 1
    assert [m.message["x"] for m in whole if m.topic == "/pose"] == [float(i) for i in range(n)]
    numbers = [m.message.frame_number for m in whole if m.topic == "/depth/front"]
    assert numbers == [1000 + i for i in range(n)]


def test_every_segment_carries_the_effective_config_and_the_map(tmp_path):
    robot = load_robot_config(ROOT / "config" / "robot.yaml")
    arena = load_plane_map(ROOT / "config" / "maps" / "paper_arena.yaml")
    rng = np.random.default_rng(10)
    rec = unlimited(tmp_path / "run.mcap", max_file_bytes=400 * 1024)
    rec.write_config(0.0, CONFIG_YAML, MAP_YAML, effective_config=effective_config_dict(robot, arena.source))
    rec.write(ms.TOPIC_MAP, 0.0, ms.map_message(arena, 0.0))
    for i in range(12):
        rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
    rec.close()
    assert len(rec.files) >= 3
    for p in rec.files:
        alone = RecordingReader(p, follow_segments=False)
        assert [m.topic for m in alone.messages()][:2] == ["/config", "/map"], p
        back = alone.robot_config()
        assert replace(back, source=robot.source) == robot, p
        assert back.map_path == str(ROOT / "config" / "maps" / "paper_arena.yaml")
    whole = list(read_recording(rec.files[0]))
    assert [m.topic for m in whole].count("/map") == 1  # repeated per segment, yielded once
    (m,) = [m.message for m in whole if m.topic == "/map"]
    assert [p["id"] for p in m["planes"]] == [p.id for p in arena.planes]


def test_a_recording_without_or_with_a_stale_effective_config(tmp_path):
    with unlimited(tmp_path / "old.mcap") as rec:
        rec.write_config(0.0, CONFIG_YAML, MAP_YAML)  # as recordings were made before they carried it
    assert RecordingReader(tmp_path / "old.mcap").robot_config() is None
    stale = effective_config_dict(load_robot_config(ROOT / "config" / "robot.yaml"))
    stale["chassis"]["gear_ratio"] = 30  # a key this code does not know (any more)
    with unlimited(tmp_path / "stale.mcap") as rec:
        rec.write_config(0.0, CONFIG_YAML, MAP_YAML, effective_config=stale)
    with pytest.raises(ConfigError, match=r"stale.mcap:/config: chassis: unknown key\(s\): gear_ratio"):
        RecordingReader(tmp_path / "stale.mcap").robot_config()


def test_segments_of_another_run_are_not_mixed_in(tmp_path):
    rng = np.random.default_rng(4)
    for run in range(2):
        with unlimited(tmp_path / "run.mcap", max_file_bytes=300 * 1024) as rec:
            for i in range(6 - 3 * run):  # the second, shorter run overwrites run.mcap only
                rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
    assert (tmp_path / "run_003.mcap").exists()
    assert recording_segments(tmp_path / "run.mcap") == [Path(p) for p in rec.files]


def test_oldest_segments_are_deleted_beyond_the_total_budget(tmp_path):
    rng = np.random.default_rng(5)
    rec = Recorder(str(tmp_path / "rec-{index:03d}.mcap"), max_file_bytes=400 * 1024,
                   max_total_bytes=1300 * 1024, min_free_bytes=0)
    rec.write_config(0.0, CONFIG_YAML, MAP_YAML)
    for i in range(30):
        rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
        rec.write_pose(i / 30, float(i), 0.0, 0.0, np.eye(3))
    rec.close()
    on_disk = sorted(tmp_path.glob("rec-*.mcap"))
    assert [str(p) for p in on_disk] == rec.files
    assert on_disk[0].name != "rec-000.mcap", "nothing was deleted"
    assert sum(p.stat().st_size for p in on_disk) <= 1300 * 1024
    # What is left is the end of the run, still a readable recording with its config.
    got = list(read_recording(on_disk[0]))
    assert got[0].topic == "/config"
    assert [m.message["x"] for m in got if m.topic == "/pose"][-1] == 29.0


class FakeDisk:
    def __init__(self, free):
        self.free = free
        self.asked = []

    def __call__(self, directory):
        self.asked.append(directory)
        return self.free


def test_stops_cleanly_when_free_space_falls_under_the_reserve(tmp_path, caplog):
    rng = np.random.default_rng(6)
    disk = FakeDisk(free=10_000 * MiB)
    path = tmp_path / "run.mcap"
    rec = Recorder(str(path), max_file_bytes=1 << 40, max_total_bytes=1 << 41, min_free_bytes=500 * MiB,
                   chunk_bytes=64 * 1024, free_bytes=disk)
    rec.write_config(0.0, CONFIG_YAML, MAP_YAML)
    written = 0
    with caplog.at_level(logging.WARNING, logger="robot.recording.recorder"):
        for i in range(20):
            if i == 8:
                disk.free = 499 * MiB
            ok = rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
            written += ok
            rec.write_pose(i / 30, float(i), 0.0, 0.0, np.eye(3))
    assert not rec.active and 8 <= written < 20
    assert "under the 500.0 MiB reserve" in rec.stopped_reason
    assert [r.getMessage() for r in caplog.records if r.name == "robot.recording.recorder"] == \
        ["recording stopped: " + rec.stopped_reason]
    assert rec.write_status(1.0, {"state": "x"}) is False
    rec.close()
    # Stopped by our own check: the file was finished properly, summary and all.
    with open(path, "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count >= 1 + written
    got = list(read_recording(path))
    numbers = [m.message.frame_number for m in got if m.topic == "/depth/front"]
    assert numbers == list(range(1000, 1000 + written))


def test_does_not_start_when_the_disk_is_already_full(tmp_path):
    rec = Recorder(str(tmp_path / "run.mcap"), min_free_bytes=500 * MiB, free_bytes=FakeDisk(100 * MiB))
    assert not rec.active and "reserve" in rec.stopped_reason
    assert rec.write_pose(0.0, 0, 0, 0, np.eye(3)) is False
    assert not (tmp_path / "run.mcap").exists()
    rec.close()


class FillingFile(io.FileIO):
    """A file on a disk with ``budget`` bytes left: the write that crosses it lands partly, then ENOSPC.

    ``stays_full``: other writers take any space freed afterwards, so every later write fails too;
    otherwise only that one write fails (space was freed elsewhere meanwhile).
    """

    def __init__(self, path, budget, stays_full):
        super().__init__(path, "wb")
        self.budget = budget
        self.stays_full = stays_full
        self.failed = False

    def write(self, data):
        room = self.budget - self.tell()
        if self.failed and self.stays_full:
            raise OSError(errno.ENOSPC, "No space left on device")
        if len(data) <= room or self.failed:
            return super().write(data)
        self.failed = True
        if room > 0:
            super().write(bytes(data[:room]))
        raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("stays_full", [True, False], ids=["disk-stays-full", "space-freed-later"])
def test_enospc_stops_recording_and_keeps_what_was_written(tmp_path, stays_full):
    rng = np.random.default_rng(7)
    path = tmp_path / "run.mcap"
    frames = [frame(rng, "front", i, width=424, height=240) for i in range(12)]
    rec = Recorder(str(path), max_file_bytes=1 << 40, max_total_bytes=1 << 41, min_free_bytes=0,
                   chunk_bytes=64 * 1024, opener=lambda p: FillingFile(p, 1_500_000, stays_full))
    rec.write_config(0.0, CONFIG_YAML, MAP_YAML)
    results = [rec.write_depth(i / 30, f) for i, f in enumerate(frames)]  # must not raise
    assert not rec.active and "No space left on device" in rec.stopped_reason
    assert results[0] and not results[-1]
    rec.close()

    reader = RecordingReader(path)
    got = list(reader.messages())
    assert got[0].topic == "/config"
    depth = [m.message for m in got if m.topic == "/depth/front"]
    assert 1 <= len(depth) < len(frames)
    for d, f in zip(depth, frames):  # a prefix of the run, bit-exact
        assert np.array_equal(d.depth, f.depth) and d.frame_number == f.frame_number
    assert path.stat().st_size <= 1_500_000
    if stays_full:
        assert reader.truncated == [path]  # no room even for a footer: ends at its last whole chunk
    else:
        assert reader.truncated == []  # closed with DataEnd + Footer: a valid MCAP for any tool
        # mcap's own strict sequential reader raises unless the footer and magic are there.
        with open(path, "rb") as f:
            assert sum(1 for _ in NonSeekingReader(f).iter_messages(log_time_order=False)) == len(got)


def test_truncated_file_reads_up_to_the_last_chunk(tmp_path):
    rng = np.random.default_rng(8)
    path = tmp_path / "run.mcap"
    with unlimited(path, chunk_bytes=64 * 1024) as rec:
        for i in range(6):
            rec.write_depth(i / 30, frame(rng, "front", i, width=424, height=240))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # as if the power went off
    reader = RecordingReader(cut)
    got = list(reader.messages())
    assert reader.truncated == [cut] and 1 <= len(got) < 6


def test_reader_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="no such recording"):
        list(read_recording(tmp_path / "missing.mcap"))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"PK\x03\x04 this is a zip, not a recording" * 10)
    with pytest.raises(InputError, match="junk.mcap: not an MCAP file"):
        list(read_recording(junk))


def test_bad_messages_are_bugs_not_disk_trouble(tmp_path):
    with unlimited(tmp_path / "run.mcap") as rec:
        with pytest.raises(ValueError, match="vy"):
            rec.write_cmd(0.0, {"vx": 0.1})
        bad = DepthFrame("front", np.zeros((4, 4), np.float32), 0.001, np.eye(3))
        with pytest.raises(ValueError, match="uint16"):
            rec.write_depth(0.0, bad)
        with pytest.raises(ValueError, match="3x3"):
            rec.write_pose(0.0, 0, 0, 0, np.eye(2))
        with pytest.raises(ValueError, match="no schema"):
            rec.write("/unknown", 0.0, {})
        assert rec.active


def test_config_errors(tmp_path, monkeypatch):
    with pytest.raises(ConfigError, match="only {start} and {index}"):
        Recorder(str(tmp_path / "run-{date}.mcap"))
    with pytest.raises(ConfigError, match="compression"):
        Recorder(str(tmp_path / "run.mcap"), compression="gzip")
    monkeypatch.setitem(sys.modules, "mcap.writer", None)
    with pytest.raises(ConfigError, match="pip install"):
        Recorder(str(tmp_path / "run.mcap"))


def test_unwritable_directory_stops_instead_of_raising(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    rec = Recorder(str(blocker / "run.mcap"), min_free_bytes=0)
    assert not rec.active and "cannot open" in rec.stopped_reason
    assert rec.write_status(0.0, {"state": "x"}) is False


def test_null_recorder_has_the_recorder_interface():
    public = {n for n, v in inspect.getmembers(Recorder) if not n.startswith("_") and callable(v)}
    null = NullRecorder()
    for name in public:
        ours = inspect.signature(getattr(Recorder, name))
        theirs = inspect.signature(getattr(NullRecorder, name))
        assert list(ours.parameters) == list(theirs.parameters), name
    assert null.write_depth(0.0, None) is False and null.stopped_reason is None and not null.active


def test_background_recorder_writes_in_order(tmp_path):
    rng = np.random.default_rng(9)
    path = tmp_path / "run.mcap"
    frames = [frame(rng, "front", i, width=212, height=120) for i in range(5)]
    with BackgroundRecorder(unlimited(path)) as rec:
        rec.write_config(0.0, CONFIG_YAML, MAP_YAML)
        for i, f in enumerate(frames):
            assert rec.write_depth(i / 30, f)
            assert rec.write_pose(i / 30, float(i), 0.0, 0.0, np.eye(3))
    got = list(read_recording(path))
    assert [m.topic for m in got] == ["/config"] + ["/depth/front", "/pose"] * 5
    assert all(np.array_equal(m.message.depth, f.depth) for m, f in
               zip([m for m in got if m.topic == "/depth/front"], frames))
    assert rec.dropped == 0


def test_background_recorder_drops_rather_than_blocks():
    entered, release = threading.Event(), threading.Event()

    class SlowDisk(NullRecorder):
        active = True
        calls = 0

        def write_status(self, t, message):
            SlowDisk.calls += 1
            entered.set()
            release.wait(5)
            return True

    rec = BackgroundRecorder(SlowDisk(), max_queue=2)
    assert rec.write_status(0.0, {"n": 0})
    assert entered.wait(5)  # the worker is stuck on the first message
    results = [rec.write_status(0.1 * i, {"n": i}) for i in range(1, 5)]
    assert results == [True, True, False, False] and rec.dropped == 2
    release.set()
    rec.close()
    assert SlowDisk.calls == 3


def test_schema_lookup():
    assert ms.schema_for("/depth/left")[0] == "foxglove.RawImage"
    assert ms.schema_for("/roi/left")[0] == "foxglove.CompressedImage"
    with pytest.raises(ValueError):
        ms.schema_for("/depth/")
    # one registry: every topic a sink publishes has a schema, and every schema has a publisher
    published = set(ms.RECORDED_TOPICS) | set(ms.LIVE_TOPICS)
    assert published == set(ms.SCHEMAS) | set(ms.PREFIX_SCHEMAS)
    for topic in published:
        name, body = ms.schema_for(topic + "front" if topic.endswith("/") else topic)
        assert body["title"] == name and set(body["required"]) <= set(body["properties"]), topic


# Depth as Foxglove sees it, its bandwidth budget, ROI images, and the clock  ----------------------

def test_depth_is_a_16uc1_raw_image_and_decimation_keeps_the_geometry():
    rng = np.random.default_rng(11)
    f = frame(rng, "front", 0)
    msg = ms.encode_depth(f)
    assert (msg["encoding"], msg["width"], msg["height"], msg["step"]) == ("16UC1", 848, 480, 2 * 848)
    assert msg["frame_id"] == "front_optical_frame" and msg["decimation"] == 1
    raw = np.frombuffer(base64.b64decode(msg["data"]), dtype="<u2").reshape(480, 848)
    assert np.array_equal(raw, f.depth)  # what Foxglove's Image panel colour-maps: the depth units themselves
    assert len(ms.dumps(msg)) <= ms.depth_message_bytes(848, 480)  # what the budget charges covers it
    half = ms.decode_depth(ms.encode_depth(f, decimation=2))
    assert half.depth.shape == (240, 424) and np.array_equal(half.depth, f.depth[::2, ::2])
    # a point seen at pixel (2u, 2v) of the camera is at (u, v) of the decimated image
    p = np.array([0.3, -0.2, 1.7])
    uv_full = (f.K @ p)[:2] / p[2]
    uv_half = (half.K @ p)[:2] / p[2]
    np.testing.assert_allclose(uv_half, uv_full / 2)


def test_depth_recorded_before_as_16_bit_png_still_reads_back():
    import cv2

    rng = np.random.default_rng(12)
    f = frame(rng, "left", 3, width=212, height=120)
    ok, png = cv2.imencode(".png", f.depth)
    old = {"format": "png", "data": base64.b64encode(png.tobytes()).decode(), "camera": "left", "width": 212,
           "height": 120, "K": f.K.reshape(9).tolist(), "depth_scale": 0.001, "t_capture": f.t_capture,
           "frame_number": f.frame_number}
    back = ms.decode_depth(old)
    assert np.array_equal(back.depth, f.depth) and back.frame_number == f.frame_number
    bad = ms.encode_depth(f)
    bad["data"] = bad["data"][:-8]
    with pytest.raises(ValueError, match="malformed depth message"):
        ms.decode_depth(bad)


def test_the_depth_budget_skips_whole_frames_and_keeps_the_rest_bit_exact(tmp_path):
    rng = np.random.default_rng(13)
    frames = [frame(rng, "front", i, width=212, height=120) for i in range(60)]  # 2 s at 30 fps
    size = ms.depth_message_bytes(212, 120)
    mbit_s = 2.0  # 250 kB/s: about 3.6 of these 68 kB frames per second
    path = tmp_path / "run.mcap"
    with unlimited(path) as rec:
        rec.set_depth_budget(mbit_s)
        written = [rec.write_depth(f.t_capture, f) for f in frames]
    kept = [f for f, w in zip(frames, written) if w]
    assert rec.depth_skipped == len(frames) - len(kept)
    # within the rate over the run plus the one second the bucket holds, and not starved either
    duration = frames[-1].t_capture - frames[0].t_capture
    assert len(kept) * size <= mbit_s * 1e6 / 8 * (duration + 1.0)
    assert len(kept) >= int(mbit_s * 1e6 / 8 * duration / size)
    got = [m.message for m in read_recording(path) if m.topic == "/depth/front"]
    assert [d.frame_number for d in got] == [f.frame_number for f in kept]
    assert all(np.array_equal(d.depth, f.depth) for d, f in zip(got, kept))
    # behind the worker thread the same frames pass: the budget runs on the frames' times, not the machine's
    with BackgroundRecorder(unlimited(tmp_path / "bg.mcap")) as bg:
        bg.set_depth_budget(mbit_s)
        assert [bg.write_depth(f.t_capture, f) for f in frames] == written  # refused before taking a queue place
    assert bg.depth_skipped == rec.depth_skipped
    with unlimited(tmp_path / "none.mcap") as rec:
        rec.set_depth_budget(0.0)  # no depth at all
        assert not any(rec.write_depth(f.t_capture, f) for f in frames[:5])
        rec.set_depth_budget(None)  # no cap
        assert all(rec.write_depth(f.t_capture, f) for f in frames[:5])


def test_roi_images_are_recorded_at_most_a_few_per_second_per_camera(tmp_path):
    label = np.full((120, 212), -1, np.int32)
    label[20:80, 30:150] = 2
    path = tmp_path / "run.mcap"
    with BackgroundRecorder(unlimited(path)) as rec:
        for i in range(60):  # 2 s at 30 fps, two cameras
            for cam in ("front", "left"):
                rec.write_roi(i / 30, cam, label)
    got = [m for m in read_recording(path) if m.topic.startswith("/roi/")]
    for cam in ("front", "left"):
        times = [m.message["t"] for m in got if m.topic == "/roi/" + cam]
        assert 2 * ms.ROI_MAX_HZ - 1 <= len(times) <= 2 * ms.ROI_MAX_HZ + 1
        assert min(b - a for a, b in zip(times, times[1:])) >= 1.0 / ms.ROI_MAX_HZ - 1e-9
    assert got[0].message["format"] == "png" and got[0].message["frame_id"].endswith("_optical_frame")


def test_a_recording_without_a_clock_offset_is_read_as_monotonic_time(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "old.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("robot.Status", "jsonschema", ms.schema_text("/status").encode())
        chan = w.register_channel("/status", "json", schema)
        w.add_message(chan, log_time=7_250_000_000, data=b'{"t": 7.25}', publish_time=7_250_000_000)
        w.finish()
    (m,) = read_recording(path)
    assert m.t == 7.25 and m.clock_offset_ns == 0
