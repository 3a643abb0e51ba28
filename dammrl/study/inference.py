"""How a study decides a check: exact sign tests over the units its results vary at.

A learned configuration's reaches are not independent: every reach of one training run
shares that run's network, and runs differ far more than reaches do. So a comparison that
involves a learned configuration has the *training runs* as its units (a run's value: the
mean over the reaches it ran), and one between configurations that learn nothing has the
*reaches* (each a pure function of its seed). With a handful of runs no test of a mean is
valid whatever the runs' distribution (Bahadur & Savage 1956): a skewed one, such as a few
runs that hover above the button, makes a t-test over run means reject a true null several
times too often (about 9 % instead of 2.5 % one-sided at ten runs, ``tests/test_inference``).
The sign test is exact for any distribution: under the null that the median unit lies on
the bound, the units on either side are a fair coin's throws. So a check here asks
whether the *median unit* (the typical training run, or the typical reach) lies on the
claimed side; its interval is the distribution-free interval of the median (order
statistics), which excludes the bound exactly when the test passes, ties aside.

- Ties at the bound are left out of the test (exact conditionally on their number): for a
  success compared reach by reach, the reaches where both or neither succeeded, so the test
  is McNemar's exact test.
- p is two-sided-equivalent: twice the one-sided binomial tail, so p < 0.05 when the
  median's 95 % interval lies wholly on the claimed side.
- Holm's (1979) step-down correction keeps a claim's family-wise error at its level.

``tests/test_inference.py`` simulates studies with no true effect at the number of training
runs shipped (normal, heavy-tailed, skewed and bimodal run effects; reaches with skewed
noise) and fails if any check passes more often than its nominal level.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.stats import binom

from dammrl.study.stats import NO_DATA, Estimate

Side = Literal["above", "below"]
LEVEL = 0.05  # two-sided-equivalent: each one-sided tail 2.5 %


def unit_values(values: np.ndarray, units: np.ndarray) -> np.ndarray:
    """The mean of ``values`` within each unit label (NaN values left out; a unit with no
    finite value left out), ordered by label."""
    x = np.asarray(values, dtype=float)
    labels = np.asarray(units)
    keep = np.isfinite(x)
    x, labels = x[keep], labels[keep]
    if x.size == 0:
        return np.empty(0)
    order, inverse = np.unique(labels, return_inverse=True)
    sums = np.bincount(inverse, weights=x, minlength=order.size)
    counts = np.bincount(inverse, minlength=order.size)
    return sums / counts


def median_interval(units: np.ndarray, level: float = LEVEL) -> Estimate:
    """The median of ``units`` with its distribution-free interval: order statistics
    [x_(r), x_(n+1-r)] with the largest r whose coverage is at least 1 - ``level``
    (unbounded with fewer than 6 units: no pair of order statistics covers 95 %)."""
    x = np.sort(np.asarray(units, dtype=float))
    x = x[np.isfinite(x)]
    n = x.size
    if n == 0:
        return NO_DATA
    r = int(binom.ppf(level / 2, n, 0.5))  # P(B <= r - 1) <= level / 2 < P(B <= r)
    if binom.cdf(r, n, 0.5) <= level / 2:
        r += 1
    median = float(np.median(x))
    if r < 1:
        return Estimate(median, -math.inf, math.inf, n)
    return Estimate(median, min(median, float(x[r - 1])), max(median, float(x[n - r])), n)


@dataclass(frozen=True)
class SignTest:
    """An exact sign test that the median unit lies on one side of a bound."""

    median: Estimate  # the median unit [distribution-free 95 % interval]
    mean: float  # the mean over the units (descriptive)
    units: int  # every unit with a value
    on_side: int  # units strictly on the claimed side
    tied: int  # units exactly on the bound (left out of the test)
    p: float  # two-sided-equivalent

    def text(self, scale: float = 1.0, digits: int = 2, unit: str = "units") -> str:
        """'median [interval]; k of n units on the side (t tied), mean m'."""
        if self.units == 0:
            return "no data"
        tied = f", {self.tied} tied" if self.tied else ""
        return (f"median {self.median.text(scale, digits)}; {self.on_side} of "
                f"{self.units - self.tied} {unit} on the claimed side{tied}; mean "
                f"{self.mean * scale:.{digits}f}")  # fmt: skip


def sign_test(units: np.ndarray, side: Side, bound: float = 0.0) -> SignTest:
    """Exact binomial test that the median of ``units`` lies ``side`` of ``bound``."""
    x = np.asarray(units, dtype=float)
    x = x[np.isfinite(x)]
    on_side = int(np.count_nonzero(x > bound if side == "above" else x < bound))
    tied = int(np.count_nonzero(x == bound))
    p = one_sided_p(on_side, x.size - tied)
    mean = float(x.mean()) if x.size else math.nan
    return SignTest(median_interval(x), mean, int(x.size), on_side, tied, min(1.0, 2 * p))


def one_sided_p(on_side: int, untied: int) -> float:
    """P(at least ``on_side`` of ``untied`` fair coins land on the claimed side)."""
    if untied == 0:
        return 1.0
    return float(binom.sf(on_side - 1, untied, 0.5))


def equivalence_test(units: np.ndarray, low: float, high: float) -> SignTest:
    """Two one-sided sign tests (the TOST logic, exact) that the median of ``units`` lies
    inside (``low``, ``high``): the larger one-sided p, doubled; on_side counts the units
    inside the margins."""
    x = np.asarray(units, dtype=float)
    x = x[np.isfinite(x)]
    above_low, below_high = sign_test(x, "above", low), sign_test(x, "below", high)
    p = max(above_low.p, below_high.p)
    inside = int(np.count_nonzero((x > low) & (x < high)))
    mean = float(x.mean()) if x.size else math.nan
    return SignTest(median_interval(x), mean, int(x.size), inside, 0, p)


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's (1979) step-down adjusted p-values: a family's checks compared with one
    level keep its family-wise error rate at that level."""
    order = np.argsort(p_values, kind="stable")
    m = len(p_values)
    adjusted = [0.0] * m
    running = 0.0
    for rank, index in enumerate(order):
        running = max(running, min(1.0, (m - rank) * float(p_values[index])))
        adjusted[index] = running
    return adjusted


def power(units: int, share_on_side: float, level: float) -> float:
    """The chance that a sign test over ``units`` passes at the two-sided-equivalent
    ``level`` when each unit lands on the claimed side with ``share_on_side`` (planning the
    number of training runs)."""
    needed = next((k for k in range(units + 1) if 2 * one_sided_p(k, units) < level), None)
    return 0.0 if needed is None else float(binom.sf(needed - 1, units, share_on_side))
