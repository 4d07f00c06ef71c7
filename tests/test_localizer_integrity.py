"""Localization integrity: a pose reported as good is good, and its uncertainty is honest.

Scenes are the realistic D435i model (drivers/sim/render.py) with what a site adds (drivers/sim/
clutter.py): panels and door leaves parallel to a wall, walls not as drawn, depth scale and mount
errors. The localizer always gets the drawing and the nominal mounts."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from drivers.sim.building import free_space_poses
from drivers.sim.clutter import as_built, door_leaf, map_openings, parallel_panel
from drivers.sim.render import DepthNoise, SimScene, render_depth_frame
from robot.base.geometry import pose_to_T_ground_robot
from robot.cli.main import main
from robot.config import QualityConfig, load_robot_config
from robot.control.core import ControllerCore
from robot.fusion.quality import DEGRADED, LOCALIZED, FusedProtection, QualityMonitor
from robot.localization.localizer import FIX_STATUSES, Localizer, coarse_covariance
from robot.maps.plane_map import PlaneMap, load_plane_map, make_plane

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
P = ROBOT.localizer
FACING_WEST = (0.5, 0.5, math.pi)  # the front camera looks at wall_west (x = -0.25) from 0.65 m
WEST_D = 0.75  # wall_west's offset from the robot centre there


def frames(scene, pose, seed=0, noise="realistic", robot=ROBOT, cameras=("front", "left")):
    rng = np.random.default_rng(seed)
    return [render_depth_frame(robot, scene, c, pose, rng=rng, noise=noise, frame_number=seed) for c in cameras]


def coarse_near(truth, seed, std=(0.05, math.radians(5))):
    rng = np.random.default_rng(1000 + seed)
    return (truth[0] + rng.normal(0, std[0]), truth[1] + rng.normal(0, std[0]), truth[2] + rng.normal(0, std[1]))


def report(res, plane_id, camera="front"):
    return [p for p in res.planes if p.id == plane_id and p.camera == camera][0]


def pose_error(res, truth):
    return math.hypot(res.x - truth[0], res.y - truth[1]), abs(math.remainder(res.phi - truth[2], 2 * math.pi))


def west_panel(offset, share, side):
    """A panel parallel to wall_west ``offset`` in front of it, hiding ``share`` of the front
    camera's image width of it (at FACING_WEST) from one image edge (``side`` +-1): the rest of
    the camera's view still shows the wall."""
    cam_y = FACING_WEST[1] - ROBOT.camera("front").mount_xyz[1]
    to_panel = 0.4 - (-0.25 + offset)  # the camera is at x = 0.4
    edge = cam_y + side * to_panel * (2 * share - 1) * math.tan(math.radians(ROBOT.camera("front").hfov_deg / 2))
    region = (0.0, edge + 0.25) if side > 0 else (edge + 0.25, 1.5)  # along the wall from its start at y = -0.25
    return parallel_panel(ARENA["wall_west"], offset, 1.0, None, region=region)


@pytest.mark.parametrize("offset", [0.05, 0.1, 0.2, 0.3])
@pytest.mark.parametrize("share,side", [(0.6, 1), (0.6, -1), (0.75, 1), (0.75, -1)])
def test_a_panel_in_front_of_most_of_the_wall_is_never_taken_for_it(offset, share, side):
    scene = SimScene(ARENA, [west_panel(offset, share, side)])
    res = Localizer(ROBOT, ARENA).localize(frames(scene, FACING_WEST, seed=3), coarse_near(FACING_WEST, 3))
    west = report(res, "wall_west")
    if west.used:
        assert west.d == pytest.approx(WEST_D, abs=0.02), west.to_json()  # the wall, not the panel
        assert pose_error(res, FACING_WEST)[0] < 0.02
    else:
        assert west.reason  # dropped, saying why
    if share == 0.6:  # 40 % of the view still shows the wall: found behind the panel
        assert west.used, west.to_json()


def _room_with_a_door():
    """A wall 1.5 m in front of the robot with a 0.9 m door in it, and the side walls."""
    def face(pid, a, b, door=None, h=2.5):
        a, b = np.array(a, float), np.array(b, float)
        u = (b - a) / np.linalg.norm(b - a)
        length = float(np.linalg.norm(b - a))

        def quad(s0, s1, z0, z1):
            p0, p1 = a + s0 * u, a + s1 * u
            return [[p0[0], p0[1], z0], [p1[0], p1[1], z0], [p1[0], p1[1], z1], [p0[0], p0[1], z1]]
        if door is None:
            return make_plane(pid, [quad(0, length, 0, h)])
        s, w, top = door
        return make_plane(pid, [quad(0, s, 0, h), quad(s, s + w, top, h), quad(s + w, length, 0, h)])
    # Walk each face with the room on the right.
    return PlaneMap([face("front_wall", (1.5, 2.0), (1.5, -2.0), door=(1.6, 0.9, 2.1)),
                     face("left_wall", (-1.0, 2.0), (1.5, 2.0)), face("right_wall", (1.5, -2.0), (-1.0, -2.0))])


@pytest.mark.parametrize("angle", [20.0, 60.0, 120.0, 160.0, 175.0])
@pytest.mark.parametrize("hinge", ["start", "end"])
def test_an_open_door_leaf_is_never_taken_for_the_wall(angle, hinge):
    room = _room_with_a_door()
    opening = map_openings(room)[0]
    truth = (0.3, 0.0, 0.0)  # facing the door wall (x = 1.5) from 1.1 m: the camera is 1.1 m away
    scene = SimScene(room, [door_leaf(opening, angle, hinge=hinge)])
    res = Localizer(ROBOT, room).localize(frames(scene, truth, seed=5, cameras=("front",)), coarse_near(truth, 5))
    wall = report(res, "front_wall")
    if wall.used:
        # Swung back against the wall the leaf is a panel 4 cm in front of it: a fit to it is off by that.
        assert wall.d == pytest.approx(1.5 - truth[0], abs=0.02), wall.to_json()
        assert abs(res.x - truth[0]) < 0.02
    else:
        assert wall.reason


def test_identification_does_not_depend_on_the_seed():
    # The same frames under 100 frame numbers (what seeded the old RANSAC): the same decision.
    scene = SimScene(ARENA, [west_panel(0.15, 0.65, 1)])
    base = frames(scene, FACING_WEST, seed=11)
    loc = Localizer(ROBOT, ARENA)
    coarse = coarse_near(FACING_WEST, 11)
    outcomes = set()
    for k in range(100):
        shuffled = [dataclasses.replace(f, frame_number=k * 7919 + i) for i, f in enumerate(base)]
        res = loc.localize(shuffled, coarse)
        west = report(res, "wall_west")
        outcomes.add((west.used, west.d, res.x, res.y, res.phi))
    assert len(outcomes) == 1
    # Independent noise draws of the same scene: the wall behind the panel each time, never the panel.
    found = 0
    for seed in range(20):
        west = report(loc.localize(frames(scene, FACING_WEST, seed=100 + seed), coarse_near(FACING_WEST, seed)),
                      "wall_west")
        assert not west.used or west.d == pytest.approx(WEST_D, abs=0.02)
        found += west.used
    assert found >= 19


def _turned(plane, deg, shift):
    """The plane as built: turned ``deg`` about the vertical through its centre and moved ``shift`` along its normal."""
    c = plane.vertices.mean(axis=0)
    a = math.radians(deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_plane(plane.id, [(p - c) @ Rz.T + c + shift * plane.normal for p in plane.polygons])


@pytest.mark.parametrize("bad,camera", [("wall_east", "left"), ("wall_west", "front")])
def test_leave_one_out_drops_the_one_wall_that_breaks_agreement(bad, camera):
    # Three walls in four views: the front camera sees south and west, the left one south and east.
    truth = (0.3, 0.3, -3 * math.pi / 4)
    world = PlaneMap([_turned(p, 4.0, 0.03) if p.id == bad else p for p in ARENA.planes])
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(world), truth, seed=2), (0.33, 0.28, truth[2] + 0.03))
    assert res.status in FIX_STATUSES
    dropped = report(res, bad, camera)
    assert not dropped.used and "breaks the agreement" in dropped.reason
    assert [e["id"] for e in res.integrity["excluded"]] == [bad]
    assert sum(p.used for p in res.planes) == 3
    pos, head = pose_error(res, truth)
    assert pos < 0.005 and head < math.radians(0.2)


def test_a_wall_seen_by_both_cameras_and_built_off_the_drawing_is_dropped_in_both_views():
    truth = (0.3, 0.3, -3 * math.pi / 4)
    world = PlaneMap([_turned(p, 4.0, 0.03) if p.id == "wall_south" else p for p in ARENA.planes])
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(world), truth, seed=2), (0.33, 0.28, truth[2] + 0.03))
    assert sorted((e["id"], e["camera"]) for e in res.integrity["excluded"]) == [("wall_south", "front"),
                                                                                ("wall_south", "left")]
    assert res.status == "degenerate"  # y now rests on the coarse pose alone, and says so
    assert res.cov[1, 1] >= 0.05**2


def _perturbed(robot, rng):
    cams = tuple(dataclasses.replace(
        c, mount_xyz=tuple(float(v) for v in np.add(c.mount_xyz, rng.normal(0, P.mount_position_std, 3))),
        mount_rpy_deg=tuple(float(v) for v in np.add(c.mount_rpy_deg, rng.normal(0, P.mount_angle_std_deg, 3))))
        for c in robot.cameras)
    return dataclasses.replace(robot, cameras=cams)


def _random_scene(rng, scale_std):
    """A random arena pose with walls as built, the mounts off and the depth scale off by N(0, scale_std)."""
    truth = free_space_poses(ARENA, 1, rng, clearance=0.3, z=0.15)[0]
    scale = {c.name: float(rng.normal(0, scale_std)) for c in ROBOT.cameras}
    noise = DepthNoise.realistic(scale_error=scale, unit_seed=int(rng.integers(1 << 30)))
    scene = SimScene(ARENA, walls=as_built(ARENA, rng))
    fr = frames(scene, truth, seed=int(rng.integers(1 << 30)), noise=noise, robot=_perturbed(ROBOT, rng))
    coarse = (truth[0] + rng.normal(0, 0.03), truth[1] + rng.normal(0, 0.03), truth[2] + rng.normal(0, 0.05))
    return truth, fr, coarse


def test_a_depth_scale_error_within_its_uncertainty_gives_an_honest_covariance():
    rng = np.random.default_rng(5)
    loc = Localizer(ROBOT, ARENA)
    nees = []
    for _ in range(40):
        truth, fr, coarse = _random_scene(rng, P.depth_scale_std)
        res = loc.localize(fr, coarse)
        assert res.status in FIX_STATUSES
        e = np.array([res.x - truth[0], res.y - truth[1], math.remainder(res.phi - truth[2], 2 * math.pi)])
        nees.append(float(e @ np.linalg.solve(res.cov, e)))
    # An honest 3-dof covariance gives mean 3; the mean of 40 has a spread of about 0.4.
    assert 1.5 < np.mean(nees) < 4.5, nees


def test_a_depth_scale_error_far_beyond_its_uncertainty_is_flagged():
    # South seen by both cameras: with the front one reading 10 % short its view of it disagrees.
    truth = (0.3, 0.3, -3 * math.pi / 4)
    noise = DepthNoise.realistic(scale_error={"front": -0.10})
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(ARENA), truth, seed=4, noise=noise), (0.33, 0.28, truth[2]))
    assert res.status == "inconsistent" and "disagree" in res.integrity["reason"]
    assert res.protection["horizontal_m"] is None and res.measurements == []
    # Within its uncertainty the same geometry is fine.
    noise = DepthNoise.realistic(scale_error={"front": -P.depth_scale_std})
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(ARENA), truth, seed=4, noise=noise), (0.33, 0.28, truth[2]))
    assert res.status in FIX_STATUSES


def test_a_coarse_heading_90_degrees_off_is_contradicted_not_reported():
    # The walls the wrong heading predicts are all in view at some other distance: the fits are
    # consistent with each other, but one predicted wall's ROI shows depth far behind it.
    truth, coarse = (0.2, 0.9, 0.3), (0.2, 0.9, 1.8708)
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(ARENA), truth, seed=0), coarse)
    assert res.status == "inconsistent"
    assert "wall_north" in res.integrity["reason"] and res.integrity["evidence_against"]
    assert not any(p.used for p in res.planes) and res.measurements == []
    # Nothing is claimed: the coarse pose with the coarse uncertainty, and no protection level.
    assert (res.x, res.y, res.phi) == coarse
    assert np.all(np.sqrt(np.diag(res.cov)) >= [0.1, 0.1, math.radians(10) - 1e-9])
    assert res.protection["horizontal_m"] is None and res.protection["heading_rad"] is None


def test_a_far_wall_under_a_scale_error_is_not_dropped_by_the_second_pass():
    # A wall 5 m ahead read 1 % long moves by 5 cm: the second pass, with the first pass's tight
    # covariance, must still admit it.
    far = make_plane("far", [[[5.1, 5, 0], [5.1, -5, 0], [5.1, -5, 3], [5.1, 5, 3]]])
    side = make_plane("side", [[[-1, 1.2, 0], [6, 1.2, 0], [6, 1.2, 3], [-1, 1.2, 3]]])
    pm = PlaneMap([far, side])
    truth = (0.0, 0.0, 0.0)
    for scale in (0.01, -0.01):
        res = Localizer(ROBOT, pm).localize(
            frames(SimScene(pm), truth, noise=DepthNoise.realistic(scale_error=scale), cameras=("front",)),
            (0.05, -0.03, 0.02))
        assert res.passes == 2 and report(res, "far").used, [p.to_json() for p in res.planes]
        # Seen through an uncalibrated depth scale, x is known to about 5 cm: honestly weak.
        assert res.status == "degenerate" and math.sqrt(res.cov[0, 0]) > 0.03
        assert abs(res.x - truth[0]) < 3 * math.sqrt(res.cov[0, 0])


def test_protection_levels_bound_the_error_over_a_random_sample():
    rng = np.random.default_rng(21)
    loc = Localizer(ROBOT, ARENA)
    for _ in range(25):
        truth, fr, coarse = _random_scene(rng, P.depth_scale_std)
        res = loc.localize(fr, coarse, coarse_covariance(0.1, math.radians(10)))
        pos, head = pose_error(res, truth)
        assert res.protection["risk"] == P.integrity_risk
        if res.status in FIX_STATUSES + ("degenerate",):
            assert pos <= res.horizontal_pl and head <= res.heading_pl, (truth, res.status, pos, res.horizontal_pl)
            assert res.horizontal_pl >= 3.7 * math.sqrt(np.linalg.eigvalsh(res.cov[:2, :2])[0])


def test_two_walls_from_a_cold_start_cannot_vouch_for_each_other():
    # One wrong wall among two cannot be detected: the horizontal protection level rests on the
    # coarse pose (0.1 m), far above the covariance's own bound.
    res = Localizer(ROBOT, ARENA).localize(frames(SimScene(ARENA), FACING_WEST, seed=1), (0.53, 0.47, math.pi + 0.05))
    assert res.status == "unprotected" and sum(p.used for p in res.planes) == 2
    assert res.horizontal_pl > 0.3 > 3.7 * math.sqrt(np.linalg.eigvalsh(res.cov[:2, :2])[-1])
    # So the pose is not vouched for: 'unprotected', the reason naming the bound and its limit,
    # while its planes still go to the fusion with their honest covariance.
    assert "horizontal protection level" in res.integrity["reason"] and "alert limit" in res.integrity["reason"]
    assert len(res.measurements) == 2
    # A looser alert limit is a choice the config can make: then the same fix is vouched for.
    loose = dataclasses.replace(ROBOT, quality=dataclasses.replace(ROBOT.quality, horizontal_alert_limit=1.0,
                                                                  heading_alert_limit_deg=30.0))
    res = Localizer(loose, ARENA).localize(frames(SimScene(ARENA), FACING_WEST, seed=1), (0.53, 0.47, math.pi + 0.05))
    assert res.status == "ok" and res.integrity["reason"] == ""


def test_localize_json_reports_protection_levels(capsys, tmp_path):
    paths = []
    for cam in ("front", "left"):
        p = tmp_path / f"{cam}.npz"
        assert main(["render", "--robot", "config/robot.yaml", "--map", "config/maps/paper_arena.yaml",
                     "--pose", "0.3", "0.3", str(-3 * math.pi / 4), "--camera", cam, "--out", str(p), "--seed", "2"]) == 0
        paths.append(str(p))
    capsys.readouterr()
    assert main(["localize", "--robot", "config/robot.yaml", "--map", "config/maps/paper_arena.yaml",
                 "--init", "0.32", "0.29", "-2.33", "--init-std", "0.02", "1", "--json", *paths]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "ok"
    prot = out["protection"]
    assert set(prot) == {"horizontal_m", "heading_rad", "risk"} and prot["risk"] == P.integrity_risk
    assert 0.0 < prot["horizontal_m"] < 1.0 and 0.0 < prot["heading_rad"] < 0.2
    assert out["integrity"]["excluded"] == [] and out["integrity"]["walls_used"] == 4


def test_quality_degrades_when_a_protection_level_exceeds_its_alert_limit():
    q = QualityMonitor()
    q.note_fix(0.0)
    for k in range(10):
        q.note_update(0.05 * k, True)
    P_fused = np.diag([0.004**2, 0.004**2, math.radians(0.2) ** 2])
    assert q.evaluate(0.5, P_fused).state == LOCALIZED
    # The fused covariance is tiny, but the last localization leans on a wall a wrong one could
    # have moved by 12 cm unseen: the fused pose cannot be vouched for to 10 cm.
    r = q.evaluate(0.55, P_fused, FusedProtection(np.diag([0.005**2, 0.005**2, 1e-6]), 0.12, 0.001))
    assert r.state == DEGRADED and r.protection_exceeded and "horizontal protection level" in r.reason
    assert r.horizontal_pl > QualityConfig().horizontal_alert_limit


def test_the_controller_slows_down_while_a_protection_level_is_over_its_limit():
    core = ControllerCore(ROBOT, vision=True, t_start=0.0)
    core.set_pose(0.0, 0.0, 0.0, 0.0, np.diag([1e-6, 1e-6, 1e-6]))
    core.set_chassis_link(True)
    q = QualityMonitor()
    q.note_fix(0.0)
    q.note_update(0.0, True)
    fine = q.evaluate(0.01, np.diag([1e-6, 1e-6, 1e-6]))
    over = q.evaluate(0.02, np.diag([1e-6, 1e-6, 1e-6]), FusedProtection(None, 0.5, 0.0))
    assert not fine.protection_exceeded and over.protection_exceeded
    core._t_last_odom = 0.02  # fresh odometry: only the quality decides
    assert core.speed_scale(0.02, fine)[0] == 1.0
    scale, reason = core.speed_scale(0.02, over)
    assert scale == ROBOT.health.slow_scale and "protection level" in reason


def test_a_map_plane_carries_its_as_built_tolerance():
    from robot.base.errors import ConfigError
    from robot.maps.plane_map import DEFAULT_TOLERANCE, parse_plane_map

    quad = [[0, 0, 0], [1, 0, 0], [1, 0, 1]]
    m = parse_plane_map({"planes": [{"id": "a", "vertices": quad},
                                    {"id": "b", "vertices": quad, "tolerance": 0.02},
                                    {"id": "c", "vertices": quad, "source": {"ifc_type": ["IfcCurtainWall"]}}]})
    assert [p.tolerance for p in m.planes] == [DEFAULT_TOLERANCE, 0.02, 0.005]
    assert [p.tolerance for p in parse_plane_map({"tolerance": 0.003, "planes": [{"id": "a", "vertices": quad}]}).planes] \
        == [0.003]
    # Saved and loaded again, a tolerance that is not the default for its source is kept.
    assert parse_plane_map(m.to_yaml_data()).planes[1].tolerance == 0.02
    with pytest.raises(ConfigError, match="tolerance"):
        parse_plane_map({"planes": [{"id": "a", "vertices": quad, "tolerance": -0.01}]})
    # Imported maps get it from their element types; a looser wall counts for more in the covariance.
    assert {p.tolerance for p in load_plane_map("config/maps/institute_ground.yaml").planes} <= {0.01, 0.02, 0.03}
    loose = PlaneMap([dataclasses.replace(p, tolerance=0.05) for p in ARENA.planes])
    fr = frames(SimScene(ARENA), FACING_WEST, seed=1)
    tight = Localizer(ROBOT, ARENA).localize(fr, FACING_WEST, coarse_covariance(0.02, 0.02))
    wide = Localizer(ROBOT, loose).localize(fr, FACING_WEST, coarse_covariance(0.02, 0.02))
    assert math.sqrt(wide.cov[0, 0]) > 2 * math.sqrt(tight.cov[0, 0])


# -- the fused pose: a wrong wall's bound outlives the prior it was taken from --------------------

def localized(walls, directions, h, heading):
    """A localization result that carries only the integrity fields the fusion reads."""
    hyp = {"walls": list(walls), "directions": directions, "horizontal_m": h, "heading_rad": heading}
    return dataclasses.make_dataclass("R", [("integrity", dict), ("systematic_cov", object), ("risk", float)])(
        {"separation_m": 0.0, "separation_rad": 0.0, "prior_bounded": [hyp]}, None, 1e-3)


def test_a_wrong_wall_bound_is_carried_until_other_walls_observe_what_it_left_unobserved():
    """Leaving wall_north out leaves y to the prior. On a wide prior that bound is 0.4 m; once the
    filter's own pose (built on wall_north) is the prior, the same hypothesis comes back bounded by
    a few millimetres: the fused pose keeps the 0.4 m until another wall facing y is fused."""
    north = {"wall_north": (0.0, -1.0)}
    first = FusedProtection.from_localization(localized(["wall_north"], [[0.0, 1.0, 0.0]], 0.4, 0.01), None, north)
    assert first.prior_bound_h == pytest.approx(0.4)
    again = FusedProtection.from_localization(localized(["wall_north"], [[0.0, 1.0, 0.0]], 0.004, 0.001), first,
                                              {**north, "wall_east": (-1.0, 0.0)})  # east faces x: y stays open
    assert again.prior_bound_h == pytest.approx(0.4)
    assert again.levels(np.diag([1e-6, 1e-6, 1e-8]))[0] >= 0.4
    lifted = FusedProtection.from_localization(localized(["wall_north"], [[0.0, 1.0, 0.0]], 0.004, 0.001), again,
                                               {**north, "wall_east": (-1.0, 0.0), "wall_south": (0.0, 1.0)})
    assert lifted.prior_bound_h == 0.0 and lifted.open_faults == ()
    # A hypothesis without a wrong wall is the filter's own business (its covariance keeps what is unobserved).
    none = FusedProtection.from_localization(localized([], [[0.0, 1.0, 0.0]], 0.3, 0.01), None, north)
    assert none.prior_bound_h == 0.0



def test_a_relocalized_pose_s_hidden_wall_bound_holds_until_another_wall_observes_its_direction():
    """A relocalization's hidden wall (a panel may stand in front of it) bounds the fused pose by
    its offset along its direction; neither the wall itself nor a wall across that direction
    lifts it, a wall facing along it does."""
    from types import SimpleNamespace

    P = np.diag([1e-4, 1e-4, 1e-5])
    seed = FusedProtection.from_hidden_walls([{"plane": "w1", "up_to_m": 0.5, "direction": [1.0, 0.0]}], P)
    assert seed.levels(P)[0] >= 0.5 + 3.0 * 0.01
    assert FusedProtection.from_hidden_walls([], P).levels(P)[0] < 0.05
    fix = SimpleNamespace(integrity={}, systematic_cov=None, risk=1e-3)  # an accepted localization, no faults of its own
    kept = FusedProtection.from_localization(fix, seed, {"w1": (1.0, 0.0), "w2": (0.0, 1.0)})
    assert kept.levels(P)[0] >= 0.5
    lifted = FusedProtection.from_localization(fix, kept, {"w1": (1.0, 0.0), "w2": (0.0, 1.0), "w3": (-0.95, 0.3)})
    assert lifted.levels(P)[0] < 0.05 and lifted.open_faults == ()


def test_a_panel_hiding_a_wall_from_a_cold_start_never_makes_the_fused_pose_confidently_wrong():
    """The robot stands still from a cold start (0.1 m, 10 deg); a panel 0.26 m in front of
    wall_east covers all the front camera sees of it (site scene, realistic camera). The first
    localization takes the panel for the wall, rightly unprotected; later ones, on the filter's
    pose, find the panel where they expect the wall. The fused pose is as wrong as the first fix,
    and its protection level must keep saying so, every frame: never above the error, never
    'localized' with it."""
    truth, coarse = (0.638, 0.529, 0.169), (0.673, 0.714, 0.309)
    panel = parallel_panel(ARENA["wall_east"], 0.26, 1.0, None, region=(0.038, 1.170))
    scene = SimScene(ARENA, [panel])
    noise = DepthNoise.realistic(scale_error={"front": -0.0018, "left": 0.0056}, unit_seed=123)
    core = ControllerCore(ROBOT, vision=True, t_start=0.0, plane_map=ARENA)
    core.set_pose(0.0, *coarse, coarse_covariance(0.1, math.radians(10.0)))
    loc = Localizer(ROBOT, ARENA)
    rng = np.random.default_rng(966)
    errors = []
    for k in range(12):
        t = 0.2 * (k + 1)
        shots = [render_depth_frame(ROBOT, scene, c, truth, rng=rng, noise=noise, frame_number=k) for c in ("front", "left")]
        pose, cov = core.coarse_pose(t)
        core.on_localization(loc.localize(shots, pose, cov), t)
        (x, y, _), _ = core.pose(t)
        q = core.evaluate_quality(t)
        err = math.hypot(x - truth[0], y - truth[1])
        errors.append(err)
        assert err <= q.horizontal_pl, (k, err, q.horizontal_pl)
        assert not (q.state == LOCALIZED and err > 0.05), (k, err, q)
    assert max(errors) > 0.15  # the scene does what it is meant to: the panel pulled the pose


def test_a_panel_seen_at_a_slant_in_a_corner_is_not_taken_for_the_wall():
    """The front camera sees wall_west at a grazing angle, a panel 0.14 m in front of it over most
    of what it sees; behind the panel lie the rest of wall_west and, past the corner, wall_north:
    two surfaces, neither holding half of what is behind. That is depth behind the panel, not
    flying pixels: over 20 draws of noise and coarse pose the panel is never used (before: 3
    times, the pose 0.13 m off), and the wall itself is found in some."""
    truth, coarse = (0.060, 0.435, 1.732), (-0.067, 0.361, 1.883)
    panel = parallel_panel(ARENA["wall_west"], 0.142, 1.0, None, region=(0.364, 0.999))
    scene = SimScene(ARENA, [panel])
    loc = Localizer(ROBOT, ARENA)
    pi = ARENA["wall_west"].pi @ pose_to_T_ground_robot(*truth)
    d_wall = abs(pi[3]) / np.linalg.norm(pi[:3])  # the wall's distance from the robot centre
    found = 0
    for seed in range(20):
        noise = DepthNoise.realistic(scale_error={"front": 0.008, "left": -0.0016}, unit_seed=seed)
        rng = np.random.default_rng(seed)
        start = tuple(c + rng.normal(0, 0.03) for c in coarse)
        res = loc.localize(frames(scene, truth, seed=seed, noise=noise), start, coarse_covariance(0.1, math.radians(10.0)))
        west = report(res, "wall_west", "front")
        if west.used:
            offset = abs(west.d) / np.linalg.norm(west.normal) - d_wall
            assert abs(offset) < 0.02, (seed, offset)  # the wall, never the panel 0.14 m in front of it
            found += 1
    assert found >= 3


def test_two_surfaces_behind_are_surfaces_and_flying_pixels_are_not():
    from robot.localization import plane_fit as pf

    params = pf.FitParams()
    rng = np.random.default_rng(4)
    rx, ry = rng.uniform(-0.4, 0.4, 400), rng.uniform(-0.3, 0.3, 400)
    near, far = 1.0 / (0.5 + 0.3 * rx), 1.0 / (0.4 - 0.2 * rx + 0.05 * ry)  # two slanted planes, 1/z linear
    z = np.where(np.arange(400) % 5 < 3, near, far)  # 60 % and 40 %: neither a majority of... both planes
    assert pf._two_surfaces(rx, ry, z, params)
    z_fly = rng.uniform(1.0, 3.0, 400)  # depths strung along the rays between two surfaces
    assert not pf._two_surfaces(rx, ry, z_fly, params) and not pf._one_surface(rx, ry, z_fly, params)
