"""The protective stop in the closed loop (simulated clock): a person in the path is never touched."""

from __future__ import annotations

import math
from pathlib import Path

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


def test_the_cluttered_building_run_keeps_its_site_items_clear_of_the_path():
    """The false-stop benchmark (scripts/bench_safety.py) counts every stop-zone tick on the FZK
    room tour as false: that holds only if no random item stands within reach of the course."""
    from drivers.sim.world import sample_world
    from robot.sim.safety_experiment import path_course

    root = Path(__file__).resolve().parents[1]
    tour = load_path(root / "config" / "paths" / "fzk_house_room.yaml")
    fzk = load_plane_map(root / "config" / "maps" / "fzk_haus_ground.yaml")
    course = path_course(tour, 0.1)
    legs = [(tour.start.x, tour.start.y)] + [(w.x, w.y) for w in tour.waypoints]
    assert course[0] == legs[0] and course[-1] == legs[-1]
    assert all(math.hypot(b[0] - a[0], b[1] - a[1]) <= 0.1 + 1e-9 for a, b in zip(course, course[1:]))
    for seed in range(5):
        _, scene = sample_world(fzk, (tour.start.x, tour.start.y, tour.start.heading), seed, 0.01, 0, site=10,
                                as_built=True, keep_clear=course)
        assert len(scene.clutter) >= 5  # the room is cluttered, not emptied by the constraint
        for item in scene.clutter:
            lo, hi = item.bounds()
            for x, y in course:
                gap = math.hypot(x - min(max(x, lo[0]), hi[0]), y - min(max(y, lo[1]), hi[1]))
                assert gap >= 0.5, (seed, item.kind, (x, y))
