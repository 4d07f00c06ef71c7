"""Wheel odometry samples to the pose filter's prediction inputs: which interval each one spans,
with what noise, and the gaps no sample spans. Pure.

A sample carries the mean wheel speeds over its own board interval ``dt``, ending at ``t``. The
chassis drivers never drop a sample (reports lost on the line make the next one span longer; a
queue that overflows merges samples), so consecutive samples tile the time line and the filter
integrates each over the host interval since the previous one. Two things need care:

- **The noise of a long interval.** The motor ripple on a mean wheel speed averages out over a
  longer interval like white noise with one report period's correlation, so its variance is
  ``sigma_w^2 * min(1, RIPPLE_CORRELATION / interval)``: a gap bridged by cumulative ticks is not
  charged the ripple of one 10 ms sample stretched over seconds. Quantisation comes with the
  sample (tick^2 / 6 over its dt), and the filter adds slip per metre and its per-second floor.
- **A gap no sample spans.** When the encoder baseline restarted (the board reset and its
  counters with it), the sample after it covers only its own ``dt``, and the motion before it is
  unknown. That is judged on the board's clock, where it is exact: a sample continues the
  previous one when its start, ``t_board - dt``, is the previous ``t_board`` (host times carry
  the clock mapping's jitter, tens of milliseconds on a loaded host). The filter then gets a
  zero-twist input up to the sample's start whose covariance covers what the robot could have
  done unseen: keep its last speed until its wheels braked to rest (the board's watchdog plus
  the braking time), or a small floor. The core treats such a gap as a fault.
"""

from __future__ import annotations

import math
from typing import List, Optional, Tuple, Union

import numpy as np

from robot.base.samples import WheelOdometry
from robot.config import ChassisConfig

RIPPLE_CORRELATION = 0.01  # s: one board report period
BOARD_TIME_ROUNDING = 1e-6  # s: board times are sums of microseconds; only rounding separates contiguous samples
UNSEEN_POS_FLOOR = 0.005  # m std of motion nobody saw, even from rest (a board rebooting under its motors)
UNSEEN_HEADING_FLOOR = math.radians(0.5)

# (t, mean body twist (vx, vy, wz), its 3x3 covariance): floats and rows of floats for a sample
# (a hundred a second, and the filter works in floats), arrays for the rare gap input.
Step = Tuple[float, Union[Tuple[float, float, float], np.ndarray], Union[Tuple[Tuple[float, ...], ...], np.ndarray]]


class OdometryFeed:
    """Turns each sample into one or two filter inputs; ``forward`` and ``forward_covariance`` are
    the kinematics (``MecanumKinematics``)."""

    def __init__(self, kinematics, chassis: ChassisConfig, wheel_speed_noise: float):
        self.kinematics = kinematics
        self.chassis = chassis
        self.wheel_speed_noise = float(wheel_speed_noise)
        self._last_twist: Optional[Tuple[float, float, float]] = None  # of the previous sample; None after a pose reset
        self._last_board: Optional[float] = None  # board time the previous sample ended at

    def reset(self) -> None:
        """The pose was set: the next sample starts the odometry afresh."""
        self._last_twist = None
        self._last_board = None

    def steps(self, odo: WheelOdometry, quantisation_variance: float, t_last: float) -> Tuple[List[Step], Optional[str]]:
        """The filter inputs for ``odo`` (the previous input ended at ``t_last``) and, when the sample
        does not reach back to it, what the gap was."""
        twist = self.kinematics.forward_floats(odo.speeds)
        interval = float(odo.t) - float(t_last)
        dt = float(odo.dt)
        if not (math.isfinite(interval) and math.isfinite(dt) and interval > 0.0 and dt > 0.0):
            return [(odo.t, twist, self._twist_cov(quantisation_variance, max(dt, 1e-3)))], None
        last_board, self._last_board = self._last_board, float(odo.t_board)
        t_start = float(odo.t) - dt
        gap = t_start - float(t_last)
        contiguous = last_board is None or abs(float(odo.t_board) - dt - last_board) <= BOARD_TIME_ROUNDING
        if self._last_twist is None or contiguous or gap <= 0.0:
            self._last_twist = twist
            return [(odo.t, twist, self._twist_cov(quantisation_variance, interval))], None
        unseen = self._unseen_cov(gap)
        self._last_twist = twist
        return ([(t_start, np.zeros(3), unseen), (odo.t, twist, self._twist_cov(quantisation_variance, dt))],
                f"odometry gap of {gap:.2f} s (encoder baseline restarted): motion unknown")

    def _twist_cov(self, quantisation_variance: float, interval: float) -> Tuple[Tuple[float, ...], ...]:
        ripple = self.wheel_speed_noise ** 2 * min(1.0, RIPPLE_CORRELATION / interval)
        return self.kinematics.forward_covariance_rows(ripple + max(0.0, float(quantisation_variance)))

    def _unseen_cov(self, gap: float) -> np.ndarray:
        """Mean-twist covariance over ``gap`` whose displacement covers what the robot could do unseen."""
        ch = self.chassis
        last = self._last_twist if self._last_twist is not None else np.zeros(3)
        wheels = np.abs(np.asarray(self.kinematics.inverse(*last), dtype=float))
        moving = min(gap, ch.watchdog_timeout + float(wheels.max()) / ch.max_wheel_accel)
        pos = math.hypot(last[0], last[1]) * moving + UNSEEN_POS_FLOOR
        heading = abs(last[2]) * moving + UNSEEN_HEADING_FLOOR
        return np.diag([pos * pos, pos * pos, heading * heading]) / (gap * gap)

