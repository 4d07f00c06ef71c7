"""Encoder reports (cumulative int32 ticks per wheel on the board's clock) to wheel odometry. Pure.

The serial driver and the simulated-clock runner both feed reports through this, so odometry
means the same thing on the robot and in simulation. Wheel order FL, FR, RL, RR.

No motion is ever lost between reports that arrive: each sample is the difference of cumulative
ticks since the previous report received, so reports lost on the line only make the next sample
span longer. Samples that cannot be delivered in time are merged, never dropped
(``merge_odometry``): the merged sample spans both intervals exactly.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

from firmware_protocol.counters import delta_i32
from robot.base.samples import WheelOdometry

_TWO_PI = 2.0 * math.pi


class EncoderOdometry:
    """Differences successive tick reports into angles and mean speeds.

    Angles are accumulated on the host side, so they stay continuous when the board resets its
    counters (call ``reset_baseline`` then: the next report only sets a new baseline). A jump
    faster than any wheel can turn is never integrated: it is a counter reset or garbage.
    """

    def __init__(self, ticks_per_rev: int, max_wheel_speed: float):
        if ticks_per_rev <= 0:
            raise ValueError(f"ticks_per_rev must be > 0, got {ticks_per_rev}")
        self.ticks_per_rev = int(ticks_per_rev)
        self.rad_per_tick = _TWO_PI / ticks_per_rev
        self.max_wheel_speed = float(max_wheel_speed)
        self.implausible = 0  # reports refused as faster than any wheel can turn
        self._cum = [0, 0, 0, 0]
        self._prev_ticks: Optional[Tuple[int, ...]] = None
        self._prev_board_s = 0.0

    def reset_baseline(self) -> None:
        self._prev_ticks = None

    def update(self, ticks: Sequence[int], board_s: float, t_host: float) -> Optional[WheelOdometry]:
        """A report's ticks at board time ``board_s`` (s, unwrapped) sampled at host time ``t_host``."""
        ticks = tuple(int(v) for v in ticks)
        if self._prev_ticks is None:
            self._prev_ticks, self._prev_board_s = ticks, board_s
            return None
        dt = board_s - self._prev_board_s
        if dt <= 0.0:
            return None
        k = self.rad_per_tick
        d = [delta_i32(n, o) for n, o in zip(ticks, self._prev_ticks)]
        self._prev_ticks, self._prev_board_s = ticks, board_s
        if max(abs(x) for x in d) * k > 3.0 * self.max_wheel_speed * dt + 20 * k:
            self.implausible += 1
            return None
        self._cum = [c + x for c, x in zip(self._cum, d)]
        return WheelOdometry(t=t_host, angles=tuple(c * k for c in self._cum),
                             speeds=tuple(x * k / dt for x in d), dt=dt, t_board=board_s)

    def speed_variance(self, dt: float) -> float:
        return quantisation_variance(self.ticks_per_rev, dt)


def merge_odometry(earlier: WheelOdometry, later: WheelOdometry) -> WheelOdometry:
    """One sample spanning two consecutive ones: the later's angles and times, the mean speeds over both.

    The cumulative angles make this exact: the start of ``earlier``'s interval is its angles less
    its speeds times its dt."""
    dt = earlier.dt + later.dt
    start = [a - w * earlier.dt for a, w in zip(earlier.angles, earlier.speeds)]
    speeds = tuple((a - a0) / dt for a, a0 in zip(later.angles, start))
    return WheelOdometry(t=later.t, angles=later.angles, speeds=speeds, dt=dt, t_board=later.t_board)  # type: ignore[arg-type]


def quantisation_variance(ticks_per_rev: int, dt: float) -> float:
    """Variance (rad/s)^2 of a mean wheel speed over dt from tick quantisation alone.

    The difference of two independently quantised angles is off by a triangular error of
    variance tick^2 / 6."""
    tick = _TWO_PI / ticks_per_rev
    return (tick * tick / 6.0) / max(dt, 1e-3) ** 2
