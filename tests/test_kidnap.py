"""The kidnapped robot and the robot that wakes up without a pose, on the simulated clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.config import load_robot_config
from robot.config.calibration import Calibration, CameraCalibration, apply_calibration
from robot.control.path_file import load_path
from robot.control.recovery import RELOCALIZING, TRACKING
from robot.maps.plane_map import load_plane_map
from robot.sim.runner import RunSettings, _PathRun

# The simulated cameras read depth exactly and sit where configured, and a calibration file that
# says so gives the robot the calibrated error model: localized in this large room, it drives the
# tour at cruise speed, where the uncalibrated one drives it slowed down (docs/calibration.md).
# What is tested here is the same either way; the tour just takes a third of the time.
_CONFIGURED = load_robot_config("config/robot.yaml")
ROBOT = apply_calibration(_CONFIGURED, Calibration(
    {c.name: CameraCalibration(depth_scale=1.0, mount_rpy_deg=c.mount_rpy_deg) for c in _CONFIGURED.cameras}))
HOUSE = load_plane_map("config/maps/fzk_haus_ground.yaml")
PLAN = load_path("config/paths/fzk_house_room.yaml")


def drive(**kw):
    run = _PathRun(ROBOT, HOUSE, PLAN, RunSettings(vision=True, max_time=150.0, **kw))
    run.drive()
    return run, run.result(0.0)


def speed_at(trace: np.ndarray, t: float) -> float:
    k = int(np.searchsorted(trace[:, 0], t))
    a, b = trace[max(k - 1, 0)], trace[min(k + 1, len(trace) - 1)]
    return math.hypot(b[1] - a[1], b[2] - a[2]) / max(b[0] - a[0], 1e-9)


def test_a_kidnapped_robot_stops_relocalizes_resumes_and_finishes():
    t_kidnap, where = 6.0, (9.6, 7.2, 0.6)  # mid-way along the first leg
    run, res = drive(kidnap_at=(t_kidnap, *where))
    # It noticed within 2 s and held still ...
    held = [t for t, s in run.recovery_log if s == RELOCALIZING and t >= t_kidnap]
    assert held and held[0] - t_kidnap < 2.0, run.recovery_log
    window = (res.truth_trace[:, 0] >= held[0]) & (res.truth_trace[:, 0] <= held[0] + 3.0)
    assert min(speed_at(res.truth_trace, t) for t in res.truth_trace[window, 0]) < 0.01
    # ... relocalized with a unique answer, went back to tracking ...
    assert [v for t, v in run.relocalizations if t >= t_kidnap][-1] == "unique"
    assert any(s == TRACKING and t > held[0] for t, s in run.recovery_log)
    # ... and finished the path at every target within its tolerance.
    assert res.finished, res.reason
    assert [r.index for r in res.targets] == list(range(len(PLAN.waypoints)))
    assert max(r.error for r in res.targets) < 0.01


def test_a_robot_without_a_pose_relocalizes_before_it_moves():
    run, res = drive(known_start=False)
    assert run.relocalizations and run.relocalizations[0][1] == "unique"
    t_found = run.relocalizations[0][0]
    moving = [t for t, vx, vy, wz, sent in run.commands if sent and max(abs(vx), abs(vy), abs(wz)) > 1e-6]
    assert moving and moving[0] > t_found
    assert res.finished and max(r.error for r in res.targets) < 0.01


def test_without_a_kidnap_nothing_is_relocalized():
    run, res = drive()
    assert res.finished and run.relocalizations == []
    assert all(s == TRACKING for _, s in run.recovery_log)


@pytest.mark.parametrize("wrong", [(9.6, 7.2, 2.0)])
def test_a_wrong_saved_pose_is_detected_and_corrected(wrong):
    """The path's start is not where the robot stands: the views contradict it, it relocalizes."""
    from dataclasses import replace

    from robot.control.path_file import StartPose

    plan = replace(PLAN, start=StartPose(*wrong))  # believed start ...
    run = _PathRun(ROBOT, HOUSE, plan, RunSettings(vision=True, max_time=150.0))
    run.world.board.pose = (PLAN.start.x, PLAN.start.y, PLAN.start.heading)  # ... true start
    run.core.recovery.start_from_saved_pose(0.0)
    run.drive()
    res = run.result(0.0)
    assert run.relocalizations and run.relocalizations[0][1] == "unique"
    assert res.finished and max(r.error for r in res.targets) < 0.01
