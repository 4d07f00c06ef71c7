"""Map summary, camera height band and validity checks (robot.maps.tools), and `robotctl map info|check`."""

from __future__ import annotations

import argparse
import copy
import io
import json
import math
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import yaml

from robot.base.errors import ConfigError
from robot.cli import maps as cli_map
from robot.config import CameraConfig, load_robot_config
from robot.maps.plane_map import load_plane_map
from robot.maps.tools import (
    camera_band_from_config,
    camera_height_band,
    check_map_data,
    map_summary,
)

ROOT = Path(__file__).resolve().parents[1]
ARENA = ROOT / "config" / "maps" / "paper_arena.yaml"


def arena_data():
    return yaml.safe_load(ARENA.read_text())


def reverse(plane: dict) -> None:
    plane["vertices"] = plane["vertices"][::-1]


def codes(issues, severity="error"):
    return sorted((i.code, i.planes) for i in issues if i.severity == severity)


def box_room(thickness=0.2, size=4.0, height=2.5):
    """A room of four solid walls, both faces of each mapped, normals towards free space."""
    t, s, h = thickness, size, height
    planes = []

    def face(pid, a, b):  # bottom edge a -> b; the right-hand normal (b - a) x z is the free side
        planes.append({"id": pid, "vertices": [[*a, 0.0], [*b, 0.0], [*b, h], [*a, h]]})

    # outer faces (seen from outside), then inner faces (seen from inside the room)
    face("south_out", (-t, -t), (s + t, -t))
    face("east_out", (s + t, -t), (s + t, s + t))
    face("north_out", (s + t, s + t), (-t, s + t))
    face("west_out", (-t, s + t), (-t, -t))
    face("south_in", (s, 0), (0, 0))
    face("east_in", (s, s), (s, 0))
    face("north_in", (0, s), (s, s))
    face("west_in", (0, 0), (0, s))
    return {"planes": planes}


# ---------------------------------------------------------------------------- height band

def test_height_band_of_level_cameras_is_floor_to_top_ray_at_max_range():
    cfg = load_robot_config(ROOT / "config" / "robot.yaml")
    lo, hi, eye = camera_band_from_config(cfg)
    cam = cfg.cameras[0]
    expect_hi = cam.mount_xyz[2] + cfg.localizer.max_range * math.tan(math.radians(cam.vfov_deg / 2))
    assert lo == 0.0  # the lowest ray reaches the floor well within 6 m
    assert hi == pytest.approx(expect_hi, abs=1e-9)
    assert eye == pytest.approx(cam.mount_xyz[2])


@pytest.mark.parametrize("pitch_deg", [-15.0, 10.0])
def test_height_band_follows_camera_pitch(pitch_deg):
    cam = CameraConfig("c", 848, 480, 30, 87, 58, (0.0, 0.0, 0.4), (0.0, pitch_deg, 0.0))
    lo, hi = camera_height_band([cam], 0.3, 6.0)
    p, half = math.radians(pitch_deg), math.radians(29)
    # Positive pitch tips the nose down; the image's top edge is `half` above the optical axis.
    # A point at depth D on that edge: D * (cos p * tan(half) - sin p) above the camera.
    top = 0.4 + max(D * (math.cos(p) * math.tan(half) - math.sin(p)) for D in (0.3, 6.0))
    bottom = 0.4 + min(D * (-math.cos(p) * math.tan(half) - math.sin(p)) for D in (0.3, 6.0))
    assert hi == pytest.approx(top, abs=1e-9)
    assert lo == pytest.approx(max(0.0, bottom), abs=1e-9)


def test_height_band_of_an_upward_camera_does_not_reach_the_floor():
    cam = CameraConfig("up", 848, 480, 30, 87, 58, (0.0, 0.0, 0.5), (0.0, -40.0, 0.0))
    lo, hi = camera_height_band([cam], 0.3, 6.0)
    assert lo > 0.5 and hi > 5.0


# ---------------------------------------------------------------------------- summary

def test_summary_of_the_paper_arena():
    s = map_summary(load_plane_map(ARENA), band=(0.0, 3.4))
    assert s["planes"] == 4 and s["polygons"] == 4 and s["vertices"] == 16
    assert s["extent"]["min"] == [-0.25, -0.25, 0.0]
    assert s["extent"]["max"] == [1.25, 1.25, 0.3]
    assert s["height_band"] == [0.0, 0.3]
    assert s["area_m2"] == pytest.approx(4 * 1.5 * 0.3)
    assert s["orientation"] == {"vertical": 4, "horizontal": 0, "sloped": 0}
    assert s["planes_in_camera_band"] == 4


def test_summary_counts_only_planes_reaching_into_the_band():
    s = map_summary(load_plane_map(ARENA), band=(0.5, 3.4))
    assert s["planes_in_camera_band"] == 0


# ---------------------------------------------------------------------------- checks

def test_valid_maps_have_no_issues():
    for data in (arena_data(), box_room()):
        issues, pm = check_map_data(data)
        assert issues == [] and len(pm) == len(data["planes"])
    pm = check_map_data(box_room())[1]
    assert pm["south_out"].normal @ [0, -1, 0] == pytest.approx(1.0)  # the fixture is what it says
    assert pm["east_in"].normal @ [-1, 0, 0] == pytest.approx(1.0)


def test_flipped_thin_wall_is_caught_by_the_edge_rule():
    data = arena_data()
    reverse(data["planes"][2])  # wall_north now faces out of the arena
    issues, _ = check_map_data(data)
    assert codes(issues) == [("flipped", ("wall_north",))]
    assert codes(issues, "warning") == []  # the neighbours are not blamed


def test_flipped_face_of_a_solid_wall_is_caught_by_the_back_face_rule():
    data = box_room()
    reverse(data["planes"][5])  # east_in now faces into the east wall
    issues, _ = check_map_data(data)
    assert codes(issues) == [("flipped", ("east_in",))]
    msg = [i.message for i in issues][0]
    assert "0.20 m in front of it is the back of plane 'east_out'" in msg


def test_back_face_rule_alone_names_the_flipped_face():
    # Without shared edges (walls apart at the corners) only the back-face rule can see it.
    data = box_room()
    for p in data["planes"]:
        v = np.array(p["vertices"])
        centre = v.mean(axis=0)
        p["vertices"] = (centre + 0.9 * (v - centre)).tolist()  # shrink: corners no longer meet
    reverse(data["planes"][1])  # east_out faces into the wall
    issues, _ = check_map_data(data)
    assert codes(issues) == [("flipped", ("east_out",))]


def test_back_face_rule_ignores_backs_farther_than_a_wall():
    data = box_room()
    issues, _ = check_map_data(data, max_thickness=0.1)  # thinner than the 0.2 m walls
    assert issues == []
    reverse(data["planes"][5])
    issues, _ = check_map_data(data, max_thickness=0.1)
    # The edge rule still blames it: two of its shared edges (room corners) disagree.
    assert codes(issues) == [("flipped", ("east_in",))]


def test_flipped_polygon_inside_a_multi_polygon_plane_is_invalid():
    data = arena_data()
    v = data["planes"][0].pop("vertices")
    left = [v[0], [0.5, -0.25, 0.0], [0.5, -0.25, 0.3], v[3]]
    right = [[0.5, -0.25, 0.0], v[1], v[2], [0.5, -0.25, 0.3]]
    data["planes"][0]["polygons"] = [left, right[::-1]]
    issues, pm = check_map_data(data)
    assert codes(issues) == [("invalid", ("wall_south",))]
    assert "clockwise relative to polygon 0" in issues[0].message
    assert len(pm) == 3  # the other planes are still checked


def test_every_invalid_plane_is_reported_not_just_the_first():
    data = arena_data()
    data["planes"][0]["vertices"][0][1] += 0.01  # 10 mm off its plane
    data["planes"][3]["vertices"] = data["planes"][3]["vertices"][:2]
    issues, _ = check_map_data(data)
    got = {i.planes[0]: i.message for i in issues if i.code == "invalid"}
    assert set(got) == {"wall_south", "wall_west"}
    assert "not planar" in got["wall_south"] and "at least 3 are needed" in got["wall_west"]


def test_duplicate_ids_and_duplicate_planes():
    data = arena_data()
    copy_same_id = copy.deepcopy(data["planes"][1])
    shifted = copy.deepcopy(data["planes"][1])
    shifted["id"] = "wall_east_again"
    for v in shifted["vertices"]:
        v[1] -= 0.5  # same plane, overlapping half of wall_east
    data["planes"] += [copy_same_id, shifted]
    issues, _ = check_map_data(data)
    assert ("duplicate_id", ("wall_east",)) in codes(issues)
    assert ("duplicate", ("wall_east", "wall_east_again")) in codes(issues)


def test_touching_coplanar_planes_are_not_duplicates():
    data = arena_data()
    v = data["planes"][0].pop("vertices")
    data["planes"][0]["vertices"] = [v[0], [0.5, -0.25, 0.0], [0.5, -0.25, 0.3], v[3]]
    data["planes"].append({"id": "wall_south_b",
                           "vertices": [[0.5, -0.25, 0.0], v[1], v[2], [0.5, -0.25, 0.3]]})
    issues, _ = check_map_data(data)
    assert issues == []


def test_bow_tie_with_nonzero_area_is_a_self_intersection():
    data = arena_data()
    data["planes"][0]["vertices"] = [[1.25, -0.25, 0.0], [-0.25, -0.25, 0.0], [0.75, -0.25, 0.3],
                                     [-0.25, -0.25, 0.3]]
    issues, _ = check_map_data(data)
    assert ("self_intersection", ("wall_south",)) in codes(issues)


def test_structurally_broken_file_raises_the_loader_error():
    with pytest.raises(ConfigError, match="'planes' must be a non-empty list"):
        check_map_data({"planes": []}, source="m.yaml")


# ---------------------------------------------------------------------------- CLI

def run_cli(argv):
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    cli_map.register(sub)
    args = parser.parse_args(argv)
    out = io.StringIO()
    with redirect_stdout(out):
        rc = args.func(args)
    return rc, out.getvalue()


def test_cli_check_exit_status_and_json(tmp_path):
    rc, out = run_cli(["map", "check", str(ARENA), "--json"])
    assert rc == 0 and json.loads(out)["valid"] is True
    data = arena_data()
    reverse(data["planes"][0])
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    rc, out = run_cli(["map", "check", str(bad), "--json"])
    report = json.loads(out)
    assert rc == 1 and report["valid"] is False and report["errors"] == 1
    assert report["issues"][0]["planes"] == ["wall_south"]
    rc, out = run_cli(["map", "check", str(bad)])
    assert rc == 1 and "INVALID" in out and "[flipped] plane 'wall_south'" in out


def test_cli_check_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        run_cli(["map", "check", str(tmp_path / "nope.yaml")])


def test_cli_info_with_floor_plan(tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "plan.png"
    rc, out = run_cli(["map", "info", str(ARENA), "--png", str(png), "--json"])
    s = json.loads(out)
    assert rc == 0 and s["planes"] == 4 and s["png"] == str(png)
    assert s["camera_band"][0] == 0.0 and s["planes_in_camera_band"] == 4
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    rc, out = run_cli(["map", "info", str(ARENA)])
    assert "4 planes" in out and "height band z 0.000..0.300 m" in out


# ---------------------------------------------------------------------------- shipped building maps

BUILDING_MAPS = ["fzk_haus_ground.yaml", "duplex_level1.yaml", "institute_ground.yaml"]


@pytest.mark.parametrize("name", BUILDING_MAPS)
def test_shipped_building_maps_load_and_pass_the_check(name):
    path = ROOT / "config" / "maps" / name
    data = yaml.safe_load(path.read_text())
    issues, pm = check_map_data(data, str(path))
    assert [i for i in issues if i.severity == "error"] == []
    assert len(pm) == len(data["planes"]) >= 18
    for p in pm.planes:  # every plane says where it came from
        assert p.source["ifc_guid"] and p.source["ifc_type"] and p.source["storey"]
    assert "Imported by `robotctl map import-ifc`" in path.read_text().splitlines()[0]


def test_flipped_face_in_a_real_building_map_is_caught():
    data = yaml.safe_load((ROOT / "config" / "maps" / "fzk_haus_ground.yaml").read_text())
    pm = check_map_data(data)[1]
    # The inside face of the west exterior wall, x = 0.3, facing +x into the house.
    target = [p.id for p in pm.planes if p.normal @ [1, 0, 0] > 0.999 and abs(p.d + 0.3) < 1e-6]
    assert len(target) == 1
    item = [p for p in data["planes"] if p["id"] == target[0]][0]
    if "vertices" in item:
        item["vertices"] = item["vertices"][::-1]
    else:
        item["polygons"] = [poly[::-1] for poly in item["polygons"]]
    issues, _ = check_map_data(data)
    assert codes(issues) == [("flipped", (target[0],))]
    assert "0.30 m in front of it is the back of plane" in issues[0].message
    # The edge rule alone (back-face rule looking less than a wall deep) blames the same plane,
    # and not the interior walls whose only shared edge is with it.
    issues, _ = check_map_data(data, max_thickness=0.05)
    assert codes(issues) == [("flipped", (target[0],))]
    assert "shared edges" in issues[0].message


def test_a_wall_not_built_yet_is_kept_out_of_the_planes_and_saved_again(tmp_path):
    """``built: false``: in the model, not on the site. Nothing predicts it; saving keeps it."""
    from robot.maps.plane_map import parse_plane_map, save_plane_map

    data = yaml.safe_load(Path("config/maps/paper_arena.yaml").read_text())
    data["planes"][0]["built"] = False
    wall = data["planes"][0]["id"]
    pm = parse_plane_map(data, "site.yaml")
    assert wall not in [p.id for p in pm.planes] and [p.id for p in pm.not_built] == [wall]
    assert len(pm) == len(data["planes"]) - 1
    save_plane_map(pm, tmp_path / "again.yaml")
    again = load_plane_map(tmp_path / "again.yaml")
    assert [p.id for p in again.not_built] == [wall] and len(again) == len(pm)
    # The check checks it on its own and says what the site lacks; info lists it.
    issues, checked = check_map_data(data, "site.yaml")
    assert not [i for i in issues if i.severity == "error"] and [p.id for p in checked.not_built] == [wall]
    out = io.StringIO()
    with redirect_stdout(out):
        assert cli_map.cmd_info(argparse.Namespace(map=str(tmp_path / "again.yaml"), png=None, robot=None,
                                                   json=True)) == 0
    assert json.loads(out.getvalue())["not_built"] == [wall]
    # Bad values are one clear error naming the plane.
    data["planes"][0]["built"] = "no"
    with pytest.raises(ConfigError, match=rf"plane '{wall}'.*'built' must be true or false"):
        parse_plane_map(data, "site.yaml")
    for item in data["planes"]:
        item["built"] = False
    with pytest.raises(ConfigError, match="every plane is marked 'built: false'"):
        parse_plane_map(data, "site.yaml")


def test_where_a_wall_is_not_built_the_marked_map_localizes_and_the_drawn_one_says_why_not():
    """The cameras see through a wall of the model that is not there: with the model as drawn
    every localization there is `inconsistent` and says how to mark it; with the wall marked
    ``built: false`` the same frames give a full fix within a centimetre."""
    from drivers.sim.clutter import WallDeviation, built_walls
    from drivers.sim.render import DepthNoise, SimScene, render_depth_frame
    from robot.localization.localizer import FIX_STATUSES, Localizer, coarse_covariance
    from robot.maps.plane_map import parse_plane_map

    robot = load_robot_config("config/robot.yaml")
    house = load_plane_map("config/maps/fzk_haus_ground.yaml")
    data = yaml.safe_load(Path("config/maps/fzk_haus_ground.yaml").read_text())
    for item in data["planes"]:
        if item["id"] == "w005":
            item["built"] = False
    marked = parse_plane_map(data, "site.yaml")
    pose = (2.851, 8.121, -0.849)  # facing w005 from 1 m
    scene = SimScene(house, walls=built_walls(house, {"w005": WallDeviation(built=False)}))
    # The marked map renders the same site: what it predicts is what stands.
    assert len(SimScene(marked).polygons()) == len(scene.polygons())
    frames = [render_depth_frame(robot, scene, c.name, pose, rng=np.random.default_rng(1), noise=DepthNoise.realistic())
              for c in robot.cameras]
    start, cov = (pose[0] + 0.01, pose[1] - 0.01, pose[2] + 0.005), coarse_covariance(0.02, math.radians(1.0))
    drawn = Localizer(robot, house).localize(frames, start, cov)
    assert drawn.status == "inconsistent" and "w005" in drawn.integrity["reason"]
    assert "built: false" in drawn.integrity["reason"]
    fixed = Localizer(robot, marked).localize(frames, start, cov)
    assert fixed.status in FIX_STATUSES and math.hypot(fixed.x - pose[0], fixed.y - pose[1]) < 0.01
