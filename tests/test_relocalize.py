"""Global relocalization: no coarse pose, a verdict that is never confidently wrong."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from drivers.sim.clutter import parallel_panel
from drivers.sim.render import DepthNoise, SimScene, render_depth_frame
from robot.base.errors import InputError, RobotError
from robot.config import load_robot_config
from robot.localization.localizer import FIX_STATUSES
from robot.localization.relocalize import AMBIGUOUS, NONE, UNIQUE, Relocalizer
from robot.maps.plane_map import load_plane_map
from robot.recording.snapshot import save_snapshot

ROBOT = load_robot_config("config/robot.yaml")
ARENA = load_plane_map("config/maps/paper_arena.yaml")
HOUSE = load_plane_map("config/maps/fzk_haus_ground.yaml")


def frames_at(plane_map, pose, seed=0, scene=None):
    rng = np.random.default_rng(seed)
    scene = scene or SimScene(plane_map)
    return [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, noise=DepthNoise()) for c in ROBOT.cameras]


def pose_error(h, pose):
    return math.hypot(h.x - pose[0], h.y - pose[1]), abs(math.remainder(h.phi - pose[2], 2 * math.pi))


@pytest.fixture(scope="module")
def house():
    return Relocalizer(ROBOT, HOUSE)


@pytest.mark.parametrize("seed, phi", list(enumerate([-3.0, -2.356, 0.785, 1.571, 2.356])))
def test_unique_recovery_in_a_house_from_arbitrary_headings(house, seed, phi):
    pose = (9.5, 7.0, phi)  # the large room of the house
    res = house.relocalize(frames_at(HOUSE, pose, seed=seed))
    assert res.verdict == UNIQUE, res.reason
    d_xy, d_phi = pose_error(res.hypotheses[0], pose)
    assert d_xy < 0.02 and d_phi < math.radians(1.0)
    # Refined by the normal localizer: millimetres, with an honest covariance.
    h = res.hypotheses[0]
    assert h.refined and h.status in FIX_STATUSES
    sx, sy = math.sqrt(h.cov[0][0]), math.sqrt(h.cov[1][1])
    assert abs(h.x - pose[0]) < 5 * max(sx, 1e-3) and abs(h.y - pose[1]) < 5 * max(sy, 1e-3)


def test_the_square_arena_centre_is_ambiguous_with_all_four_headings():
    pose = (0.5, 0.5, 0.3)
    res = Relocalizer(ROBOT, ARENA).relocalize(frames_at(ARENA, pose, seed=3))
    assert res.verdict == AMBIGUOUS
    assert len(res.hypotheses) == 4
    for expect in (-math.pi / 2, 0.0, math.pi / 2, math.pi):
        assert any(abs(math.remainder(h.phi - pose[2] - expect, 2 * math.pi)) < math.radians(1.0) for h in res.hypotheses)
    for h in res.hypotheses:
        assert math.hypot(h.x - 0.5, h.y - 0.5) < 0.02


def test_any_arena_pose_comes_back_with_its_symmetric_twins_and_the_truth_among_them():
    pose = (0.2, 0.9, 0.3)  # the square arena maps every pose onto three others
    res = Relocalizer(ROBOT, ARENA).relocalize(frames_at(ARENA, pose, seed=4))
    assert res.verdict == AMBIGUOUS and len(res.hypotheses) == 4
    assert min(pose_error(h, pose)[0] for h in res.hypotheses) < 0.02


def test_outside_every_room_there_is_no_answer(house):
    lo, hi = HOUSE.bounds()
    pose = (float(lo[0]) - 2.0, float(lo[1]) - 2.0, -2.4)  # outside, looking away from the building
    res = house.relocalize(frames_at(HOUSE, pose, scene=SimScene(HOUSE, backdrop=False)))
    assert res.verdict == NONE and res.hypotheses == []


def test_a_view_of_one_wall_only_is_not_enough(house):
    pose = (7.28, 7.29, -0.785)  # both cameras see one long wall
    res = house.relocalize(frames_at(HOUSE, pose))
    assert res.verdict != UNIQUE or pose_error(res.hypotheses[0], pose)[0] < 0.02


def test_repeated_rooms_are_never_a_wrong_unique():
    """Rooms alike but for where their doors are: ambiguous, none, or unique only when right."""
    from drivers.sim.building import free_space_poses, room_grid_map

    grid = room_grid_map(3, 3, seed=1)
    pose = free_space_poses(grid, 1, np.random.default_rng(2), z=0.15)[0]
    pose = (float(pose[0]), float(pose[1]), 0.4)
    res = Relocalizer(ROBOT, grid).relocalize(frames_at(grid, pose, seed=5))
    if res.verdict == UNIQUE:
        d_xy, d_phi = pose_error(res.hypotheses[0], pose)
        assert d_xy < 0.02 and d_phi < math.radians(1.0)
    if res.verdict == AMBIGUOUS:
        assert any(pose_error(h, pose)[0] < 0.03 for h in res.hypotheses)


def test_bad_input_is_one_clear_error(house, tmp_path):
    with pytest.raises(InputError, match="at least one depth frame"):
        house.relocalize([])
    f = frames_at(HOUSE, (7.28, 7.29, 0.8))[0]
    f.camera = "rear"
    with pytest.raises(RobotError, match="unknown camera 'rear'"):
        house.relocalize([f])
    with pytest.raises(InputError, match="outside the map"):
        house.relocalize(frames_at(HOUSE, (7.28, 7.29, 0.8)), region=(100.0, 100.0, 101.0, 101.0))


def test_cli_relocalize_json_and_exit_status(tmp_path):
    # (5.7, 8.0, 0.785) was used until the one-panel credit: a twin 7 m away then explains the
    # view as well if a panel hides one of its walls, and the honest verdict there is ambiguous.
    pose = (9.5, 7.0, 0.785)
    paths = []
    for f in frames_at(HOUSE, pose, seed=2):
        p = tmp_path / f"{f.camera}.npz"
        save_snapshot(p, f)
        paths.append(str(p))
    cmd = [sys.executable, "-m", "robot.cli.main", "relocalize", "--map", "config/maps/fzk_haus_ground.yaml", "--json"]
    r = subprocess.run(cmd + paths, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    import json

    doc = json.loads(r.stdout)
    assert doc["verdict"] == UNIQUE and set(doc) >= {"verdict", "hypotheses", "ms"}
    h = doc["hypotheses"][0]
    assert set(h) >= {"x", "y", "phi", "cov", "score", "planes"}
    assert math.hypot(h["x"] - pose[0], h["y"] - pose[1]) < 0.02
    r = subprocess.run(cmd[:-1] + ["--region", "50", "50", "60", "60"] + paths, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "outside the map" in r.stderr
    r = subprocess.run(cmd + [paths[0], paths[0]], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "same camera" in r.stderr


def test_a_twin_that_wins_on_clutter_but_sees_through_walls_is_not_unique(house):
    """fzk_haus_ground is nearly point-symmetric. With two doors standing almost closed in their
    openings (the map has the openings, so the truth scores them as clutter) the 180 deg twin
    scores 20 to 47 nats above the truth, beyond the unique margin in some draws, while it sees
    through its predicted walls ten times as often. Never a unique twin; the truth in the list.
    Since the verification scores a surface standing in front of a wall as the one object it is
    (PANEL_PRIOR), the near-closed leaves no longer cost the truth pixel by pixel: it wins, uniquely."""
    from drivers.sim.clutter import door_leaf, map_openings, person

    openings = {round(o.s0, 2): o for o in map_openings(HOUSE) if o.plane_id == "w007"}
    clutter = [door_leaf(openings[1.31], 7.74), door_leaf(openings[4.92], 3.64),
               person(6.166, 2.502, -1.380, height=1.79), person(9.311, 5.472, -1.803, height=1.735)]
    scene = SimScene(HOUSE, clutter=clutter)
    pose = (3.0049, 8.4096, 1.9990)
    for seed in range(6):
        res = house.relocalize(frames_at(HOUSE, pose, seed=seed, scene=scene), seed=seed)
        right = [pose_error(h, pose)[0] < 0.03 and pose_error(h, pose)[1] < math.radians(1.0) for h in res.hypotheses]
        if res.verdict == UNIQUE:
            assert right[0], (seed, res.hypotheses[0].to_json())
        else:
            assert res.verdict == AMBIGUOUS and any(right), (seed, res.verdict, res.reason)


def test_the_wall_finder_ignores_the_ceiling_and_orients_a_far_wall():
    """Seen over the top of the walls, the ceiling's points end in an arc at the range limit, and a
    line along that arc passed for a far wall 7 to 15 deg off every wall of duplex_level1 (even in
    exact depth), so the one wall across the room matched nothing. Its direction comes with a
    standard deviation that the pair matching widens its tolerance by."""
    from robot.localization.relocalize import extract_walls

    duplex = load_plane_map("config/maps/duplex_level1.yaml")
    pose = (4.575, -6.207, 1.346)  # w000, the y-normal wall, is 5.8 m ahead; the rest are x-normal
    cam = ROBOT.camera("front")
    scene = SimScene(duplex)
    found = 0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        frame = render_depth_frame(ROBOT, scene, "front", pose, rng=rng, noise=DepthNoise())
        walls = extract_walls(frame, cam, np.random.default_rng(seed), min_range=0.2, max_range=6.0)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        angles = [math.degrees(math.atan2(s * w.n_r[0] + c * w.n_r[1], c * w.n_r[0] - s * w.n_r[1])) for w in walls]
        # Every wall found is a wall of the map's two directions (within 3 deg), and the far one is among them.
        assert all(min(abs(math.remainder(a - m, 360.0)) for m in (0.0, 90.0, 180.0, -90.0)) < 3.0 for a in angles), angles
        far = [w for w, a in zip(walls, angles) if abs(math.remainder(a + 90.0, 360.0)) < 3.0]
        assert all(0.0 < w.angle_std < math.radians(3.0) for w in far)
        found += bool(far)
    # About 100 points at 5.8 m, near the 2 % a wall needs: not in every draw (seeds 1 and 2 miss it).
    assert found >= 1


# A panel parallel to the wall the front camera sees, along all of it (a row of boards or
# sheets): that wall looks nearer, and the view like another place of the house or the same place
# moved. Scored pixel by pixel (before), each of these came back unique and 0.3 to 9 m off.
PANEL_CASES = [((9.587, 2.355, -1.132), "w013", 0.26), ((9.599, 5.071, 0.04), "w015", 0.18),
               ((1.275, 8.644, -1.39), "w007", 0.16), ((10.686, 2.423, 0.701), "w015", 0.30)]


def panel_frames(pose, wall, offset):
    scene = SimScene(HOUSE, [parallel_panel(HOUSE[wall], offset, 1.0, None)])
    return [render_depth_frame(ROBOT, scene, c.name, pose, rng=np.random.default_rng(2),
                               noise=DepthNoise.realistic(unit_seed=2)) for c in ROBOT.cameras]


def off_within_hidden_wall(h, pose, tol=0.02):
    ex, ey = pose[0] - h.x, pose[1] - h.y
    for hw in h.hidden_walls:
        ux, uy = hw["direction"]
        if -tol <= ex * ux + ey * uy <= hw["up_to_m"] + tol and abs(-ex * uy + ey * ux) <= tol:
            return True
    return False


@pytest.mark.parametrize("pose, wall, offset", PANEL_CASES)
def test_a_panel_hiding_the_wall_in_view_is_never_a_wrong_unique(house, pose, wall, offset):
    res = house.relocalize(panel_frames(pose, wall, offset))
    if res.verdict == UNIQUE:
        h = res.hypotheses[0]
        d_xy, d_phi = pose_error(h, pose)
        assert d_phi < math.radians(1.0)
        # Right, or off only along the direction its hidden-wall bound names, and within it.
        assert d_xy < 0.02 or off_within_hidden_wall(h, pose), (d_xy, h.to_json())
    elif pose == PANEL_CASES[0][0]:  # its truth is found from other walls: among the hypotheses
        assert res.verdict == AMBIGUOUS, res.reason
        # The truth among the hypotheses, or where one of them says a hidden wall may put it.
        assert any(pose_error(h, pose)[1] < math.radians(1.0) and (pose_error(h, pose)[0] < 0.05 or
                   off_within_hidden_wall(h, pose, 0.05)) for h in res.hypotheses), [h.to_json() for h in res.hypotheses]


def test_a_relocalized_pose_behind_a_hidden_wall_is_never_confidently_wrong(house):
    """Unique, 0.3 m off: the panel stands where the map has the wall, and nothing else the
    cameras see fixes that direction. The answer says so (hidden_walls); given to the robot, the
    fused protection level keeps covering the error while the localizer, on the filter's own
    pose, keeps finding the panel where it expects the wall: never 'localized' with the error."""
    from robot.control.core import ControllerCore
    from robot.fusion.quality import LOCALIZED
    from robot.localization.localizer import Localizer

    pose, wall, offset = PANEL_CASES[3]
    shots = panel_frames(pose, wall, offset)
    res = house.relocalize(shots)
    assert res.verdict == UNIQUE, res.reason
    h = res.hypotheses[0]
    assert pose_error(h, pose)[0] > 0.2  # the scene does what it is meant to
    assert wall in [hw["plane"] for hw in h.hidden_walls] and off_within_hidden_wall(h, pose)
    core = ControllerCore(ROBOT, vision=True, t_start=0.0, plane_map=HOUSE)
    core.set_pose(0.0, h.x, h.y, h.phi, np.asarray(h.cov), hidden_walls=h.hidden_walls)
    loc = Localizer(ROBOT, HOUSE)
    scene = SimScene(HOUSE, [parallel_panel(HOUSE[wall], offset, 1.0, None)])
    rng = np.random.default_rng(7)
    for k in range(6):
        t = 0.2 * (k + 1)
        frames = [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, noise=DepthNoise.realistic(unit_seed=7),
                                     frame_number=k) for c in ROBOT.cameras]
        p, cov = core.coarse_pose(t)
        core.on_localization(loc.localize(frames, p, cov), t)
        (x, y, _), _ = core.pose(t)
        q = core.evaluate_quality(t)
        err = math.hypot(x - pose[0], y - pose[1])
        assert err <= q.horizontal_pl, (k, err, q.horizontal_pl)
        assert not (q.state == LOCALIZED and err > 0.05), (k, err, q)
    # Without the bound the relocalization carried, the same fused pose claimed centimetres.
    core2 = ControllerCore(ROBOT, vision=True, t_start=0.0, plane_map=HOUSE)
    core2.set_pose(0.0, h.x, h.y, h.phi, np.asarray(h.cov))
    p, cov = core2.coarse_pose(0.2)
    core2.on_localization(loc.localize(shots, p, cov), 0.2)
    assert core2.evaluate_quality(0.2).horizontal_pl < 0.2


def test_hidden_walls_in_a_recording_are_checked():
    from robot.recording import schema

    good = schema.set_pose_message(1.0, 0.0, 0.0, 0.0, np.eye(3), "relocalization",
                                   [{"plane": "w1", "up_to_m": 0.5, "direction": [1.0, 0.0]}])
    assert schema.hidden_walls_from_json(good["hidden_walls"]) == good["hidden_walls"]
    assert schema.hidden_walls_from_json(None) == []
    for bad in ("x", [1], [{"plane": "w1"}], [{"plane": "w1", "up_to_m": -1, "direction": [1, 0]}],
                [{"plane": "w1", "up_to_m": 0.5, "direction": [3, 0]}]):
        with pytest.raises(ValueError):
            schema.hidden_walls_from_json(bad)


def test_pair_solutions_of_one_pose_are_one_cluster_across_cell_borders():
    """Pair solutions scatter by centimetres; where they straddle a cell border (here x = 0.15 m
    and the heading's wrap at +-pi), they are still one pose to verify, while poses farther
    apart than the cluster size stay apart."""
    from robot.localization.relocalize import CLUSTER_PHI, CLUSTER_XY, _cluster

    rng = np.random.default_rng(4)
    truth = [(CLUSTER_XY, 1.0, 0.3), (2.0, 2.0, math.pi - 0.002), (2.0 + 2.5 * CLUSTER_XY, 2.0, math.pi)]
    hyps = []
    for k, (x, y, phi) in enumerate(truth):
        for j in range(12):
            hyps.append((x + rng.normal(0, 0.01), y + rng.normal(0, 0.01),
                         math.remainder(phi + rng.normal(0, 0.003), 2 * math.pi), (k, j)))
    clusters = _cluster(hyps)
    assert len(clusters) == 3
    assert sorted(c[3] for c in clusters) == [12, 12, 12]
    for x, y, phi in truth:
        c = min(clusters, key=lambda c: math.hypot(c[0] - x, c[1] - y))
        assert math.hypot(c[0] - x, c[1] - y) < 0.01
        assert abs(math.remainder(c[2] - phi, 2 * math.pi)) < 0.003
        assert c[0] != x or c[1] != y  # (a mean of the members, not the truth itself)
    # Two poses a little more than the cluster size apart are two places to verify.
    apart = [(0.05, 0.05, 0.0, (0, 0)), (0.05 + 1.1 * CLUSTER_XY, 0.05, 0.0, (0, 1)),
             (0.05, 0.05, 1.1 * CLUSTER_PHI, (0, 2))]
    assert len(_cluster(apart)) == 3


def test_a_row_of_alike_offices_lists_every_one_with_the_truth_among_them():
    """In institute_ground's row of alike offices more places than the usual refinement budget
    explain the view equally well: the answer lists them all (it listed the first 24 and, for
    two draws in three, not the true one), and the truth is among them."""
    from robot.localization.relocalize import MAX_REFINE

    rel = Relocalizer(ROBOT, load_plane_map("config/maps/institute_ground.yaml"))
    pose = (24.753, 13.053, 1.953)
    res = rel.relocalize(frames_at(rel.map, pose, seed=1), seed=1)
    assert res.verdict == AMBIGUOUS
    assert len(res.hypotheses) > MAX_REFINE
    assert min(pose_error(h, pose)[0] + pose_error(h, pose)[1] for h in res.hypotheses) < 0.03


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_best_the_localizer_leaves_loose_along_one_wall_is_pinned_by_the_score(house, seed):
    """In the hall of the house the cameras see one long wall well and the door jambs and wall ends
    that fix the position along it only as slivers, too small for a plane fit: the localizer's fix
    is degenerate. The score sees the slivers; it pins the loose direction, with a deliberately
    wide standard deviation, and the verdict is unique."""
    pose = (3.422, 1.783, -0.473)
    frames = [render_depth_frame(ROBOT, SimScene(HOUSE), c.name, pose, rng=np.random.default_rng(seed),
                                 noise=DepthNoise.realistic()) for c in ROBOT.cameras]
    res = house.relocalize(frames, seed=seed)
    assert res.verdict == UNIQUE, res.reason
    h = res.hypotheses[0]
    assert h.status == "degenerate" and h.loose is not None and h.pinned is not None
    u = np.array(h.loose)
    err = np.array([h.x - pose[0], h.y - pose[1]])
    assert abs(float(err @ u)) < h.pinned  # within one std along the pinned direction
    assert abs(float(err @ np.array([-u[1], u[0]]))) < 0.01  # the localizer's own direction: millimetres
    cov = np.asarray(h.cov)
    assert math.isclose(float(u @ cov[:2, :2] @ u), h.pinned ** 2, rel_tol=1e-9)
    assert h.to_json()["pinned"]["std_m"] == h.pinned


class _Profile:
    """A scorer stand-in: the score along x only, from ``f``."""

    def __init__(self, f):
        self.f, self.last_see_through, self.last_plain, self.last_two = f, 0.0, 0.0, 0.0

    def score(self, pose, rels=None):
        s = self.f(pose[0])
        self.last_plain = self.last_two = s
        return s, 0.9, ["w"]


@pytest.mark.parametrize("profile, pinned_at", [
    (lambda x: -4000.0 * (x - 0.06) ** 2, 0.06),  # one peak: 40 nats down 0.1 m either side
    (lambda x: -100.0 * x ** 2, None),  # too flat: within 40 nats all the way to PIN_REACH
    (lambda x: -4000.0 * min((x - 0.15) ** 2, (x + 0.15) ** 2), None),  # two places along the direction
])
def test_the_pin_takes_one_peak_and_refuses_a_flat_or_split_profile(house, profile, pinned_at):
    from robot.localization.relocalize import PIN_STEP, Hypothesis

    best = Hypothesis(0.0, 0.0, 0.3, np.diag([1e-6, 0.0025, 1e-6]), 0.0, 0.9, ["w"], True, "degenerate",
                      loose=(1.0, 0.0))
    got = house._pin(best, _Profile(profile), 40.0)
    if pinned_at is None:
        assert got is None
        return
    assert got is not None and abs(got.x - pinned_at) < 1e-9 and got.y == 0.0 and got.phi == 0.3
    assert 0.1 <= got.pinned <= 0.1 + 2 * PIN_STEP  # the half-width of the stretch within 40 nats
    assert math.isclose(got.cov[0][0], got.pinned ** 2) and got.cov[1][1] == 0.0025  # the other directions kept


def _benchmark_clutter(name: str, kinds: list) -> list:
    """The clutter of a benchmark site saved in tests/data (each solid's kind and faces), checked
    to be the one the test was written for."""
    from drivers.sim.clutter import Solid

    data = np.load(f"tests/data/{name}")
    found = [str(k) for k in data["kinds"]]
    assert found == kinds
    return [Solid(kind, tuple(data[f] for f in sorted(data.files) if f.startswith(f"s{i}_")))
            for i, kind in enumerate(found)]


def test_a_shelving_front_standing_where_a_twin_s_wall_would_be_is_no_wrong_unique(house):
    """A site of the benchmark (tests/data/fzk_shelving_twin_clutter.npz: its clutter's faces): a
    shelving unit's front stands where the 180 deg twin of the pose in the house would see a wall.
    The twin rests on two walls and leads the true pose, which rests on five as cleanly, by some
    400 nats, all of them the shelving's pixels as clutter. It must not come back unique."""
    clutter = _benchmark_clutter("fzk_shelving_twin_clutter.npz", ["panel", "shelving", "panel", "door"])
    pose = (1.309, 4.780, 1.537)
    scene = SimScene(HOUSE, clutter=clutter)
    for seed in range(3):
        frames = [render_depth_frame(ROBOT, scene, c.name, pose, rng=np.random.default_rng(seed),
                                     noise=DepthNoise.realistic()) for c in ROBOT.cameras]
        res = house.relocalize(frames, seed=seed)
        assert res.verdict != UNIQUE or pose_error(res.hypotheses[0], pose)[0] < 0.05, (seed, res.reason)
        assert res.verdict == AMBIGUOUS and "rests on 2 walls only" in res.reason, res.reason


def _unbuilt_site():
    """A site of the benchmark (tests/data/fzk_unbuilt_wall_clutter.npz: its clutter's faces, two
    panels, a person, a shelving unit) in the house, with wall w005, the one the front camera faces,
    in the map but not built: the cameras see through it into the room behind."""
    from drivers.sim.clutter import WallDeviation, built_walls

    clutter = _benchmark_clutter("fzk_unbuilt_wall_clutter.npz", ["panel", "person", "panel", "shelving"])
    return SimScene(HOUSE, clutter=clutter, walls=built_walls(HOUSE, {"w005": WallDeviation(built=False)}))


UNBUILT_POSE = (2.851, 8.121, -0.849)


def test_a_wall_not_built_yet_is_no_wrong_unique(house):
    """Seen through the missing wall, the room behind makes a place 7.1 m away explain the view,
    while the true pose, which predicts the wall, sees through it on two thirds of its pixels.
    Without the check for a missing wall that place came back unique for 3 of these 4 noise draws.
    Now no draw is unique, and where the check decides, the truth is in the list, named as the
    place that needs w005 missing."""
    scene = _unbuilt_site()
    by_check = 0
    for seed in range(4):
        frames = [render_depth_frame(ROBOT, scene, c.name, UNBUILT_POSE, rng=np.random.default_rng(seed),
                                     noise=DepthNoise.realistic()) for c in ROBOT.cameras]
        res = house.relocalize(frames, seed=seed)
        assert res.verdict != UNIQUE or pose_error(res.hypotheses[0], UNBUILT_POSE)[0] < 0.05, (seed, res.reason)
        if "not built" in res.reason:
            by_check += 1
            truth = [h for h in res.hypotheses if pose_error(h, UNBUILT_POSE)[0] < 0.05
                     and pose_error(h, UNBUILT_POSE)[1] < math.radians(1.0)]
            assert truth and truth[0].unbuilt == "w005", (seed, [(h.x, h.y, h.unbuilt) for h in res.hypotheses])
            assert "'w005'" in res.reason and truth[0].to_json()["unbuilt"] == "w005"
    assert by_check >= 3


def _boards_where_the_wall_would_be():
    """A site of the benchmark (tests/data/fzk_unbuilt_wall_boards.npz: a person, a panel 6 cm in
    front of w005 over 63 % of it, a pallet stack, an open door leaf) in the house, with w005 in
    the map but not built: the front camera sees the boards where the wall would stand, and
    beside and above them the room behind."""
    from drivers.sim.clutter import WallDeviation, built_walls

    clutter = _benchmark_clutter("fzk_unbuilt_wall_boards.npz", ["person", "panel", "pallet", "door"])
    return SimScene(HOUSE, clutter=clutter, walls=built_walls(HOUSE, {"w005": WallDeviation(built=False)}))


BOARDS_POSE = (2.725, 8.704, -0.145)


def test_boards_stacked_where_a_wall_is_not_built_yet_are_no_wrong_unique(house):
    """The truth explains the boards best as a panel before w005, and then sees through w005 on a
    quarter of its pixels; scored with w005 left out everywhere, the boards are clutter before
    the room behind. Either way it stayed hundreds of nats short of a place about 7 m away, turned
    180 deg, which came back unique. The check now scores every pixel of the missing wall on what
    stands behind it but keeps the wall's plane for the one panel a place may have: the truth
    with w005 missing comes within the margin, and no draw is unique."""
    scene = _boards_where_the_wall_would_be()
    for seed in range(3):
        frames = [render_depth_frame(ROBOT, scene, c.name, BOARDS_POSE, rng=np.random.default_rng(seed),
                                     noise=DepthNoise.realistic()) for c in ROBOT.cameras]
        res = house.relocalize(frames, seed=seed)
        assert res.verdict != UNIQUE or pose_error(res.hypotheses[0], BOARDS_POSE)[0] < 0.05, (seed, res.reason)
        if res.verdict == AMBIGUOUS:
            assert any(pose_error(h, BOARDS_POSE)[0] < 0.05 and pose_error(h, BOARDS_POSE)[1] < math.radians(1.0)
                       for h in res.hypotheses), (seed, res.reason, [(h.x, h.y, h.unbuilt) for h in res.hypotheses])


def test_a_missing_wall_is_scored_as_what_stands_behind_it():
    """The score's two tools for it: the wall the view is seen through most, and the score without it."""
    from drivers.sim.clutter import WallDeviation, built_walls
    from robot.localization.relocalize import _Scorer

    rel = Relocalizer(ROBOT, HOUSE)
    scene = SimScene(HOUSE, walls=built_walls(HOUSE, {"w005": WallDeviation(built=False)}))
    frames = [render_depth_frame(ROBOT, scene, c.name, UNBUILT_POSE, rng=np.random.default_rng(0),
                                 noise=DepthNoise.realistic()) for c in ROBOT.cameras]
    scorer = _Scorer(ROBOT, HOUSE, [(frames, (0.0, 0.0, 0.0))], rel.index, rel.max_range)
    through = scorer.see_through_by_wall(UNBUILT_POSE)
    group = max(through, key=through.get)
    assert group == scorer.coplanar["w005"] and through[group] > 10 * sum(n for g, n in through.items() if g != group)
    with_wall, _, _ = scorer.score(UNBUILT_POSE)
    assert scorer.last_see_through > 0.3
    without, support, _ = scorer.score(UNBUILT_POSE, without=group)
    assert scorer.last_see_through < 0.02 and support > 0.9
    assert without > with_wall + 1000
    # In the house as built the same pose sees no wall through, and leaving w005 out costs its
    # pixels: a depth on the plane of a wall said not to be built is no wall.
    built = [render_depth_frame(ROBOT, SimScene(HOUSE), c.name, UNBUILT_POSE, rng=np.random.default_rng(0),
                                noise=DepthNoise.realistic()) for c in ROBOT.cameras]
    scorer = _Scorer(ROBOT, HOUSE, [(built, (0.0, 0.0, 0.0))], rel.index, rel.max_range)
    assert sum(scorer.see_through_by_wall(UNBUILT_POSE).values()) <= 5
    assert scorer.score(UNBUILT_POSE, without=group)[0] < scorer.score(UNBUILT_POSE)[0] - 50


def test_two_panels_facing_each_other_across_a_room_are_no_wrong_unique(house):
    """Panels 0.20 and 0.19 m in front of opposite walls of one room: the place shifted by one
    panel's offset (that panel taken for its wall, the other as the hidden one) scores as well as
    the truth, which needs both hidden. An in-place turn, as the recovery makes it: no view
    may give a unique answer off by more than 2 cm outside a hidden-wall bound it names (the
    code before SECOND_PANEL_PRIOR's verdict rule answered unique 187 mm off here)."""
    from robot.control.recovery import views_from_latest

    scene = SimScene(HOUSE, [parallel_panel(HOUSE["w004"], 0.20, 1.0, None, region=(0.07, 2.65)),
                             parallel_panel(HOUSE["w016"], 0.187, 1.0, None, region=(3.26, 11.2))])
    x, y, start = 5.909, 7.565, -2.555
    views = []
    for k in range(4):
        pose = (x, y, start + k * math.pi / 2)
        rng = np.random.default_rng(k)
        frames = [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, noise=DepthNoise.realistic(unit_seed=k))
                  for c in ROBOT.cameras]
        views.append((frames, (0.0, 0.0, k * math.pi / 2 + math.radians(0.2 * k))))  # odometry 0.2 deg off per step
        first, more = views_from_latest(views)
        res = house.relocalize(first, more_views=more)
        if res.verdict == UNIQUE:
            h = res.hypotheses[0]
            d_xy, d_phi = pose_error(h, pose)
            assert d_phi < math.radians(1.0) and (d_xy < 0.02 or off_within_hidden_wall(h, pose)), (k, d_xy, h.to_json())
            break
    else:
        # Not unique after the whole turn: the place the second panel makes as good is listed.
        assert any(pose_error(h, pose)[0] < 0.02 and pose_error(h, pose)[1] < math.radians(1.0)
                   for h in res.hypotheses), (res.reason, [h.to_json() for h in res.hypotheses])
