"""When the robot does not know where it is: hold still, relocalize, resume only when confirmed.

A pure state machine with explicit time, beside the health supervisor. It decides when a global
relocalization (``robot.localization.relocalize``) is needed and whether the robot may move; the
shell runs the relocalization off the loop and hands the verdict back.

States:

- ``tracking``: the normal localizer keeps the pose; nothing to do.
- ``checking``: the pose came from a saved file (or a person): the first localizations must
  confirm it; if they do not, relocalize.
- ``relocalizing``: waiting for a verdict on fresh frames; the robot holds still.
- ``ambiguous``: several poses explain the views; the robot holds, the hypotheses are reported,
  and relocalization is retried every ``retry_period`` (new views, or a person, decide).
- ``turning`` (only with ``turn_in_place``): the last relocalization was ambiguous or found
  nothing; the core turns the robot in place by ``turn_step_deg`` (a pure rotation, braked to
  still), then the next relocalization uses every view of this sequence: the first view's frames
  and, for each later one, its frames with its pose relative to the first by odometry. The
  sequence ends on ``unique`` (confirming as usual), or when the next view would pass
  ``max_turn_deg`` (or repeat the first heading), or when the turn was stopped (the protective
  stop, a fault): then the verdict stands and is reported as without a turn. A sequence that ended
  so is not turned again until a new trigger (or an operator's request, ``force``: the control
  socket's ``recover``): a robot that has looked all round, or was stopped by something beside
  it, does not start moving on its own.
- ``moving`` (only with ``move_to_tell_apart``): the sequence ended ambiguous (after the turn, if
  any) and the shell planned a short move (``robot.localization.viewpoint``: a turn on the spot
  to face the way, then straight ahead) after which the map predicts different depth for the
  hypotheses; the core drives it by wheel odometry, braked to still, then the next
  relocalization uses every view of the sequence and the new one. At most ``max_moves`` per trigger; a move that was stopped (the protective
  stop, a fault) ends the sequence as a stopped turn does.
- ``confirming``: a unique verdict set the pose; the robot holds until the normal localizer has
  accepted ``confirm_updates`` plane updates from it.

Triggers into ``relocalizing``: no pose at start-up; quality ``lost`` for ``lost_after`` s; a
saved pose the cameras contradict; a *kidnap*: for ``kidnap_time`` s (and at least
``kidnap_frames`` localizations) the localizer fitted at least ``kidnap_min_walls`` walls and
the fusion gate rejected every one (odometry and every wall disagree). A view with fewer fitted
walls, all rejected, neither counts nor clears the run: one wall alone is as likely a panel or a
stack of boards standing in front of it as a moved robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple, TypeVar

from robot.base.geometry import compose_se2, invert_se2
from robot.config.recovery import RecoveryConfig

T = TypeVar("T")

TRACKING = "tracking"
CHECKING = "checking"
RELOCALIZING = "relocalizing"
AMBIGUOUS = "ambiguous"
CONFIRMING = "confirming"
TURNING = "turning"
MOVING = "moving"

FULL_TURN = 2.0 * math.pi
_TURN_EPS = 1e-6  # rad: a view exactly at max_turn_deg is still taken


Pose = Tuple[float, float, float]


def views_from_latest(views: Sequence[Tuple[T, Pose]]) -> Tuple[T, List[Tuple[T, Pose]]]:
    """The views of a sequence, each given with its odometry pose in the first view's robot frame,
    re-based on the latest: (its frames, [(frames, pose relative to it)] for the earlier ones).

    The relocalizer answers for its first view and refines on it first, so giving it the latest
    puts the hypotheses where the robot stands now, with the normal localizer's covariance there."""
    frames, here = views[-1]
    back = invert_se2(here)
    return frames, [(f, compose_se2(back, rel)) for f, rel in views[:-1]]


@dataclass
class RecoverySupervisor:
    config: RecoveryConfig = field(default_factory=RecoveryConfig)
    state: str = TRACKING
    reason: str = ""
    hypotheses: List[dict] = field(default_factory=list)
    attempts: int = 0
    _lost_since: Optional[float] = None
    _rejected_run: List[float] = field(default_factory=list)
    _checked: int = 0
    _confirmed: int = 0
    _next_try: float = -math.inf
    _requested: bool = False
    # The views of the present relocalization sequence (an in-place turn gathers several).
    view_index: int = 0  # of the view the shell is asked for: 0 starts a new sequence (drop the others)
    turn_goal: float = 0.0  # rad, heading of the next view relative to the first (turning: where to stop)
    _views: int = 0  # views taken in this sequence
    _sequence_open: bool = False
    _may_turn: bool = True  # False once a sequence has turned as far as it may, or its turn was stopped
    _after_turn: Tuple[str, str] = (RELOCALIZING, "")  # (state, reason) the verdict left, if the turn stops
    turn_note: str = ""  # how the last turn of this trigger ended, repeated in the retries' reasons
    # The move of an ambiguous sequence: its end (dx, dy, dphi) in the robot frame where it starts.
    move_goal: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    wants_move_plan: bool = False  # the shell should plan a move from ``hypotheses`` (move_planned)
    _moves: int = 0  # moves made for this trigger
    # Counts every move ever started: the core starts a move afresh when it changes (two moves
    # can follow each other within one control tick: the robot still, relocalized, a new plan).
    move_serial: int = 0

    # -- inputs ------------------------------------------------------------------------------

    def start_without_pose(self, t: float) -> None:
        self._enter(RELOCALIZING, t, "no initial pose")

    def start_from_saved_pose(self, t: float) -> None:
        if self.config.enabled:
            self.state, self.reason, self._checked = CHECKING, "checking the saved pose against the cameras", 0

    def on_quality(self, t: float, state: str) -> None:
        if state == "lost":
            if self._lost_since is None:
                self._lost_since = t
            elif self.state == TRACKING and t - self._lost_since >= self.config.lost_after:
                self._enter(RELOCALIZING, t, f"localization lost for {t - self._lost_since:.1f} s")
        else:
            self._lost_since = None

    def on_fusion(self, t: float, fitted: int, accepted: int) -> None:
        """One localization's outcome: how many walls it fitted, how many the fusion gate took."""
        c = self.config
        if self.state == CHECKING:
            if accepted:
                self.state, self.reason = TRACKING, ""
            elif fitted:
                self._checked += 1
                if self._checked >= c.check_frames:
                    self._enter(RELOCALIZING, t, f"the saved pose disagrees with {self._checked} views")
            return
        if self.state == CONFIRMING:
            self._confirmed += accepted
            if self._confirmed >= c.confirm_updates:
                self.state, self.reason = TRACKING, ""
            elif fitted and not accepted:
                self._checked += 1
                if self._checked >= c.check_frames:
                    self._enter(RELOCALIZING, t, "the relocalized pose was not confirmed")
            return
        if self.state != TRACKING:
            return
        if accepted == 0 and 0 < fitted < c.kidnap_min_walls:
            return
        if fitted >= 1 and accepted == 0:
            self._rejected_run.append(t)
            span = t - self._rejected_run[0]
            if len(self._rejected_run) >= c.kidnap_frames and span >= c.kidnap_time:
                self._enter(RELOCALIZING, t, f"kidnapped? for {span:.1f} s every fitted wall of "
                            f"{len(self._rejected_run)} views disagreed with the pose")
        elif accepted:
            self._rejected_run = []

    def on_verdict(self, t: float, verdict: str, hypotheses: List[dict], reason: str = "",
                   may_turn: bool = True) -> None:
        """The relocalizer's answer; on 'unique' the shell has set the pose from the first hypothesis.

        ``may_turn``: False when the attempt failed for a reason a turn cannot help (a bad frame)."""
        self._requested = False
        self.hypotheses = list(hypotheses)
        self._views += 1
        if verdict == "unique":
            self.state, self.reason, self._confirmed, self._checked = CONFIRMING, "confirming the relocalized pose", 0, 0
            self._sequence_open = False
            return
        turned = self.turn_goal
        after = f" after turning {math.degrees(turned):.0f} deg in place" if turned > 0.0 else ""
        if self._moves and self._sequence_open:
            after += f"{' and' if after else ' after'} {self._moves} move(s) to tell them apart"
        if verdict == "ambiguous":
            state = AMBIGUOUS
            why = (f"ambiguous: {len(hypotheses)} poses explain the views" + after
                   + (f" ({reason})" if reason else ""))
        else:
            state = RELOCALIZING
            why = "relocalization found no pose" + after + (f": {reason}" if reason else "")
        goal = self._views * math.radians(self.config.turn_step_deg)
        if (self.config.turn_in_place and may_turn and self._may_turn and self._sequence_open
                and goal <= math.radians(self.config.max_turn_deg) + _TURN_EPS and goal < FULL_TURN - _TURN_EPS):
            self._after_turn = (state, why)
            self.state, self.turn_goal = TURNING, goal
            self.reason = f"turning in place to {math.degrees(goal):.0f} deg for another view ({why})"
            return
        if (verdict == "ambiguous" and self.config.move_to_tell_apart and may_turn and self._may_turn
                and self._sequence_open and self._moves < self.config.max_moves and len(hypotheses) > 1):
            # Looked round as far as it may (or does not turn): ask the shell for a move.
            self._after_turn = (state, why)
            self.state, self.reason, self.wants_move_plan = state, f"{why}; planning a move to tell them apart", True
            return
        self._close_sequence(t, state, why, turned)

    def _close_sequence(self, t: float, state: str, why: str, turned: float) -> None:
        if self._sequence_open and self._views > 1:
            self._may_turn = False  # it has looked as far round as it may: no new turn on the retries
            self.turn_note = (f"no new turn: it turned {math.degrees(turned):.0f} deg in place already"
                              + (f" and moved {self._moves} time(s)" if self._moves else ""))
        elif self.turn_note and self.config.turn_in_place:
            why = f"{why}; {self.turn_note}"
        self._sequence_open = False
        self.state, self.reason = state, why
        self._next_try = t + self.config.retry_period

    def move_planned(self, t: float, move: Optional[Tuple[float, float, float]], why: str = "") -> None:
        """The shell's plan for ``wants_move_plan``: the move's end (dx, dy, dphi) in the robot frame,
        or None (no move up to ``move_max_distance`` tells the hypotheses apart; ``why`` says so)."""
        if not self.wants_move_plan:
            return
        self.wants_move_plan = False
        state, reason = self._after_turn
        if move is None:
            note = why or "no move would tell the places apart"
            self._close_sequence(t, state, f"{reason}; {note}", self.turn_goal)
            self._may_turn, self.turn_note = False, note  # the retries look from here, without turning or moving
            return
        self._moves += 1
        self.move_serial += 1
        self.state, self.move_goal = MOVING, (float(move[0]), float(move[1]), float(move[2]))
        self.reason = (f"moving {math.hypot(move[0], move[1]):.2f} m (turning {math.degrees(move[2]):+.0f} deg to "
                       f"face the way first) for a view that tells the places apart ({reason})")

    def move_done(self, t: float) -> None:
        """The core has driven the move and braked: relocalize with one more view."""
        if self.state != MOVING:
            return
        self.state = RELOCALIZING
        self.reason = (f"relocalizing with view {self._views + 1} after moving "
                       f"{math.hypot(self.move_goal[0], self.move_goal[1]):.2f} m")
        self._next_try = t
        self._requested = False

    def move_stopped(self, t: float, why: str) -> None:
        """The move could not go on (the protective stop, a fault): the last verdict stands."""
        if self.state == MOVING:
            self._motion_stopped(t, f"the move was stopped: {why}")

    def _motion_stopped(self, t: float, note: str) -> None:
        """A turn or move stopped: the verdict before it stands, and this trigger moves no more."""
        state, reason = self._after_turn
        self.turn_note = note
        self.state, self.reason = state, f"{reason}; {note}"
        self._sequence_open = False
        self._may_turn = False
        self._next_try = t + self.config.retry_period

    @property
    def moving(self) -> bool:
        return self.state == MOVING

    @property
    def moves_left(self) -> int:
        """Moves this trigger may still make (the planner looks for a path of two where it may)."""
        return max(0, self.config.max_moves - self._moves)

    def turn_done(self, t: float) -> None:
        """The core has turned to ``turn_goal`` and braked: relocalize with one more view."""
        if self.state != TURNING:
            return
        self.state = RELOCALIZING
        self.reason = f"relocalizing with view {self._views + 1} at {math.degrees(self.turn_goal):.0f} deg"
        self._next_try = t
        self._requested = False

    def turn_stopped(self, t: float, why: str) -> None:
        """The turn could not go on (the protective stop, a fault): the last verdict stands."""
        if self.state == TURNING:
            self._motion_stopped(t, f"the in-place turn was stopped: {why}")

    @property
    def turning(self) -> bool:
        return self.state == TURNING

    @property
    def in_sequence(self) -> bool:
        """A relocalization sequence is gathering views: the shell keeps the odometry since its first."""
        return self._sequence_open

    def force(self, t: float, why: str) -> None:
        """An operator or the fleet asks for a relocalization now."""
        self._enter(RELOCALIZING, t, why)

    def pose_set_by_operator(self, t: float) -> None:
        """A person set the pose: check it like a saved one."""
        self.hypotheses = []
        self._requested = False
        self._sequence_open, self._may_turn, self.turn_goal, self.turn_note = False, True, 0.0, ""
        self._moves, self.wants_move_plan = 0, False
        self.start_from_saved_pose(t)

    # -- outputs -----------------------------------------------------------------------------

    @property
    def doubting(self) -> bool:
        """Some recent views disagree with the pose, or it is not confirmed: claim no arrival."""
        return self.state != TRACKING or bool(self._rejected_run)

    @property
    def holding(self) -> bool:
        """The robot must not move (it does not know where it is, or has not confirmed it)."""
        return self.state in (RELOCALIZING, AMBIGUOUS, CONFIRMING, TURNING, MOVING)

    def wants_relocalization(self, t: float) -> bool:
        """True once per attempt: the shell should relocalize on the next frames."""
        if self._requested or self.wants_move_plan or self.state not in (RELOCALIZING, AMBIGUOUS) or t < self._next_try:
            return False
        self._requested = True
        self.attempts += 1
        if not self._sequence_open:
            self._sequence_open, self._views, self.turn_goal = True, 0, 0.0
        self.view_index = self._views
        return True

    def _enter(self, state: str, t: float, why: str) -> None:
        if not self.config.enabled:
            return
        self.state, self.reason = state, why
        self._rejected_run = []
        self._next_try = t
        self._requested = False
        self._sequence_open, self._may_turn, self.turn_goal, self.turn_note = False, True, 0.0, ""
        self._moves, self.wants_move_plan = 0, False

    def to_json(self) -> dict:
        return {"state": self.state, "reason": self.reason, "attempts": self.attempts, "hypotheses": self.hypotheses,
                "views": self._views if self._sequence_open or self.state == TURNING else 0,
                "turn_goal_deg": math.degrees(self.turn_goal) if self.state == TURNING else None,
                "move_goal": list(self.move_goal) if self.state == MOVING else None}
