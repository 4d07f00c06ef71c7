"""A bandwidth budget for the heavy channels (depth images): a token bucket on the app's clock.

A sink asks ``admit(t, nbytes)`` before it encodes a message; the bucket refills at the
configured rate and holds at most one second of it, so a burst after a quiet spell is bounded
too. It runs on the messages' own times, not on a clock of its own, so the same inputs admit
the same frames on any machine, at any speed (and in a test).
"""

from __future__ import annotations

import math
from typing import Optional

BURST_S = 1.0  # s of the rate the bucket holds


class ByteBudget:
    """At most ``max_mbit_s`` megabits per second, averaged over about ``BURST_S``; 0 admits nothing."""

    def __init__(self, max_mbit_s: float, burst_s: float = BURST_S):
        rate = float(max_mbit_s)
        if not math.isfinite(rate) or rate < 0.0:
            raise ValueError(f"bandwidth budget must be a finite number of Mbit/s >= 0, got {max_mbit_s!r}")
        self.max_mbit_s = rate
        self.rate = rate * 1e6 / 8.0  # bytes per second
        self.capacity = self.rate * float(burst_s)
        self._tokens = self.capacity
        self._t: Optional[float] = None
        self.admitted = 0
        self.refused = 0

    def admit(self, t: float, nbytes: int) -> bool:
        """Charge ``nbytes`` at time ``t`` (s) if the budget allows it. A message larger than the
        bucket passes when the bucket is full and leaves it in debt, so a low rate spaces big
        frames out instead of refusing them for good; the average stays within the rate."""
        if self.rate <= 0.0 or not math.isfinite(t):
            self.refused += 1
            return False
        if self._t is not None and t > self._t:
            self._tokens = min(self.capacity, self._tokens + (t - self._t) * self.rate)
        if self._t is None or t > self._t:
            self._t = t
        need = float(nbytes)
        if self._tokens >= min(need, self.capacity):
            self._tokens -= need
            self.admitted += 1
            return True
        self.refused += 1
        return False
