"""Where to look from next when the views cannot tell places apart (active relocalization).

A relocalization that stays ``ambiguous`` after the robot has looked all round has seen nothing
that differs between its hypotheses: alike rooms of a building, seen from where the robot
stands, predict the same depth. Turning further shows the same headings again. Moving does not:
a step to one side puts other walls, another door or a room's end into view, and the
hypotheses then predict different depth there. This module picks that step.

For every candidate move (a turn on the spot to face the way, then straight ahead: the front
camera, and with it the protective stop, sees where the robot goes) and every pose hypothesis, it predicts the depth image each
camera would see after the move, from the map alone, on a coarse pixel grid. A pixel tells two
hypotheses apart where their predicted depths differ by more than ``DEPTH_APART``, or where one
predicts a wall nearer than ``SURE_RANGE`` and the other none (farther, a D435i often returns
nothing at all). A pair stays *alike* when fewer than ``min_share`` of the grid's pixels tell it
apart. The move taken leaves the fewest alike pairs, fewer than where the robot stands; among
equals the shortest (the least driving while not localized). Hypotheses at the same place
(``SAME_PLACE_XY``, ``SAME_PLACE_PHI``) count once. A move must keep the robot's circumscribed
circle plus ``clearance`` off every wall in *every* hypothesis (the robot is at one of them, not
known which). Site clutter is left to the protective stop, which stays in force while the
robot moves.

Where no single move tells all places apart (the way that would runs into a wall: out of a
small office, round a corner) and the recovery may move twice or more, paths of two moves are
searched as well: the first clear in every hypothesis, the second clear from where the first
ends in every hypothesis. A path that leaves fewer places alike than the best single move is
taken, but only its first move is driven (the second is ``then``): the relocalization after it
sees what it sees, and the next plan starts from that verdict.

Measured (2026-12-07, the relocalization benchmark's scenes, realistic camera, site clutter):
one planned move of 0.5 to 2 m made 7 of 8 moved one-view ambiguous verdicts a correct unique
one in a house (fzk_haus_ground) and 16 of 30 in an office floor whose offices repeat
(institute_ground), map-symmetric ones among them. With up to two moves (a path of two where
no single move does), 29 of 42 moved poses over the four maps against 23 of 40, and after a full
in-place turn 8 of 11 against 2 of 4; no wrong unique verdict.

Pure geometry on the map: no frames, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from robot.base.geometry import compose_se2, pose_to_T_ground_robot
from robot.config import RobotConfig
from robot.localization.roi import CameraGrid, predict_views, rasterize_views
from robot.maps.plane_index import PlaneIndex
from robot.maps.plane_map import PlaneMap

Pose = Tuple[float, float, float]

# Predicted depths further apart than this tell two places apart for sure: beyond a panel's
# offset from its wall and many times the depth noise and a 1 % scale error at the range limit.
DEPTH_APART = 0.3  # m
SURE_RANGE = 4.5  # m: a wall nearer than this returns depth (a predicted wall farther may show as nothing)
# Hypotheses nearer than this are one place: no move tells them apart (the localizer's
# refinement does), and a pair of them must not veto every move.
SAME_PLACE_XY = 0.3  # m
SAME_PLACE_PHI = math.radians(5.0)
GRID_STRIDE = 16  # image pixels between predicted grid pixels (848 x 480 -> 53 x 30 per camera)
DIRECTIONS = 16  # candidate directions of travel, evenly spaced in the robot frame
MAX_DISTANCE = 2.0  # m: the longest move planned (measured: 0.5 to 2 m sufficed in a house)
CLEARANCE = 0.15  # m kept between the robot's circumscribed circle and every wall, in every hypothesis
MIN_SHARE = 0.05  # of the grid's pixels: fewer telling a pair apart leave it alike
# The two-move search predicts views at every clear pair of moves (up to (DIRECTIONS x steps)^2
# end poses per place): it looks at the best few places only, a second plan after the first move
# weighs them all.
TWO_MOVE_PLACES = 4
# Heights (robot frame, m) at which a wall blocks the robot: its body between floor and top.
BODY_BAND = (0.02, 0.6)


@dataclass(frozen=True)
class Move:
    """A move from the present view's robot frame: turn by ``dphi`` to face (dx, dy), then drive there."""

    dx: float  # m, along robot x
    dy: float  # m, along robot y
    dphi: float  # rad, the heading of the way, turned on the spot first
    alike: int  # pairs of places the predicted views after the move do not tell apart
    alike_here: int  # the same where the robot stands
    places: int  # places among the hypotheses (those nearer than SAME_PLACE_* count once)
    # The second move of a two-move path (in the robot frame after this one), which makes ``alike``:
    # this move alone does not tell the places apart.
    then: Optional[Tuple[float, float, float]] = None

    @property
    def distance(self) -> float:
        return math.hypot(self.dx, self.dy)

    def to_json(self) -> dict:
        out = {"dx": round(self.dx, 4), "dy": round(self.dy, 4), "dphi": round(self.dphi, 6),
               "distance": round(self.distance, 4),
               "alike_pairs": self.alike, "alike_pairs_here": self.alike_here, "places": self.places}
        if self.then is not None:
            out["then"] = {"dx": round(self.then[0], 4), "dy": round(self.then[1], 4), "dphi": round(self.then[2], 6),
                           "distance": round(math.hypot(self.then[0], self.then[1]), 4)}
        return out


def wall_segments(plane_map: PlaneMap, z_lo: float, z_hi: float, samples: int = 5) -> np.ndarray:
    """(S, 4) floor-plan segments (x0, y0, x1, y1) where vertical map polygons cut the heights
    ``z_lo``..``z_hi``: at ``samples`` heights across the band, each polygon's crossings of that
    horizontal line, paired by the even-odd rule (a door's notch leaves a gap, a lintel above the
    band none). Conservative: the union over the sampled heights."""
    out: List[Tuple[float, float, float, float]] = []
    heights = np.linspace(z_lo, z_hi, max(samples, 2))
    for p in plane_map.planes:
        n = np.asarray(p.normal, float)
        if abs(n[2]) > 0.7:  # a floor, ceiling or ramp: nothing the robot drives into at its height
            continue
        h = math.hypot(n[0], n[1])
        t = np.array([-n[1] / h, n[0] / h])  # along the wall in the floor plan
        for poly in p.polygons:
            v = np.asarray(poly, float)
            if v[:, 2].max() < z_lo or v[:, 2].min() > z_hi:
                continue
            nxt = np.roll(v, -1, axis=0)
            for z in heights:
                a, b = v[:, 2] - z, nxt[:, 2] - z
                cross = (a > 0) != (b > 0)
                if not cross.any():
                    continue
                f = a[cross] / (a[cross] - b[cross])
                pts = v[cross, :2] + f[:, None] * (nxt[cross, :2] - v[cross, :2])
                order = np.argsort(pts @ t)
                pts = pts[order]
                for k in range(0, len(pts) - 1, 2):
                    out.append((pts[k, 0], pts[k, 1], pts[k + 1, 0], pts[k + 1, 1]))
    return np.array(out, float).reshape(-1, 4)


def segment_distance(p0: np.ndarray, p1: np.ndarray, segs: np.ndarray) -> float:
    """Least distance between the segment p0-p1 and any of ``segs`` (S, 4); inf if there are none.

    Two segments that do not cross are nearest at an end point of one of them."""
    if len(segs) == 0:
        return math.inf
    a, b = segs[:, :2], segs[:, 2:]
    p0 = np.asarray(p0, float)
    p1 = np.asarray(p1, float)
    r, s = p1 - p0, b - a
    den = r[0] * s[:, 1] - r[1] * s[:, 0]
    qp = a - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = (qp[:, 0] * s[:, 1] - qp[:, 1] * s[:, 0]) / den
        uu = (qp[:, 0] * r[1] - qp[:, 1] * r[0]) / den
    if np.any((den != 0) & (tt >= 0) & (tt <= 1) & (uu >= 0) & (uu <= 1)):
        return 0.0
    return float(min(_point_to_segments(p0, a, b).min(), _point_to_segments(p1, a, b).min(),
                     _points_to_segment(a, p0, p1).min(), _points_to_segment(b, p0, p1).min()))


def _point_to_segments(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    d = s1 - s0
    L2 = np.einsum("ij,ij->i", d, d)
    u = np.clip(np.einsum("ij,ij->i", p - s0, d) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
    return np.hypot(*(p - (s0 + u[:, None] * d)).T)


def _points_to_segment(q: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    r = p1 - p0
    L2 = float(r @ r)
    u = np.clip(((q - p0) @ r) / L2, 0.0, 1.0) if L2 > 0 else np.zeros(len(q))
    return np.hypot(*(q - (p0 + u[:, None] * r)).T)


class ViewpointPlanner:
    """Plans the move that best tells a relocalization's hypotheses apart (see the module's text)."""

    def __init__(self, robot: RobotConfig, plane_map: PlaneMap, index: Optional[PlaneIndex] = None,
                 stride: int = GRID_STRIDE):
        self.robot = robot
        self.map = plane_map
        self.index = index if index is not None else PlaneIndex(plane_map)
        self.max_range = robot.localizer.max_range
        self.grids = []
        for cam in robot.cameras:
            s = max(1, int(stride))
            self.grids.append((cam, CameraGrid(cam.intrinsics_from_fov(), cam.width, cam.height, s)))
        self.segments = wall_segments(plane_map, *BODY_BAND)
        sc = robot.safety
        # The circle the footprint sweeps when it turns about the robot origin: the move keeps it
        # off the walls whatever the robot's heading error.
        self.radius = math.hypot(sc.footprint_length / 2.0 + abs(sc.footprint_offset_x), sc.footprint_width / 2.0)

    def predicted_depth(self, pose: Pose) -> np.ndarray:
        """Depth (m) each camera would see at ``pose`` from the map alone, on the grid, all cameras'
        pixels in one flat array; NaN where no wall is predicted within range."""
        out = []
        for cam, grid in self.grids:
            T_gc = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
            views = predict_views(self.map, self.index, T_gc, grid, self.max_range)
            z = np.full(grid.shape, np.nan)
            if views:
                label = rasterize_views(views, grid)
                table = np.array([v.pi_camera for v in views], float).reshape(len(views), 4)
                cols, rows = grid.rays
                has = label >= 0
                r_idx, c_idx = np.nonzero(has)
                pis = table[label[r_idx, c_idx]]
                denom = pis[:, 0] * cols[c_idx] + pis[:, 1] * rows[r_idx] + pis[:, 2]
                with np.errstate(divide="ignore", invalid="ignore"):
                    zp = -pis[:, 3] / denom
                zp[~((zp > 0) & (zp < self.max_range))] = np.nan
                z[r_idx, c_idx] = zp
            out.append(z.ravel())
        return np.concatenate(out)

    def alike_pairs(self, poses: Sequence[Pose], min_share: float) -> int:
        """How many pairs of ``poses`` fewer than ``min_share`` of the grid's pixels tell apart."""
        depths = [self.predicted_depth(p) for p in poses]
        n = 0
        for i in range(len(depths)):
            for j in range(i + 1, len(depths)):
                n += apart_share(depths[i], depths[j]) < min_share
        return n

    @staticmethod
    def places(poses: Sequence[Pose]) -> List[Pose]:
        """``poses`` (best first) without those at the same place as a better one."""
        out: List[Pose] = []
        for p in poses:
            if not any(math.hypot(p[0] - q[0], p[1] - q[1]) < SAME_PLACE_XY
                       and abs(math.remainder(p[2] - q[2], 2.0 * math.pi)) < SAME_PLACE_PHI for q in out):
                out.append(p)
        return out

    def clear(self, poses: Sequence[Pose], move: Tuple[float, float], clearance: float) -> bool:
        """Whether the move to (dx, dy) (robot frame) keeps the robot ``clearance`` off every wall
        from every pose, the turn on the spot at its start included (the circle is the one the
        footprint sweeps)."""
        need = self.radius + clearance
        for p in poses:
            end = compose_se2(p, (move[0], move[1], 0.0))
            if segment_distance(np.array(p[:2]), np.array(end[:2]), self.segments) < need:
                return False
        return True

    def plan(self, poses: Sequence[Pose], max_distance: float = MAX_DISTANCE, clearance: float = CLEARANCE,
             min_share: float = MIN_SHARE, steps: int = 4, moves: int = 1) -> Optional[Move]:
        """The move (up to ``max_distance``, in ``steps`` lengths and DIRECTIONS directions, the
        robot turned to face the way) after which the fewest pairs of ``poses`` (the robot's present
        pose hypotheses, best first) look alike; None if no move leaves fewer than where the robot
        stands, or there is one place. With ``moves`` >= 2, where a path of two moves leaves fewer
        alike than any single move, its first move (the second in ``then``)."""
        places = self.places([(float(p[0]), float(p[1]), float(p[2])) for p in poses])
        if len(places) < 2 or not max_distance > 0.0:
            return None
        here = self.alike_pairs(places, min_share)
        if here == 0:
            return None
        candidates = self._moves(max_distance, steps)
        best: Optional[Move] = None
        for move in candidates:
            if not self.clear(places, move[:2], clearance):
                continue
            alike = self.alike_pairs([compose_se2(p, move) for p in places], min_share)
            if alike < here and (best is None or alike < best.alike):
                best = Move(move[0], move[1], move[2], alike, here, len(places))
        if moves < 2 or (best is not None and best.alike == 0):
            return best
        # Two moves where one leaves places alike (none does, or one pair still is): the path that
        # leaves the fewest, if fewer than the best single move does.
        path = self._two_moves(places[:TWO_MOVE_PLACES], candidates, clearance, min_share)
        if path is None:
            return best
        alike, first, second = path
        if len(places) > TWO_MOVE_PLACES:  # (searched among the best few: judged again over all of them)
            there = [compose_se2(p, first) for p in places]
            if not (self.clear(places, first[:2], clearance) and self.clear(there, second[:2], clearance)):
                return best
            alike = self.alike_pairs([compose_se2(p, second) for p in there], min_share)
        if alike < (here if best is None else best.alike):
            return Move(first[0], first[1], first[2], alike, here, len(places), then=second)
        return best

    def _two_moves(self, places: List[Pose], candidates: List[Tuple[float, float, float]], clearance: float,
                   min_share: float) -> Optional[Tuple[int, Tuple[float, float, float], Tuple[float, float, float]]]:
        """The path of two moves (each one of ``candidates``, each clear from where it starts in
        every hypothesis) after which the fewest pairs of ``places`` look alike, fewer than where
        the robot stands; among equals the shortest: (pairs alike after it, first, second), or None."""
        here = self.alike_pairs(places, min_share)
        if here == 0:
            return None
        best: Optional[Tuple[int, float, Tuple, Tuple]] = None
        for first in candidates:
            if not self.clear(places, first[:2], clearance):
                continue
            there = [compose_se2(p, first) for p in places]
            d1 = math.hypot(first[0], first[1])
            for second in candidates:
                length = d1 + math.hypot(second[0], second[1])
                if best is not None and best[0] == 0 and length >= best[1]:
                    continue  # (nothing here can beat a shorter path that tells them all apart)
                if not self.clear(there, second[:2], clearance):
                    continue
                alike = self.alike_pairs([compose_se2(p, second) for p in there], min_share)
                if alike < here and (best is None or (alike, length) < best[:2]):
                    best = (alike, length, first, second)
        return None if best is None else (best[0], best[2], best[3])

    @staticmethod
    def _moves(max_distance: float, steps: int) -> List[Tuple[float, float, float]]:
        """The candidate moves (dx, dy, dphi), shortest first: DIRECTIONS directions, ``steps`` lengths."""
        out = []
        for k in range(1, max(1, steps) + 1):
            dist = max_distance * k / max(1, steps)
            for j in range(DIRECTIONS):
                a = 2.0 * math.pi * j / DIRECTIONS
                out.append((dist * math.cos(a), dist * math.sin(a), float(math.remainder(a, 2.0 * math.pi))))
        return out


def plan_recovery_move(planner: ViewpointPlanner, hypotheses: Sequence, max_distance: float,
                       clearance: float, moves_left: int = 1) -> Tuple[Optional[Tuple[float, float, float]], str]:
    """The recovery's move from a relocalization's hypotheses (refined ones, best first): its end
    (dx, dy, dphi) in the robot frame, or None and why not. With two or more ``moves_left``, the
    first of two moves where no single one tells the places apart."""
    poses = [(h.x, h.y, h.phi) for h in hypotheses if h.refined]
    move = planner.plan(poses, max_distance, clearance, moves=min(2, moves_left))
    if move is None:
        return None, no_move_reason(max_distance, moves_left)
    return (move.dx, move.dy, move.dphi), ""


def no_move_reason(max_distance: float, moves: int) -> str:
    """Why nothing was planned, for ``plan(..., moves=moves)`` returning None."""
    most = "path of two moves" if moves >= 2 else "move"
    return f"no {most} of up to {max_distance:.1f} m would tell the places apart"


def apart_share(z_a: np.ndarray, z_b: np.ndarray) -> float:
    """Share of grid pixels whose predicted depths (NaN: no wall) tell two places apart."""
    fa, fb = np.isfinite(z_a), np.isfinite(z_b)
    with np.errstate(invalid="ignore"):
        apart = ((fa & fb & (np.abs(z_a - z_b) > DEPTH_APART)) | (fa & ~fb & (z_a < SURE_RANGE))
                 | (fb & ~fa & (z_b < SURE_RANGE)))
    return float(apart.mean()) if len(apart) else 0.0
