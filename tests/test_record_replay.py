"""A recorded simulated run replays to the same poses; a changed map shows up as a difference; the
recording carries the effective config the run used, the pose at the control rate and the REP-105
transforms; frames skipped under the depth budget replay from their recorded planes."""

from __future__ import annotations

import asyncio
import collections
import json
import math
import os
import subprocess
import sys
from dataclasses import replace

from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.recording.reader import RecordingReader, read_recording
from robot.recording.recorder import BackgroundRecorder, Recorder
from robot.sim.realtime import RealtimeSimSettings, sim_rig
from robot.sim.replay import replay

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
PLAN = parse_path({"start": {"x": 0.4, "y": 0.6, "heading": 0.0},
                   "waypoints": [{"x": 0.7, "y": 0.6, "heading": 0.0, "tolerance": 0.005}]})


class _CountingRecorder(BackgroundRecorder):
    """Counts what the app hands over, so a run lasts until it has recorded enough, however fast the machine."""

    def __init__(self, recorder):
        super().__init__(recorder, max_queue=1 << 20)  # a busy machine must delay the writes, not drop them
        self.counts = collections.Counter()

    def write(self, topic, t, message):
        self.counts["gyro" if "gyro_wz" in message else topic] += 1
        return super().write(topic, t, message)


def _record_run(path, robot=ROBOT, gyro=0):
    """Record the simulated app until it has localized 10 frames, fused 5 poses, 200 odometry (and
    ``gyro`` gyro) samples; the timeout only guards against a hang."""
    rec = _CountingRecorder(Recorder(str(path)))
    opts = AppOptions(install_signal_handlers=False, status_period=0.25, stop_when_done=False)

    def on_tick(app, t):
        c = rec.counts
        if c["/planes"] >= 10 and c["/pose"] >= 5 and c["/odometry"] > 200 and c["gyro"] >= gyro:
            app.request_stop("test done")

    with sim_rig(robot, ARENA, (0.4, 0.6, 0.0), RealtimeSimSettings(fps=8, decimation=4), opts, plan=PLAN,
                 recorder=rec, on_tick=on_tick) as rig:
        assert asyncio.run(asyncio.wait_for(rig.app.run(), 120.0)) == 0
    assert rig.app.exit_reason == "test done"
    return rig.app


def test_recorded_sim_run_replays_to_the_same_poses(tmp_path):
    path = tmp_path / "run.mcap"
    app = _record_run(path)
    messages = list(read_recording(path))
    topics = {m.topic for m in messages}
    assert {"/config", "/map", "/tf", "/tf_static", "/odometry", "/planes", "/plane_fits", "/pose", "/cmd",
            "/status"} <= topics
    assert any(t.startswith("/depth/") for t in topics) and any(t.startswith("/roi/") for t in topics)
    # the pose at the control rate: every control tick after the pose was set recorded the pose it used
    pose_t = {m.message["t"] for m in messages if m.topic == "/pose"}
    cmd_t = [m.message["t"] for m in messages if m.topic == "/cmd" and m.message["t"] >= min(pose_t)]
    assert len(cmd_t) > 50 and set(cmd_t) <= pose_t
    # odom -> base_link is continuous (no faster than the robot can drive); map -> odom takes the corrections
    tf = [m.message for m in messages if m.topic == "/tf"]
    odom = [(f["t"], next(x for x in f["transforms"] if x["child_frame_id"] == "base_link")["translation"]) for f in tf]
    for (t0, a), (t1, b) in zip(odom, odom[1:]):
        assert math.hypot(b["x"] - a["x"], b["y"] - a["y"]) <= ROBOT.control.max_speed * 1.5 * (t1 - t0) + 1e-3
    last = [m for m in messages if m.topic == "/cmd"][-1]  # log times: wall-clock ns; messages: monotonic s
    assert last.log_time_ns > 1.5e18 and abs(last.t - last.message["t"]) < 1.0
    # the effective config (every key after defaults, and the map loaded) opens the recording
    first = next(iter(read_recording(path)))
    assert first.topic == "/config"
    assert first.message["effective_config"]["map"] == os.path.abspath(ARENA.source)
    assert replace(RecordingReader(path).robot_config(), source=ROBOT.source) == ROBOT
    # the frames of both cameras went to the filter together, one fusion step per set of frames
    steps = collections.Counter(m.message["fusion_step"] for m in messages if m.topic == "/planes")
    assert max(steps.values()) == len(ROBOT.cameras)
    report = replay(path)
    assert report.localizations >= 10 and report.poses_compared >= 5 and report.odometry > 200
    assert report.ok(), report.to_json()
    assert report.localizations == app.stats.localizations
    assert report.relocalized == report.localizations  # every localized frame within the default budget
    # the CLI says the same; a shifted wall in the map makes the replay differ (exit 1)
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "replay", str(path), "--json"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0 and json.loads(p.stdout)["identical"] is True
    moved = tmp_path / "moved.yaml"
    moved.write_text(open("config/maps/paper_arena.yaml").read().replace("1.25", "1.27"))
    p = subprocess.run([sys.executable, "-m", "robot.cli.main", "replay", str(path), "--map", str(moved), "--json"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 1, p.stderr
    assert json.loads(p.stdout)["max_position_diff_m"] > 1e-4


def test_a_run_with_the_gyro_fused_replays_identically_too(tmp_path):
    left = ROBOT.camera("left")
    cams = tuple(replace(c, realsense=replace(c.realsense, imu_enabled=True)) if c is left else c for c in ROBOT.cameras)
    path = tmp_path / "gyro.mcap"
    _record_run(path, replace(ROBOT, cameras=cams), gyro=100)
    gyro = [m for m in read_recording(path, ["/odometry"]) if "gyro_wz" in m.message]
    assert len(gyro) >= 100
    # the robot.yaml text says the IMU is off; the effective config says what the run really did
    recorded = RecordingReader(path).robot_config()
    assert recorded.camera("left").realsense.imu_enabled and not ROBOT.camera("left").realsense.imu_enabled
    report = replay(path)
    assert report.ok(), report.to_json()


def test_replay_of_a_missing_or_foreign_file_is_one_clear_error(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    for f in (str(tmp_path / "none.mcap"), str(bad)):
        p = subprocess.run([sys.executable, "-m", "robot.cli.main", "replay", f], capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr


def test_frames_over_the_depth_budget_replay_from_their_recorded_planes(tmp_path):
    """0.01 Mbit/s lets one 68 kB depth frame through a minute: nearly every localization of the run
    is fused from its recorded plane measurements, the few recorded frames are localized again,
    and the fused poses still agree exactly."""
    tight = replace(ROBOT, recording=replace(ROBOT.recording, depth_max_mbit_s=0.01))
    path = tmp_path / "tight.mcap"
    _record_run(path, tight)
    depth = [m for m in read_recording(path, ["/depth/"])]
    report = replay(path)
    assert report.ok(), report.to_json()
    assert report.relocalized == len(depth) >= 1 and report.missing_frames == 0
    assert report.relocalized + report.from_recorded_planes == report.localizations
    assert report.from_recorded_planes > report.relocalized
