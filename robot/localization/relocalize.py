"""Global relocalization: where the robot is from its depth frames and the plane map alone.

No coarse pose. The map's walls are few, large and exactly known, so the search is over wall
correspondences rather than over poses:

1. **Walls in each frame, without a prior.** Every depth frame is back-projected into the robot
   frame (the mounts are known, the floor is z = 0). Walls are vertical, so their points project
   onto lines of the floor plan: sequential RANSAC on the projected points finds each line, a
   least-squares refit gives the wall's normal ``n_r`` (towards the camera) and offset ``d_r``
   (``n_r . p + d_r = 0`` in the robot frame) and the span its points cover.
2. **Hypotheses from pairs.** Two observed walls that are not parallel, matched to two map walls
   whose normals make the same angle, fix the pose: the heading turns ``n_r`` into the map's
   ``n_g``, and the position solves ``n_g,a . t = d_r,i - d_g,a`` for both walls. Map pairs are
   only formed between walls close enough to be seen together (the spatial index), which keeps
   the search linear in the map size. A hypothesis survives only if the pose lies on the
   observable side of both walls, inside the map (or the region asked for), and the observed
   spans fall on the map walls' polygons.
3. **Clusters.** Hypotheses within a few centimetres and a degree are merged; the most supported
   are verified.
4. **Verification by prediction.** From each candidate pose, the ROI machinery predicts which map
   plane every pixel of a coarse grid should see and at what depth. The measured depth scores
   each pixel with a robust log-likelihood: agreement within the depth noise is good, a point in
   front of the predicted wall is clutter (a small penalty), and a point *behind* a wall the
   candidate says is there is free-space evidence against it (a large penalty). A surface
   standing parallel in front of one predicted wall (a panel) is one object, not as many pieces
   of clutter as it has pixels: its pixels score as on it, at one fixed cost (``PANEL_PRIOR``).
5. **Refinement and verdict.** The best candidates are refined by the normal localizer and scored
   again. The verdict is ``unique`` when the best beats every other by at least
   ``UNIQUE_MARGIN`` (a log-likelihood difference, in nats, after scaling down for correlated
   pixels; more for more views), ``ambiguous`` when several are within that margin (all of them
   are returned: a square room, identical offices), and ``none`` when nothing is supported. A
   unique answer must also be one the normal localizer refined (a hypothesis whose refinement
   went astray is not confirmed), and points just behind a predicted wall's edge, where a depth
   jump's flying pixels land, are not counted against it. A rival that sees through its walls
   less than the best is never out-scored, only out-cluttered: the verdict is then ambiguous.
   The best hypotheses are also scored moved back from each wall that alone fixes a direction,
   as far as a panel could stand in front of it: the best's own such rivals are its
   ``hidden_walls`` (how far along which direction the pose may lie), another's within the
   margin make the verdict ambiguous.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from robot.base.errors import InputError
from robot.base.geometry import compose_se2, compose_se2_jacobians, invert_se2, invert_se2_jacobian, pose_to_T_ground_robot, wrap_angle
from robot.base.samples import DepthFrame
from robot.config import CameraConfig, RobotConfig
from robot.localization import fit_kernels
from robot.localization.localizer import FIX_STATUSES, Localizer, coarse_covariance
from robot.localization.roi import CameraGrid, predict_views, rasterize_views
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap

UNIQUE = "unique"
AMBIGUOUS = "ambiguous"
NONE = "none"

# Nats between the best and the runner-up for a unique verdict from one view. Measured on the
# benchmark's buildings with site clutter and the realistic camera: twin rooms (mirrored units,
# rows of alike offices) differ by up to about 33 nats from clutter and noise alone, while most
# right answers have no far competitor at all; 40 keeps every twin seen there ambiguous.
UNIQUE_MARGIN = 40.0
VIEW_MARGIN = 12.0  # nats more per further view (its odometry pose and clutter: model error of its own)
PIXEL_CORRELATION = 4.0  # the grid's pixels are not independent: log-likelihoods are divided by this
MIN_SUPPORT = 0.35  # a hypothesis must explain this share of the scored wall pixels
# ... and a unique verdict this share. Site clutter hides a quarter of the wall pixels of some right
# answers (measured: 67-75 %, leading by 170-820 nats), but at 0.65 a place 7 m off with 76 %
# led the truth by 78 nats in the house, confirmed by the localizer: a wrong unique.
UNIQUE_SUPPORT = 0.8
UNIQUE_SEE_THROUGH = 0.03  # a unique pose sees through at most this share of its predicted wall pixels
# ... unless it is clean and far ahead: clutter standing in front of its walls is all a pose
# explaining CLEAN_SUPPORT to UNIQUE_SUPPORT of them leaves unexplained when it sees through at most
# CLEAN_SEE_THROUGH of them (clutter cannot stand behind a wall), and a lead of CLEAN_LEAD margins
# over every other hypothesis (and over knowing nothing, score 0), counted both ways as the margin
# is, keeps a place that explains the views as poorly from winning on a lucky draw: the wrong
# unique at 76 % (above) led by two margins. Measured on the benchmark's in-place turns in
# fzk_haus_ground: the true pose at 76 and 78 %, seeing through 0 and 0.3 %, led by 2,980 and 660 nats.
CLEAN_SUPPORT = 0.65
CLEAN_SEE_THROUGH = 0.005
CLEAN_LEAD = 4.0
# Clutter in front of a wall costs a few nats a pixel, and a twin pose can win those back by
# chance (its predicted walls fall where the clutter stands); a point behind a predicted wall
# cannot come from clutter. A rival within CLEANER_REACH margins of the best that sees through
# its walls less than the best by CLEANER_BY (a share of the scored pixels) is therefore not
# beaten, whatever the scores say: measured in fzk_haus_ground, a 180 deg twin won by 46 nats on
# clutter while seeing through 1.5 % of its pixels against the truth's 0.1 %.
CLEANER_REACH = 2.0
CLEANER_BY = 0.005
# A best that rests on two walls is two flat surfaces in view, and site clutter has flat faces of
# that size (shelving, stacked boards). Measured in fzk_haus_ground: a shelving unit's front stood
# where the 180 deg twin's wall would be, and the twin, resting on two walls, led the true pose
# (resting on five, as clean: 97 % support, 1.2 % seen through) by 350 to 420 nats, the cost of
# the shelving's pixels as clutter. A refined rival that rests on FEW_WALLS_BY more walls,
# explaining as much of its walls as a unique answer must and seeing through its walls no more
# than the best does (within CLEANER_BY), is not beaten by such a best, whatever the scores. Its
# localizer status does not matter: a panel before one of its walls made the true pose's fix
# inconsistent for one noise draw in three. (One of 195 right unique answers in the two
# buildings had a rival on two more walls as complete, but seeing through 2 % where it saw none.)
FEW_WALLS = 2
FEW_WALLS_BY = 2
# A surface parallel to a wall and a little in front of it (a panel, boards, a door leaf) makes
# every pixel of that wall look like clutter, and the same view like a room where the wall stands
# that much nearer: scored pixel by pixel, the true pose lost to such a twin by hundreds of nats
# (measured in fzk_haus_ground: unique verdicts metres off). So one hidden wall per pose is
# scored as the one object it is: its pixels as on that surface, at the cost of this prior (nats;
# well under UNIQUE_MARGIN, so that a pose needing a panel and one that does not stay within
# reach of each other; and a panel never wins a unique verdict, see ``relocalize``).
PANEL_PRIOR = 10.0
# A second hidden wall. Scored with one panel, a room with a panel along one wall and boards
# against the opposite one lost to a room 13 cm narrower where the panel is that room's wall, by
# 490 nats (a wrong unique 3.6 m off in fzk_haus_ground; the second panel gains 770 nats). But a
# second panel in the score itself let a pose turned 90 deg in a clean room explain two walls
# as panels and win (a wrong unique), and a place 9 m off explain clutter as one and push the
# true pose out of an ambiguous list. So the score keeps one, and a second, at this prior (a
# second hidden wall in one view is much rarer than a first), only keeps a rival in the running
# against the best: it never ranks a pose higher, never makes a unique verdict.
SECOND_PANEL_PRIOR = 2.0 * UNIQUE_MARGIN
# Nor is a best unique that needs a second hidden wall (by more than the margin). Two panels
# facing each other across a room make the place shifted by one panel's offset, that panel taken
# for its wall and the other one as the hidden wall, score as well as the truth, which needs both;
# and the truth, shifted along a direction the other walls fix, is no rival the one-panel scan
# finds. Measured in fzk_haus_ground, in-place turns between panels 0.19 and 0.20 m in front of
# opposite walls: unique answers 187 mm off, the truth 15 to 20 nats behind with two panels.
# A wall of the model that is not built yet (a construction site builds its partitions late): the
# right pose sees through it, into the room behind, and scores thousands of nats down, while a
# place elsewhere that takes the room behind for its own explains the view. Measured with the
# wall the front camera sees most of left unbuilt (60 poses each in fzk_haus_ground and
# institute_ground, one view): 3 wrong unique answers 7 to 22 m off, each seeing through 2.3 to
# 2.6 % of its own pixels (unique allows 3 %). So before a unique verdict the best is checked
# against the places the walls in view were matched to: each scored without the wall it sees
# through most (and UNBUILT_PRIOR nats for a wall missing), and one that comes within the margin
# keeps the verdict ambiguous. Like a second panel, it only keeps a rival in the running: a
# missing wall never ranks a place higher and never makes a unique verdict.
# The prior: at 10 nats, 4 of 102 right unique answers in the same two buildings became ambiguous
# (another place with one wall missing came within the margin); at 40, 2 did, and the same wrong
# ones were caught (the right pose with the wall missing led them by 120 nats and more).
UNBUILT_PRIOR = UNIQUE_MARGIN
UNBUILT_CANDIDATES = 64  # places checked, in the order of how well the walls in view land on map walls
UNBUILT_MIN_PIXELS = 8  # grid pixels seen through one wall, at the coarse stride
UNBUILT_SAME_PLACE = (0.3, math.radians(5.0))  # m, rad: nearer the best is the best itself
PANEL_MIN_OFFSET = 0.02  # m: nearer is the wall itself (as built)
PANEL_MAX_OFFSET = 0.5  # m: what leans on or stands against a wall
PANEL_MIN_PIXELS = 8  # grid pixels
PANEL_FAMILIES = 6  # refined hypotheses (the best first) whose panel rivals are scored
PANEL_SCAN_STEP = 0.04  # m: the coarse scan of the offsets of a hiding panel (refined to 1 cm)
NOTHING_PREDICTED = 0.0  # log-likelihood ratio of a valid pixel where the map predicts no wall
IN_WEIGHT = 0.9  # share of a predicted wall's pixels expected on it (the rest: clutter in front)
SEE_THROUGH = -8.0  # log-likelihood ratio of a point behind a wall the pose predicts
ANGLE_TOL = math.radians(3.0)  # matching the angle between two walls
# Heights (robot frame, m) where the wall finder looks. The floor says nothing about x, y, phi,
# and a ceiling is worse than nothing: its points end in an arc at the camera's range limit, and a
# line along that arc looks like a far wall (measured in duplex_level1: "walls" 7 to 15 deg off
# every map wall, found even in exact depth). Walls and clutter fill the band below any ceiling.
WALL_BAND = (0.05, 2.0)
# Points that count for a wall's direction: measured over 458 walls of the four maps (realistic
# camera, site clutter), 20 puts 92 % of the direction errors within 3 of their standard deviations.
ANGLE_POINTS_EFFECTIVE = 20
ANGLE_TOL_MAX = math.radians(12.0)  # no pair is matched looser than this
MIN_PAIR_ANGLE = math.radians(25.0)  # walls closer to parallel than this do not fix a position
CLUSTER_XY = 0.15  # m: pair solutions scatter by centimetres; the refinement does the rest
CLUSTER_PHI = math.radians(4.0)
SCORE_STRIDE = 16  # pixels between scored grid points at 848x480
COARSE_STRIDE = 32  # the same for the first, coarse verification of every cluster
AGREEMENT_BLOCK = 1 << 18  # poses x map walls per block when ranking clusters (a few MB per array)
MAX_VERIFY = 400  # clusters verified by prediction (all of them in a building floor)
REFINE_SLACK = 10.0  # nats a refined pose may score below its start and still be taken (scoring noise)
# A best the localizer fixes in all but one direction of position (the walls that would fix it are
# slivers too small for it to fit, but the score sees them): profiled by the score this far along
# that direction, in these steps (see Relocalizer._pin).
PIN_REACH = 0.3  # m
PIN_STEP = 0.02  # m
MAX_REFINE = 24  # verified candidates refined by the localizer (those within reach of the best)
MAX_REFINE_ALIKE = 96  # ... and where most of them are alike (within the margin of the best), up to this many
# A later view's pose relative to the first comes from odometry (an in-place turn): refined per
# hypothesis within these bounds (wheel odometry turns a few tenths of a degree off per 45 deg).
VIEW_POS_STD = 0.02  # m
VIEW_PHI_STD = math.radians(1.0)
VIEW_MAX_SHIFT = 0.05  # m: a refined view pose farther from the odometry's is a wrong wall
VIEW_MAX_TURN = math.radians(3.0)
# Where the localizer cannot fix a view, its pose is searched by the score in these steps, at most
# this many rounds of one step per coordinate (see Relocalizer._search_view).
VIEW_SEARCH_XY = 0.01  # m
VIEW_SEARCH_PHI = math.radians(0.25)
VIEW_SEARCH_ROUNDS = 6


@dataclass
class ObservedWall:
    camera: str
    n_r: np.ndarray  # (2,) unit normal in the robot frame, towards the camera
    d_r: float  # n_r . p + d_r = 0 for points p (x, y) of the wall, robot frame
    span: Tuple[np.ndarray, np.ndarray]  # the two ends (x, y) of its points along the wall, robot frame
    points: int
    angle_std: float = 0.0  # rad: how well the points fix the wall's direction (see extract_walls)


@dataclass
class Hypothesis:
    x: float
    y: float
    phi: float
    cov: np.ndarray
    score: float  # log-likelihood (nats, correlation-scaled) of the frames given this pose
    support: float  # share of scored wall pixels that agree
    planes: List[str] = field(default_factory=list)  # map walls that support it
    refined: bool = False
    status: str = ""  # the normal localizer's status after refinement
    see_through: float = 0.0  # share of scored pixels measured behind a wall this pose predicts
    rels: Optional[List[Tuple[float, float, float]]] = None  # the views' refined poses relative to the first
    # A rival of another hypothesis: that one with (wall, offset m, ux, uy) a panel standing the
    # offset in front of the wall, the robot moved that far along (ux, uy), away from the wall.
    hidden: Optional[Tuple[str, float, float, float]] = None
    free: bool = True  # (a rival) along a direction no other wall fixes
    plain_score: float = math.nan  # its score pixel by pixel, without a panel's credit
    two_panel_score: float = math.nan  # its score with a second wall hidden too (SECOND_PANEL_PRIOR)
    panels: List[Hypothesis] = field(default_factory=list)  # such rivals of this one (scored)
    # The panels this pose cannot exclude (set on the answers of a verdict): each {"plane", "up_to_m", "direction"}.
    hidden_walls: List[Dict] = field(default_factory=list)
    # (ux, uy): the one direction of position the localizer left unobserved (status degenerate).
    loose: Optional[Tuple[float, float]] = None
    # m: that direction pinned by the score (Relocalizer._pin): the std given to it; None: not pinned.
    pinned: Optional[float] = None
    # (a rival) the map wall, or coplanar group of walls, this place needs to be not built yet.
    unbuilt: Optional[str] = None

    @property
    def top_score(self) -> float:
        """Its score, or that of a rival of it that a panel explains better."""
        return max([self.score] + [v.score for v in self.panels])

    def to_json(self) -> Dict:
        return {"x": self.x, "y": self.y, "phi": self.phi, "cov": np.asarray(self.cov).tolist(),
                "score": self.score, "support": self.support, "planes": list(self.planes),
                "refined": self.refined, "status": self.status, "see_through": self.see_through,
                **({"hidden_walls": list(self.hidden_walls)} if self.hidden_walls else {}),
                **({"unbuilt": self.unbuilt} if self.unbuilt is not None else {}),
                **({"pinned": {"direction": [float(c) for c in self.loose], "std_m": self.pinned}}
                   if self.pinned is not None and self.loose is not None else {})}


@dataclass
class RelocalizationResult:
    verdict: str
    hypotheses: List[Hypothesis]
    reason: str
    ms: float
    walls_seen: int

    def to_json(self) -> Dict:
        return {"verdict": self.verdict, "hypotheses": [h.to_json() for h in self.hypotheses], "reason": self.reason,
                "ms": self.ms, "walls_seen": self.walls_seen}


Pose = Tuple[float, float, float]
View = Tuple[Sequence[DepthFrame], Pose]  # frames taken together, and that robot pose in view 0's robot frame


def _wall_in_frame0(w: ObservedWall, rel: Pose) -> ObservedWall:
    """A wall observed from a later view, expressed in view 0's robot frame."""
    c, s = math.cos(rel[2]), math.sin(rel[2])
    R = np.array([[c, -s], [s, c]])
    n0 = R @ w.n_r
    d0 = w.d_r - float(n0 @ np.array(rel[:2]))
    span = tuple(R @ e + np.array(rel[:2]) for e in w.span)
    return ObservedWall(w.camera, n0, d0, span, w.points, w.angle_std)


# -- 1. walls in a frame ---------------------------------------------------------------------------


def _frame_points_robot(frame: DepthFrame, cam: CameraConfig, stride: int, min_range: float,
                        max_range: float) -> np.ndarray:
    z = frame.depth_m()[::stride, ::stride].astype(float)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w]
    ok = (z > min_range) & (z < max_range)
    K = frame.K
    zz = z[ok]
    p_c = np.stack([(u[ok] * stride - K[0, 2]) / K[0, 0] * zz, (v[ok] * stride - K[1, 2]) / K[1, 1] * zz, zz], axis=1)
    T = cam.T_robot_camera
    return p_c @ T[:3, :3].T + T[:3, 3]


def extract_walls(frame: DepthFrame, cam: CameraConfig, rng: np.random.Generator, max_walls: int = 6,
                  min_range: float = 0.2, max_range: float = 6.0) -> List[ObservedWall]:
    """Vertical planes in one frame, found without a prior (sequential 2-point RANSAC in the floor plan)."""
    stride = max(1, int(round(4 * frame.depth.shape[1] / float(cam.width))))
    p = _frame_points_robot(frame, cam, stride, min_range, max_range)
    p = p[(p[:, 2] > WALL_BAND[0]) & (p[:, 2] < WALL_BAND[1])]
    xy = p[:, :2]
    c_xy = cam.T_robot_camera[:2, 3]
    rng_dist = np.hypot(*(xy - c_xy).T) if len(xy) else np.zeros(0)
    walls: List[ObservedWall] = []
    min_points = max(60, int(0.02 * len(xy)))
    alive = np.ones(len(xy), dtype=bool)
    for _ in range(max_walls):
        idx = np.nonzero(alive)[0]
        if len(idx) < min_points:
            break
        pts = xy[idx]
        # The tolerance follows the depth noise (~ z^2) with a floor for as-built walls.
        tol = 0.01 + 0.004 * rng_dist[idx] ** 2
        pairs = rng.integers(0, len(pts), size=(80, 2))
        best, best_in = _best_line(pts, pairs, tol)
        if best < min_points:
            break
        q = pts[best_in]
        # Least-squares line (principal axis), then the inliers again with the refined line.
        mu = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - mu, full_matrices=False)
        n = vt[1]
        r = np.abs((pts - mu) @ n)
        inl = r < tol
        q = pts[inl]
        # A wall's points form one connected run along it; take the largest run (gaps > 0.3 m split).
        along = (q - mu) @ vt[0]
        order = np.argsort(along)
        gaps = np.nonzero(np.diff(along[order]) > 0.3)[0]
        bounds = np.concatenate([[0], gaps + 1, [len(order)]])
        k = int(np.argmax(np.diff(bounds)))
        run = order[bounds[k]:bounds[k + 1]]
        alive[idx[inl]] = False
        if len(run) < min_points:
            continue
        q = q[run]
        mu = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - mu, full_matrices=False)
        n = vt[1]
        d = -float(n @ mu)
        if n @ c_xy + d < 0:  # towards the camera
            n, d = -n, -d
        s = (q - mu) @ vt[0]
        # Trimmed ends: a few points of a neighbouring surface at a corner must not stretch the span.
        s_lo, s_hi = np.percentile(s, [3.0, 97.0])
        span = (mu + vt[0] * s_lo, mu + vt[0] * s_hi)
        if np.linalg.norm(span[1] - span[0]) < 0.2:
            continue  # a post or a box edge: too short to orient
        # The direction's standard deviation from the spread of the points about the line, with
        # the points counted as ANGLE_POINTS_EFFECTIVE at most: depth errors are correlated
        # along a wall (the camera's smooth disparity error, the matcher's window).
        r_rms = float(np.sqrt(np.mean(((q - mu) @ n) ** 2)))
        n_eff = min(len(q), ANGLE_POINTS_EFFECTIVE)
        angle_std = r_rms * math.sqrt(12.0 / n_eff) / max(float(s_hi - s_lo), 0.2)
        walls.append(ObservedWall(cam.name, n, d, span, len(q), angle_std))
    return walls


def _best_line(pts: np.ndarray, pairs: np.ndarray, tol: np.ndarray) -> Tuple[int, Optional[np.ndarray]]:
    """Of the lines through the point pairs ``pairs`` (K, 2) of ``pts`` (N, 2) at least 0.1 m
    apart, the one with most points within ``tol`` (N,) of it (the first of equal counts): (its
    count, its inliers), or (-1, None) if no pair is that far apart. Compiled when the backend is
    numba (fit_kernels.best_line), else numpy (the reference)."""
    if fit_kernels.backend() == "numba":
        return fit_kernels.best_line(pts, pairs, tol)
    best, best_in = -1, None
    x, y = pts[:, 0], pts[:, 1]
    for a, b in pairs.tolist():
        d0, d1 = float(pts[b, 0] - pts[a, 0]), float(pts[b, 1] - pts[a, 1])
        L = math.hypot(d0, d1)
        if L < 0.1:
            continue
        n0, n1 = -d1 / L, d0 / L
        inl = np.abs((x - pts[a, 0]) * n0 + (y - pts[a, 1]) * n1) < tol
        cnt = int(np.count_nonzero(inl))
        if cnt > best:
            best, best_in = cnt, inl
    return best, best_in


# -- 2. map walls and hypotheses ------------------------------------------------------------------


@dataclass
class _MapWalls:
    index: np.ndarray  # map plane index of each wall
    n: np.ndarray  # (W, 2) unit horizontal normals
    d: np.ndarray  # (W,)
    ang: np.ndarray  # (W,) normal angle
    a_end: np.ndarray  # (W, 2) ends of each wall's horizontal span
    b_end: np.ndarray
    centre: np.ndarray  # (W, 2)
    tang: np.ndarray = None  # (W, 2) unit direction along each wall (the normal turned +90 deg)
    s_lo: np.ndarray = None  # (W,) the wall's horizontal extent along ``tang``
    s_hi: np.ndarray = None

    def __post_init__(self) -> None:
        # Fixed by the map: computed once, not for every hypothesis and cluster tested on it.
        self.tang = np.stack([-self.n[:, 1], self.n[:, 0]], axis=1)
        sa = np.einsum("ij,ij->i", self.a_end, self.tang)
        sb = np.einsum("ij,ij->i", self.b_end, self.tang)
        self.s_lo, self.s_hi = np.minimum(sa, sb), np.maximum(sa, sb)


def _map_walls(plane_map: PlaneMap) -> _MapWalls:
    rows = []
    for i, p in enumerate(plane_map.planes):
        n3 = np.asarray(p.normal, float)
        h = math.hypot(n3[0], n3[1])
        if h < 0.95:
            continue  # not a wall (floor, ceiling, ramp)
        n = n3[:2] / h
        d = float(p.d) / h
        v = p.vertices[:, :2]
        t = np.array([-n[1], n[0]])
        s = v @ t
        foot = -d * n
        rows.append((i, n, d, foot + t * s.min(), foot + t * s.max()))
    if not rows:
        raise InputError(f"{plane_map.source}: no walls (vertical planes) to relocalize against")
    idx = np.array([r[0] for r in rows])
    n = np.array([r[1] for r in rows])
    a, b = np.array([r[3] for r in rows]), np.array([r[4] for r in rows])
    return _MapWalls(idx, n, np.array([r[2] for r in rows]), np.arctan2(n[:, 1], n[:, 0]), a, b, (a + b) / 2)


@dataclass
class _MapPairs:
    """Every ordered pair of map walls near enough to be seen together, sorted by the angle between
    their normals (b's angle minus a's), so that the pairs matching an observed angle are one
    slice."""

    a: np.ndarray
    b: np.ndarray
    delta: np.ndarray


def _map_pairs(mw: _MapWalls, index: PlaneIndex, reach: float) -> _MapPairs:
    plane_to_wall = -np.ones(index.n, dtype=np.int64)
    plane_to_wall[mw.index] = np.arange(len(mw.index))
    a_list, b_list = [], []
    lo = np.minimum(mw.a_end, mw.b_end)
    hi = np.maximum(mw.a_end, mw.b_end)
    for ka in range(len(mw.index)):
        # Walls whose horizontal extent comes within ``reach`` of this wall's extent (a long
        # corridor wall pairs with the short walls near either end, not only its middle).
        near = plane_to_wall[np.asarray(index.near_box(lo[ka], hi[ka], reach), dtype=np.int64)]
        near = near[(near >= 0) & (near != ka)]
        a_list.append(np.full(len(near), ka))
        b_list.append(near)
    a = np.concatenate(a_list) if a_list else np.zeros(0, np.int64)
    b = np.concatenate(b_list) if b_list else np.zeros(0, np.int64)
    delta = wrap_angle(mw.ang[b] - mw.ang[a])
    order = np.argsort(delta)
    return _MapPairs(a[order], b[order], np.asarray(delta)[order])


def _span_fits(ends_r: np.ndarray, phi: np.ndarray, t: np.ndarray, mw: _MapWalls, k: np.ndarray,
               tol: float) -> np.ndarray:
    """Whether an observed span (two ends, robot frame) lands on map wall k's extent, per hypothesis."""
    c, s = np.cos(phi), np.sin(phi)
    tang, lo, hi = mw.tang[k], mw.s_lo[k], mw.s_hi[k]
    ok = np.ones(len(k), dtype=bool)
    for e in ends_r:
        gx = c * e[0] - s * e[1] + t[:, 0]
        gy = s * e[0] + c * e[1] + t[:, 1]
        sv = gx * tang[:, 0] + gy * tang[:, 1]
        ok &= (sv >= lo - tol) & (sv <= hi + tol)
    return ok


def _offset_through_middle(w: ObservedWall, n_g: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``d_r`` of wall ``w`` if its normal were the map's ``n_g`` (K, 2) turned into the robot frame
    at heading (cos, sin) = (c, s), the line passing through the middle of its points."""
    m = (w.span[0] + w.span[1]) / 2
    return -((c * n_g[:, 0] + s * n_g[:, 1]) * m[0] + (-s * n_g[:, 0] + c * n_g[:, 1]) * m[1])


def _hypotheses(walls: List[ObservedWall], mw: _MapWalls, pairs: _MapPairs, region
                ) -> List[Tuple[float, float, float, Tuple[int, int]]]:
    """Poses implied by matching each non-parallel pair of observed walls to map wall pairs."""
    out = []
    lo, hi = region
    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            wi, wj = walls[i], walls[j]
            ai = math.atan2(wi.n_r[1], wi.n_r[0])
            aj = math.atan2(wj.n_r[1], wj.n_r[0])
            if abs(math.sin(aj - ai)) < math.sin(MIN_PAIR_ANGLE):
                continue
            d_obs = float(wrap_angle(aj - ai))
            # A far or short wall's direction is known to a few degrees only: the pair's angle is
            # matched within what both directions allow, the heading taken from the better one.
            tol = min(max(ANGLE_TOL, 3.0 * math.hypot(wi.angle_std, wj.angle_std)), ANGLE_TOL_MAX)
            sel = []
            for dd in (d_obs - 2 * math.pi, d_obs, d_obs + 2 * math.pi):
                s0 = np.searchsorted(pairs.delta, dd - tol)
                s1 = np.searchsorted(pairs.delta, dd + tol)
                sel.append(np.arange(s0, s1))
            sel = np.concatenate(sel)
            if len(sel) == 0:
                continue
            ka, kb = pairs.a[sel], pairs.b[sel]
            if wj.angle_std < wi.angle_std:
                phi = np.asarray(wrap_angle(mw.ang[kb] - aj))
            else:
                phi = np.asarray(wrap_angle(mw.ang[ka] - ai))
            # n_a . t = d_i - d_a and n_b . t = d_j - d_b, by Cramer's rule, each observed offset
            # taken through the middle of its wall's points along the map wall's normal at this
            # heading (where the points are, the poorly oriented wall's line is still right).
            na, nb = mw.n[ka], mw.n[kb]
            c, s = np.cos(phi), np.sin(phi)
            r1, r2 = _offset_through_middle(wi, na, c, s) - mw.d[ka], _offset_through_middle(wj, nb, c, s) - mw.d[kb]
            det = na[:, 0] * nb[:, 1] - na[:, 1] * nb[:, 0]
            good = np.abs(det) > 1e-6
            with np.errstate(divide="ignore", invalid="ignore"):
                tx = (r1 * nb[:, 1] - r2 * na[:, 1]) / det
                ty = (na[:, 0] * r2 - nb[:, 0] * r1) / det
            t = np.stack([tx, ty], axis=1)
            good &= np.all(t >= lo, axis=1) & np.all(t <= hi, axis=1)
            good &= _span_fits(np.array(wi.span), phi, t, mw, ka, 0.15)
            good &= _span_fits(np.array(wj.span), phi, t, mw, kb, 0.15)
            for k in np.nonzero(good)[0]:
                out.append((float(t[k, 0]), float(t[k, 1]), float(phi[k]), (int(mw.index[ka[k]]), int(mw.index[kb[k]]))))
    return out


def _cluster(hyps) -> List[Tuple[float, float, float, int, set]]:
    """Merge the pair hypotheses that are one pose: (x, y, phi, members, map planes), most members
    first. Hypotheses are binned in cells of CLUSTER_XY and CLUSTER_PHI, and then the cells' means
    that lie within those distances of a larger cell's mean are merged into it: the pair
    solutions of one pose scatter by centimetres across cell borders, and a building floor's
    relocalization verified half its clusters twice (measured on a 300-plane floor: 576 clusters
    for 256 places)."""
    cells: Dict[Tuple[int, int, int], List] = {}
    for x, y, phi, pair in hyps:
        cells.setdefault(_cell_of(x, y, phi), []).append((x, y, phi, pair))
    means = {key: _mean_pose(members) for key, members in cells.items()}
    order = sorted(cells, key=lambda key: -len(cells[key]))  # (stable: ties as the hypotheses came)
    taken = set()
    out = []
    for key in order:
        if key in taken:
            continue
        taken.add(key)
        x, y, phi = means[key]
        members = list(cells[key])
        for other in _neighbour_cells(x, y, phi):
            if other in taken or other not in cells:
                continue
            xo, yo, phio = means[other]
            if math.hypot(xo - x, yo - y) < CLUSTER_XY and abs(wrap_angle(phio - phi)) < CLUSTER_PHI:
                taken.add(other)
                members += cells[other]
        x, y, phi = _mean_pose(members)
        out.append((x, y, phi, len(members), {p for m in members for p in m[3]}))
    out.sort(key=lambda c: -c[3])
    return out


def _cell_of(x: float, y: float, phi: float) -> Tuple[int, int, int]:
    return (int(math.floor(x / CLUSTER_XY)), int(math.floor(y / CLUSTER_XY)),
            int(math.floor(wrap_angle(phi) / CLUSTER_PHI)))


def _neighbour_cells(x: float, y: float, phi: float) -> List[Tuple[int, int, int]]:
    """Every cell holding a point within CLUSTER_XY (in x and y) and CLUSTER_PHI of (x, y, phi);
    the heading's cells found by sampling half a cell apart, so that the wrap at +-pi is
    crossed as any other border."""
    ix, iy, _ = _cell_of(x, y, phi)
    phis = sorted({_cell_of(x, y, phi + k * 0.5 * CLUSTER_PHI)[2] for k in (-2, -1, 0, 1, 2)})
    return [(ix + dx, iy + dy, ip) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for ip in phis]


def _mean_pose(members) -> Tuple[float, float, float]:
    """Mean (x, y, phi) of hypotheses, the headings averaged about the first's (plain floats:
    a floor has thousands of small clusters)."""
    n = len(members)
    ref = members[0][2]
    dphi = sum(wrap_angle(m[2] - ref) for m in members) / n
    return sum(m[0] for m in members) / n, sum(m[1] for m in members) / n, wrap_angle(ref + dphi)


def _wall_agreements(walls: List[ObservedWall], mw: _MapWalls, poses: np.ndarray) -> np.ndarray:
    """``_wall_agreement`` of every pose (K, 3) at once: a relocalization ranks hundreds of
    clusters, and one pose at a time that was a fifth of its CPU in numpy calls on small arrays."""
    poses = np.asarray(poses, float).reshape(-1, 3)
    total = np.zeros(len(poses))
    if not len(poses) or not walls:
        return total
    # Poses by blocks: a (poses x map walls) array for a 20,000-plane map and thousands of
    # clusters would be gigabytes.
    block = max(1, AGREEMENT_BLOCK // max(1, len(mw.n)))
    if len(poses) > block:
        return np.concatenate([_wall_agreements(walls, mw, poses[i:i + block]) for i in range(0, len(poses), block)])
    x, y, phi = poses[:, 0], poses[:, 1], poses[:, 2]
    c, s = np.cos(phi), np.sin(phi)
    cos_tol = math.cos(ANGLE_TOL)
    tang, lo, hi = mw.tang, mw.s_lo - 0.15, mw.s_hi + 0.15
    for w in walls:
        gx = c * w.n_r[0] - s * w.n_r[1]
        gy = s * w.n_r[0] + c * w.n_r[1]
        d_g = w.d_r - (gx * x + gy * y)
        same = ((gx[:, None] * mw.n[None, :, 0] + gy[:, None] * mw.n[None, :, 1]) > cos_tol) \
            & (np.abs(mw.d[None, :] - d_g[:, None]) < 0.08)
        ip, k = np.nonzero(same)
        if not len(ip):
            continue
        ok = np.ones(len(ip), dtype=bool)
        for e in w.span:  # both ends of its points on the map wall's extent (_span_fits, per pose)
            ex = c[ip] * e[0] - s[ip] * e[1] + x[ip]
            ey = s[ip] * e[0] + c[ip] * e[1] + y[ip]
            sv = ex * tang[k, 0] + ey * tang[k, 1]
            ok &= (sv >= lo[k]) & (sv <= hi[k])
        hit = np.zeros(len(poses), dtype=bool)
        hit[ip[ok]] = True
        total[hit] += w.points
    return total


# -- 4. verification by prediction ----------------------------------------------------------------


class _Scorer:
    """Log-likelihood of the frames' depth given a pose, on a coarse pixel grid."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, views: Sequence[View], index: PlaneIndex,
                 max_range: float, stride: int = SCORE_STRIDE):
        self.robot, self.map, self.index, self.max_range = robot, plane_map, index, max_range
        self.coplanar = coplanar_groups(plane_map)
        self.items = []
        # Per item, the most its pixels can add to a score (fine, coarse): each pixel at best lies
        # exactly on its predicted wall or panel (see score's floor).
        self.most: List[Tuple[float, float]] = []
        self.last_see_through = 0.0
        self.last_plain = 0.0
        self.last_two = 0.0
        for view, (frames, rel) in enumerate(views):
            for f in frames:
                cam = robot.camera(f.camera)
                stride = max(1, int(round(stride * f.depth.shape[1] / float(cam.width))))
                grid = CameraGrid(np.asarray(f.K, float), f.depth.shape[1], f.depth.shape[0], stride)
                z = f.depth_m()[::stride, ::stride].astype(float)
                h, w = grid.shape
                z = np.ascontiguousarray(z[:h, :w])
                cols, rows = grid.rays
                # Measured points, to tell floor pixels (no information) from the rest.
                xr = cols[None, :] * z
                yr = rows[:, None] * z
                p_c = np.stack([xr, yr, z], axis=-1).reshape(-1, 3)
                T = cam.T_robot_camera
                z_robot = (p_c @ T[:3, :3].T + T[:3, 3])[:, 2].reshape(h, w)
                valid = (z > robot.localizer.min_range) & (z < max_range) & (z_robot > 0.05)
                # Returns beyond the range the walls are scored in are too noisy to place a wall,
                # and the floor says nothing of x, y or heading; but both are free space: a pose
                # that puts a wall nearer, in front of them, is seeing through it (the right pose
                # sees them through an opening the map has, or below a wall's foot).
                free = (z > robot.localizer.min_range) & ((z >= max_range) | (z_robot <= 0.05))
                self.items.append((cam, grid, z, valid, free if free.any() else None, rel, view))
                self.most.append((self._most(z[valid], False), self._most(z[valid], True)))
        self.last_cut = False

    def _most(self, zm: np.ndarray, coarse: bool) -> float:
        """The largest log-likelihood sum valid pixels at depths ``zm`` can reach: each one's term
        at a residual of zero (on its predicted wall, or on a panel), nothing where that is
        negative (a pixel no wall is predicted for scores zero)."""
        peak = _log_ratio(_density(np.zeros(len(zm)), _depth_sigma(zm, coarse)), self.max_range)
        return float(np.maximum(peak, 0.0).sum())

    def score(self, pose: Tuple[float, float, float], coarse: bool = False,
              rels: Optional[Sequence[Pose]] = None, floor: float = -math.inf,
              without: Optional[str] = None) -> Tuple[float, float, List[str]]:
        """(log-likelihood, share of wall pixels that agree, supporting walls) of the frames at ``pose``.

        ``rels``: each view's pose relative to the first, if not the odometry's (refined for this pose).

        ``coarse``: for hypotheses straight from a wall pair, a few centimetres and a degree off
        their refined pose; the agreement band is widened so that they are ranked by where
        they are, not by how exactly.

        ``floor``: a score below it is of no interest. Once what the frames scored so far, with
        the best panel gain so far and the most the frames still to score can add, falls short
        of it, scoring stops: ``last_cut`` is set and the first value returned is that upper
        bound, not the score (the others are 0 and []). Otherwise the result is the same as
        without a floor, to the bit.

        ``without``: a wall group (``coplanar_groups``) scored as not built at all: its pixels are
        scored on what stands behind it, those nearer than its plane still on it for a panel
        (``_unbuilt_pixels``).
        """
        total, agree, scored, through = 0.0, 0, 0, 0
        seen: Dict[str, int] = {}
        panels: Dict[str, List[float]] = {}  # map wall -> [log-likelihood gain, pixels] if a panel hides it
        # A hiding panel is one object with one offset from its wall in every view and camera:
        # the pixels in front of walls are kept until all are in, and each wall's offset is
        # their median over all of them (each frame taking its own offset let a room of another
        # size explain a wall as a panel here and as the wall there: a wrong unique 3.6 m off).
        in_front: List[Tuple] = []
        gain_most = 0.0  # the most a panel can gain on the frames scored so far (for ``floor``)
        self.last_cut = False
        most_left = sum(m[1 if coarse else 0] for m in self.most) if floor > -math.inf else 0.0
        for item, (cam, grid, z, valid, free, rel, view) in enumerate(self.items):
            if floor > -math.inf:
                # Every term of a pixel, and a panel's gain on it, is at most its peak: the
                # score can reach at most this (a panel's prior left out, which only lowers it).
                bound = (total + gain_most + most_left) / PIXEL_CORRELATION
                if bound < floor:
                    self.last_cut = True
                    return bound, 0.0, []
                most_left -= self.most[item][1 if coarse else 0]
            if rels is not None:
                rel = rels[view]
            T_gc = pose_to_T_ground_robot(*compose_se2(pose, rel)) @ cam.T_robot_camera
            views = predict_views(self.map, self.index, T_gc, grid, self.max_range)
            # (Rasterizing marks the views it finds hidden: the prediction without a wall group
            # rasterizes copies made before, so that what that wall hid is drawn.)
            unmarked = [replace(v) for v in views] if without is not None else None
            label = rasterize_views(views, grid) if views else np.full(grid.shape, -1, np.int32)
            cols, rows = grid.rays
            # Each view's plane in C, a row per view: a pixel's plane by table lookup (a list of
            # rows built pixel by pixel was a tenth of a relocalization's CPU on a 300-plane map).
            table = np.array([v.pi_camera for v in views], float).reshape(len(views), 4)
            n_free, px = _pixels(label, table, z, valid, free, cols, rows, coarse)
            if without is not None:
                # The wall's pixels on what stands behind it, but what stands nearer than its plane
                # (the boards it will be built of) may still be the one panel: scored against what
                # is behind it instead, those boards counted against the place piece by piece, and
                # a right pose with its wall missing lost to a wrong one 6.9 m off (fzk_haus_ground).
                # (A copy: the label image is the grid's buffer, which the prediction without the
                # group is rasterized into.)
                label = label.copy()
                n_free, px = self._unbuilt_pixels(unmarked, label, table, grid, z, valid, free, coarse, without,
                                                  n_free, px)
            total += SEE_THROUGH * n_free
            through += n_free
            scored += n_free
            if px is None:
                continue
            r_idx, c_idx, edge, lab, lab_seen, res_own, res, zm, sigma, denom, d = px
            inlier = np.abs(res) < 3.0
            # Behind a predicted wall's edge is where a depth jump's flying pixels land (between the
            # edge and what lies beyond it): no evidence that the wall is not there.
            behind = (res >= 3.0) & ~edge
            # Log-likelihood ratio against knowing nothing (depth uniform over the range): a pixel
            # on its predicted wall gains up to ~5 nats, clutter in front costs at most log(0.1),
            # and a point behind a predicted wall is free-space evidence against the pose.
            ll = np.where(behind, SEE_THROUGH, _log_ratio(_density(res, sigma), self.max_range))
            total += float(ll.sum())
            agree += int(np.count_nonzero(inlier))
            nearer = res_own < -1.0  # (the offset window decides; a coarse score's sigma is decimetres)
            if nearer.any():
                ray = np.stack([cols[c_idx], rows[r_idx], np.ones(len(r_idx))], axis=1)
                in_front.append((views, lab, nearer, zm, ray, denom, d, sigma, ll, inlier))
                if floor > -math.inf:
                    # A panel's pixels are any in front (one standing before a neighbouring wall
                    # too), each gaining at most up to its peak.
                    peak = _log_ratio(_density(np.zeros(len(zm)), sigma), self.max_range)
                    gain_most += float(np.maximum(peak - ll, 0.0)[nearer].sum())
            through += int(np.count_nonzero(behind))
            scored += len(res)
            per_view = np.bincount(lab_seen[inlier], minlength=len(views))
            for k in np.nonzero(per_view)[0]:
                pid = views[int(k)].plane_id
                seen[pid] = seen.get(pid, 0) + int(per_view[k])
            # Valid measurements where the map predicts nothing (beyond the map, through an opening
            # to the outside, furniture) say nothing either way: the baseline.
            total += NOTHING_PREDICTED * float(np.count_nonzero(valid & (label < 0)))  # (zero: the baseline)
        # One wall at most may be hidden by a surface standing parallel in front of it (a panel,
        # stacked boards): its pixels are one object, not as many independent pieces of clutter.
        if in_front:
            self._panel_gains(panels, in_front)
        self.last_plain = total / PIXEL_CORRELATION  # pixel by pixel, no panel taken
        ranked = sorted(panels.values(), key=lambda v: -v[0])
        prior = 0.0
        if ranked and ranked[0][0] / PIXEL_CORRELATION > PANEL_PRIOR:
            total += ranked[0][0]
            agree += int(ranked[0][1])
            prior = PANEL_PRIOR
        score = total / PIXEL_CORRELATION - prior
        # With a second wall hidden as well: what keeps a rival in the running (see relocalize).
        self.last_two = score
        if prior and len(ranked) > 1 and ranked[1][0] / PIXEL_CORRELATION > SECOND_PANEL_PRIOR:
            self.last_two = score + ranked[1][0] / PIXEL_CORRELATION - SECOND_PANEL_PRIOR
        support = agree / scored if scored else 0.0
        self.last_see_through = through / scored if scored else 0.0
        planes = [p for p, n in sorted(seen.items(), key=lambda kv: -kv[1]) if n >= 5]
        return score, support, planes

    def _unbuilt_pixels(self, views: Sequence, label: np.ndarray, table: np.ndarray, grid: CameraGrid, z: np.ndarray,
                        valid: np.ndarray, free: Optional[np.ndarray], coarse: bool, without: str, n_free: int,
                        px: Optional[Tuple[np.ndarray, ...]]) -> Tuple[int, Optional[Tuple[np.ndarray, ...]]]:
        """One frame's ``_pixels`` (``n_free``, ``px``, from ``label`` and ``table`` with every wall
        in ``views``, as predicted and not yet rasterized) with the wall group ``without`` not
        built at all.

        Every pixel of the group is scored as ``_pixels`` scores it without the group: on what
        stands behind it, or as clutter before it; where nothing stands behind it, a pixel is
        dropped as a return where the map predicts no wall. A depth on the group's own plane is
        no wall there: the wall is either built or not, and a twin place that saw part of a
        wall through an opening the truth has must not keep the rest of it. One thing stays:
        a pixel nearer than the group's plane (``_panel_gains``'s test) is kept on it for the
        panel a place may have, so that boards standing where the wall would be, parallel to
        it, are one object, as before a wall that is built. Unscored returns on its pixels are
        tested against what stands behind it too."""
        gone = [k for k, v in enumerate(views) if self.coplanar.get(v.plane_id, v.plane_id) == without]
        if not gone:
            return n_free, px
        on_gone = np.isin(label, gone)
        cols, rows = grid.rays
        keep = [k for k in range(len(views)) if k not in gone]
        rest = [views[k] for k in keep]
        label_wo = rasterize_views(rest, grid) if rest else np.full(label.shape, -1, np.int32)
        table_wo = np.array([v.pi_camera for v in rest], float).reshape(len(rest), 4)
        if free is not None:
            n_free += (_free_see_through(np.where(on_gone, label_wo, -1), _label_edges(label_wo), free, table_wo, z,
                                         cols, rows, coarse)
                       - _free_see_through(np.where(on_gone, label, -1), _label_edges(label), free, table, z, cols,
                                           rows, coarse))
        if px is None:
            return n_free, px
        res_own = px[5]
        mine = on_gone[px[0], px[1]]
        if not mine.any():
            return n_free, px
        _, px_wo = _pixels(label_wo, table_wo, z, valid & on_gone, None, cols, rows, coarse)
        where = np.full(label.shape, -1, np.intp)
        if px_wo is not None:
            where[px_wo[0], px_wo[1]] = np.arange(len(px_wo[0]))
        at = where[px[0], px[1]]
        px = tuple(a.copy() for a in px)
        to_views = np.array(keep, np.intp)  # the rest's indices into ``views``
        if coarse:
            # A coarse score's band is decimetres wide: boards a few centimetres before the wall
            # cannot be told from it, and a pixel within the band is left as with the wall (a
            # filter for the fine score, which tells them apart, and never a verdict).
            mine &= res_own >= 3.0
        # Scored without the group: the edge flag, the wall scored on and its residual.
        scored_wo = np.flatnonzero(mine & (at >= 0))
        if len(scored_wo):
            j = at[scored_wo]
            for i_field in (2, 6):
                px[i_field][scored_wo] = px_wo[i_field][j]
            px[4][scored_wo] = to_views[px_wo[4][j]]
        # Where nothing stands behind it, a pixel before the group's plane is clutter before
        # nothing (a residual far from any wall, not behind one), kept for the panel.
        panel = mine & (res_own < -1.0)
        lone = np.flatnonzero(panel & (at < 0))
        px[6][lone] = -1e3
        px[2][lone] = False
        # Every other pixel of the group is the rest's entirely: own wall, its residual and plane.
        moved = np.flatnonzero(mine & ~panel & (at >= 0))
        if len(moved):
            j = at[moved]
            px[3][moved] = to_views[px_wo[3][j]]
            for i_field in (5, 9, 10):
                px[i_field][moved] = px_wo[i_field][j]
        stay = ~(mine & ~panel & (at < 0))
        if not stay.all():
            px = tuple(a[stay] for a in px)
            if not len(px[0]):
                return n_free, None
        return n_free, px

    def see_through_by_wall(self, pose: Tuple[float, float, float], coarse: bool = False,
                            rels: Optional[Sequence[Pose]] = None) -> Dict[str, int]:
        """Per wall group (``coplanar_groups``), how many grid pixels the frames at ``pose`` measure
        behind it (scored returns and free space alike, off the walls' edges, by the score's
        3-sigma test): where a wall that is not built would be seen through."""
        counts: Dict[str, int] = {}
        for cam, grid, z, valid, free, rel, view in self.items:
            if rels is not None:
                rel = rels[view]
            T_gc = pose_to_T_ground_robot(*compose_se2(pose, rel)) @ cam.T_robot_camera
            views = predict_views(self.map, self.index, T_gc, grid, self.max_range)
            if not views:
                continue
            label = rasterize_views(views, grid)
            at = (label >= 0) & ~_label_edges(label) & (valid if free is None else valid | free)
            r_idx, c_idx = np.nonzero(at)
            if not len(r_idx):
                continue
            cols, rows = grid.rays
            lab = label[r_idx, c_idx]
            pis = np.array([v.pi_camera for v in views], float).reshape(len(views), 4)[lab]
            zm = z[r_idx, c_idx]
            with np.errstate(divide="ignore", invalid="ignore"):
                z_pred = -pis[:, 3] / (pis[:, 0] * cols[c_idx] + pis[:, 1] * rows[r_idx] + pis[:, 2])
            behind = (z_pred > 0.0) & (zm - z_pred >= 3.0 * _depth_sigma(zm, coarse))
            for k, n in enumerate(np.bincount(lab[behind], minlength=len(views)).tolist()):
                if n:
                    g = self.coplanar.get(views[k].plane_id, views[k].plane_id)
                    counts[g] = counts.get(g, 0) + n
        return counts

    def _panel_gains(self, panels: Dict[str, List[float]], in_front: List[Tuple]) -> None:
        """For each predicted wall with depth in front of it: what the pixels in front of their
        walls gain if a surface parallel to that wall, at the median offset of that depth over
        every view and camera (within ``PANEL_MAX_OFFSET``), hides it. The surface is one object:
        where it also stands in front of a neighbouring wall (a panel that spans a room ends at
        the next wall), those pixels are on it too; walls in one plane (a wall's segments between
        its doors) are one wall to it. ``in_front``: per frame, (views, lab, front,
        zm, ray, denom, d, sigma, ll, inlier) of its scored pixels, ``front`` those in front."""
        # (Small arrays, called for most scores: labels grouped by one stable sort, not a mask per
        # label; the median of a sorted copy; one error state for the loop. The same arithmetic as
        # np.unique, np.median and a mask per label: the same result, to the bit.)
        offsets: Dict[str, List[np.ndarray]] = {}
        groups = []
        for views, lab, front, zm, _ray, denom, d, _sigma, _ll, _inlier in in_front:
            s = zm * denom + d  # the measured point's distance in front of its predicted wall
            idx = np.flatnonzero(front)
            lab_idx = lab[idx]
            order = np.argsort(lab_idx, kind="stable")
            lab_sorted = lab_idx[order]
            bounds = [0] + (np.flatnonzero(lab_sorted[1:] != lab_sorted[:-1]) + 1).tolist() + [len(order)]
            ks = lab_sorted[bounds[:-1]].tolist() if len(order) else []
            groups.append((idx, ks))
            for j, k in enumerate(ks):
                off = s[idx[order[bounds[j]:bounds[j + 1]]]]
                offsets.setdefault(self.coplanar.get(views[k].plane_id, views[k].plane_id), []).append(
                    off[(off > PANEL_MIN_OFFSET) & (off <= PANEL_MAX_OFFSET)])
        delta_of: Dict[str, float] = {}
        for pid, parts in offsets.items():
            ok = np.concatenate(parts)
            n = len(ok)
            if n >= PANEL_MIN_PIXELS:
                ok.sort()
                delta_of[pid] = float(ok[n // 2]) if n % 2 else (float(ok[n // 2 - 1]) + float(ok[n // 2])) / 2.0
        if not delta_of:
            return
        with np.errstate(divide="ignore", invalid="ignore"):
            for (views, _lab, _front, zm, ray, _denom, _d, sigma, ll, inlier), (idx, ks) in zip(in_front, groups):
                done = set()
                ray_idx = zm_idx = sigma_idx = None
                for k in ks:
                    g = self.coplanar.get(views[k].plane_id, views[k].plane_id)
                    delta = delta_of.get(g)
                    if delta is None or g in done:
                        continue  # (walls in one plane: one panel, its pixels counted once)
                    done.add(g)
                    if ray_idx is None:
                        ray_idx, zm_idx, sigma_idx = ray[idx], zm[idx], sigma[idx]
                    pi = np.asarray(views[k].pi_camera, float)
                    z_alt = -(pi[3] - delta) / (ray_idx @ pi[:3])
                    r_alt = (zm_idx - z_alt) / sigma_idx
                    on = (np.abs(r_alt) < 3.0) & (z_alt > 0.0)
                    if not on.any():
                        continue
                    sel = idx[on]
                    ll_alt = _log_ratio(_density(r_alt[on], sigma[sel]), self.max_range)
                    acc = panels.setdefault(g, [0.0, 0])
                    acc[0] += float(np.maximum(ll_alt - ll[sel], 0.0).sum())
                    acc[1] += int(np.count_nonzero(~inlier[sel]))  # newly explained (for the support)


# -- 5. the whole search --------------------------------------------------------------------------


class Relocalizer:
    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, localizer: Optional[Localizer] = None):
        self.robot = robot
        self.map = plane_map
        self.localizer = localizer or Localizer(robot, plane_map)
        self.index = self.localizer.index
        self.walls = _map_walls(plane_map)
        self.max_range = robot.localizer.max_range
        # Two walls seen at once are both within the range of one robot: within twice it of each other.
        self.pairs = _map_pairs(self.walls, self.index, 2.0 * self.max_range)

    def relocalize(self, frames: Sequence[DepthFrame], region: Optional[Sequence[float]] = None,
                   seed: int = 0, more_views: Sequence[View] = ()) -> RelocalizationResult:
        """Hypotheses for the robot pose at ``frames``, best first, with a verdict.

        ``more_views``: frames taken from other poses of the same robot (an in-place turn), each
        with that pose relative to the first (odometry); they add walls and evidence.
        """
        t0 = time.perf_counter()
        if not frames:
            raise InputError("relocalize needs at least one depth frame")
        views: List[View] = [(list(frames), (0.0, 0.0, 0.0))] + [(list(f), tuple(float(v) for v in rel))
                                                                   for f, rel in more_views]
        for fs, rel in views:
            if not all(math.isfinite(v) for v in rel):
                raise InputError(f"relative pose of a view must be finite, got {rel}")
            for f in fs:
                self.robot.camera(f.camera)  # unknown camera: one clear error
        lo_map, hi_map = self.map.bounds()
        if region is not None:
            x0, y0, x1, y1 = (float(v) for v in region)
            if not (x0 < x1 and y0 < y1) or x1 < lo_map[0] or x0 > hi_map[0] or y1 < lo_map[1] or y0 > hi_map[1]:
                raise InputError(f"region ({x0}, {y0}, {x1}, {y1}) is empty or outside the map "
                                 f"({lo_map[0]:.2f}, {lo_map[1]:.2f}, {hi_map[0]:.2f}, {hi_map[1]:.2f})")
            bounds = (np.array([x0, y0]), np.array([x1, y1]))
        else:
            bounds = (lo_map[:2], hi_map[:2])
        rng = np.random.default_rng(seed)
        # Find the walls in each frame.
        walls: List[ObservedWall] = []
        for fs, rel in views:
            for f in fs:
                found = extract_walls(f, self.robot.camera(f.camera), rng, min_range=self.robot.localizer.min_range,
                                      max_range=self.max_range)
                walls += [_wall_in_frame0(w, rel) for w in found]
        # Pose hypotheses from pairs of non-parallel walls matched to map pairs.
        hyps = _hypotheses(walls, self.walls, self.pairs, bounds)
        if not hyps:
            why = ("fewer than two non-parallel walls in view" if len(walls) < 2 else
                   "no pair of map walls matches the walls in view")
            return RelocalizationResult(NONE, [], why, (time.perf_counter() - t0) * 1e3, len(walls))
        # Merge the hypotheses that agree; rank them by how many of the observed walls (weighted by
        # their points) land on a map wall, and verify the best by predicting the frames.
        clusters = _cluster(hyps)
        agreement = _wall_agreements(walls, self.walls, np.array([c[:3] for c in clusters], float)).tolist()
        order = sorted(range(len(clusters)), key=lambda k: (-agreement[k], -clusters[k][3]))
        clusters = [clusters[k] for k in order[:MAX_VERIFY]]
        scorer = _Scorer(self.robot, self.map, views, self.index, self.max_range)
        coarse = _Scorer(self.robot, self.map, views, self.index, self.max_range, stride=COARSE_STRIDE)
        scale = (COARSE_STRIDE / SCORE_STRIDE) ** 2  # comparable with the fine scores (4x fewer pixels)
        # The coarse scores use the odometry's view poses: their error grows with every view.
        reach = 4 * (UNIQUE_MARGIN + VIEW_MARGIN * (len(views) - 1))
        # Only a cluster within ``reach`` of the best is refined, so one whose first frames already
        # leave it short of that, whatever the rest could add, need not be scored to the end (in
        # agreement order the good ones come first: on a 300-plane floor two in three stop
        # before the last camera). Its entry keeps that upper bound and no support (None).
        scored = []
        top = -math.inf
        for x, y, phi, _, _ in clusters:
            s, support, planes = coarse.score((x, y, phi), coarse=True, floor=(top - reach) / scale)
            s *= scale
            if coarse.last_cut:
                scored.append((s, None, x, y, phi, planes))
                continue
            top = max(top, s)
            scored.append((s, support, x, y, phi, planes))
        scored.sort(key=lambda r: -r[0])
        # Refine the best with the normal localizer and score again.
        best_score = scored[0][0]
        refined: List[Hypothesis] = []
        # Each further view brings its own model error (its odometry pose, its clutter): over many
        # views a twin of a symmetric building drifts tens of nats from the right pose, so the
        # margin grows with the views.
        margin = UNIQUE_MARGIN + VIEW_MARGIN * (len(views) - 1)
        limit = MAX_REFINE
        k = 0
        while k < len(scored):
            s, support, x, y, phi, _planes = scored[k]
            if s < best_score - reach:
                if len(refined) >= 2:
                    break
                if any(e[1] is None for e in scored[k:]):
                    # Fewer than two within reach: the next best are refined too, in the order of
                    # their scores, so those known only by a bound are scored now.
                    rest = [e if e[1] is not None else _in_full(coarse, e, scale) for e in scored[k:]]
                    scored[k:] = sorted(rest, key=lambda r: -r[0])
                    s, support, x, y, phi, _planes = scored[k]
            if k >= limit:
                # A floor of alike places (a row of offices, mirrored flats) fills the refinements
                # with poses the views cannot tell apart; the answer must list them all, so that
                # the true one is among them: while most refined so far are within the margin of
                # the best, refine on.
                lead = max((h.score for h in refined), default=-math.inf)
                alike = sum(1 for h in refined if h.score >= lead - margin)
                if limit >= MAX_REFINE_ALIKE or 2 * alike < limit:
                    break
                limit = min(MAX_REFINE_ALIKE, 2 * limit)
            h = self._refine(views, (x, y, phi), scorer)
            if h is not None:
                refined.append(h)
            k += 1
        hyps_out = _merge(refined)
        hyps_out = [h for h in hyps_out if h.support >= MIN_SUPPORT]
        ms = (time.perf_counter() - t0) * 1e3
        if not hyps_out:
            return RelocalizationResult(NONE, [], "no hypothesis explains the depth (support below "
                                        f"{MIN_SUPPORT:.0%})", ms, len(walls))
        hyps_out.sort(key=lambda h: -h.score)
        # A panel hiding a wall that a pose rests on is explained as well by that pose moved back
        # from the wall: the refined hypotheses within reach are scored with those rivals. The
        # best's own rivals are the same place, not rivals of it: what they leave open is how far
        # along one direction (the answer's hidden_walls), not where. Another hypothesis whose
        # rival comes within the margin of the best is a place the views do not exclude. A rival
        # never ranks its hypothesis higher: its offset is fitted (the best of many), and a fitted
        # offset can explain clutter (measured: a person at the lens made a wrong unique).
        best = hyps_out[0]
        for h in [h for h in hyps_out if h.refined and h.score >= best.score - CLEANER_REACH * margin][:PANEL_FAMILIES]:
            h.panels = self._panel_rivals(h, scorer, coarse, fixed=h is best, enough=best.score - margin)

        def reach(h: Hypothesis) -> float:
            if h is best:
                return h.score
            return _or_two(h.top_score, h.two_panel_score)

        def reach_plain(h: Hypothesis) -> float:
            return max([_plain(h)] + ([] if h is best else [_plain(v) for v in h.panels]))

        # The lead must hold both ways a panel can be counted: every hypothesis with its panel's
        # credit (the best with its own), and every one pixel by pixel, no panel credited. A panel
        # may keep a place in the running, never win it: a place a few decimetres larger than the
        # true room explains the true wall as a panel before its own and wins on that credit
        # (measured in fzk_haus_ground with an open door and people about, a unique answer 3.3 m
        # off), but pixel by pixel it loses to the true room. Comparing the best without its
        # panel against the others with theirs (the rule before) also held that case, and turned
        # ambiguous every view where the true pose itself needs a panel and a place metres away
        # needs one too (measured: such a place 218 nats behind with both credited and 226
        # pixel by pixel, "within the margin" only by crediting it alone).
        # A second hidden wall (SECOND_PANEL_PRIOR) likewise: in a rival's reach, never in the best's.
        lead_from = _plain(best)  # (never above its score)
        close = [h for h in hyps_out if h is best or reach(h) >= best.score - margin
                 or reach_plain(h) >= lead_from - margin]
        cleaner = [h for h in hyps_out[1:] if reach(h) >= lead_from - CLEANER_REACH * margin
                   and h.see_through < best.see_through - CLEANER_BY and h.support >= UNIQUE_SUPPORT]
        broader = [h for h in hyps_out[1:] if len(best.planes) <= FEW_WALLS and h.refined
                   and len(h.planes) >= len(best.planes) + FEW_WALLS_BY and h.support >= UNIQUE_SUPPORT
                   and h.see_through <= best.see_through + CLEANER_BY]
        if len(close) == 1 and broader:
            return RelocalizationResult(AMBIGUOUS, _with_panels([best] + broader, best.score - margin),
                                        f"the best hypothesis rests on {len(best.planes)} walls only and leads by "
                                        f"{lead_from - reach(broader[0]):.0f} nats a pose that rests on "
                                        f"{len(broader[0].planes)} as cleanly: flat clutter can stand for a wall",
                                        ms, len(walls))
        if len(close) == 1 and cleaner:
            return RelocalizationResult(AMBIGUOUS, _with_panels([best] + cleaner, best.score - margin),
                                        f"the best hypothesis leads by {lead_from - reach(cleaner[0]):.0f} nats, "
                                        f"but sees through {best.see_through:.1%} of its predicted wall pixels where "
                                        f"{len(cleaner)} other(s) see through {cleaner[0].see_through:.1%}: clutter can "
                                        "make the lead, not the free space", ms, len(walls))
        _with_panels([best], best.score - margin)
        # Unique only as the normal localizer refined it: a hypothesis whose refinement went astray
        # is a pose only the coarse score vouches for (in the benchmark, most wrong uniques were).
        # A fix the localizer leaves loose along one direction of position is confirmed in the
        # others, and unique only if the score pins that one (_pin).
        def supported(h: Hypothesis) -> bool:
            # Explains enough of its wall pixels, or is clean and far ahead (CLEAN_SUPPORT).
            if h.support >= UNIQUE_SUPPORT:
                return True
            rest = [o for o in hyps_out if o is not h]
            lead = min(h.score - max([reach(o) for o in rest] + [0.0]),
                       _plain(h) - max([reach_plain(o) for o in rest] + [0.0]))
            return h.support >= CLEAN_SUPPORT and h.see_through <= CLEAN_SEE_THROUGH and lead >= CLEAN_LEAD * margin

        def two_hidden(h: Hypothesis) -> bool:
            # Explains the views well only with a second wall hidden as well (see SECOND_PANEL_PRIOR).
            return math.isfinite(h.two_panel_score) and h.two_panel_score > h.score + margin

        if (len(close) == 1 and best.refined and supported(best) and not two_hidden(best)
                and best.see_through <= UNIQUE_SEE_THROUGH):
            if best.status == "degenerate" and best.loose is not None:
                pinned = self._pin(best, scorer, margin)
                if pinned is not None:
                    hyps_out[0] = best = pinned
            if best.status in FIX_STATUSES or (best.pinned is not None and supported(best) and not two_hidden(best)
                                               and best.see_through <= UNIQUE_SEE_THROUGH):
                unbuilt = self._unbuilt_rivals(best, clusters, scorer, coarse, margin, scale)
                ms = (time.perf_counter() - t0) * 1e3
                if not unbuilt:
                    return RelocalizationResult(UNIQUE, hyps_out, "", ms, len(walls))
                u = unbuilt[0]
                return RelocalizationResult(
                    AMBIGUOUS, _with_panels([best] + unbuilt, best.score - margin),
                    f"a place {math.hypot(u.x - best.x, u.y - best.y):.1f} m away explains the views within "
                    f"{margin:.0f} nats of the best if wall '{u.unbuilt}' is not built yet (a model can show walls "
                    "a site does not have yet)", ms, len(walls))
        if len(close) == 1:
            h = hyps_out[0]
            if not h.refined:
                why = "the best hypothesis is not confirmed: the normal localizer's refinement of it went astray"
            elif two_hidden(h):
                why = (f"the best hypothesis explains the views well only with two walls hidden by panels "
                       f"({h.two_panel_score - h.score:.0f} nats more than with one): a place shifted by one panel's "
                       "offset, that panel taken for its wall, explains them as well")
                # Those places: the best moved back from each of its walls, by the score with two
                # hidden walls, listed after it where they come within the margin of its own.
                twins = [v for v in self._panel_rivals(h, scorer, coarse, fixed=True, two=True)
                         if math.isfinite(v.two_panel_score) and v.two_panel_score >= h.two_panel_score - margin]
                hyps_out = hyps_out[:1] + twins + hyps_out[1:]
            elif h.status == "degenerate" and h.loose is not None and supported(h) \
                    and h.see_through <= UNIQUE_SEE_THROUGH:
                why = (f"best hypothesis not confirmed by the localizer (degenerate), and the views do not fix its "
                       f"position along ({h.loose[0]:.2f}, {h.loose[1]:.2f}) within {PIN_REACH:g} m either")
            elif h.status not in FIX_STATUSES:
                why = f"best hypothesis not confirmed by the localizer ({h.status})"
            elif h.see_through > UNIQUE_SEE_THROUGH:
                why = (f"the cameras see through walls the best hypothesis predicts ({h.see_through:.1%} of its pixels; "
                       f"unique allows {UNIQUE_SEE_THROUGH:.0%}): a view it does not explain")
            else:
                why = (f"best hypothesis explains only {h.support:.0%} of the wall pixels (unique needs {UNIQUE_SUPPORT:.0%}, "
                       f"or {CLEAN_SUPPORT:.0%} seeing through at most {CLEAN_SEE_THROUGH:.1%} and leading by "
                       f"{CLEAN_LEAD:g} margins)")
            return RelocalizationResult(AMBIGUOUS, _with_panels(hyps_out, best.score - margin), why, ms, len(walls))
        return RelocalizationResult(AMBIGUOUS, _with_panels(close, best.score - margin),
                                    f"{len(close)} hypotheses within {margin:.0f} nats of each other: the views "
                                    "cannot tell them apart", ms, len(walls))

    def _unbuilt_rivals(self, best: Hypothesis, clusters: Sequence[Tuple], scorer: _Scorer, coarse: _Scorer,
                        margin: float, scale: float) -> List[Hypothesis]:
        """Other places the walls in view were matched to (``clusters``, best matched first; up to
        UNBUILT_CANDIDATES of them) that explain the views within ``margin`` of ``best`` if the
        wall each sees through most is not built, UNBUILT_PRIOR taken: rivals of a unique
        verdict. Each is scored without that wall on the coarse grid first, against the best's own
        coarse score; one within the reach that has hypotheses refined (four margins) is placed by
        the fine score (``_search_unbuilt``) and compared with the best's."""
        bar = best.score - margin
        coarse_bar = coarse.score((best.x, best.y, best.phi), coarse=True)[0] * scale - 4.0 * margin
        out: List[Hypothesis] = []
        tried = 0
        for x, y, phi, _, _ in clusters:
            if tried >= UNBUILT_CANDIDATES:
                break
            if any(math.hypot(x - h.x, y - h.y) < UNBUILT_SAME_PLACE[0]
                   and abs(float(wrap_angle(phi - h.phi))) < UNBUILT_SAME_PLACE[1] for h in [best] + out):
                continue
            tried += 1
            through = coarse.see_through_by_wall((x, y, phi), coarse=True)
            if not through:
                continue
            group, n = max(through.items(), key=lambda kv: (kv[1], kv[0]))
            if n < UNBUILT_MIN_PIXELS:
                continue
            s, _, _ = coarse.score((x, y, phi), coarse=True, without=group)
            if s * scale - UNBUILT_PRIOR < coarse_bar:
                continue
            pose = self._search_unbuilt(scorer, (x, y, phi), group)
            s, support, planes = scorer.score(pose, without=group)
            if s - UNBUILT_PRIOR >= bar:
                out.append(Hypothesis(pose[0], pose[1], pose[2], coarse_covariance(0.05, math.radians(3.0)),
                                      s - UNBUILT_PRIOR, support, planes, False, "", scorer.last_see_through,
                                      plain_score=scorer.last_plain - UNBUILT_PRIOR, unbuilt=group))
        out.sort(key=lambda h: -h.score)
        return out

    def _search_unbuilt(self, scorer: _Scorer, pose: Pose, without: str) -> Pose:
        """``pose`` moved by the fine score with the wall group ``without`` not built: coordinate
        steps of 4, 2 and 1 cm and 1, 0.5 and 0.25 deg, each kept while it gains (a pair's pose is
        centimetres and a degree off, and the fine score is sharp)."""
        best_s = scorer.score(pose, without=without)[0]
        for step_xy, step_phi in ((0.04, math.radians(1.0)), (0.02, math.radians(0.5)), (0.01, math.radians(0.25))):
            for _ in range(VIEW_SEARCH_ROUNDS):
                moved = False
                for d in ((step_xy, 0.0, 0.0), (-step_xy, 0.0, 0.0), (0.0, step_xy, 0.0), (0.0, -step_xy, 0.0),
                          (0.0, 0.0, step_phi), (0.0, 0.0, -step_phi)):
                    q = (pose[0] + d[0], pose[1] + d[1], float(wrap_angle(pose[2] + d[2])))
                    s = scorer.score(q, without=without)[0]
                    if s > best_s:
                        best_s, pose, moved = s, q, True
                if not moved:
                    break
        return pose

    def _panel_rivals(self, best: Hypothesis, scorer: _Scorer, coarse: _Scorer, fixed: bool = True,
                      enough: float = math.inf, two: bool = False) -> List[Hypothesis]:
        """The poses that explain the views as well as ``best`` does if one wall it rests on is
        hidden by a surface standing up to ``PANEL_MAX_OFFSET`` in front of it: the robot is then
        that much farther from the wall, along the direction its other walls leave free, or straight
        away from it where they fix that direction too (such a rival is near the best only if
        they disagree with the wall; ``fixed=False`` leaves those out). Scored, not refined (the
        localizer cannot tell them apart either).

        ``enough``: a rival along a free direction that scores this much decides everything the
        verdict asks of it (it is within the margin of the best; the hidden wall's bound there is
        PANEL_MAX_OFFSET whatever its offset), so the nearest offset is tried first and the scan
        runs only where that falls short (two free rivals in three stopped there when measured, at
        one score instead of some twenty)."""
        walls = []
        for pid in best.planes:
            plane = self.map[pid]
            n = np.asarray(plane.normal[:2], float)
            if math.hypot(n[0], n[1]) < 0.9:
                continue  # not a wall
            n = n / math.hypot(n[0], n[1])
            if float(n @ np.array([best.x, best.y])) + plane.d < 0.0:
                n = -n  # towards the robot
            walls.append((pid, n))
        out: List[Hypothesis] = []
        for pid, n in walls:
            others = [m for q, m in walls if q != pid]
            # Free: across the others' normal (along n where there is no other wall). Where the
            # others fix that direction too, straight away from the wall: that rival comes within
            # the margin only if they disagree with the wall by a panel's offset (a panel in front
            # of one of two parallel walls seen in different views of a turn).
            u, free = n, not others
            if others and not any(abs(float(np.cross(a, b))) > math.sin(MIN_PAIR_ANGLE)
                                  for i, a in enumerate(others) for b in others[i + 1:]):
                across = np.array([-others[0][1], others[0][0]])
                if abs(float(across @ n)) >= math.sin(MIN_PAIR_ANGLE):
                    u, free = across, True
            if not (free or fixed):
                continue
            along = float(u @ n)
            sx, sy = float(u[0]) / along, float(u[1]) / along  # moves the robot 1 m farther from the wall

            def at(delta: float, sx: float = sx, sy: float = sy) -> Tuple[float, float, float]:
                return (best.x + delta * sx, best.y + delta * sy, best.phi)

            ux, uy = float(u[0]) * math.copysign(1.0, along), float(u[1]) * math.copysign(1.0, along)  # away from it
            grid = np.arange(PANEL_MIN_OFFSET * 2, PANEL_MAX_OFFSET + 1e-9, PANEL_SCAN_STEP)
            if not len(grid):
                continue
            def scored(dl: float, at=at, floor: float = -math.inf) -> Tuple[float, float, float, List[str], float, float, float]:
                sc, support, planes = scorer.score(at(dl), rels=best.rels, floor=floor)
                return (sc, dl, support, planes, scorer.last_see_through, scorer.last_plain,
                        math.nan if scorer.last_cut else scorer.last_two)

            first = scored(float(grid[0])) if free and math.isfinite(enough) and not two else None
            if first is not None and first[0] >= enough and first[2] >= MIN_SUPPORT:
                pick = first
            elif two:
                # By the score with a second hidden wall too (``two``): on the fine grid (the coarse
                # score's wide band leaves that profile flat), to the end (a floor bounds the score
                # with one).
                pick = max((scored(float(dl)) for dl in grid), key=lambda r: _or_two(r[0], r[6]))
                d0 = pick[1]
                fine = np.arange(max(PANEL_MIN_OFFSET, d0 - 1.5 * PANEL_SCAN_STEP),
                                 min(PANEL_MAX_OFFSET, d0 + 1.5 * PANEL_SCAN_STEP) + 1e-9, 0.01)
                pick = max([pick] + [scored(float(dl)) for dl in fine], key=lambda r: _or_two(r[0], r[6]))
            else:
                # Both scans keep the best offset; an offset that cannot beat the best so far is
                # not scored to the end (its bound stays below the best: the same pick).
                rough: List[float] = []
                for dl in grid:
                    rough.append(coarse.score(at(float(dl)), coarse=True, rels=best.rels,
                                              floor=max(rough, default=-math.inf))[0])
                d0 = float(grid[int(np.argmax(rough))])
                pick = None
                for dl in np.arange(max(PANEL_MIN_OFFSET, d0 - 1.5 * PANEL_SCAN_STEP),
                                    min(PANEL_MAX_OFFSET, d0 + 1.5 * PANEL_SCAN_STEP) + 1e-9, 0.01):
                    got = scored(float(dl), floor=pick[0] if pick is not None else -math.inf)
                    if pick is None or got > pick:
                        pick = got
            sc, dl, support, planes, through, plain, sc_two = pick
            if support >= MIN_SUPPORT:
                x, y, phi = at(dl)
                out.append(Hypothesis(x, y, phi, best.cov, sc, support, planes, False, "", through, best.rels,
                                      (pid, round(dl, 3), ux, uy), free, plain, two_panel_score=sc_two))
        return out

    def _refine(self, views: Sequence[View], pose, scorer: _Scorer) -> Optional[Hypothesis]:
        """The normal localizer from this hypothesis, on the first view it can confirm it from; the
        other views' poses are then refined from that one the same way (odometry of a turn is off
        by a fraction of a degree, which over several metres would score a right pose down), or by
        the score where the localizer cannot fix them (``_search_view``)."""
        cov0 = coarse_covariance(0.05, math.radians(3.0))
        res = None
        k = 0
        for k in range(len(views)):
            fs, rel = views[k]
            res = self.localizer.localize(fs, compose_se2(pose, rel), cov0)
            if res.status in FIX_STATUSES:
                break
        s0, support0, planes0 = scorer.score(pose)
        through0 = scorer.last_see_through
        unrefined = Hypothesis(pose[0], pose[1], pose[2], cov0, s0, support0, planes0, False, res.status, through0,
                               plain_score=scorer.last_plain, two_panel_score=scorer.last_two)
        if res.status == "no_planes":
            return unrefined
        # Every view's pose in G: the fixed one (view k) as the localizer put it, the others by
        # odometry from it, then each refined in its turn. The first view's too: a fix from a later
        # view carries that view's odometry error into the first one's pose otherwise (measured: a
        # view 1.5 m from the first, its odometry 1 % and 0.3 deg off, scored the true pose 110 to
        # 180 nats down and made a twin 3.6 m away unique).
        fixed = (res.x, res.y, float(wrap_angle(res.phi)))
        back = invert_se2(rel)
        poses = [compose_se2(fixed, compose_se2(back, r)) for _, r in views]
        if len(views) > 1:
            poses = self._refine_views(views, poses, k, scorer)
        p = poses[0]
        to_first = invert_se2(p)
        rels = [compose_se2(to_first, q) for q in poses] if len(views) > 1 else None
        s, support, planes = scorer.score(p, rels=rels)
        if s0 > s + REFINE_SLACK:  # the refinement went astray (a wrong wall): keep the unrefined pose
            return unrefined
        cov = view_covariance((res.x, res.y, res.phi), np.asarray(res.cov), rel)
        return Hypothesis(p[0], p[1], p[2], cov, s, support, planes, True, res.status, scorer.last_see_through, rels,
                          plain_score=scorer.last_plain, loose=_loose_position(res.status, res.unobservable),
                          two_panel_score=scorer.last_two)

    def _pin(self, best: Hypothesis, scorer: _Scorer, margin: float) -> Optional[Hypothesis]:
        """``best`` with its loose direction of position fixed by the views' score, or None.

        The localizer leaves a direction loose when the walls it can fit are parallel: the wall
        ends, door jambs and short walls that fix the rest are slivers too small for a plane fit
        (under ``min_roi_pixels``), yet they are in the score's pixels. So the score is profiled
        along that direction, PIN_REACH either way: the pose goes where it peaks, and the stretch
        within ``margin`` of the peak (the unique verdict's own margin between places) is the
        uncertainty left, its half-width taken as one standard deviation: a likelihood that falls
        by the margin there is far steeper than that (some nine standard deviations for a normal
        one), so the covariance errs wide, never narrow. Not pinned (None) if that stretch reaches
        PIN_REACH on either side or is not one piece (two places along the direction explain the
        views)."""
        assert best.loose is not None
        ux, uy = best.loose
        ts = np.arange(-PIN_REACH, PIN_REACH + 1e-9, PIN_STEP)
        scores = [scorer.score((best.x + t * ux, best.y + t * uy, best.phi), rels=best.rels)[0] for t in ts]
        k = int(np.argmax(scores))
        inside = [i for i, sc in enumerate(scores) if sc >= scores[k] - margin]
        if inside[0] == 0 or inside[-1] == len(ts) - 1 or inside[-1] - inside[0] + 1 != len(inside):
            return None
        half = max(float(ts[inside[-1]] - ts[k]), float(ts[k] - ts[inside[0]])) + PIN_STEP
        p = (best.x + float(ts[k]) * ux, best.y + float(ts[k]) * uy, best.phi)
        s, support, planes = scorer.score(p, rels=best.rels)
        u = np.array([ux, uy, 0.0])
        keep = np.eye(3) - np.outer(u, u)
        cov = keep @ np.asarray(best.cov, float) @ keep + half * half * np.outer(u, u)
        return replace(best, x=p[0], y=p[1], cov=cov, score=s, support=support, planes=planes,
                       see_through=scorer.last_see_through, plain_score=scorer.last_plain, pinned=half,
                       two_panel_score=scorer.last_two)

    def _refine_views(self, views: Sequence[View], poses: List[Pose], fixed: int, scorer: _Scorer) -> List[Pose]:
        """Each view's pose in G (``poses``: view ``fixed`` by the localizer, the others by odometry
        from it) re-estimated by the localizer from there, within what odometry allows
        (VIEW_MAX_SHIFT, VIEW_MAX_TURN); by the score where it finds no fix there."""
        cov = coarse_covariance(VIEW_POS_STD, VIEW_PHI_STD)
        out = list(poses)
        loose = []
        for j, (fs, _) in enumerate(views):
            if j == fixed:
                continue
            res = self.localizer.localize(fs, poses[j], cov)
            if res.status in FIX_STATUSES:
                r = (res.x, res.y, float(wrap_angle(res.phi)))
                d = compose_se2(invert_se2(poses[j]), r)
                if math.hypot(d[0], d[1]) <= VIEW_MAX_SHIFT and abs(d[2]) <= VIEW_MAX_TURN:
                    out[j] = r
                    continue
            loose.append(j)
        for j in loose:
            out[j] = self._search_view(scorer, out, j)
        return out

    def _search_view(self, scorer: _Scorer, poses: List[Pose], j: int) -> Pose:
        """View j's pose in G where the localizer could not fix it (clutter made its walls
        inconsistent, or too few are in view): the pose near its odometry's that the views score
        best, less the odometry's own log-prior (VIEW_POS_STD, VIEW_PHI_STD), by coordinate steps
        within VIEW_MAX_SHIFT and VIEW_MAX_TURN. Every hypothesis gets the same freedom; without it
        the odometry's centimetre cost the true pose more than a twin that happens to fit."""
        odo = poses[j]
        from_odo = invert_se2(odo)

        def objective(a: Pose) -> float:
            trial = list(poses)
            trial[j] = a
            to_first = invert_se2(trial[0])
            sc = scorer.score(trial[0], rels=[compose_se2(to_first, q) for q in trial])[0]
            d = compose_se2(from_odo, a)
            return sc - 0.5 * ((d[0] ** 2 + d[1] ** 2) / VIEW_POS_STD ** 2 + d[2] ** 2 / VIEW_PHI_STD ** 2)

        cur, best = odo, objective(odo)
        steps = [(VIEW_SEARCH_XY, 0.0, 0.0), (0.0, VIEW_SEARCH_XY, 0.0), (0.0, 0.0, VIEW_SEARCH_PHI)]
        for _ in range(VIEW_SEARCH_ROUNDS):
            moved = False
            for dx, dy, dphi in steps:
                for sign in (1.0, -1.0):
                    cand = compose_se2(cur, (sign * dx, sign * dy, sign * dphi))
                    d = compose_se2(from_odo, cand)
                    if math.hypot(d[0], d[1]) > VIEW_MAX_SHIFT or abs(d[2]) > VIEW_MAX_TURN:
                        continue
                    f = objective(cand)
                    if f > best:
                        cur, best, moved = cand, f, True
                        break
            if not moved:
                break
        return cur


def view_covariance(pose_k: Pose, cov_k: np.ndarray, rel: Pose) -> np.ndarray:
    """The covariance of the first view's pose, pose_k o rel^-1, from view k's fix (``cov_k``) and
    the odometry's relative pose ``rel`` of view k, uncertain by VIEW_POS_STD and VIEW_PHI_STD: a
    fix taken after part of a turn is only as good as the turn's odometry."""
    back = invert_se2(rel)
    Ja, Jb = compose_se2_jacobians(pose_k, back)
    cov = Ja @ cov_k @ Ja.T
    if any(abs(v) > 0.0 for v in rel):
        J_rel = Jb @ invert_se2_jacobian(rel)
        cov = cov + J_rel @ coarse_covariance(VIEW_POS_STD, VIEW_PHI_STD) @ J_rel.T
    return cov


def _label_edges(label: np.ndarray) -> np.ndarray:
    """Cells of a label image next to a cell (4-neighbourhood) with another label, or none."""
    edge = np.zeros(label.shape, bool)
    diff_v = label[1:, :] != label[:-1, :]
    diff_h = label[:, 1:] != label[:, :-1]
    edge[1:, :] |= diff_v
    edge[:-1, :] |= diff_v
    edge[:, 1:] |= diff_h
    edge[:, :-1] |= diff_h
    return edge


def _pixels(label: np.ndarray, table: np.ndarray, z: np.ndarray, valid: np.ndarray, free: Optional[np.ndarray],
            cols: np.ndarray, rows: np.ndarray, coarse: bool) -> Tuple[int, Optional[Tuple[np.ndarray, ...]]]:
    """A view's pixels as a score weighs them, from its label image (the row of ``table``, each
    predicted wall in C, per grid pixel; -1 for none) and the measured depths ``z``: how many of
    the unscored returns (``free``) lie behind the wall predicted there (:func:`_free_see_through`),
    and of the scored ones (a wall predicted, ``valid`` depth), in row-major order, None if there
    are none: (rows, cols, at a wall's edge, own wall, wall scored on (:func:`_edge_alternatives`),
    residual on the own wall and the one scored, in std; depth, its std, n . ray and d of the own
    wall). Compiled when the backend is numba (fit_kernels.score_pixels), else numpy (the reference)."""
    if fit_kernels.backend() == "numba":
        return fit_kernels.score_pixels(label, table, z, valid, free, cols, rows, DEPTH_SIGMA if coarse else
                                        DEPTH_SIGMA[:2] + (0.0, 0.0), coarse)
    edges = _label_edges(label)
    n_free = 0 if free is None else _free_see_through(label, edges, free, table, z, cols, rows, coarse)
    has = (label >= 0) & valid
    if not has.any():
        return n_free, None
    r_idx, c_idx = np.nonzero(has)
    edge = edges[r_idx, c_idx]
    lab = label[r_idx, c_idx]
    pis = table[lab]
    denom = pis[:, 0] * cols[c_idx] + pis[:, 1] * rows[r_idx] + pis[:, 2]  # n . ray, ray = (x/z, y/z, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_pred = -pis[:, 3] / denom
    zm = z[r_idx, c_idx]
    sigma = _depth_sigma(zm, coarse)
    res_own = (zm - z_pred) / sigma
    res, lab_seen = _edge_alternatives(label, table, r_idx, c_idx, edge, lab, res_own, zm, sigma, cols, rows)
    return n_free, (r_idx, c_idx, edge, lab, lab_seen, res_own, res, zm, sigma, denom, pis[:, 3])


_NEIGHBOURS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]], np.intp)  # (row, col) steps: up, down, left, right


def _edge_alternatives(label: np.ndarray, table: np.ndarray, r_idx: np.ndarray, c_idx: np.ndarray, edge: np.ndarray,
                       lab: np.ndarray, res: np.ndarray, zm: np.ndarray, sigma: np.ndarray, cols: np.ndarray,
                       rows: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Residuals (in std) and walls of the pixels, where a pixel next to another predicted wall
    is taken on whichever of the two its depth fits better.

    A scored grid pixel stands for a cell a stride wide: where a predicted edge crosses the cell,
    which side its centre falls on is a matter of millimetres of pose, and the surface beyond the
    edge is as likely as the own one. Scoring it on its own wall alone cost the pose that is right
    a few nats per edge pixel against a rival whose edges lie elsewhere.

    The four neighbours are weighed together: the smallest residual wins, the own wall on a tie
    and otherwise the first neighbour in the order up, down, left, right (what taking them one
    by one, each replacing the pick only if strictly better, gives)."""
    if not edge.any():
        return res, lab
    e = np.flatnonzero(edge)
    re, ce, le = r_idx[e], c_idx[e], lab[e]
    h, w = label.shape
    ln = label[np.clip(re + _NEIGHBOURS[:, :1], 0, h - 1), np.clip(ce + _NEIGHBOURS[:, 1:], 0, w - 1)]  # (4, E)
    other = (ln >= 0) & (ln != le)
    pn = table[np.where(other, ln, 0)]  # (4, E, 4); rows of the own wall's neighbours are masked below
    with np.errstate(divide="ignore", invalid="ignore"):
        zp = -pn[..., 3] / (pn[..., 0] * cols[ce] + pn[..., 1] * rows[re] + pn[..., 2])
        rn = (zm[e] - zp) / sigma[e]
    # Own residual first: argmin takes the first of equal values (and a NaN own residual stays).
    size = np.concatenate((np.abs(res[e])[None, :], np.where(other & (zp > 0.0), np.abs(rn), np.inf)))
    pick = np.argmin(size, axis=0)
    moved = np.flatnonzero(pick > 0)
    if not len(moved):
        return res, lab
    k = pick[moved] - 1
    res = res.copy()
    res[e[moved]] = rn[k, moved]
    lab = lab.copy()
    lab[e[moved]] = ln[k, moved]
    return res, lab


COPLANAR_ANGLE = math.radians(0.5)
COPLANAR_OFFSET = 0.01  # m


def coplanar_groups(plane_map: PlaneMap) -> Dict[str, str]:
    """Each map wall's group of walls in one plane (the same side of one wall, cut by its doors
    into segments): the id of the group's first wall, by wall id. Computed once per map."""
    cached = plane_map.__dict__.get("_coplanar_groups")
    if cached is not None:
        return cached
    bins = int(round(2.0 * math.pi / COPLANAR_ANGLE))
    by_key: Dict[Tuple[int, int], List[Tuple[np.ndarray, float, str]]] = {}
    groups: Dict[str, str] = {}
    for p in plane_map.planes:
        n = np.asarray(p.normal, float)
        if abs(n[2]) >= 0.5:  # walls only: the floor and ceiling hide nothing here
            groups[p.id] = p.id
            continue
        # Binned by heading and offset; the neighbouring bins are looked in too, so that a
        # plane near a bin's border is never split from its group.
        ka = int(math.floor(math.atan2(n[1], n[0]) / COPLANAR_ANGLE))
        kd = int(math.floor(p.d / COPLANAR_OFFSET))
        near = (entry for da in (-1, 0, 1) for dd in (-1, 0, 1)
                for entry in by_key.get(((ka + da) % bins, kd + dd), ()))
        g = next((g for n2, d2, g in near
                  if float(n @ n2) > math.cos(COPLANAR_ANGLE) and abs(p.d - d2) < COPLANAR_OFFSET), p.id)
        by_key.setdefault((ka % bins, kd), []).append((n, float(p.d), g))
        groups[p.id] = g
    plane_map.__dict__["_coplanar_groups"] = groups
    return groups


def _free_see_through(label: np.ndarray, edges: np.ndarray, free: np.ndarray, table: np.ndarray, z: np.ndarray,
                      cols: np.ndarray, rows: np.ndarray, coarse: bool) -> int:
    """How many of the returns that are not scored (``free``: beyond the range, or on the floor)
    lie behind the wall a pose predicts there, by the same test as the scored ones (three of the
    score's depth std, not at a wall's edge)."""
    at = free & (label >= 0) & ~edges
    if not at.any():
        return 0
    r_idx, c_idx = np.nonzero(at)
    pis = table[label[r_idx, c_idx]]
    denom = pis[:, 0] * cols[c_idx] + pis[:, 1] * rows[r_idx] + pis[:, 2]
    zm = z[r_idx, c_idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_pred = -pis[:, 3] / denom
    return int(np.count_nonzero((z_pred > 0.0) & (zm - z_pred >= 3.0 * _depth_sigma(zm, coarse))))


# A score's depth std at depth z: A + B z^2, and for a coarse score C + D z more.
DEPTH_SIGMA = (0.01, 0.005, 0.03, 0.02)


def _depth_sigma(zm: np.ndarray, coarse: bool) -> np.ndarray:
    """Depth std (m) a score allows a pixel measured at ``zm``: depth noise plus as-built walls,
    generous on purpose; for a coarse score (a pair hypothesis, centimetres and a degree off) more."""
    a, b, c, d = DEPTH_SIGMA
    sigma = a + b * zm ** 2
    if coarse:
        sigma = sigma + c + d * zm
    return sigma


def _density(res: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Normal density (1/m) of a depth ``res`` standard deviations from its prediction."""
    return np.exp(-0.5 * res ** 2) / (sigma * math.sqrt(2.0 * math.pi))


def _log_ratio(density: np.ndarray, max_range: float) -> np.ndarray:
    """A pixel's log-likelihood ratio against knowing nothing (depth uniform over the range): on its
    predicted surface with IN_WEIGHT, clutter in front of it otherwise."""
    return np.log(IN_WEIGHT * density * max_range + (1.0 - IN_WEIGHT))


def _in_full(coarse: _Scorer, entry: Tuple, scale: float) -> Tuple:
    """A verification entry known only by its bound, scored to the end (the same layout)."""
    x, y, phi = entry[2:5]
    s, support, planes = coarse.score((x, y, phi), coarse=True)
    return s * scale, support, x, y, phi, planes


def _loose_position(status: str, unobservable: Sequence[Dict]) -> Optional[Tuple[float, float]]:
    """The one direction of position (unit, ground frame) a degenerate fix leaves unobserved; None
    if the fix is not degenerate, or leaves the heading or more than one direction loose."""
    if status != "degenerate" or len(unobservable) != 1:
        return None
    v = unobservable[0]["direction"]
    n = math.hypot(v[0], v[1])
    if abs(v[2]) > 1e-6 or n < 1e-9:
        return None
    return (v[0] / n, v[1] / n)


def _plain(h: Hypothesis) -> float:
    """A hypothesis's score pixel by pixel, without a panel's credit (its score where unknown)."""
    return h.plain_score if math.isfinite(h.plain_score) else h.score


def _or_two(score: float, two: float) -> float:
    """A score, or the same pose's score with a second wall hidden (NaN: not scored) where higher."""
    return max(score, two) if math.isfinite(two) else score


def _with_panels(hyps: Sequence[Hypothesis], floor: float) -> List[Hypothesis]:
    """``hyps``, each with the panels it cannot exclude (its rivals that score at least ``floor``)
    as its ``hidden_walls``: along a direction no other wall fixes, the panel may stand anywhere up
    to PANEL_MAX_OFFSET; along one that other walls fix too, about where the rival put it (they
    disagree with the wall by that much, or see it too far off to tell).

    A rival counts with a second hidden wall too (SECOND_PANEL_PRIOR): a panel before the wall the
    rival hides and another before the opposite wall make the place between them, shifted by the
    first panel's offset, the best with one panel (that one taken as its wall); the truth, the
    rival, needs both. Measured in fzk_haus_ground, an in-place turn: a unique answer 187 mm off
    with no bound, its rival (the truth) 590 nats behind with one panel and 15 ahead with two."""
    for h in hyps:
        h.hidden_walls = [{"plane": v.hidden[0],
                           "up_to_m": PANEL_MAX_OFFSET if v.free else min(PANEL_MAX_OFFSET, v.hidden[1] + PANEL_SCAN_STEP),
                           "direction": [v.hidden[2], v.hidden[3]]} for v in h.panels
                          if _or_two(v.score, v.two_panel_score) >= floor]
    return list(hyps)


def _merge(hyps: List[Hypothesis]) -> List[Hypothesis]:
    out: List[Hypothesis] = []
    for h in sorted(hyps, key=lambda h: -h.score):
        if any(math.hypot(h.x - o.x, h.y - o.y) < 0.03 and abs(float(wrap_angle(h.phi - o.phi))) < math.radians(1.5)
               for o in out):
            continue
        out.append(h)
    return out
