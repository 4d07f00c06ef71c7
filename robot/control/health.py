"""Health supervision (issue 4): how fast the robot may drive, decided from explicit times. Pure.

- No successful localization for ``slow_after`` s: drive at ``slow_scale`` of the planned speed.
- None for ``stop_after`` s: stop (speed scale 0) until localization succeeds again.
- Chassis link down: never command; wheels are stopped by the board's watchdog and the driver.
- A command older than ``max_command_age`` s is never sent.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

from robot.config import HealthConfig


class HealthSupervisor:
    def __init__(self, config: HealthConfig, t_start: float):
        self.config = config
        self.last_localization = t_start  # the initial pose counts as a fix
        self.chassis_ok = False
        self.reason = "starting"

    def localization_succeeded(self, t: float) -> None:
        self.last_localization = max(self.last_localization, t)

    def speed_scale(self, t: float) -> Tuple[float, str]:
        """(scale in [0, 1], reason) for the trajectory controller at time t."""
        if not self.chassis_ok:
            return 0.0, "chassis link down"
        if not self.config.vision_required:
            return 1.0, "ok (odometry only allowed)"
        age = t - self.last_localization
        if age >= self.config.stop_after:
            return 0.0, f"no successful localization for {age:.1f} s: stopped"
        if age >= self.config.slow_after:
            return self.config.slow_scale, f"no successful localization for {age:.1f} s: slowed down"
        return 1.0, "ok"

    def command_fresh(self, t_issued: float, t_now: float) -> bool:
        age = t_now - t_issued
        return math.isfinite(age) and 0.0 <= age <= self.config.max_command_age


def stale(t_issued: Optional[float], t_now: float, max_age: float) -> bool:
    return t_issued is None or not (0.0 <= t_now - t_issued <= max_age)
