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
- ``confirming``: a unique verdict set the pose; the robot holds until the normal localizer has
  accepted ``confirm_updates`` plane updates from it.

Triggers into ``relocalizing``: no pose at start-up; quality ``lost`` for ``lost_after`` s; a
saved pose the cameras contradict; a *kidnap*: for ``kidnap_time`` s (and at least
``kidnap_frames`` localizations) the localizer fitted walls but the fusion gate rejected every
one (odometry and every wall disagree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import List, Optional

from robot.config.recovery import RecoveryConfig

TRACKING = "tracking"
CHECKING = "checking"
RELOCALIZING = "relocalizing"
AMBIGUOUS = "ambiguous"
CONFIRMING = "confirming"


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
        if fitted >= 1 and accepted == 0:
            self._rejected_run.append(t)
            span = t - self._rejected_run[0]
            if len(self._rejected_run) >= c.kidnap_frames and span >= c.kidnap_time:
                self._enter(RELOCALIZING, t, f"kidnapped? for {span:.1f} s every fitted wall of "
                            f"{len(self._rejected_run)} views disagreed with the pose")
        elif accepted:
            self._rejected_run = []

    def on_verdict(self, t: float, verdict: str, hypotheses: List[dict], reason: str = "") -> None:
        """The relocalizer's answer; on 'unique' the shell has set the pose from the first hypothesis."""
        self._requested = False
        self.hypotheses = list(hypotheses)
        if verdict == "unique":
            self.state, self.reason, self._confirmed, self._checked = CONFIRMING, "confirming the relocalized pose", 0, 0
        elif verdict == "ambiguous":
            self.state = AMBIGUOUS
            self.reason = f"ambiguous: {len(hypotheses)} poses explain the views" + (f" ({reason})" if reason else "")
            self._next_try = t + self.config.retry_period
        else:
            self.state = RELOCALIZING
            self.reason = "relocalization found no pose" + (f": {reason}" if reason else "")
            self._next_try = t + self.config.retry_period

    def force(self, t: float, why: str) -> None:
        """An operator or the fleet asks for a relocalization now."""
        self._enter(RELOCALIZING, t, why)

    def pose_set_by_operator(self, t: float) -> None:
        """A person set the pose: check it like a saved one."""
        self.hypotheses = []
        self._requested = False
        self.start_from_saved_pose(t)

    # -- outputs -----------------------------------------------------------------------------

    @property
    def doubting(self) -> bool:
        """Some recent views disagree with the pose, or it is not confirmed: claim no arrival."""
        return self.state != TRACKING or bool(self._rejected_run)

    @property
    def holding(self) -> bool:
        """The robot must not move (it does not know where it is, or has not confirmed it)."""
        return self.state in (RELOCALIZING, AMBIGUOUS, CONFIRMING)

    def wants_relocalization(self, t: float) -> bool:
        """True once per attempt: the shell should relocalize on the next frames."""
        if self._requested or self.state not in (RELOCALIZING, AMBIGUOUS) or t < self._next_try:
            return False
        self._requested = True
        self.attempts += 1
        return True

    def _enter(self, state: str, t: float, why: str) -> None:
        if not self.config.enabled:
            return
        self.state, self.reason = state, why
        self._rejected_run = []
        self._next_try = t
        self._requested = False

    def to_json(self) -> dict:
        return {"state": self.state, "reason": self.reason, "attempts": self.attempts, "hypotheses": self.hypotheses}
