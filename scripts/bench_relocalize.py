"""Global relocalization: verdicts over random free-space poses, with and without an in-place turn, and time.

    python scripts/bench_relocalize.py [--quick]

Poses are drawn in free space (``drivers.sim.building.free_space_poses``) of the paper arena and
the three building maps; both cameras, the realistic camera model where the simulator has it,
random site clutter. A verdict is *correct unique* when the first hypothesis is within 20 mm and
1 deg of the truth, or (it is the normal localizer's refined pose) within 1 deg and within the
covariance it claims (squared Mahalanobis distance at most 11.34, the chi-square 99 % point for
three degrees of freedom: the localizer's own accuracy, as the issue asks after refinement; the
table says how many were counted so), *wrong unique* otherwise; *ambiguous* is counted with or without the truth
among its hypotheses (within 30 mm and 1 deg). "Two walls" restricts to poses where the cameras
see at least two non-parallel map walls from the truth, each unoccluded by the scene's clutter on
enough of the image to measure (``two_walls_visible``).

*Map-symmetric* poses are those where one of the relocalizer's other hypotheses (30 mm or 1 deg
or more from the truth) sees the same map: exact depth of the map alone, without clutter,
rendered from that hypothesis agrees with the truth's (within 2 cm or 1 %) on 97 % of the
pixels either sees within range, in both cameras. A twin is found only as exactly as the
truth's own hypothesis (the nearest within 0.3 m and 2 deg, where the views leave a direction
loose): the twin is also rendered from where the map's symmetry that takes the truth's own
hypothesis onto it takes the truth. No method can tell such poses apart from
these views, so the right verdict there is *ambiguous* with the truth in the list; the 90 %
target for a correct *unique* is over the other poses. A pose whose verdict is unique or none is
never counted as map-symmetric (there is no twin to test): it stays in the denominator.

*Twin but for one wall a panel could hide* (one view only, ``panel_twin``): an ambiguous list
with the truth where a refined rival, scored with a panel's credit, sees the truth's map except
where its own walls lie behind the truth's by up to twice the panel reach along the ray. A panel
standing where the truth's wall is would make that rival the right answer, so the relocalizer's
one-panel model must keep it; the table's last column leaves these poses out as well.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import os
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from drivers.sim.building import free_space_poses, grid_for_planes, room_grid_map  # noqa: E402
from drivers.sim.render import SimScene, render_depth_frame  # noqa: E402
from robot.base.geometry import compose_se2, invert_se2, pose_to_T_ground_robot  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.control.recovery import views_from_latest  # noqa: E402
from robot.localization.relocalize import AMBIGUOUS, PANEL_MAX_OFFSET, UNIQUE, Relocalizer  # noqa: E402
from robot.localization.roi import CameraGrid, predict_plane_views, rasterize_views  # noqa: E402
from robot.localization.viewpoint import ViewpointPlanner  # noqa: E402
from robot.maps.plane_map import load_plane_map  # noqa: E402

ROBOT = load_robot_config(ROOT / "config" / "robot.yaml")
MAPS = ["paper_arena", "fzk_haus_ground", "institute_ground", "duplex_level1"]
# The turn's table: every third pose (a multi-view relocalization costs more with every view),
# turned as the product turns: by its configured step (recovery.turn_step_deg), up to 360 deg.
# (A 90 deg step, this table's until 2026-12-07, gave fewer uniques: on institute_ground 25 of 35
# poses that are not map-symmetric against 28 of 36 at 45 deg, the same poses.)
TURN_EVERY = 3
TURN_STEP_DEG = ROBOT.recovery.turn_step_deg
# The planned move's table: where one view is ambiguous, on another third of the poses (those
# after each turned one), the move robot/localization/viewpoint.py plans from its hypotheses,
# driven with odometry off by MOVE_ODO_SCALE per axis and MOVE_ODO_PHI_DEG (1 sigma), then
# relocalized with both views.
MOVE_PHASE = 1
MOVE_ODO_SCALE = 0.01
MOVE_ODO_PHI_DEG = 0.3
TWO = "two_"  # the move tables' keys for the outcome with up to two moves (recovery.max_moves: 2)


def _noise():
    try:
        from drivers.sim.render import resolve_noise

        return resolve_noise("realistic"), "realistic"
    except (ImportError, ValueError, TypeError):
        from drivers.sim.render import DepthNoise

        return DepthNoise(), "simple"


def _clutter(plane_map, rng, keep_clear):
    try:
        from drivers.sim.clutter import random_site_clutter

        return list(random_site_clutter(plane_map, rng, 4, keep_clear=keep_clear)), "site clutter (4 items)"
    except (ImportError, TypeError):
        from drivers.sim.render import random_clutter

        return random_clutter(plane_map, 4, rng, keep_clear=keep_clear), "random boxes (4)"


def two_walls_visible(plane_map, pose, index, scene) -> bool:
    """Whether the cameras see two map walls at least 25 deg from parallel, each on at least 40
    points of a 16-pixel grid within 6 m, unoccluded: the exact depth of the scene (with its
    clutter) there lies on the wall. A wall that a stack of boards or a person hides from view is
    not in view, whatever the map alone would show."""
    normals = []
    for cam in ROBOT.cameras:
        grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, 16)
        T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
        views = predict_plane_views(plane_map, index.in_view(T, grid.frustum, 6.0), T, grid, 6.0)
        if not views:
            continue
        label = rasterize_views(views, grid)
        h, w = grid.shape
        z = render_depth_frame(ROBOT, scene, cam.name, pose, noise=None).depth_m()[::16, ::16][:h, :w]
        cols, rows = grid.rays
        for k, v in enumerate(views):
            r_idx, c_idx = np.nonzero(label == k)
            if len(r_idx) < 40:
                continue
            pi = np.asarray(v.pi_camera, float)
            with np.errstate(divide="ignore", invalid="ignore"):
                z_wall = -pi[3] / (pi[0] * cols[c_idx] + pi[1] * rows[r_idx] + pi[2])
            if np.count_nonzero(np.abs(z[r_idx, c_idx] - z_wall) < 0.02 + 0.01 * z_wall) < 40:
                continue
            n = plane_map.planes[v.plane_index].normal
            if math.hypot(n[0], n[1]) > 0.95:
                normals.append(np.asarray(n[:2]) / math.hypot(n[0], n[1]))
    return any(abs(float(np.cross(a, b))) > math.sin(math.radians(25)) for i, a in enumerate(normals)
               for b in normals[i + 1:])


CHI2_3_99 = 11.34
COUNTED_BY_COVARIANCE: List[float] = []  # position errors of correct uniques more than 20 mm off
LISTED_BY_COVARIANCE: List[float] = []  # the same of the truth's hypothesis in an ambiguous list, more than 30 mm off


def classify(res, pose) -> str:
    def near(h, tol):
        return math.hypot(h.x - pose[0], h.y - pose[1]) < tol and abs(math.remainder(h.phi - pose[2], 2 * math.pi)) < math.radians(1.0)

    def covers(h) -> bool:
        """A refined hypothesis whose own covariance takes in the truth (chi-square, 3 dof, 0.99):
        the truth's, found as exactly as the views allow (a degenerate fix leaves one direction
        to the pair solution's centimetres)."""
        e = np.array([h.x - pose[0], h.y - pose[1], math.remainder(h.phi - pose[2], 2 * math.pi)])
        return h.refined and near(h, float("inf")) and float(e @ np.linalg.solve(np.asarray(h.cov), e)) <= CHI2_3_99

    if res.verdict == UNIQUE:
        h = res.hypotheses[0]
        if near(h, 0.02):
            return "unique_ok"
        if within_hidden_wall(h, pose):
            return "unique_bounded"
        if covers(h):
            COUNTED_BY_COVARIANCE.append(math.hypot(h.x - pose[0], h.y - pose[1]))
            return "unique_ok"
        return "unique_wrong"
    if res.verdict == AMBIGUOUS:
        if any(near(h, 0.03) for h in res.hypotheses):
            return "ambiguous_with_truth"
        own = [h for h in res.hypotheses if covers(h)]
        if own:
            LISTED_BY_COVARIANCE.append(min(math.hypot(h.x - pose[0], h.y - pose[1]) for h in own))
            return "ambiguous_with_truth"
        return "ambiguous_without_truth"
    return "none"


def within_hidden_wall(h, pose, tol: float = 0.02) -> bool:
    """Whether a unique answer off by more than ``tol`` is off only where it says it may be: along
    the direction a panel hiding one of its walls leaves open, within the offset it allows."""
    ex, ey = pose[0] - h.x, pose[1] - h.y
    if abs(math.remainder(h.phi - pose[2], 2 * math.pi)) >= math.radians(1.0):
        return False
    for hw in getattr(h, "hidden_walls", None) or ():
        ux, uy = hw["direction"]
        along, across = ex * ux + ey * uy, abs(-ex * uy + ey * ux)
        if -tol <= along <= hw["up_to_m"] + tol and across <= tol:
            return True
    return False


SYM_AGREE = 0.97  # share of the in-range pixels that must agree for two poses to see the same map
SYM_TOL, SYM_REL = 0.02, 0.01  # m, and relative: depth agreement
SYM_DECIMATION = 4


def _map_depths(plane_map, pose, cache: Dict) -> List[np.ndarray]:
    """Exact depth of the map alone seen from ``pose`` by each camera (decimated)."""
    scene = cache.setdefault("scene", SimScene(plane_map, floor=False, backdrop=False))
    return [render_depth_frame(ROBOT, scene, c.name, pose, noise=None, decimation=SYM_DECIMATION).depth_m()
            for c in ROBOT.cameras]


def map_twin(plane_map, pose, hypotheses, cache: Dict) -> bool:
    """Whether a hypothesis away from the truth sees the same map as the truth (see the docstring)."""
    # The map alone: no floor (it says nothing of x, y, phi) and no backdrop (what lies beyond the
    # map's openings is no part of it, and the relocalizer scores no pixel the map predicts nothing
    # for). The backdrop, a box around the map's bounds, is not symmetric when the map is: twin
    # units side by side see it at different distances through their windows.
    max_range = ROBOT.localizer.max_range

    def same_view(p) -> bool:
        for a, b in zip(truth, _map_depths(plane_map, p, cache)):
            va, vb = (a > 0) & (a < max_range), (b > 0) & (b < max_range)
            seen = va | vb
            agree = va & vb & (np.abs(a - b) <= np.maximum(SYM_TOL, SYM_REL * np.maximum(a, b)))
            if np.count_nonzero(seen) and np.count_nonzero(agree) < SYM_AGREE * np.count_nonzero(seen):
                return False
        return True

    truth = _map_depths(plane_map, pose, cache)
    own = _own_hypothesis(pose, hypotheses)
    for h in hypotheses:
        hp = (h.x, h.y, h.phi)
        if math.hypot(h.x - pose[0], h.y - pose[1]) < 0.03 and abs(math.remainder(h.phi - pose[2], 2 * math.pi)) < math.radians(1.0):
            continue
        if same_view(hp):
            return True
        # A twin is found as exactly as the truth's own hypothesis: as far off, in its own frame.
        # The map's symmetry that takes the one onto the other takes the truth to the twin's true pose.
        if own is not None and h is not own:
            if same_view(compose_se2(compose_se2(hp, invert_se2((own.x, own.y, own.phi))), pose)):
                return True
    return False


def panel_twin(plane_map, pose, hypotheses, cache: Dict) -> bool:
    """Whether a hypothesis away from the truth, refined and scored with a panel hiding one of its
    walls, sees the truth's map but for surfaces that lie behind the truth's by no more than a
    panel's reach: where the truth sees a wall, the rival sees its own wall farther away (a panel
    standing where the truth's wall is would hide it). Such a rival is what the relocalizer's
    one-panel model must keep (a real panel there makes it the right answer), so no method with
    that model can tell the two apart from these views."""
    max_range = ROBOT.localizer.max_range

    truth = None
    for h in hypotheses:
        if not (h.refined and math.isfinite(h.plain_score) and h.score > h.plain_score):
            continue  # no panel's credit in its score
        if math.hypot(h.x - pose[0], h.y - pose[1]) < 0.03 and abs(math.remainder(h.phi - pose[2], 2 * math.pi)) < math.radians(1.0):
            continue
        truth = _map_depths(plane_map, pose, cache) if truth is None else truth
        ok = True
        for a, b in zip(truth, _map_depths(plane_map, (h.x, h.y, h.phi), cache)):
            va, vb = (a > 0) & (a < max_range), (b > 0) & (b < max_range)
            seen = va | vb
            agree = va & vb & (np.abs(a - b) <= np.maximum(SYM_TOL, SYM_REL * np.maximum(a, b)))
            # along the ray a panel's reach is at least its offset from the wall (more at a slant)
            hidden = va & vb & ~agree & (b > a) & (b - a <= 2.0 * PANEL_MAX_OFFSET)
            if np.count_nonzero(seen) and np.count_nonzero(agree | hidden) < SYM_AGREE * np.count_nonzero(seen):
                ok = False
                break
        if ok:
            return True
    return False


OWN_REACH = (0.3, math.radians(2.0))  # m, rad: a hypothesis this near the truth is the truth's own, found inexactly


def _own_hypothesis(pose, hypotheses):
    """The hypothesis nearest the truth within :data:`OWN_REACH`, or None."""
    near = [h for h in hypotheses if math.hypot(h.x - pose[0], h.y - pose[1]) < OWN_REACH[0]
            and abs(math.remainder(h.phi - pose[2], 2 * math.pi)) < OWN_REACH[1]]
    return min(near, key=lambda h: math.hypot(h.x - pose[0], h.y - pose[1])) if near else None


def _note(counts: Dict[str, int], k: str, sym: bool, ptwin: bool = False) -> None:
    counts[k] = counts.get(k, 0) + 1
    if sym:
        counts["sym_" + k] = counts.get("sym_" + k, 0) + 1
    elif ptwin:
        counts["ptwin_" + k] = counts.get("ptwin_" + k, 0) + 1


def frames_at(scene, pose, rng, noise):
    return [render_depth_frame(ROBOT, scene, c.name, pose, rng=rng, noise=noise) for c in ROBOT.cameras]


def _refined_poses(res) -> List[Tuple[float, float, float]]:
    """The poses the recovery plans a move from (the refined hypotheses, best first)."""
    return [(h.x, h.y, h.phi) for h in res.hypotheses if h.refined]


def planned_move(rel: Relocalizer, planner: ViewpointPlanner, scene, pose, views, res, rng, noise,
                 max_moves: int = 2) -> Tuple[str, float, str, float]:
    """The verdicts after the planned moves from an ambiguous verdict ``res`` on ``views`` (each
    (frames, odometry pose in the first view's frame), the last one taken at the true ``pose``),
    each relocalized with all views before it and the moved one, as the recovery does: (verdict
    and length with one move allowed, the same with up to ``max_moves``; 'no_move' where none is
    planned). With more moves allowed the first plan may be the first of two moves, which one
    move allowed never makes: the one-move outcome is then driven on its own, from a copy of
    ``rng`` as it stood (the same draws as a run with one move allowed)."""
    first_plan = planner.plan(_refined_poses(res), moves=min(2, max_moves))
    one: Tuple[str, float] = ("no_move", 0.0)
    if first_plan is not None and first_plan.then is not None:
        single = planner.plan(_refined_poses(res), moves=1)
        if single is not None:
            one = _drive_moves(rel, planner, scene, pose, list(views), res, copy.deepcopy(rng), noise, 1, single)[0]
    last, after_first = _drive_moves(rel, planner, scene, pose, list(views), res, rng, noise, max_moves, first_plan)
    if first_plan is not None and first_plan.then is None:
        one = after_first  # the first move was the single move a one-move recovery makes
    return one[0], one[1], last[0], last[1]


def _drive_moves(rel: Relocalizer, planner: ViewpointPlanner, scene, pose, views, res, rng, noise, max_moves: int,
                 move) -> Tuple[Tuple[str, float], Tuple[str, float]]:
    """Drive ``move`` (planned from ``res``) and the moves planned after it while the verdict
    stays ambiguous, up to ``max_moves`` in all: (the last verdict, the path's length) and the
    same after the first move."""
    verdict, total = "no_move", 0.0
    after_first = (verdict, total)
    for left in range(max_moves, 0, -1):
        if left < max_moves:
            move = planner.plan(_refined_poses(res), moves=min(2, left))
        if move is None:
            break
        moved = compose_se2(pose, (move.dx, move.dy, move.dphi))
        odo = (move.dx * (1.0 + rng.normal(0.0, MOVE_ODO_SCALE)), move.dy * (1.0 + rng.normal(0.0, MOVE_ODO_SCALE)),
               move.dphi + math.radians(rng.normal(0.0, MOVE_ODO_PHI_DEG)))
        views.append((frames_at(scene, moved, rng, noise), compose_se2(views[-1][1], odo)))
        first, more = views_from_latest(views)
        res = rel.relocalize(first, more_views=more, seed=int(rng.integers(1 << 30)))
        verdict, total, pose = classify(res, moved), total + move.distance, moved
        if left == max_moves:
            after_first = (verdict, total)
        if res.verdict != AMBIGUOUS:
            break
    return (verdict, total), after_first


def _note_move(table: Dict[str, int], lengths: List[float], k: str, length: float, sym: bool,
               prefix: str = "") -> None:
    table[prefix + k] = table.get(prefix + k, 0) + 1
    if sym:
        table[prefix + "sym_" + k] = table.get(prefix + "sym_" + k, 0) + 1
    if length > 0.0:
        lengths.append(length)


def run_map(name: str, n: int, seed: int, noise) -> Tuple[Dict[str, int], Dict[str, int], Dict[str, int], Dict[str, int],
                                                          List[float], List[int], str, Dict[str, int], List[float],
                                                          Dict[str, int], List[float], List[float], List[float]]:
    """One stationary view per pose and, where it is not unique, the in-place turn of the recovery
    supervisor (recovery.turn_in_place): views at heading + k * turn_step_deg from the same position,
    each with its odometry heading (0.2 deg of error per step, accumulating), until unique or
    max_turn_deg; the verdict is for the last view's pose, as the robot uses it."""
    plane_map = load_plane_map(ROOT / "config" / "maps" / f"{name}.yaml")
    rel = Relocalizer(ROBOT, plane_map)
    planner = ViewpointPlanner(ROBOT, plane_map, rel.index)
    moved: Dict[str, int] = {}
    move_lengths: List[float] = []
    move_lengths_two: List[float] = []  # (the whole path's, with up to two moves)
    turn_move_lengths_two: List[float] = []
    turn_moved: Dict[str, int] = {}  # the planned move after the turn, where it ends ambiguous
    turn_move_lengths: List[float] = []
    rng = np.random.default_rng(seed)
    poses = free_space_poses(plane_map, n, rng, z=0.15)
    step = math.radians(TURN_STEP_DEG)
    max_turn = math.radians(360.0)  # the target: a turn of up to 360 deg
    counts: Dict[str, int] = {}
    counts_two: Dict[str, int] = {}
    turn: Dict[str, int] = {}
    turn_two: Dict[str, int] = {}
    times: List[float] = []
    views_used: List[int] = []
    clutter_desc = ""
    twin_cache: Dict = {}
    for i_pose, pose in enumerate(poses):
        pose = (float(pose[0]), float(pose[1]), float(pose[2]))
        # Each pose draws from its own stream: how many views an earlier pose's turn took must not
        # change the clutter and noise of the poses after it, or two versions of the relocalizer
        # are compared on different scenes.
        rng = np.random.default_rng([seed, i_pose])
        clutter, clutter_desc = _clutter(plane_map, rng, [pose[:2]])
        scene = SimScene(plane_map, clutter=clutter)
        frames = frames_at(scene, pose, rng, noise)
        t0 = time.process_time()
        res = rel.relocalize(frames, seed=int(rng.integers(1 << 30)))
        times.append(time.process_time() - t0)
        k_single = classify(res, pose)
        two = two_walls_visible(plane_map, pose, rel.index, scene)
        sym = k_single.startswith("ambiguous") and map_twin(plane_map, pose, res.hypotheses, twin_cache)
        ptwin = (not sym and k_single == "ambiguous_with_truth"
                 and panel_twin(plane_map, pose, res.hypotheses, twin_cache))
        _note(counts, k_single, sym, ptwin)
        k_turn, views = k_single, [(frames, (0.0, 0.0, 0.0))]
        odo_phi = 0.0
        k = 1
        turning = i_pose % TURN_EVERY == 0
        while turning and res.verdict != UNIQUE and k * step <= max_turn + 1e-9 and k * step < 2 * math.pi - 1e-9:
            turned = (pose[0], pose[1], pose[2] + k * step)
            odo_phi += step + math.radians(rng.normal(0.0, 0.2))
            views.append((frames_at(scene, turned, rng, noise), (0.0, 0.0, odo_phi)))
            first, more = views_from_latest(views)
            res = rel.relocalize(first, more_views=more, seed=int(rng.integers(1 << 30)))
            k_turn = classify(res, turned)
            k += 1
        if two:
            _note(counts_two, k_single, sym, ptwin)
        if i_pose % TURN_EVERY == MOVE_PHASE and k_single.startswith("ambiguous"):
            k_move, length, k_two, length_two = planned_move(rel, planner, scene, pose, [(frames, (0.0, 0.0, 0.0))],
                                                             res, rng, noise)
            _note_move(moved, move_lengths, k_move, length, sym)
            _note_move(moved, move_lengths_two, k_two, length_two, sym, TWO)
        if not turning:
            continue
        views_used.append(len(views))
        # The turned views: symmetric only if the map looks the same from the twin in every view.
        sym_turn = k_turn.startswith("ambiguous") and all(
            map_twin(plane_map, (pose[0], pose[1], pose[2] + j * step),
                     [dataclasses.replace(h, phi=h.phi - (k - 1 - j) * step) for h in res.hypotheses], twin_cache)
            for j in range(k))
        _note(turn, k_turn, sym_turn)
        if two:
            _note(turn_two, k_turn, sym_turn)
        if k_turn.startswith("ambiguous"):  # the recovery's next step when both are on: a planned move
            k_move, length, k_two, length_two = planned_move(
                rel, planner, scene, (pose[0], pose[1], pose[2] + (k - 1) * step), views, res, rng, noise)
            _note_move(turn_moved, turn_move_lengths, k_move, length, sym_turn)
            _note_move(turn_moved, turn_move_lengths_two, k_two, length_two, sym_turn, TWO)
    return (counts, counts_two, turn, turn_two, times, views_used, clutter_desc, moved, move_lengths, turn_moved,
            turn_move_lengths, move_lengths_two, turn_move_lengths_two)


def _row(name, counts, total_label="", panels: bool = True):
    total = sum(v for k, v in counts.items() if not k.startswith(("sym_", "ptwin_")))
    u_ok = counts.get("unique_ok", 0)
    sym = sum(v for k, v in counts.items() if k.startswith("sym_"))
    sym_ok = counts.get("sym_ambiguous_with_truth", 0)
    rest = total - sym
    row = (f"| {name}{total_label} | {total} | {u_ok} ({100.0 * u_ok / max(total, 1):.0f} %) | "
           f"{counts.get('unique_bounded', 0)} | {counts.get('unique_wrong', 0)} | "
           f"{counts.get('ambiguous_with_truth', 0)} | {counts.get('ambiguous_without_truth', 0)} | {counts.get('none', 0)} | "
           f"{sym} ({sym_ok} with the truth) | {u_ok} of {rest} ({100.0 * u_ok / max(rest, 1):.0f} %) |")
    if not panels:
        return row
    ptwin = sum(v for k, v in counts.items() if k.startswith("ptwin_"))
    rest2 = rest - ptwin
    return row + f" {ptwin} | {u_ok} of {rest2} ({100.0 * u_ok / max(rest2, 1):.0f} %) |"


def move_table(results, at: int, at_two: int, title: str) -> List[str]:
    """The outcomes with one move allowed (``results[name][at]``, lengths at ``at + 1``) and, in the
    last columns, with up to two (the same table's ``TWO`` keys, path lengths at ``at_two``)."""
    lines = [title, "",
             "| map | ambiguous poses | no move planned | moved | correct unique | unique, off within its hidden-wall "
             "bound | WRONG unique | ambiguous, truth in list | ambiguous, truth missing | none | of the moved "
             "map-symmetric ones: correct unique | up to two moves: moved | correct unique | WRONG unique | "
             "ambiguous, truth in list | other (off within the bound, truth missing, none) | of the moved map-symmetric "
             "ones: correct unique |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    tot: Dict[str, int] = {}
    lengths: List[float] = []
    lengths_two: List[float] = []
    for name in MAPS + ["**all**"]:
        if name == "**all**":
            m = tot
        else:
            m = results[name][at]
            lengths += results[name][at + 1]
            lengths_two += results[name][at_two]
            for k, v in m.items():
                tot[k] = tot.get(k, 0) + v
        plain = {k: v for k, v in m.items() if not k.startswith("sym_") and not k.startswith(TWO)}
        two = {k[len(TWO):]: v for k, v in m.items() if k.startswith(TWO) and not k.startswith(TWO + "sym_")}
        n_all = sum(plain.values())
        n_moved = n_all - plain.get("no_move", 0)
        sym_moved = sum(v for k, v in m.items() if k.startswith("sym_") and k != "sym_no_move")
        n_two = sum(two.values()) - two.get("no_move", 0)
        sym_two = sum(v for k, v in m.items() if k.startswith(TWO + "sym_") and k != TWO + "sym_no_move")
        other = n_two - two.get("unique_ok", 0) - two.get("unique_wrong", 0) - two.get("ambiguous_with_truth", 0)
        lines.append(f"| {name} | {n_all} | {plain.get('no_move', 0)} | {n_moved} | {plain.get('unique_ok', 0)} | "
                     f"{plain.get('unique_bounded', 0)} | {plain.get('unique_wrong', 0)} | "
                     f"{plain.get('ambiguous_with_truth', 0)} | {plain.get('ambiguous_without_truth', 0)} | "
                     f"{plain.get('none', 0)} | {m.get('sym_unique_ok', 0)} of {sym_moved} | {n_two} | "
                     f"{two.get('unique_ok', 0)} | {two.get('unique_wrong', 0)} | {two.get('ambiguous_with_truth', 0)} | "
                     f"{other} | {m.get(TWO + 'sym_unique_ok', 0)} of {sym_two} |")
    if lengths:
        lines += ["", f"Move length (one move): median {np.median(lengths):.2f} m, max {max(lengths):.2f} m."]
    if lengths_two:
        lines += [f"Path length with up to two moves: median {np.median(lengths_two):.2f} m, max "
                  f"{max(lengths_two):.2f} m."]
    return lines + [""]


def whole_recovery(results) -> List[str]:
    """The recovery with everything on (the turn, then up to two moves), on the turn table's poses:
    correct uniques over the poses that are not map-symmetric from the turn's views (a pose the
    moves resolved counts where it is not; those it resolved that are, are counted apart)."""
    lines = ["**The whole recovery: the in-place turn, then up to two planned moves** (the turn table's poses)", "",
             "| map | poses not map-symmetric after the turn | correct unique after the turn | ... and after the moves "
             "| WRONG unique | map-symmetric after the turn made correct unique by the moves |",
             "|---|---|---|---|---|---|"]
    tot = [0, 0, 0, 0, 0]
    for name in MAPS + ["**all**"]:
        if name == "**all**":
            row = tot
        else:
            turn, moved = results[name][2], results[name][7]
            total = sum(v for k, v in turn.items() if not k.startswith(("sym_", "ptwin_")))
            rest = total - sum(v for k, v in turn.items() if k.startswith("sym_"))
            u_turn = turn.get("unique_ok", 0)
            by_moves = moved.get(TWO + "unique_ok", 0) - moved.get(TWO + "sym_unique_ok", 0)
            wrong = turn.get("unique_wrong", 0) + moved.get(TWO + "unique_wrong", 0)
            row = [rest, u_turn, u_turn + by_moves, wrong, moved.get(TWO + "sym_unique_ok", 0)]
            tot = [a + b for a, b in zip(tot, row)]
        rest, u_turn, u_all, wrong, sym_ok = row
        lines.append(f"| {name} | {rest} | {u_turn} ({100.0 * u_turn / max(rest, 1):.0f} %) | {u_all} "
                     f"({100.0 * u_all / max(rest, 1):.0f} %) | {wrong} | {sym_ok} |")
    return lines + [""]


PANEL_POSES = 40  # per map


def panel_table(quick: bool, noise) -> List[str]:
    """One stationary view with a panel parallel to the wall the front camera sees most, 8 to 30
    cm in front of it, along all of it: that wall looks nearer by that much, and the view like
    another place or the same place moved. Any unique answer must be right, or off only along the
    direction its hidden-wall bound names and within it."""
    from drivers.sim.clutter import parallel_panel
    from robot.localization.localizer import Localizer, coarse_covariance

    lines = ["**A panel hiding the wall in front of the robot**", "",
             "Free-space poses where the front camera sees a map wall; a panel parallel to it 8 to 30 cm in front, "
             "over its whole length and height (a row of boards or sheets), the realistic camera, one stationary view.",
             "", "| map | poses | correct unique | unique, off within its hidden-wall bound | WRONG unique | ambiguous, "
             "truth in list | ambiguous, truth missing | none |", "|---|---|---|---|---|---|---|---|"]
    total: Dict[str, int] = {}
    for i, name in enumerate(["fzk_haus_ground", "institute_ground"]):
        plane_map = load_plane_map(ROOT / "config" / "maps" / f"{name}.yaml")
        rel, loc = Relocalizer(ROBOT, plane_map), Localizer(ROBOT, plane_map)
        rng = np.random.default_rng(500 + i)
        counts: Dict[str, int] = {}
        n = 0
        for pose in free_space_poses(plane_map, 400, rng, z=0.15):
            if n >= (8 if quick else PANEL_POSES):
                break
            pose = (float(pose[0]), float(pose[1]), float(pose[2]))
            shots = frames_at(SimScene(plane_map), pose, rng, noise)
            res = loc.localize(shots, pose, coarse_covariance(0.02, math.radians(1.0)))
            front = [p for p in res.planes if p.camera == ROBOT.cameras[0].name and p.used]
            if not front:
                continue
            wall = plane_map[max(front, key=lambda p: p.inliers).id]
            n += 1
            scene = SimScene(plane_map, clutter=[parallel_panel(wall, float(rng.uniform(0.08, 0.3)), 1.0, None)])
            k = classify(rel.relocalize(frames_at(scene, pose, rng, noise), seed=int(rng.integers(1 << 30))), pose)
            counts[k] = counts.get(k, 0) + 1
            total[k] = total.get(k, 0) + 1
        lines.append(_panel_row(name, counts))
    lines += [_panel_row("**all**", total), ""]
    return lines


UNBUILT_POSES = 60  # per map


def front_wall(plane_map, index, pose):
    """The map wall the front camera sees most of from ``pose`` (map alone, 16-pixel grid, 6 m), or None."""
    cam = ROBOT.cameras[0]
    grid = CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, 16)
    T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    views = predict_plane_views(plane_map, index.in_view(T, grid.frustum, 6.0), T, grid, 6.0)
    if not views:
        return None
    label = rasterize_views(views, grid)
    best = None
    for k, v in enumerate(views):
        n = plane_map.planes[v.plane_index].normal
        count = int(np.count_nonzero(label == k))
        if math.hypot(n[0], n[1]) > 0.95 and count and (best is None or count > best[0]):
            best = (count, v.plane_id)
    return None if best is None else best[1]


def unbuilt_site(plane_map, index, seed: int, i_pose: int, pose):
    """Pose ``i_pose`` of a map's one-view table with the wall its front camera sees most of left out
    of the scene (in the map, not built): (scene, that pose's random stream after its clutter), or
    None where the front camera sees no wall. The stream goes on as the one-view table's does."""
    from drivers.sim.clutter import WallDeviation, built_walls

    wall = front_wall(plane_map, index, pose)
    if wall is None:
        return None
    rng = np.random.default_rng([seed, i_pose])
    clutter, _ = _clutter(plane_map, rng, [pose[:2]])
    return SimScene(plane_map, clutter=clutter, walls=built_walls(plane_map, {wall: WallDeviation(built=False)})), rng


@contextlib.contextmanager
def unbuilt_check_off():
    """The relocalizer without its check for places that explain the views if a wall is missing."""
    import robot.localization.relocalize as relocalize_module

    kept = relocalize_module.UNBUILT_CANDIDATES
    relocalize_module.UNBUILT_CANDIDATES = 0
    try:
        yield
    finally:
        relocalize_module.UNBUILT_CANDIDATES = kept


def unbuilt_table(quick: bool, noise) -> List[str]:
    """One stationary view where the wall the front camera sees most of is in the map but not built
    (a site builds its partitions late): the cameras see through it. Each view relocalized twice, with
    the check for places that explain it if a wall is missing (relocalize.UNBUILT_*) and without it."""
    lines = ["**A wall in view not built yet**", "",
             "The first free-space poses of each map's one-view table (the same clutter and camera model); the map wall "
             "the front camera sees most of is left out of the scene, so the cameras see through it, one stationary "
             "view. Each view relocalized with the check for places that explain it if one wall is missing and, on "
             "the same frames and seed, without it ('before').", "",
             "| map | poses | correct unique | WRONG unique | ambiguous, truth in list | ambiguous, truth missing | none "
             "| ambiguous by the check | before: correct unique | before: WRONG unique |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    total: Dict[str, int] = {}
    for i, name in enumerate(MAPS):
        plane_map = load_plane_map(ROOT / "config" / "maps" / f"{name}.yaml")
        rel = Relocalizer(ROBOT, plane_map)
        seed = 100 + i
        poses = free_space_poses(plane_map, 130, np.random.default_rng(seed), z=0.15)
        c: Dict[str, int] = {}
        for i_pose in range(6 if quick else UNBUILT_POSES):
            pose = tuple(float(v) for v in poses[i_pose])
            site = unbuilt_site(plane_map, rel.index, seed, i_pose, pose)
            if site is None:
                continue
            scene, rng = site
            frames = frames_at(scene, pose, rng, noise)
            rseed = int(rng.integers(1 << 30))
            res = rel.relocalize(frames, seed=rseed)
            k = classify(res, pose)
            c["poses"] = c.get("poses", 0) + 1
            c[k] = c.get(k, 0) + 1
            c["by_check"] = c.get("by_check", 0) + int(res.verdict == AMBIGUOUS and "not built" in res.reason)
            with unbuilt_check_off():
                k0 = classify(rel.relocalize(frames, seed=rseed), pose)
            c["before_" + k0] = c.get("before_" + k0, 0) + 1
        lines.append(unbuilt_row(name, c))
        for k, v in c.items():
            total[k] = total.get(k, 0) + v
    lines += [unbuilt_row("**all**", total), ""]
    return lines


def unbuilt_row(name: str, c: Dict[str, int], by_check: bool = True) -> str:
    """A row of the unbuilt-wall tables from counts of ``classify``'s classes, with and ('before_')
    without the check; ``by_check``: with the column of verdicts the check made ambiguous."""
    return (f"| {name} | {c.get('poses', 0)} | {c.get('unique_ok', 0) + c.get('unique_bounded', 0)} | "
            f"{c.get('unique_wrong', 0)} | {c.get('ambiguous_with_truth', 0)} | {c.get('ambiguous_without_truth', 0)} | "
            f"{c.get('none', 0)} | " + (f"{c.get('by_check', 0)} | " if by_check else "")
            + f"{c.get('before_unique_ok', 0) + c.get('before_unique_bounded', 0)} | {c.get('before_unique_wrong', 0)} |")


def _panel_row(name: str, c: Dict[str, int]) -> str:
    n = sum(c.values())
    return (f"| {name} | {n} | {c.get('unique_ok', 0)} | {c.get('unique_bounded', 0)} | {c.get('unique_wrong', 0)} | "
            f"{c.get('ambiguous_with_truth', 0)} | {c.get('ambiguous_without_truth', 0)} | {c.get('none', 0)} |")


def scaling(quick: bool) -> List[str]:
    lines = ["", "### Relocalization time against map size", "",
             "Synthetic floors of square 4 m rooms with one door per inner wall (every room looks alike: "
             "the verdict is expected to be ambiguous or none); CPU time of one relocalization from two "
             "frames at random free-space poses (the first on each map included: it pays what a map builds "
             "lazily), and the one-time cost of building the wall-pair table.", "",
             "| planes | pair table (s) | pairs | poses | median s | p95 s |", "|---|---|---|---|---|---|"]
    noise, _ = _noise()
    for n in ((10, 200, 2000) if quick else (10, 300, 2000, 20000)):
        plane_map = room_grid_map(*grid_for_planes(n), seed=n)
        t0 = time.process_time()
        rel = Relocalizer(ROBOT, plane_map)
        build = time.process_time() - t0
        rng = np.random.default_rng(n)
        # Twenty poses where a relocalization takes about a second or less: a median of six moved by
        # a tenth of a second between runs of the same code.
        poses = free_space_poses(plane_map, 3 if quick else (20 if n <= 2000 else 6), rng, z=0.15)
        ts = []
        for pose in poses:
            frames = frames_at(SimScene(plane_map), tuple(float(v) for v in pose), rng, noise)
            t1 = time.process_time()
            rel.relocalize(frames)
            ts.append(time.process_time() - t1)
        lines.append(f"| {len(plane_map)} | {build:.2f} | {len(rel.pairs.a)} | {len(ts)} | {np.median(ts):.3f} | "
                     f"{np.percentile(ts, 95):.3f} |")
    return lines


def _machine():
    """The fixed numpy and pure-Python workloads of the CPU benchmark, timed now: this machine's
    speed against the reference's, for comparing the times here with other runs and machines."""
    from bench_cpu import machine_factor

    return machine_factor(5)


def run(quick: bool = False) -> str:
    machine_start = _machine()
    noise, noise_name = _noise()
    n = 8 if quick else 130
    lines = ["## Global relocalization (`robotctl relocalize`)", "",
             f"Random free-space poses per map ({n} each; each pose's clutter and noise from a random stream of its own, so "
             f"that how one pose's turn went changes nothing after it), both cameras, {noise_name} camera model; one stationary "
             "view, and (second table) the same poses with the recovery's in-place turn where that view is not "
             "unique (a view every turn step, odometry heading error 0.2 deg per step, relocalized with all "
             "views until unique). CPU time per relocalization (`time.process_time`). 'Two walls in view': the "
             "cameras see two map walls at least 25 deg from parallel, each unoccluded by the clutter on at least "
             "40 points of a 16-pixel grid within 6 m. 'Map-symmetric': another hypothesis sees the same map (the "
             "map alone rendered from both, within 2 cm or 1 % on 97 % of the pixels; the twin also from where the "
             "map's symmetry that takes the truth's own hypothesis, found to a few centimetres where the views leave "
             "a direction loose, onto it takes the truth): no method can tell them apart, and the target for a "
             "correct unique is over the other poses. 'Twin but for one wall a panel could hide' (one view): "
             "an ambiguous list with the truth where a refined rival scored with a panel's credit sees the truth's map "
             "(as above) except where its own walls lie behind the truth's by up to twice the panel reach along the "
             "ray: a panel standing where the truth's wall is would make the rival the right answer, and the "
             "relocalizer must keep that answer (the panel table below). The last column leaves these out too.", ""]
    header = ["| map | poses | correct unique | unique, off within its hidden-wall bound | WRONG unique | ambiguous, "
              "truth in list | ambiguous, truth missing | none | map-symmetric (ambiguous, truth in list) | correct "
              "unique of the other poses |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    # The single view's table also counts the twins but for a hidden wall (see panel_twin).
    header_one = [header[0] + " twin but for one wall a panel could hide (ambiguous, truth in list) | correct unique "
                  "of the poses neither |", header[1] + "---|---|"]
    all_times = {}
    results = {}
    desc = ""
    for i, name in enumerate(MAPS):
        (counts, two, turn, turn_two, times, views, desc, moved, lengths, turn_moved, turn_lengths, lengths_two,
         turn_lengths_two) = run_map(name, n, 100 + i, noise)
        results[name] = (counts, two, turn, turn_two, views, moved, lengths, turn_moved, turn_lengths, lengths_two,
                         turn_lengths_two)
        all_times[(name, False)] = times
    for turned in (False, True):
        title = (f"In-place turn where one view is not unique, every {TURN_EVERY}rd pose (steps of {TURN_STEP_DEG:g} deg up to "
                 "360 deg, until unique)" if turned else "One stationary view")
        lines += [f"**{title}**", ""] + (header if turned else header_one)
        tot: Dict[str, int] = {}
        tot_two: Dict[str, int] = {}
        for name in MAPS:
            counts, two, turn, turn_two, views = results[name][:5]
            c, t2 = (turn, turn_two) if turned else (counts, two)
            lines.append(_row(name, c, panels=not turned))
            lines.append(_row(name, t2, " (two walls in view)", panels=not turned))
            for k, v in c.items():
                tot[k] = tot.get(k, 0) + v
            for k, v in t2.items():
                tot_two[k] = tot_two.get(k, 0) + v
        lines.append(_row("**all**", tot, panels=not turned))
        lines.append(_row("**all** (two walls in view)", tot_two, panels=not turned))
        if turned:
            views = [v for name in MAPS for v in results[name][4]]
            lines += ["", f"Views per pose with the turn: median {np.median(views):.0f}, max {max(views)} "
                      f"({sum(1 for v in views if v > 1)} of {len(views)} poses turned)."]
        lines += ["", f"Clutter: {desc}.", ""]
        if not turned:
            cov_ok = list(COUNTED_BY_COVARIANCE)
            listed = list(LISTED_BY_COVARIANCE)
            lines += [f"Correct uniques more than 20 mm off but within the covariance the localizer claims (all views, "
                      f"both tables): {len(cov_ok)}" + (f", position errors {', '.join(f'{1e3 * v:.0f}' for v in cov_ok)} mm."
                                                        if cov_ok else "."),
                      "",
                      f"Ambiguous lists counted 'truth in list' by a hypothesis more than 30 mm off whose covariance "
                      f"takes in the truth (all views, both tables; chi-square, 3 dof, 0.99; refined, heading within "
                      f"1 deg; mostly degenerate fixes, whose loose direction comes from the pair solution): {len(listed)}"
                      + (f", position errors {', '.join(f'{1e3 * v:.0f}' for v in sorted(listed))} mm." if listed else "."),
                      ""]
    lines += move_table(results, 5, 9, (
        f"**One planned move where one view is ambiguous** (every {TURN_EVERY}rd pose, not those turned above): the "
        "move `robot/localization/viewpoint.py` plans from the view's hypotheses (a turn on the spot to face the way, "
        "then up to 2 m straight ahead, clear of every wall in every hypothesis), driven with odometry off by "
        f"{100 * MOVE_ODO_SCALE:g} % per axis and {MOVE_ODO_PHI_DEG:g} deg (1 sigma), then relocalized with both "
        "views. Map-symmetric poses are in: a move can show what the first view could not. The last columns: "
        "the recovery with `max_moves: 2`, which, where no single move tells the places apart, plans a path of two "
        "(the first clear in every hypothesis, the second clear from its end in every hypothesis), drives the first, "
        "relocalizes with every view, and plans again from that verdict."))
    lines += move_table(results, 7, 10, (
        "**The in-place turn, then one planned move where the turn ends ambiguous** (the poses of the turn's table; "
        "the recovery with `turn_in_place` and `move_to_tell_apart` both on): planned from the turn's last verdict, "
        "driven as above, relocalized with every view of the turn and the moved one. 'Map-symmetric' is the turn "
        "table's."))
    lines += whole_recovery(results)
    lines += panel_table(quick, noise)
    lines += unbuilt_table(quick, noise)
    lines += ["| map | median s | p95 s (one view) |", "|---|---|---|"]
    for name in MAPS:
        ts = all_times[(name, False)]
        lines.append(f"| {name} | {np.median(ts):.3f} | {np.percentile(ts, 95):.3f} |")
    lines += scaling(quick)
    from bench_cpu import machine_line

    end = _machine()
    lines += ["", machine_line(machine_start) + f" At the end of this section: x{end['numpy_factor']:.2f} (numpy) and "
              f"x{end['python_factor']:.2f} (Python). These machines are shared, and the relocalization times move "
              "with their load more than these fixed workloads do: compare runs by interleaved tests, not by "
              "this table alone."]
    return "\n".join(lines)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
