"""The ``recovery:`` section: when the robot relocalizes itself and when it may move again.

The state machine that uses it is ``robot.control.recovery``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class RecoveryConfig:
    enabled: bool = True
    lost_after: float = 5.0  # s of quality 'lost' before relocalizing
    kidnap_frames: int = 4  # localizations in a row with every fitted wall rejected ...
    kidnap_time: float = 1.0  # s ... and for at least this long
    check_frames: int = 6  # localizations a saved pose has to be confirmed by one accepted wall
    confirm_updates: int = 3  # accepted plane updates after a relocalization before moving
    retry_period: float = 2.0  # s between relocalization attempts while ambiguous or without an answer
    auto_resume: bool = True  # resume the mission after confirmation (False: wait for a 'resume' command)

    def __post_init__(self):
        for name in ("lost_after", "kidnap_time", "retry_period"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.1 <= v <= 120.0):
                raise ValueError(f"recovery.{name} must be in [0.1, 120] s, got {v}")
        for name in ("kidnap_frames", "check_frames", "confirm_updates"):
            v = getattr(self, name)
            if not 1 <= v <= 100:
                raise ValueError(f"recovery.{name} must be in [1, 100], got {v}")
