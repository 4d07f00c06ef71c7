"""A calibration file makes the cameras better known, not only better corrected: once it gives
every camera's depth scale (and mount angles), the localizer's error model takes the calibrated
uncertainty in place of an uncalibrated camera's 1 %, with a floor for what drifts between
calibrations (robot.config.calibration, docs/calibration.md).

What it is for, measured on the simulated clock in the FZK house's large room (walls 3 to 4 m
away): with the uncalibrated error model the fused protection level stays over its 100 mm alert
limit, so the robot drives the whole tour slowed down; calibrated, it is localized and drives at
cruise speed. The protection level must stay honest either way, including when the camera has
drifted since its calibration by twice the floor's standard deviation.
"""

from __future__ import annotations

from dataclasses import replace

import pytest

from drivers.sim.render import resolve_noise
from drivers.sim.world import WorldSettings
from robot.base.errors import ConfigError
from robot.config import load_robot_config
from robot.config.calibration import CameraCalibration, apply_calibration, calibration_yaml, parse_calibration
from robot.config.defaults import DEFAULT_ROBOT
from robot.control.path_file import load_path
from robot.fusion.quality import LOCALIZED
from robot.maps.plane_map import load_plane_map
from robot.sim.runner import RunSettings, localized_share, run_path

ROBOT = load_robot_config(DEFAULT_ROBOT)
HOUSE = load_plane_map("config/maps/fzk_haus_ground.yaml")
TOUR = load_path("config/paths/fzk_house_room.yaml")
CALIBRATED = {"front": {"depth_scale": 1 / 1.01, "depth_scale_std": 0.0004,
                        "mount": {"rpy_deg": [0.0, 0.0, 0.0], "rpy_std_deg": [0.01, 0.02, 0.01]}},
              "left": {"depth_scale": 1 / 1.01, "depth_scale_std": 0.0004,
                       "mount": {"rpy_deg": [0.0, 0.0, 90.0], "rpy_std_deg": [0.01, 0.03, 0.01]}}}


def calibrated(cameras) -> object:
    return apply_calibration(ROBOT, parse_calibration({"cameras": cameras}, "cal.yaml"))


def test_the_error_model_takes_the_calibrated_floor_once_every_camera_is_calibrated():
    loc = ROBOT.localizer
    assert (loc.depth_scale_std, loc.mount_angle_std_deg) == (0.01, 0.3)  # the uncalibrated defaults
    robot = calibrated(CALIBRATED)
    assert robot.localizer.depth_scale_std == loc.calibrated_depth_scale_std == 0.0025
    assert robot.localizer.mount_angle_std_deg == loc.calibrated_mount_angle_std_deg == 0.05
    # a file whose own std is larger than the floor is taken at its word
    worse = {k: {**v, "depth_scale_std": 0.004} for k, v in CALIBRATED.items()}
    worse["left"] = {**worse["left"], "mount": {"rpy_deg": [0.0, 0.0, 90.0], "rpy_std_deg": [0.01, 0.2, 0.01]}}
    robot = calibrated(worse)
    assert robot.localizer.depth_scale_std == 0.004 and robot.localizer.mount_angle_std_deg == 0.2
    # one camera left uncalibrated: the shared model must still cover its 1 %, and its mount's 0.3 deg
    robot = calibrated({"front": CALIBRATED["front"]})
    assert (robot.localizer.depth_scale_std, robot.localizer.mount_angle_std_deg) == (0.01, 0.3)
    # a scale without its std (an older file, another tool): the floor
    robot = calibrated({k: {"depth_scale": v["depth_scale"]} for k, v in CALIBRATED.items()})
    assert (robot.localizer.depth_scale_std, robot.localizer.mount_angle_std_deg) == (0.0025, 0.3)
    # the floors are the config's to set
    tight = replace(ROBOT, localizer=replace(loc, calibrated_depth_scale_std=0.001))
    assert apply_calibration(tight, parse_calibration({"cameras": CALIBRATED})).localizer.depth_scale_std == 0.001


def test_the_stds_are_written_and_read_back_and_bad_ones_are_one_clear_error():
    cal = parse_calibration({"cameras": CALIBRATED}, "cal.yaml")
    text = calibration_yaml(cal)
    assert "depth_scale_std: 0.0004" in text and "rpy_std_deg: [0.01, 0.02, 0.01]" in text
    back = parse_calibration(__import__("yaml").safe_load(text), "again.yaml")
    for name, c in cal.cameras.items():
        b = back.cameras[name]
        assert b.depth_scale == pytest.approx(c.depth_scale, abs=1e-7) and b.depth_scale_std == c.depth_scale_std
        assert b.mount_rpy_deg == c.mount_rpy_deg and b.mount_rpy_std_deg == c.mount_rpy_std_deg
    assert CameraCalibration().empty and not CameraCalibration(depth_scale=1.0).empty
    for doc, expect in [
        ({"front": {"depth_scale_std": 0.001}}, "'depth_scale_std' without 'depth_scale'"),
        ({"front": {"depth_scale": 1.0, "depth_scale_std": -0.001}}, "'depth_scale_std' must be >= 0"),
        ({"front": {"depth_scale": 1.0, "depth_scale_std": 0.5}}, "'depth_scale_std' must be <= 0.1"),
        ({"front": {"mount": {"rpy_std_deg": [0.1, 0.1, 0.1]}}}, "'rpy_std_deg' without 'rpy_deg'"),
        ({"front": {"mount": {"rpy_deg": [0, 0, 0], "rpy_std_deg": [0.1, 0.1]}}}, "'rpy_std_deg' must be a list of 3"),
    ]:
        with pytest.raises(ConfigError) as e:
            parse_calibration({"cameras": doc}, "cal.yaml")
        msg = str(e.value)
        assert msg.startswith("cal.yaml: ") and expect in msg and "\n" not in msg, msg


def tour(robot, read_long: float):
    """The room tour on the simulated clock, both cameras reading depth ``read_long`` too long."""
    world = replace(WorldSettings(), depth_noise=resolve_noise("realistic", {c.name: read_long for c in ROBOT.cameras}))
    return run_path(robot, HOUSE, TOUR, RunSettings(vision=True, world=world, world_robot=ROBOT, max_time=240.0))


@pytest.mark.parametrize("what, read_long, calibration", [
    # uncalibrated: the cameras read 1 % long, as the error model assumes one may
    ("uncalibrated", 0.01, None),
    # calibrated to 1 %, and since then drifted 0.5 % further: twice the floor's standard deviation
    ("calibrated, drifted", 0.015, CALIBRATED),
])
def test_the_protection_level_covers_the_error_and_calibration_earns_the_robot_its_speed(what, read_long, calibration):
    robot = ROBOT if calibration is None else calibrated(calibration)
    res = tour(robot, read_long)
    assert res.finished, (what, res.reason)
    assert len(res.quality_trace) > 100
    # Honest either way: at every sample the true error is within the horizontal protection level.
    over = [(round(t, 1), round(err * 1e3, 1), round(hpl * 1e3, 1)) for t, _, hpl, err in res.quality_trace if err > hpl]
    assert not over, (what, over[:5])
    share = localized_share([res])
    if calibration is None:
        # ... and modest: the uncalibrated 1 % at 3 to 4 m keeps it over the 100 mm alert limit
        assert share < 0.2, (what, share)
    else:
        assert share > 0.9, (what, share)
        assert max(hpl for _, s, hpl, _ in res.quality_trace if s == LOCALIZED) <= robot.quality.horizontal_alert_limit


def test_robotctl_sim_runs_the_controller_with_a_file_and_refuses_bad_ones(capsys, tmp_path):
    from robot.cli.main import main

    base = ["sim", "--map", "config/maps/paper_arena.yaml", "--path", "config/paths/paper_4_3.yaml", "--runs", "1",
            "--modes", "vision", "--no-plots", "--vision-rate", "2"]
    (tmp_path / "bad.yaml").write_text("cameras: {front: {depth_scale: 1.0, depth_scale_std: 0.3}}\n")
    (tmp_path / "cal.yaml").write_text(calibration_yaml(parse_calibration({"cameras": CALIBRATED})))
    for extra, expect in [(["--calibration", str(tmp_path / "missing.yaml")], "missing.yaml"),
                          (["--calibration", str(tmp_path / "bad.yaml")], "'depth_scale_std' must be <= 0.1"),
                          (["--calibration", str(tmp_path / "cal.yaml"), "--realtime"], "--calibration apply to the")]:
        rc = main(base + extra)
        out, err = capsys.readouterr()
        lines = [x for x in err.strip().splitlines() if x]
        assert rc != 0 and len(lines) == 1 and expect in lines[0] and "Traceback" not in err, (extra, err)
    assert main(base + ["--calibration", str(tmp_path / "cal.yaml"), "--depth-scale-error", "0.01", "--json"]) == 0
    doc = __import__("json").loads(capsys.readouterr().out)
    assert doc["settings"]["calibration"] == str(tmp_path / "cal.yaml")
    assert doc["modes"]["vision"]["finished"] == 1 and doc["modes"]["vision"]["localized_share"] > 0.9


def test_the_controller_says_at_start_up_which_error_model_it_runs_with():
    from robot.config.calibration import error_model_note

    assert error_model_note(ROBOT.localizer) == ("localizer error model: depth scale std 1.00 %, mount angle std 0.30 deg "
                                                 "(a calibration file of every camera's scale and mount lowers them)")
    assert error_model_note(calibrated(CALIBRATED).localizer) == ("localizer error model: depth scale std 0.25 %, "
                                                                  "mount angle std 0.05 deg")


def test_robotctl_calibrate_writes_the_stds_and_says_what_the_file_does_to_the_error_model(capsys, tmp_path):
    """The user's flow: calibrate (here in the simulated surveyed arena, whose robot reads depth 1 %
    long in front and 1 % short on the left), then run with the file."""
    from robot.cli.main import main
    from robot.config.calibration import load_calibration

    out = tmp_path / "calibration.yaml"
    assert main(["calibrate", "--sim", "--map", "config/maps/paper_arena_surveyed.yaml", "--out", str(out), "--json"]) == 0
    doc = __import__("json").loads(capsys.readouterr().out)
    cal = load_calibration(out)
    stds = {p["name"]: p["std"] for p in doc["parameters"]}
    for cam in ROBOT.cameras:
        c = cal.cameras[cam.name]
        assert c.depth_scale_std == pytest.approx(stds[f"{cam.name}.depth_scale"], rel=1e-3)
        assert c.mount_rpy_std_deg is not None and max(c.mount_rpy_std_deg) < 0.05  # well under the floor
    loc = apply_calibration(ROBOT, cal).localizer
    assert doc["error_model"] == {"depth_scale_std": loc.depth_scale_std, "mount_angle_std_deg": loc.mount_angle_std_deg}
    assert (loc.depth_scale_std, loc.mount_angle_std_deg) == (0.0025, 0.05)  # the floors: the solve measures less
