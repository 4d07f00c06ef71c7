"""Health supervision (see docs/architecture.md, 'Health'): how fast the robot may drive, decided from explicit times. Pure.

- No successful localization for ``slow_after`` s: drive at ``slow_scale`` of the planned speed.
- None for ``stop_after`` s: stop (speed scale 0) until localization succeeds again.
- Chassis link down: never command; wheels are stopped by the board's watchdog and the driver.
- A command older than ``max_command_age`` s is never sent.

Faults: a control tick more than ``stall_after`` s after the previous one (the host stalled, or
its monotonic clock jumped), a chassis link that went down or came back, a board that reset or an
odometry gap (``note_fault``). The board's watchdog has stopped or is stopping the wheels, and
the pose may be off by what happened meanwhile, so the robot is held: the shell's controller
starts again from rest, and the mission waits until the pose is confirmed after the fault,
``confirm_planes`` accepted plane fixes captured after it and a position std of at most
``confirm_pos_std`` (without vision: fresh odometry), and, with ``resume_after_fault: command``,
the operator's resume as well (``acknowledge``).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

from robot.config import HealthConfig

AUTO = "auto"
COMMAND = "command"
STALL_PERIODS = 2.5  # a tick gap shorter than this many control periods is jitter, never a stall


class HealthSupervisor:
    def __init__(self, config: HealthConfig, t_start: float):
        self.config = config
        self.last_localization = t_start  # the initial pose counts as a fix
        self.chassis_ok = False
        self.reason = "starting"
        self.fault: Optional[str] = None  # why the robot is held after a fault; None when it is not
        self.t_fault = -math.inf  # when the current fault was noted: confirmations must be newer
        self.faults = 0
        self._confirmations = 0
        self._acknowledged = False
        self._t_last_tick: Optional[float] = None
        self._link_seen: Optional[bool] = None
        self._link_change: Optional[str] = None  # a link transition not yet turned into a fault

    # -- faults ---------------------------------------------------------------------------------

    def note_link(self, ok: bool, reason: str = "") -> None:
        """The chassis link as the shell sees it; a change becomes a fault at the next tick."""
        ok = bool(ok)
        if self._link_seen is not None and ok != self._link_seen:
            self._link_change = "chassis link back" if ok else f"chassis link lost ({reason or 'down'})"
        self._link_seen = ok
        self.chassis_ok = ok

    def note_tick(self, t: float, period: float) -> Optional[str]:
        """A control tick at t: the fault that began with it (a stall, a link change), or None."""
        began = None
        if self._t_last_tick is not None:
            gap = t - self._t_last_tick
            if not math.isfinite(gap) or gap > max(self.config.stall_after, STALL_PERIODS * period):
                began = f"control loop stalled for {gap:.2f} s"
        self._t_last_tick = t
        if self._link_change is not None:
            began = self._link_change if began is None else f"{began}; {self._link_change}"
            self._link_change = None
        if began is not None:
            self.note_fault(t, began)
        return began

    def note_fault(self, t: float, reason: str) -> None:
        """Hold from t on until the pose is confirmed again; a new fault restarts the confirmation."""
        self.fault = reason
        self.t_fault = t
        self.faults += 1
        self._confirmations = 0
        self._acknowledged = False

    def note_accepted(self, t_capture: float, accepted: int) -> None:
        """Plane fixes the gate accepted; only those captured after the fault confirm the pose."""
        if self.fault is not None and t_capture >= self.t_fault:
            self._confirmations += int(accepted)

    def acknowledge(self) -> None:
        """The operator's resume: with ``resume_after_fault: command`` the hold ends once confirmed."""
        self._acknowledged = True

    @property
    def holding(self) -> bool:
        return self.fault is not None

    def clear_fault(self) -> None:
        """No mission to hold (teleop, idle): the fault ends once the limiters started from rest."""
        self.fault = None

    def release(self, t: float, pos_std: float, t_last_odom: float) -> Tuple[bool, str]:
        """(whether the hold ends now, why not). Call each tick while ``holding``."""
        if self.fault is None:
            return True, ""
        cfg = self.config
        if not self.chassis_ok:
            return False, f"{self.fault}: waiting for the chassis link"
        if t_last_odom <= self.t_fault:
            return False, f"{self.fault}: waiting for fresh wheel odometry"
        if cfg.vision_required:
            if self._confirmations < cfg.confirm_planes:
                return False, (f"{self.fault}: waiting for the pose to be confirmed "
                               f"({self._confirmations} of {cfg.confirm_planes} plane fixes)")
            if not pos_std <= cfg.confirm_pos_std:
                return False, (f"{self.fault}: waiting for the pose to be confirmed "
                               f"(position std {pos_std * 1e3:.1f} mm > {cfg.confirm_pos_std * 1e3:.1f} mm)")
        if cfg.resume_after_fault == COMMAND and not self._acknowledged:
            return False, f"{self.fault}: pose confirmed, waiting for the operator's resume"
        self.fault = None
        return True, ""

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
