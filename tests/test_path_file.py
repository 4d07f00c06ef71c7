"""Path files: the shipped paper path loads; malformed files are refused naming file and problem."""

from __future__ import annotations

import pytest

from robot.base.errors import ConfigError
from robot.control.path_file import DEFAULT_SPEED, check_path_in_bounds, load_path
from robot.maps.plane_map import load_plane_map


def test_paper_path_loads_and_stays_off_the_walls(repo_root):
    plan = load_path(repo_root / "config/paths/paper_4_3.yaml")
    assert (plan.start.x, plan.start.y) == (0.0, 1.0)
    assert (plan.waypoints[-1].x, plan.waypoints[-1].y) == (1.0, 0.0)
    assert len(plan.waypoints) >= 8
    assert all(w.speed == 0.15 and w.tolerance == 0.005 for w in plan.waypoints)
    arena = load_plane_map(repo_root / "config/maps/paper_arena.yaml")
    lo, hi = arena.bounds()
    check_path_in_bounds(plan, lo, hi, margin=0.25)


def test_defaults_and_optional_fields(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("waypoints:\n  - {x: 1, y: 2}\n  - {x: 0.5, y: 0.5, heading: 1.0, speed: 0.3, dwell: 2}\n")
    plan = load_path(p)
    assert plan.start is None
    a, b = plan.waypoints
    assert a.heading is None and a.speed == DEFAULT_SPEED and a.dwell == 0.0
    assert (b.heading, b.speed, b.dwell) == (1.0, 0.3, 2.0)
    p.write_text("start: {x: 0, y: 0}\ndefaults: {speed: 0.05}\nwaypoints: [{x: 1, y: 0}]\n")
    plan = load_path(p)
    assert plan.start.heading == 0.0 and plan.waypoints[0].speed == 0.05


@pytest.mark.parametrize("text, problem", [
    ("waypoints: []\n", "'waypoints' must be a non-empty list"),
    ("start: {x: 0, y: 0}\n", "missing required key 'waypoints'"),
    ("waypoints:\n  - {x: 1, y: 2}\n  - {x: 1}\n", "waypoints[1]: missing required key 'y'"),
    ("waypoints:\n  - {x: 1, y: 2, sped: 0.1}\n", "waypoints[0]: unknown key(s): sped"),
    ("waypoints:\n  - {x: one, y: 2}\n", "waypoints[0]: 'x' must be a number, got 'one'"),
    ("waypoints:\n  - {x: .nan, y: 2}\n", "waypoints[0]: 'x' must be finite"),
    ("waypoints:\n  - {x: 0, y: 0}\n  - {x: 1, y: 2, speed: -0.1}\n", "waypoints[1]: 'speed' must be > 0"),
    ("waypoints:\n  - {x: 1, y: 2, speed: 0}\n", "waypoints[0]: 'speed' must be > 0"),
    ("waypoints:\n  - {x: 1, y: 2, speed: 15}\n", "waypoints[0]: 'speed' must be <= 2.0"),
    ("waypoints:\n  - {x: 1, y: 2, tolerance: 0}\n", "waypoints[0]: 'tolerance' must be > 0"),
    ("waypoints:\n  - {x: 1, y: 2, dwell: -1}\n", "waypoints[0]: 'dwell' must be >= 0"),
    ("waypoints:\n  - {x: 1, y: 2, heading: 90}\n", "waypoints[0]: 'heading' is in radians"),
    ("waypoints:\n  - {x: 1, y: 2, heading: true}\n", "waypoints[0]: 'heading' must be a number"),
    ("waypoints:\n  - [1, 2]\n", "waypoints[0]: expected a mapping"),
    ("start: {x: 0}\nwaypoints: [{x: 1, y: 1}]\n", "start: missing required key 'y'"),
    ("defaults: {speed: -1}\nwaypoints: [{x: 1, y: 1}]\n", "defaults: 'speed' must be > 0"),
    ("waypoints: [{x: 1, y: 1}]\nextra: 1\n", "unknown key(s): extra"),
    ("waypoints: [{x: 1, y: 1}\n", "malformed YAML"),
    ("- just a list\n", "expected a mapping"),
])
def test_malformed_files_are_refused_with_file_and_problem(tmp_path, text, problem):
    p = tmp_path / "bad_path.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_path(p)
    msg = str(e.value)
    assert str(p) in msg
    assert problem in msg


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_path(tmp_path / "none.yaml")


def test_path_outside_the_map_is_refused(tmp_path):
    p = tmp_path / "out.yaml"
    p.write_text("start: {x: 0, y: 1}\nwaypoints:\n  - {x: 0.5, y: 0.5}\n  - {x: 1.2, y: 0.5}\n")
    plan = load_path(p)
    with pytest.raises(ConfigError, match=r"waypoints\[1\]: \(1.200, 0.500\) is outside"):
        check_path_in_bounds(plan, (-0.25, -0.25), (1.25, 1.25), margin=0.1)
    check_path_in_bounds(plan, (-0.25, -0.25), (1.25, 1.25), margin=0.0)
