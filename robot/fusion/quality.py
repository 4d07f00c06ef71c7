"""Localization quality: ``localized``, ``degraded`` or ``lost``, always with a reason.

Inputs are explicit (no clock inside): the time of each plane update and whether the gate
accepted it (``note_update``), pose resets (``note_fix``), and at evaluation the filter's 3x3
covariance of (x, y, phi). Rules, checked in this order (defaults in :class:`QualityConfig`):

- ``lost`` when the position std (the larger axis of the x/y covariance ellipse) exceeds
  ``lost_pos_std`` (0.10 m), the heading std exceeds ``lost_heading_std_deg`` (5 deg), no plane
  was accepted for ``lost_after`` (10 s), or the gate refused at least ``lost_rejection_ratio``
  (90 %) of the recent planes (the map no longer agrees with the pose: kidnapped or wrong map).
- ``degraded`` when the last accepted plane is older than ``localized_within`` (1 s, odometry
  only), the position std exceeds ``localized_pos_std`` (0.02 m), the heading std exceeds
  ``localized_heading_std_deg`` (1 deg), or the gate refused at least ``degraded_rejection_ratio``
  (50 %) of the recent planes.
- ``degraded`` also when a protection level of the fused pose exceeds its alert limit
  (``horizontal_alert_limit``, 0.10 m; ``heading_alert_limit_deg``, 3 deg): the pose cannot be
  vouched for to the accuracy the robot needs, at the integrity risk the localizer works to.
- ``localized`` otherwise.

Protection levels of the fused pose (:class:`FusedProtection`, docs/localization-integrity.md):
bounds k sigma of the filter's covariance plus what the filter cannot average away, the
systematic part of the last accepted localization's covariance (depth scale, mounts, walls as
built are the same in every frame), plus the largest separation between that localization and
its leave-one-out solutions (how far one wrong wall could have moved it unseen); and never
under the bound of a wrong-wall hypothesis that only a prior bounded. A wall whose leaving out
leaves a direction unobserved (a panel hiding the only wall across that direction) is bounded
there by the prior alone: when the wall is first fused, by the pose as it was then (given to
the robot, or the filter's before the wall); afterwards by the filter's pose, which that wall
built, and which then bounds nothing: recomputed on it, the bound shrinks to nothing while the
error stays. So each such hypothesis keeps the largest bound it had, until walls fused since the
pose was given, other than its own, observe every direction it left unobserved (had the wall
been wrong, they would have disagreed with it).

The position reason names the poorly known direction, so a corridor (parallel walls only) says
which way the position is unobservable instead of inventing it (docs/architecture.md, 'Pose solver'). To stop
the state flickering at a threshold, a worse state is left only once the numbers are back
below ``hysteresis`` (80 %) of the threshold that put it there. A pose reset (``note_fix``)
counts as an accepted update for the age rules, like Nav2 AMCL's initial pose.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Deque, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from robot.config import QualityConfig
from robot.localization.integrity import protection_multipliers

LOCALIZED = "localized"
DEGRADED = "degraded"
LOST = "lost"
_RANK = {LOCALIZED: 0, DEGRADED: 1, LOST: 2}
DEFAULT_RISK = 1e-3


_MULTIPLIERS: Dict[float, Tuple[float, float]] = {}


def _multipliers(risk: float) -> Tuple[float, float]:
    """``protection_multipliers`` for the few risks in use, memoised: it runs every control tick."""
    k = _MULTIPLIERS.get(risk)
    if k is None:
        k = _MULTIPLIERS[risk] = protection_multipliers(risk)
    return k


def _largest_eigenvalue2(a: float, b: float, d: float) -> float:
    """Largest eigenvalue of the symmetric 2x2 [[a, b], [b, d]] in closed form (no LAPACK call per tick)."""
    half = 0.5 * (a - d)
    return 0.5 * (a + d) + math.sqrt(half * half + b * b)


@dataclass(frozen=True)
class FusedProtection:
    """What the last accepted localization adds to the fused pose's protection levels."""

    systematic_cov: Optional[np.ndarray] = None  # (3, 3) shared-error part of its covariance
    separation_h: float = 0.0  # m: its largest all-in to leave-one-out separation, horizontal
    separation_heading: float = 0.0  # rad
    risk: float = DEFAULT_RISK
    # Wrong-wall hypotheses that only a prior bounded, carried (module docstring): each (the walls
    # it takes for wrong, its horizontal bound m, its heading bound rad, the directions in (x, y,
    # phi) it left unobserved), with the largest bounds it had since it first appeared.
    open_faults: Tuple[Tuple[Tuple[str, ...], float, float, Tuple[Tuple[float, float, float], ...]], ...] = ()
    prior_bound_h: float = 0.0  # m: the largest horizontal bound among them that walls do not yet cover
    prior_bound_heading: float = 0.0  # rad: ... heading

    @classmethod
    def from_localization(cls, result, previous: Optional[FusedProtection] = None,
                          fused_walls: Optional[Mapping[str, Tuple[float, float]]] = None) -> FusedProtection:
        """What ``result`` (an accepted localization) adds to the fused pose. ``previous``: the
        protection before it (None: the pose was just given); ``fused_walls``: the map walls the
        filter accepted since the pose was given, this localization's included, each with its
        normal in the ground frame (x, y)."""
        info = getattr(result, "integrity", {}) or {}
        faults: Dict[Tuple[str, ...], Tuple[float, float, Tuple[Tuple[float, float, float], ...]]] = {}
        for walls, h, heading, dirs in (previous.open_faults if previous is not None else ()):
            faults[walls] = (h, heading, dirs)
        for hyp in info.get("prior_bounded") or ():
            walls = tuple(hyp.get("walls") or ())
            if not walls:  # no wall wrong: the filter's covariance keeps what is unobserved
                continue
            h, heading = float(hyp.get("horizontal_m") or 0.0), float(hyp.get("heading_rad") or 0.0)
            dirs = tuple((float(u[0]), float(u[1]), float(u[2])) for u in hyp.get("directions") or ())
            old = faults.get(walls)
            # A bound recomputed on a prior that the wall itself built says nothing new: keep the largest.
            faults[walls] = (h, heading, dirs) if old is None else (max(old[0], h), max(old[1], heading), dirs)
        fused = fused_walls or {}
        kept, bound_h, bound_heading = [], 0.0, 0.0
        for walls, (h, heading, dirs) in faults.items():
            open_h, open_heading = _open(walls, dirs, fused)
            if open_h or open_heading:
                kept.append((walls, h, heading, dirs))
                bound_h = max(bound_h, h) if open_h else bound_h
                bound_heading = max(bound_heading, heading) if open_heading else bound_heading
        return cls(getattr(result, "systematic_cov", None), float(info.get("separation_m") or 0.0),
                   float(info.get("separation_rad") or 0.0), float(getattr(result, "risk", DEFAULT_RISK)),
                   tuple(kept), bound_h, bound_heading)

    @classmethod
    def from_hidden_walls(cls, hidden_walls: Sequence[Mapping], cov: np.ndarray,
                          risk: float = DEFAULT_RISK) -> FusedProtection:
        """The protection of a relocalized pose whose walls a panel may hide (Relocalizer): for each,
        the pose may lie up to ``up_to_m`` farther along ``direction``, a wrong-wall hypothesis
        that only walls other than it can close, as those of :meth:`from_localization`."""
        k_h, _ = _multipliers(risk)
        (a, b, _), (c, d, _), _ = np.asarray(cov, float).tolist()
        sigma = math.sqrt(max(_largest_eigenvalue2(a, 0.5 * (b + c), d), 0.0))
        faults = []
        for hw in hidden_walls:
            ux, uy = (float(v) for v in hw["direction"])
            faults.append(((str(hw["plane"]),), float(hw["up_to_m"]) + k_h * sigma, 0.0, ((ux, uy, 0.0),)))
        bound = max((f[1] for f in faults), default=0.0)
        return cls(risk=risk, open_faults=tuple(faults), prior_bound_h=bound)

    def levels(self, P: np.ndarray) -> Tuple[float, float]:
        """(horizontal m, heading rad) protection levels of a fused pose with covariance P."""
        return self._levels(np.asarray(P, float).tolist())

    def _levels(self, rows: List[List[float]]) -> Tuple[float, float]:
        """``levels`` of P given as its rows of floats (the control tick has them already)."""
        k_h, k_phi = _multipliers(self.risk)
        if self.systematic_cov is not None:
            S = np.asarray(self.systematic_cov, float)
            if S.shape == (3, 3):
                # Entry by entry, the sums numpy's P + S would give; only these five are read.
                (a, b, _), (c, d, _), (_, _, e) = rows
                (sa, sb, _), (sc, sd, _), (_, _, se) = S.tolist()
                a, b, c, d, e = a + sa, b + sb, c + sc, d + sd, e + se
            else:
                (a, b, _), (c, d, _), (_, _, e) = (np.asarray(rows, float) + S).tolist()
        else:
            (a, b, _), (c, d, _), (_, _, e) = rows
        lam = _largest_eigenvalue2(a, 0.5 * (b + c), d)
        return (max(k_h * math.sqrt(max(lam, 0.0)) + self.separation_h, self.prior_bound_h),
                max(k_phi * math.sqrt(max(e, 0.0)) + self.separation_heading, self.prior_bound_heading))


_NO_PROTECTION = FusedProtection()  # the covariance alone (frozen: one instance serves every tick)

COVER_COS = 0.5  # a wall whose normal is within 60 deg of a direction observes it


def _open(walls: Sequence[str], directions: Sequence[Sequence[float]],
          fused_walls: Mapping[str, Tuple[float, float]]) -> Tuple[bool, bool]:
    """Whether a hypothesis that takes ``walls`` for wrong still leaves (position, heading)
    unobserved: whether some direction it left to the prior is observed by no wall fused since the
    pose was given, other than its own: a position direction by a wall facing it within 60 deg,
    the heading by any wall."""
    own = set(walls)
    others = [n for wall, n in fused_walls.items() if wall not in own]
    open_h = open_heading = False
    for ux, uy, uphi in directions:
        norm = math.hypot(ux, uy)
        if norm > 0.1 and not any(abs(nx * ux + ny * uy) >= COVER_COS * norm for nx, ny in others):
            open_h = True
        if abs(uphi) > 0.1 and not others:
            open_heading = True
    return open_h, open_heading


@dataclass(frozen=True)
class QualityReport:
    state: str  # localized | degraded | lost
    reason: str  # "" when localized
    pos_std: float  # m, the larger axis of the position covariance
    heading_std: float  # rad
    since_accepted: float  # s since the last accepted plane or pose reset (inf: never)
    rejection_ratio: float  # over the window; nan when too few decisions
    horizontal_pl: float = math.inf  # m, protection level of the fused position
    heading_pl: float = math.inf  # rad
    protection_exceeded: bool = False  # a protection level is over its alert limit (the controller slows down)

    def as_dict(self) -> dict:
        return {"state": self.state, "reason": self.reason, "pos_std": self.pos_std,
                "heading_std_deg": math.degrees(self.heading_std), "since_accepted": self.since_accepted,
                "rejection_ratio": self.rejection_ratio, "horizontal_pl": self.horizontal_pl,
                "heading_pl_deg": math.degrees(self.heading_pl), "protection_exceeded": self.protection_exceeded}


def _finite9(rows: Sequence[Sequence[float]]) -> bool:
    """All nine entries of a 3x3 covariance's rows are finite (unrolled: it runs every tick)."""
    (a, b, c), (d, e, f), (g, h, i) = rows
    isfinite = math.isfinite
    return (isfinite(a) and isfinite(b) and isfinite(c) and isfinite(d) and isfinite(e) and isfinite(f)
            and isfinite(g) and isfinite(h) and isfinite(i))


def position_std_axis(P: np.ndarray) -> Tuple[float, float]:
    """(std along the worst direction, that direction's angle in G) of the x/y block of P."""
    w, v = np.linalg.eigh(0.5 * (P[:2, :2] + P[:2, :2].T))
    axis = v[:, 1]
    return math.sqrt(max(float(w[1]), 0.0)), math.atan2(float(axis[1]), float(axis[0]))


class QualityMonitor:
    """Turns filter events and covariance into a quality state with a reason."""

    def __init__(self, config: Optional[QualityConfig] = None):
        self.config = config or QualityConfig()
        self._last_accepted: Optional[float] = None
        self._decisions: Deque[Tuple[float, bool]] = collections.deque()
        self._rejected = 0  # refusals among _decisions, kept as they come and go
        self._state = LOST
        self._reason = "no pose yet"
        self._fresh = True

    @property
    def state(self) -> str:
        return self._state

    def note_fix(self, t: float) -> None:
        """A pose was set (initial pose, operator fix): it counts as fresh localization."""
        self._last_accepted = t if self._last_accepted is None else max(self._last_accepted, t)
        self._decisions.clear()
        self._rejected = 0
        self._state = DEGRADED  # until the next evaluation judges the numbers
        self._reason = "pose set"
        self._fresh = True  # no hysteresis from before the reset

    def note_update(self, t: float, accepted: bool) -> None:
        """A plane measurement captured at t went through the gate (accepted or not)."""
        self._decisions.append((t, bool(accepted)))
        if not accepted:
            self._rejected += 1
        if accepted and (self._last_accepted is None or t > self._last_accepted):
            self._last_accepted = t

    def evaluate(self, t: float, P: np.ndarray, protection: Optional[FusedProtection] = None) -> QualityReport:
        """The state at t from the fused covariance P and what the last accepted localization adds
        to its protection levels (None: the covariance alone)."""
        cfg = self.config
        decisions = self._decisions
        while decisions and decisions[0][0] < t - cfg.rejection_window:
            if not decisions.popleft()[1]:
                self._rejected -= 1
        n = len(decisions)
        rejected = self._rejected
        ratio = rejected / n if n >= cfg.min_decisions else math.nan
        age = math.inf if self._last_accepted is None else max(0.0, t - self._last_accepted)
        P = np.asarray(P, dtype=float)
        rows = P.tolist() if P.shape == (3, 3) else None
        if rows is None or not _finite9(rows):
            return self._set(LOST, "covariance is not finite", math.inf, math.inf, age, ratio)
        (p00, p01, _), (p10, p11, _), (_, _, p22) = rows
        pos_std = math.sqrt(max(_largest_eigenvalue2(p00, 0.5 * (p01 + p10), p11), 0.0))
        axis = math.nan  # only a reason names it, and only above a threshold
        if pos_std > 0.5 * min(cfg.localized_pos_std, cfg.lost_pos_std) * min(cfg.hysteresis, 1.0):
            pos_std, axis = position_std_axis(P)
        heading_std = math.sqrt(max(p22, 0.0))
        hpl, vpl = (protection or _NO_PROTECTION)._levels(rows)

        # Thresholds are tightened by the hysteresis factor for the states we are trying to leave.
        rank = _RANK[self._state]
        s_lost = cfg.hysteresis if not self._fresh and rank >= _RANK[LOST] else 1.0
        s_deg = cfg.hysteresis if not self._fresh and rank >= _RANK[DEGRADED] else 1.0

        lost_reasons = self._reasons(
            cfg.lost_after * s_lost, cfg.lost_pos_std * s_lost, cfg.lost_heading_std_deg * s_lost,
            cfg.lost_rejection_ratio * s_lost, age, pos_std, axis, heading_std, ratio, rejected, n)
        over = []
        if hpl > cfg.horizontal_alert_limit * s_deg:
            over.append(f"horizontal protection level {hpl * 1000:.0f} mm over the {cfg.horizontal_alert_limit * 1000:.0f} "
                        "mm alert limit")
        if math.degrees(vpl) > cfg.heading_alert_limit_deg * s_deg:
            over.append(f"heading protection level {math.degrees(vpl):.1f} deg over the {cfg.heading_alert_limit_deg:g} "
                        "deg alert limit")
        pl = (hpl, vpl, bool(over))
        if lost_reasons:
            return self._set(LOST, "; ".join(lost_reasons), pos_std, heading_std, age, ratio, *pl)
        deg_reasons = self._reasons(
            cfg.localized_within * s_deg, cfg.localized_pos_std * s_deg,
            cfg.localized_heading_std_deg * s_deg, cfg.degraded_rejection_ratio * s_deg,
            age, pos_std, axis, heading_std, ratio, rejected, n) + over
        if deg_reasons:
            return self._set(DEGRADED, "; ".join(deg_reasons), pos_std, heading_std, age, ratio, *pl)
        return self._set(LOCALIZED, "", pos_std, heading_std, age, ratio, *pl)

    @staticmethod
    def _reasons(max_age, max_pos, max_heading_deg, max_ratio, age, pos_std, axis, heading_std, ratio,
                 rejected, n) -> List[str]:
        out = []
        if age > max_age:
            out.append("no plane accepted yet" if math.isinf(age) else f"odometry only for {age:.1f} s")
        if pos_std > max_pos:
            out.append(f"position std {pos_std * 1000:.0f} mm along {math.degrees(axis) % 180:.0f} deg")
        if math.degrees(heading_std) > max_heading_deg:
            out.append(f"heading std {math.degrees(heading_std):.1f} deg")
        if not math.isnan(ratio) and ratio >= max_ratio:
            out.append(f"gate refused {rejected} of {n} recent planes")
        return out

    def _set(self, state, reason, pos_std, heading_std, age, ratio, hpl=math.inf, vpl=math.inf,
             over=False) -> QualityReport:
        self._state, self._reason, self._fresh = state, reason, False
        return QualityReport(state, reason, pos_std, heading_std, age, ratio, hpl, vpl, over)
