"""A recorded simulated run replays to the same poses; a changed map shows up as a difference."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from dataclasses import replace

from robot.app.controller import AppOptions
from robot.config import load_robot_config
from robot.control.path_file import parse_path
from robot.maps.plane_map import load_plane_map
from robot.recording.reader import read_recording
from robot.recording.recorder import BackgroundRecorder, Recorder
from robot.sim.realtime import RealtimeSimSettings, sim_rig
from robot.sim.replay import replay

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
PLAN = parse_path({"start": {"x": 0.4, "y": 0.6, "heading": 0.0},
                   "waypoints": [{"x": 0.7, "y": 0.6, "heading": 0.0, "tolerance": 0.005}]})


def _record_run(path, robot=ROBOT):
    rec = BackgroundRecorder(Recorder(str(path)))
    opts = AppOptions(install_signal_handlers=False, status_period=0.25)
    with sim_rig(robot, ARENA, (0.4, 0.6, 0.0), RealtimeSimSettings(fps=8, decimation=4), opts, plan=PLAN,
                 recorder=rec) as rig:
        async def main():
            asyncio.get_running_loop().call_later(3.5, rig.app.request_stop, "test done")
            return await rig.app.run()
        assert asyncio.run(main()) == 0
    return rig.app


def test_recorded_sim_run_replays_to_the_same_poses(tmp_path):
    path = tmp_path / "run.mcap"
    app = _record_run(path)
    topics = {m.topic for m in read_recording(path)}
    assert {"/config", "/odometry", "/planes", "/pose", "/cmd", "/status"} <= topics
    assert any(t.startswith("/depth/") for t in topics)
    report = replay(path)
    assert report.localizations >= 10 and report.poses_compared >= 5 and report.odometry > 200
    assert report.ok(), report.to_json()
    assert report.localizations == app.stats.localizations
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
    _record_run(path, replace(ROBOT, cameras=cams))
    gyro = [m for m in read_recording(path, ["/odometry"]) if "gyro_wz" in m.message]
    assert len(gyro) > 100  # ~200 Hz for 3 s
    report = replay(path)
    assert report.ok(), report.to_json()


def test_replay_of_a_missing_or_foreign_file_is_one_clear_error(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    for f in (str(tmp_path / "none.mcap"), str(bad)):
        p = subprocess.run([sys.executable, "-m", "robot.cli.main", "replay", f], capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr
