"""PoseStore: atomic JSON save, rate limit, and loads that never crash."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from robot.app.pose_store import PoseStore

COV = np.array([[1e-4, 2e-6, 0.0], [2e-6, 4e-4, 1e-6], [0.0, 1e-6, 3e-4]])


def test_round_trip(tmp_path):
    store = PoseStore(tmp_path)
    assert store.save(10.0, 0.5, 0.25, 1.5, COV, map_name="paper_arena")
    pose, reason = PoseStore(tmp_path).load("paper_arena")
    assert reason == ""
    assert (pose.x, pose.y, pose.phi, pose.map_name) == (0.5, 0.25, 1.5, "paper_arena")
    assert np.array_equal(pose.cov, COV)
    assert pose.saved_at.endswith("+00:00")
    # Only the final file is left behind: no temporary files.
    assert sorted(os.listdir(tmp_path)) == ["last_pose.json"]


def test_rate_limit_and_force(tmp_path):
    store = PoseStore(tmp_path, min_interval=2.0)
    assert store.save(0.0, 0.0, 0.0, 0.0, COV)
    assert not store.save(1.9, 1.0, 0.0, 0.0, COV)
    assert store.load()[0].x == 0.0
    assert store.save(2.0, 2.0, 0.0, 0.0, COV)
    assert store.save(2.1, 3.0, 0.0, 0.0, COV, force=True)  # shutdown
    assert store.load()[0].x == 3.0


def test_missing_file(tmp_path):
    pose, reason = PoseStore(tmp_path / "nowhere").load()
    assert pose is None and "no saved pose" in reason


@pytest.mark.parametrize("content, problem", [
    ("{\"version\": 1, \"x\": 0.5", "not JSON"),
    ("", "not JSON"),
    ("[1, 2]", "JSON object"),
    ('{"version": 7, "x": 0, "y": 0, "phi": 0, "cov": [[1,0,0],[0,1,0],[0,0,1]]}', "unknown version"),
    ('{"version": 1, "x": "a", "y": 0, "phi": 0, "cov": [[1,0,0],[0,1,0],[0,0,1]]}', "'x' must be"),
    ('{"version": 1, "x": 0, "y": 0, "phi": NaN, "cov": [[1,0,0],[0,1,0],[0,0,1]]}', "'phi' must be"),
    ('{"version": 1, "x": 0, "y": 0, "phi": 0, "cov": [[1,0],[0,1]]}', "3x3"),
    ('{"version": 1, "x": 0, "y": 0, "phi": 0, "cov": [[1,0,0],[0,-1,0],[0,0,1]]}', "positive semi-definite"),
    ('{"version": 1, "x": 0, "y": 0, "phi": 0}', "3x3"),
])
def test_corrupt_file_gives_none_and_reason(tmp_path, content, problem):
    (tmp_path / "last_pose.json").write_text(content)
    pose, reason = PoseStore(tmp_path).load()
    assert pose is None
    assert "corrupt" in reason and problem in reason and "last_pose.json" in reason


def test_pose_from_another_map_is_refused(tmp_path):
    store = PoseStore(tmp_path)
    store.save(0.0, 1.0, 2.0, 0.0, COV, map_name="site_b")
    pose, reason = store.load("paper_arena")
    assert pose is None and "site_b" in reason


def test_failed_write_keeps_the_old_file_and_does_not_raise(tmp_path, monkeypatch):
    store = PoseStore(tmp_path)
    store.save(0.0, 1.0, 0.0, 0.0, COV)

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    assert not store.save(5.0, 2.0, 0.0, 0.0, COV)
    monkeypatch.undo()
    assert store.load()[0].x == 1.0
    assert sorted(os.listdir(tmp_path)) == ["last_pose.json"]
    assert json.loads((tmp_path / "last_pose.json").read_text())["x"] == 1.0


def test_non_finite_pose_is_not_saved(tmp_path):
    store = PoseStore(tmp_path)
    assert not store.save(0.0, float("nan"), 0.0, 0.0, COV)
    assert store.load()[0] is None
