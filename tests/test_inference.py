"""The study's inference: exact sign tests over the units results vary at.

The null simulation runs the study's own check (``claims._check`` on rows, through
``unit_values`` and ``sign_test``) on studies with no true effect, at the number of
training runs shipped and at the design's twelve (docs/results.md; until all twelve are
shipped the two differ), and fails when any check passes more often than its nominal level.
Two positive controls show the simulation can fail: study v2's two-level bootstrap over
four runs, and a t-test over run means when a few runs hover (skewed run effects).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scipy.stats import binom, binomtest, t

from dammrl.study.claims import Rule, Table, _check
from dammrl.study.configs import FIXED, R2, SEED_RUNS, checkpoint_files
from dammrl.study.inference import (
    equivalence_test,
    holm,
    median_interval,
    power,
    sign_test,
    unit_values,
)

NOMINAL = 0.025  # a check passes on its claimed side at most this often under the null
REPEATS = 20_000
REACHES_PER_RUN = 12  # a 150-seed set over twelve runs: 12 or 13 each
RUNS_SHIPPED = len(checkpoint_files(SEED_RUNS[2]))
RUNS_DESIGNED = 12  # training runs per reward in the published study's design
RUNS = sorted({RUNS_SHIPPED, RUNS_DESIGNED})

Draw = Callable[[np.random.Generator, int], np.ndarray]
RUN_EFFECTS: dict[str, Draw] = {  # how training runs differ (centred below)
    "normal, sd 0.3": lambda rng, n: rng.normal(0, 0.3, n),
    "normal, sd 1.0": lambda rng, n: rng.normal(0, 1.0, n),
    "heavy tails (t, 2 df)": lambda rng, n: rng.standard_t(2, n),
    "skewed (lognormal)": lambda rng, n: rng.lognormal(0, 1, n),
    "a fifth of runs hover (+5)": lambda rng, n: (
        np.where(rng.random(n) < 0.2, 5.0, 0.0) + rng.normal(0, 0.3, n)
    ),
}


def _normal_noise(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.normal(0, 1, n)


def _skewed_noise(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.exponential(2.0, n) - 2.0  # mean 0, median -0.6


def _null(effect: Draw, noise: Draw) -> Draw:
    """``effect`` shifted so that a run's value (its effect plus the mean noise of its
    reaches) has median 0: no effect in the median run, the null of every check."""
    rng = np.random.default_rng(99)
    values = effect(rng, 200_000) + noise(rng, 200_000 * REACHES_PER_RUN).reshape(
        -1, REACHES_PER_RUN).mean(1)  # fmt: skip
    shift = float(np.median(values))
    return lambda r, n: effect(r, n) - shift


def _rows(run_effects: np.ndarray, noise: np.ndarray, rng: np.random.Generator
          ) -> list[dict[str, Any]]:  # fmt: skip
    """Reaches of a learned configuration (one run per reach, k mod n) and a fixed one on
    the same seeds: the learned one's figure = the fixed one's + its run's effect + reach
    noise ``noise[run, j]`` (its j-th reach)."""
    rows = []
    runs = run_effects.size
    for seed in range(runs * REACHES_PER_RUN):
        run, j, base = seed % runs, seed // runs, rng.normal(0, 1)
        rows.append({"configuration": R2, "seed": seed, "run": run, "runs": runs,
                     "figure": base + run_effects[run] + noise[run, j]})  # fmt: skip
        rows.append({"configuration": FIXED, "seed": seed, "run": 0, "runs": 0,
                     "figure": base})  # fmt: skip
    return rows


def _draws(effect: Draw, noise: Draw, runs: int, repeats: int, seed: int
           ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    rng = np.random.default_rng(seed)
    effects = np.array([effect(rng, runs) for _ in range(repeats)])
    return effects, noise(rng, repeats * runs * REACHES_PER_RUN).reshape(
        repeats, runs, REACHES_PER_RUN)  # fmt: skip


def _passes(effects: np.ndarray, noise: np.ndarray) -> dict[str, np.ndarray]:
    """Whether an uncorrected check passes on each side, per repeat: the sign test over the
    runs' values (their effect plus their reaches' mean noise), vectorised."""
    values = effects + noise.mean(axis=2)
    untied = np.count_nonzero(values != 0, axis=1)
    return {side: 2 * binom.sf(np.count_nonzero(values > 0 if side == "above" else values < 0,
                                                axis=1) - 1, untied, 0.5) < 2 * NOMINAL
            for side in ("above", "below")}  # fmt: skip


def _not_above_nominal(count: int, repeats: int) -> bool:
    """The count is no evidence of a rate above the nominal one (one-sided, 0.1 %)."""
    return binomtest(count, repeats, NOMINAL, alternative="greater").pvalue > 0.001


def _check_level(effect: Draw, noise: Draw, seed: int, runs: int) -> None:
    """The study's own check (rows, units, the sign test) decides as the vectorised test
    on a hundred simulated studies; on thousands, neither side passes above nominal."""
    effects, reach_noise = _draws(effect, noise, runs, 100, seed)
    rng = np.random.default_rng(seed)
    fast = _passes(effects, reach_noise)
    for k in range(100):
        table = Table(_rows(effects[k], reach_noise[k], rng), "press")
        for side in ("above", "below"):
            rule = Rule("X", "", "", R2, FIXED, "figure", side)  # type: ignore[arg-type]
            assert (_check(table, rule).p < 2 * NOMINAL) == fast[side][k]
    effects, reach_noise = _draws(effect, noise, runs, REPEATS, seed + 1)
    for side, passed in _passes(effects, reach_noise).items():
        assert _not_above_nominal(int(passed.sum()), REPEATS), (side, int(passed.sum()))


@pytest.mark.parametrize("runs", RUNS)
@pytest.mark.parametrize("name", RUN_EFFECTS)
def test_no_check_passes_more_often_than_nominal_without_an_effect(name: str, runs: int) -> None:
    _check_level(_null(RUN_EFFECTS[name], _normal_noise), _normal_noise, 1, runs)


@pytest.mark.parametrize("runs", RUNS)
def test_reach_noise_that_is_skewed_keeps_the_level_too(runs: int) -> None:
    """Each run's value is a mean of a dozen reaches with skewed noise."""
    _check_level(_null(RUN_EFFECTS["skewed (lognormal)"], _skewed_noise), _skewed_noise, 2, runs)


def test_reaches_as_units_keep_the_level_with_a_binary_figure() -> None:
    """Configurations that learn nothing: a success compared reach by reach (McNemar's
    exact test), with half the reaches tied."""
    rng = np.random.default_rng(3)
    passes = 0
    for _ in range(1500):
        a = rng.random(150) < 0.7
        b = np.where(rng.random(150) < 0.5, a, rng.random(150) < 0.7)
        passes += sign_test(a.astype(float) - b, "above").p < 2 * NOMINAL
    assert _not_above_nominal(passes, 1500), passes


def test_the_positive_controls_fail_the_same_simulation() -> None:
    """Study v2's two-level bootstrap over four runs (percentile interval of run, then
    reach resampling) and a t-test over ten hovering-skewed run means both pass a null
    check far more often than 2.5 %: the simulation above can tell."""
    rng = np.random.default_rng(4)
    bootstrap_passes = 0
    for _ in range(300):
        reaches = rng.normal(0, 1.0, (4, 1)) + rng.normal(0, 1, (4, 30))  # 4 runs, no effect
        picks = rng.integers(0, 4, size=(1000, 4))  # runs, then reaches within each
        resampled = reaches[picks[..., None], rng.integers(0, 30, size=(1000, 4, 30))]
        low, high = np.percentile(resampled.mean(axis=(1, 2)), [2.5, 97.5])
        bootstrap_passes += low > 0 or high < 0
    assert bootstrap_passes / 300 > 2 * 2 * NOMINAL  # both sides: > twice the 5 % nominal

    hover = RUN_EFFECTS["a fifth of runs hover (+5)"]
    effects = np.array([hover(rng, 10) for _ in range(4000)])
    centred = effects - 1.0  # mean 0: the t-test's null holds, the skew remains
    statistic = centred.mean(1) / (centred.std(1, ddof=1) / np.sqrt(10))
    assert np.mean(t.cdf(statistic, 9) < NOMINAL) > 2 * NOMINAL  # "below" passes too often


def test_sign_test_is_the_exact_binomial_test() -> None:
    x = np.array([0.3, 0.1, -0.2, 0.5, 0.0, 0.7, 0.2, 0.9, 0.4, 0.6])
    test = sign_test(x, "above")
    assert (test.on_side, test.tied, test.units) == (8, 1, 10)
    one_sided = binomtest(8, 9, 0.5, alternative="greater").pvalue
    assert test.p == pytest.approx(2 * one_sided)
    assert sign_test(-x, "below").p == test.p and sign_test(x, "below").p == 1.0
    assert sign_test(np.array([]), "above").p == 1.0


@pytest.mark.parametrize("n", [6, 10, 12, 20, 150])
def test_the_median_interval_excludes_the_bound_exactly_when_the_test_passes(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(200):
        x = rng.normal(rng.uniform(-1, 1), 1, n)
        interval = median_interval(x)
        for side in ("above", "below"):
            excludes = interval.low > 0 if side == "above" else interval.high < 0
            assert (sign_test(x, side).p < 0.05) == excludes


def test_the_median_interval_covers_the_median_at_least_95_percent() -> None:
    rng = np.random.default_rng(5)
    covered = [(lambda e: e.low <= 0 <= e.high)(median_interval(rng.lognormal(0, 1, 12) - 1))
               for _ in range(3000)]  # fmt: skip
    assert np.mean(covered) >= 0.95 - 3 * np.sqrt(0.05 * 0.95 / 3000)
    assert median_interval(np.arange(5.0)).low == -np.inf  # no pair of 5 covers 95 %


def test_equivalence_passes_inside_the_margins_and_fails_outside() -> None:
    inside = equivalence_test(np.array([0.01, -0.02, 0.03, 0.0, 0.05, -0.04, 0.02]), -0.1, 0.1)
    outside = equivalence_test(np.array([0.2, 0.25, 0.05, 0.3, 0.15, 0.4, 0.3]), -0.1, 0.1)
    assert inside.p == pytest.approx(2 * 0.5**7) and inside.p < 0.05 < outside.p


def test_unit_values_average_within_each_unit() -> None:
    values = np.array([1.0, 3.0, np.nan, 10.0, 20.0, 5.0])
    np.testing.assert_allclose(unit_values(values, np.array([0, 0, 0, 1, 1, 2])), [2.0, 15.0, 5.0])


def test_holm_adjusts_as_the_step_down_procedure_does() -> None:
    """Holm (1979): sorted p times (m, m-1, ...), kept monotone; computed by hand."""
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5]) == [0.5] and holm([0.02, 0.3]) == pytest.approx([0.04, 0.3])
    assert holm([0.9, 0.8]) == [1.0, 1.0]  # capped at 1, never below an earlier step


def test_power_counts_the_outcomes_that_pass() -> None:
    """Twelve runs at Holm's strictest step in a family of four (0.0125): 11 of 12 on the
    claimed side are needed (p = 2 * 13/4096)."""
    assert power(12, 0.977, 0.0125) == pytest.approx(binom.sf(10, 12, 0.977))
    assert power(4, 1.0, 0.05) == 0.0  # four runs can never pass: 2 / 16 > 0.05
