"""Interval estimates for describing results: bootstrap means, Student-t means over
independent units, Wilson rates, paired differences, rliable's stratified bootstrap and
interquartile mean, intraclass correlation, and time to success with censoring
(Kaplan-Meier, restricted mean). A study's checks are decided elsewhere, by exact tests
over the units results vary at (``dammrl.study.inference``).

Every interval is 95 % and every bootstrap draws from a generator seeded by the caller,
so a report is reproducible to the digit.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats as scipy_stats
from scipy.stats import binomtest

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
    mean = float(data.mean())  # rounding can put a bound a hair past the mean: never past
    return Estimate(mean, min(mean, float(low)), max(mean, float(high)), int(data.size))


def t_mean(values: np.ndarray) -> Estimate:
    """Mean with its Student-t 95 % interval (NaNs dropped): exact for normal data at any
    n, and deterministic (the same values give the same interval in any report). A single
    value has no interval (NaN bounds)."""
    data = np.asarray(values, dtype=float)
    data = data[np.isfinite(data)]
    if data.size == 0:
        return NO_DATA
    mean = float(data.mean())
    if data.size < 2:
        return Estimate(mean, math.nan, math.nan, 1)
    half = float(scipy_stats.t.ppf(0.975, data.size - 1) * data.std(ddof=1) / math.sqrt(data.size))
    return Estimate(mean, mean - half, mean + half, int(data.size))


def wilson(successes: int, n: int) -> Estimate:
    """A rate with its Wilson score 95 % interval (sound near 0 % and 100 %; SciPy's,
    whose bounds are exactly 0 at 0/n and 1 at n/n)."""
    if n == 0:
        return NO_DATA
    interval = binomtest(successes, n).proportion_ci(confidence_level=0.95, method="wilson")
    p = successes / n
    return Estimate(p, min(p, float(interval.low)), max(p, float(interval.high)), n)


def paired_difference(a: np.ndarray, b: np.ndarray, rng: np.random.Generator) -> Estimate:
    """Mean of ``a - b`` over the same seeds, with a bootstrap 95 % interval over seeds.
    Seeds where either value is missing (NaN) are left out of both."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    both = np.isfinite(a) & np.isfinite(b)
    return bootstrap_mean(a[both] - b[both], rng)


def iqm(values: np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50 % (rliable's robust aggregate; with
    few runs it is less swayed than the mean by one outlying run, more efficient than the
    median)."""
    data = np.sort(np.asarray(values, dtype=float).ravel())
    data = data[np.isfinite(data)]
    cut = int(0.25 * data.size)  # as scipy.stats.trim_mean(data, 0.25)
    return float(np.mean(data[cut : data.size - cut])) if data.size else math.nan


def stratified_bootstrap(
    scores: np.ndarray,
    statistic: Callable[[np.ndarray], float],
    rng: np.random.Generator,
) -> Estimate:
    """``statistic`` of a (runs, tasks) score matrix with a stratified-bootstrap 95 %
    interval: every draw resamples the runs with replacement independently for each task
    (each held-out reach), the rliable methodology (Agarwal et al., NeurIPS 2021) for a
    handful of training seeds. NaN scores (a reach with no such figure) are left out."""
    data = np.asarray(scores, dtype=float)
    if data.size == 0 or not np.isfinite(data).any():
        return NO_DATA
    runs, tasks = data.shape
    picks = rng.integers(0, runs, size=(BOOTSTRAP_DRAWS, runs, tasks))
    draws = [statistic(data[pick, np.arange(tasks)]) for pick in picks]
    low, high = np.nanpercentile(draws, [2.5, 97.5])
    return Estimate(statistic(data), float(low), float(high), int(np.isfinite(data).sum()))


def finite_mean(values: np.ndarray) -> float:
    """The mean of the finite entries (NaN marks a reach without the figure)."""
    data = np.asarray(values, dtype=float)
    return float(np.mean(data[np.isfinite(data)]))


def stratified_difference(
    a: np.ndarray,
    b: np.ndarray,
    statistic: Callable[[np.ndarray], float],
    rng: np.random.Generator,
) -> Estimate:
    """``statistic(a) - statistic(b)`` of two (runs, tasks) matrices over the same tasks,
    with a 95 % interval: each draw resamples the runs of each group independently per
    task (the groups' runs are not paired, the tasks are shared)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.size == 0 or b.size == 0:
        return NO_DATA
    tasks = np.arange(a.shape[1])

    def draw(data: np.ndarray) -> np.ndarray:
        return data[rng.integers(0, data.shape[0], size=data.shape), tasks]

    draws = [statistic(draw(a)) - statistic(draw(b)) for _ in range(BOOTSTRAP_DRAWS)]
    low, high = np.nanpercentile(draws, [2.5, 97.5])
    return Estimate(statistic(a) - statistic(b), float(low), float(high), int(a.size + b.size))


def icc(ratings: np.ndarray, kind: str = "consistency") -> Estimate:
    """Intraclass correlation of single measurements with its 95 % interval: ``ratings``
    (n targets, k occasions), no value missing. Two-way models (Shrout & Fleiss 1979;
    McGraw & Wong 1996): ``consistency`` is ICC(3,1) = ICC(C,1), ``agreement`` ICC(2,1) =
    ICC(A,1), which also counts a shift between occasions against reliability. Test-retest
    here: the targets are a block's trials (the same target each session), the occasions
    the sessions. NaN throughout with fewer than 2 targets or 2 occasions."""
    y = np.asarray(ratings, dtype=float)
    if y.ndim != 2 or min(y.shape) < 2 or not np.all(np.isfinite(y)):
        return NO_DATA
    n, k = y.shape
    grand = y.mean()
    msr = k * float(np.sum((y.mean(axis=1) - grand) ** 2)) / (n - 1)
    msc = n * float(np.sum((y.mean(axis=0) - grand) ** 2)) / (k - 1)
    residual = y - y.mean(axis=1, keepdims=True) - y.mean(axis=0, keepdims=True) + grand
    mse = float(np.sum(residual**2)) / ((n - 1) * (k - 1))
    if msr + (k - 1) * mse <= 0:
        return NO_DATA  # every value the same: reliability is undefined
    if kind == "consistency":
        return _icc_consistency(msr, mse, n, k)
    if kind == "agreement":
        return _icc_agreement(msr, msc, mse, n, k)
    raise ValueError(f"icc kind {kind!r}: consistency or agreement")


def _icc_consistency(msr: float, mse: float, n: int, k: int) -> Estimate:
    from scipy.stats import f

    value = (msr - mse) / (msr + (k - 1) * mse)
    if mse == 0:
        return Estimate(value, value, value, n)
    ratio, df1, df2 = msr / mse, n - 1, (n - 1) * (k - 1)
    low_f, high_f = ratio / f.ppf(0.975, df1, df2), ratio * f.ppf(0.975, df2, df1)
    return Estimate(value, (low_f - 1) / (low_f + k - 1), (high_f - 1) / (high_f + k - 1), n)


def _icc_agreement(msr: float, msc: float, mse: float, n: int, k: int) -> Estimate:
    """ICC(A,1) with McGraw & Wong's (1996) interval (Satterthwaite's degrees of freedom)."""
    from scipy.stats import f

    value = (msr - mse) / (msr + (k - 1) * mse + k * (msc - mse) / n)
    if value >= 1 or mse == 0:
        return Estimate(value, value, value, n)
    a = k * value / (n * (1 - value))
    b = 1 + k * value * (n - 1) / (n * (1 - value))
    dof = (a * msc + b * mse) ** 2 / (
        (a * msc) ** 2 / (k - 1) + (b * mse) ** 2 / ((n - 1) * (k - 1))
    )
    f_low, f_high = f.ppf(0.975, n - 1, dof), f.ppf(0.975, dof, n - 1)
    spread = k * msc + (k * n - k - n) * mse
    low = n * (msr - f_low * mse) / (f_low * spread + n * msr)
    high = n * (f_high * msr - mse) / (spread + n * f_high * msr)
    return Estimate(value, min(value, low), max(value, high), n)


# ---- time to success ------------------------------------------------------------------


@dataclass(frozen=True)
class Survival:
    """Time to an event (here: success) from a Kaplan-Meier fit, restricted at a horizon."""

    median_s: float  # when half have succeeded (inf: fewer than half did by the horizon)
    median_low_s: float  # its 95 % interval (Greenwood, log-log bands; Brookmeyer-Crowley)
    median_high_s: float
    rmst_s: float  # restricted mean time to success: the area under S(t) up to the horizon
    n: int
    events: int


def time_to_success(times_s: np.ndarray, succeeded: np.ndarray, horizon_s: float) -> Survival:
    """Kaplan-Meier estimate of the time to success (SciPy's ``ecdf`` on censored data):
    ``times_s`` (n,) when each reach succeeded, or until when it was observed without
    success (right-censored). A reach that can no longer succeed (it ended in a hold) is
    observed without success up to the horizon: its time is the horizon, not its end."""
    t = np.asarray(times_s, dtype=float)
    done = np.asarray(succeeded, dtype=bool)
    if t.size == 0:
        return Survival(math.nan, math.nan, math.nan, math.nan, 0, 0)
    if not done.any():
        return Survival(math.inf, math.inf, math.inf, float(horizon_s), int(t.size), 0)
    data = scipy_stats.CensoredData(uncensored=t[done], right=t[~done])
    sf = scipy_stats.ecdf(data).sf
    with warnings.catch_warnings():  # undefined where S is 0 or 1: those bands are NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        band = sf.confidence_interval(0.95, method="log-log")
    return Survival(
        _first_below_half(sf.quantiles, sf.probabilities),
        _first_below_half(band.low.quantiles, band.low.probabilities),
        _first_below_half(band.high.quantiles, band.high.probabilities),
        _area_to(sf.quantiles, sf.probabilities, horizon_s),
        int(t.size),
        int(done.sum()),
    )


def _first_below_half(times: np.ndarray, survival: np.ndarray) -> float:
    below = np.nonzero(np.nan_to_num(survival, nan=1.0) <= 0.5)[0]
    return float(times[below[0]]) if below.size else math.inf


def _area_to(times: np.ndarray, survival: np.ndarray, horizon_s: float) -> float:
    """Area under the right-continuous step function S (1 before the first time)."""
    edges = np.concatenate([[0.0], np.minimum(times, horizon_s), [horizon_s]])
    levels = np.concatenate([[1.0], survival])
    return float(np.sum(np.diff(edges) * levels))
