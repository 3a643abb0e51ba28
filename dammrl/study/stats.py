"""Interval estimates for a study: bootstrap means, Wilson rates, paired differences.

Every interval is 95 % and every bootstrap draws from a generator seeded by the caller,
so a study's report is reproducible to the digit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Z95 = 1.959963984540054
BOOTSTRAP_DRAWS = 2000


@dataclass(frozen=True)
class Estimate:
    """A mean (or rate) with its 95 % interval; NaN throughout when there is no data."""

    value: float
    low: float
    high: float
    n: int

    def excludes_zero(self) -> bool:
        """The interval lies wholly on one side of zero (a difference is significant)."""
        return self.n > 0 and (self.low > 0 or self.high < 0)

    def text(self, scale: float = 1.0, digits: int = 2) -> str:
        if self.n == 0 or math.isnan(self.value):
            return "n/a"
        v, lo, hi = (x * scale for x in (self.value, self.low, self.high))
        return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


NO_DATA = Estimate(math.nan, math.nan, math.nan, 0)


def bootstrap_mean(values: np.ndarray, rng: np.random.Generator) -> Estimate:
    """Mean with a percentile-bootstrap 95 % interval (NaNs dropped)."""
    data = np.asarray(values, dtype=float)
    data = data[np.isfinite(data)]
    if data.size == 0:
        return NO_DATA
    draws = rng.choice(data, size=(BOOTSTRAP_DRAWS, data.size)).mean(axis=1)
    low, high = np.percentile(draws, [2.5, 97.5])
    return Estimate(float(data.mean()), float(low), float(high), int(data.size))


def wilson(successes: int, n: int) -> Estimate:
    """A rate with its Wilson score 95 % interval (sound near 0 % and 100 %)."""
    if n == 0:
        return NO_DATA
    p = successes / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + Z95**2 / (4 * n * n)) / (1 + Z95**2 / n)
    return Estimate(p, max(0.0, centre - half), min(1.0, centre + half), n)


def paired_difference(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> Estimate:
    """Mean of ``a - b`` over the same seeds, with a bootstrap 95 % interval over seeds.
    Seeds where either value is missing (NaN) are left out of both."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    both = np.isfinite(a) & np.isfinite(b)
    return bootstrap_mean(a[both] - b[both], rng)
