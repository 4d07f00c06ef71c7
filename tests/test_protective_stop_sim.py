"""The protective stop in the closed loop (simulated clock): a person in the path is never touched."""

from __future__ import annotations

import pytest

from robot.config import load_robot_config
from robot.control.path_file import load_path
from robot.maps.plane_map import load_plane_map
from robot.sim.runner import RunSettings, run_path
from robot.sim.safety_experiment import obstacle_run, stop_ticks

ROBOT = load_robot_config("config/robot.yaml")


@pytest.mark.parametrize("seed", [11, 12])
def test_the_robot_stops_before_a_person_one_metre_ahead_at_0_3_m_s(seed):
    run = obstacle_run(ROBOT, seed, speed=0.3, distance=1.0, vision=False)
    assert run.min_clearance > 0.02, run  # never touches them, with room to spare
    assert run.stopped and run.travelled < 1.0
    assert stop_ticks(run.counters) > 0


def test_without_the_person_the_same_run_is_never_limited():
    run = obstacle_run(ROBOT, 11, speed=0.3, distance=1.0, vision=False, obstacle=False)
    assert run.travelled == pytest.approx(4.0, abs=0.02)
    assert stop_ticks(run.counters) == 0


def test_no_false_stop_on_the_paper_path():
    plan = load_path("config/paths/paper_4_3.yaml")
    res = run_path(ROBOT, load_plane_map("config/maps/paper_arena.yaml"), plan, RunSettings(vision=True, vision_rate=3.0))
    assert res.finished
    assert stop_ticks(res.counters) == 0, res.counters
