"""Distribution quantiles the gates and integrity checks need, in plain Python (no scipy)."""

from __future__ import annotations

import functools
import math


@functools.lru_cache(maxsize=4096)
def chi2_quantile(probability: float, dof: int) -> float:
    """Chi-square quantile, by bisection on the regularized lower incomplete gamma function."""
    if dof <= 0:
        return 0.0

    def cdf(x: float) -> float:
        s, h = dof / 2.0, x / 2.0
        if h <= 0.0:
            return 0.0
        term = 1.0 / s
        total = term
        n = 1
        while term > 1e-15 * total and n < 2000:
            term *= h / (s + n)
            total += term
            n += 1
        return min(1.0, math.exp(s * math.log(h) - h - math.lgamma(s)) * total)

    lo, hi = 0.0, 10.0 * dof + 200.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < probability:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)
