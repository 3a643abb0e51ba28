"""The paper's claims C1-C6, each judged from a study's per-reach rows: rules version 2.

The rules are fixed before the results they judge, and versioned: every report prints
this file's SHA-256 and the commit that last changed it, and ``tests/test_study.py`` fails
when the file changes while ``CLAIMS_VERSION`` does not (a new version registers its hash
there). Nothing here is tuned to a result.

How a check is judged

- A check compares configurations on the same reach seeds (paired) with a two-level
  bootstrap: training seeds (configurations 3 and 4 run every seed of their reward), then
  reaches; 10,000 draws from a random stream of the check's own, named by its id, so an
  interval never depends on which checks were drawn before it.
- Its p is two-sided-equivalent: p < 0.05 exactly when the 95 % interval lies wholly on
  the claimed side (superiority), or inside the margin (non-inferiority and equivalence,
  two one-sided tests: TOST).
- A claim's checks are one family: Holm's correction keeps the chance that any passing
  check is a false positive at 5 %. A claim *holds* when every check passes after the
  correction, holds *partly* when some do, *does not hold* when none does.
- Success and time are judged under both criteria: the button pressed (the task as a
  person does it) and the paper's ||x - x_g|| <= eps_g. Time is the time to success under
  the criterion, restricted at the 60 s episode limit: a reach that failed counts 60 s,
  whether it held early or ran to the limit (its success never came; Kaplan-Meier with
  censoring at the horizon, whose restricted mean is this mean).

Thresholds, and why these

- ``NEAR_ZERO_OSCILLATIONS`` (C3), 0.5 per reach: N_osc is a whole count per reach and the
  paper reports zero; a mean that rounds to zero is the closest a test on data gets.
- The step windows (C3, C4), from the task instead of round numbers (v1: 4 and 16 cm):
  "near the target" is within eps_g of the goal (the goal's own tolerance); "mid-to-late"
  is the second half of the reach before that, eps_g to half the start distance.
- ``SMOOTHNESS_MARGIN`` (C4), 10 %: "smooth" beside Reward 1 is non-inferiority, SPARC not
  lower than Reward 1's by more than 10 % of Reward 1's mean |SPARC| (the conventional
  relative margin; SPARC has no published minimal important difference for stepwise
  robot motion).
- ``SETTLED_SHARE`` (C6), 10 %: the paper's training-curve figure ("both models have
  converged during training"); an agent's Q-value curve has settled when its mean moved
  from the one-but-last tenth of training to the last by less than 10 % of its largest
  move between consecutive tenths (a straight line scores 1: it never settles). Training
  seeds are the units (a t-based TOST: a handful of seeds). v1 judged instead whether the
  choice stopped changing within a reach, which Reward 2's step modulation along the
  reach (C4) contradicts by design.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from dammrl.study.configs import EVENT, FIXED, R1, R2
from dammrl.study.stats import (
    Estimate,
    Side,
    bootstrap_p,
    estimate_of,
    hierarchical_draws,
    holm,
    tost_mean,
)
from dammrl_core.task import TaskSettings

CLAIMS_VERSION = 2
ALPHA = 0.05  # family-wise, per claim (Holm)
HORIZON_S = float(TaskSettings.model_fields["episode_timeout_s"].default)  # the episode limit:
# time to success is restricted there (60 s)
NEAR_ZERO_OSCILLATIONS = 0.5  # mean N_osc per reach that rounds to zero (C3)
SMOOTHNESS_MARGIN = 0.10  # SPARC non-inferiority margin, share of the reference's |SPARC| (C4)
SETTLED_SHARE = 0.10  # Q-value move over the last tenth, share of its fastest move (C6)
TRAINING_WINDOW = 0.10  # training curves are compared in tenths (C6)

Verdict = Literal["holds", "partly", "does not hold", "not tested"]
Criterion = Literal["press", "eps_g"]
CRITERIA: dict[Criterion, tuple[str, str]] = {  # success column, its time column
    "press": ("success", "t_success_s"),
    "eps_g": ("reached", "t_reached_s"),
}
CRITERION_TEXT: dict[Criterion, str] = {"press": "button pressed", "eps_g": "||x - x_g|| <= eps_g"}
Rows = Sequence[dict[str, Any]]
Curves = dict[str, list[dict[str, np.ndarray]]]  # reward key -> per training seed, by column


def step_windows(
    goal_tolerance_m: float, start_distance_m: float
) -> dict[str, tuple[float, float]]:
    """The goal-distance windows [m] of a reach's steps: near the target, mid-to-late."""
    return {
        "near": (0.0, goal_tolerance_m),
        "mid": (goal_tolerance_m, max(goal_tolerance_m, start_distance_m / 2)),
    }


@dataclass(frozen=True)
class Check:
    key: str  # stable id: names the check's random stream
    text: str  # what is compared, with the numbers
    estimate: Estimate
    p: float  # two-sided-equivalent, before the correction
    p_holm: float = math.nan
    passed: bool = False


@dataclass(frozen=True)
class Claim:
    key: str
    statement: str
    verdict: Verdict
    checks: tuple[Check, ...]


def verdict(checks: Sequence[Check]) -> Verdict:
    if not checks:
        return "not tested"
    passed = sum(c.passed for c in checks)
    return "holds" if passed == len(checks) else "partly" if passed else "does not hold"


def judge(
    rows: Rows, criterion: Criterion = "press", training: Curves | None = None
) -> list[Claim]:
    """C1-C6 from the rows of one condition (and seed set) under ``criterion``;
    ``training``: the training curves of Reward 1 and 2 (C6), by seed."""
    table = Table(rows, criterion)
    return [_c1(table), _c2(table), _c3(table), _c4(table), _c5(table), _c6(training or {})]


# ---- the data -----------------------------------------------------------------------


class Table:
    """Rows by configuration and seed, read under one success criterion."""

    def __init__(self, rows: Rows, criterion: Criterion) -> None:
        self.success, self.time = CRITERIA[criterion]
        self.by_config: dict[str, dict[int, dict[str, Any]]] = {}
        for row in rows:
            self.by_config.setdefault(row["configuration"], {})[row["seed"]] = row

    def has(self, *configs: str) -> bool:
        return all(c in self.by_config for c in configs)

    def value(self, row: dict[str, Any], metric: str) -> float:
        """A row's figure; ``success`` and ``time`` read the criterion's columns."""
        if metric == "success":
            return float(bool(row[self.success]))
        if metric == "time":
            return restricted_time(row, self.time, self.success)
        value = row.get(metric)
        return math.nan if value is None else float(value)

    def paired(self, a: str, b: str, metric: str) -> tuple[np.ndarray, np.ndarray]:
        """a - b per seed both ran, and each seed's cluster (the training seeds used)."""
        rows_a, rows_b = self.by_config[a], self.by_config[b]
        seeds = sorted(set(rows_a) & set(rows_b))
        diffs = [self.value(rows_a[s], metric) - self.value(rows_b[s], metric) for s in seeds]
        clusters = [_run(rows_a[s]) * 1000 + _run(rows_b[s]) for s in seeds]
        return np.array(diffs, dtype=float), np.array(clusters)

    def single(self, config: str, metric: str) -> tuple[np.ndarray, np.ndarray]:
        rows = list(self.by_config[config].values())
        return (np.array([self.value(r, metric) for r in rows], dtype=float),
                np.array([_run(r) for r in rows]))  # fmt: skip


def restricted_time(row: dict[str, Any], time: str = "t_success_s",
                    success: str = "success") -> float:  # fmt: skip
    """Time to success restricted at the horizon: the horizon for a reach without success."""
    t = row.get(time)
    return min(float(t), HORIZON_S) if row.get(success) and t is not None else HORIZON_S


def _run(row: dict[str, Any]) -> int:
    return int(row.get("run") or 0)


# ---- checks -------------------------------------------------------------------------


def _stream(key: str) -> np.random.Generator:
    return np.random.default_rng([CLAIMS_VERSION, zlib.crc32(key.encode())])


def _compare(t: Table, claim: str, a: str, b: str, metric: str, side: Side, what: str,
             scale: float = 1.0, unit: str = "", digits: int = 2) -> Check:  # fmt: skip
    """a - b (paired) lies ``side`` of zero."""
    key = f"{claim}/{what}/{a}-{b}"
    diffs, clusters = t.paired(a, b, metric)
    draws = hierarchical_draws(diffs, clusters, _stream(key))
    estimate = estimate_of(_mean(diffs), draws)
    return Check(key, f"{what}: {a} - {b} = {estimate.text(scale, digits)}{unit}", estimate,
                 bootstrap_p(draws, side))  # fmt: skip


def _bound(t: Table, claim: str, config: str, metric: str, bound: float, what: str) -> Check:
    """The mean of ``config``'s ``metric`` lies below ``bound``."""
    key = f"{claim}/{what}/{config}"
    values, clusters = t.single(config, metric)
    draws = hierarchical_draws(values, clusters, _stream(key))
    estimate = estimate_of(_mean(values), draws)
    return Check(key, f"{what}: {config} {estimate.text(1, 2)} (below {bound})", estimate,
                 bootstrap_p(draws, "below", bound))  # fmt: skip


def _not_worse(t: Table, claim: str, a: str, b: str, metric: str, share: float,
               what: str) -> Check:  # fmt: skip
    """Non-inferiority (one side of TOST): a - b above -share * |mean of b|."""
    key = f"{claim}/{what}/{a}-{b}"
    diffs, clusters = t.paired(a, b, metric)
    reference, _ = t.single(b, metric)
    margin = share * abs(_mean(reference))
    draws = hierarchical_draws(diffs, clusters, _stream(key))
    estimate = estimate_of(_mean(diffs), draws)
    text = f"{what}: {a} - {b} = {estimate.text(1, 3)} (margin -{margin:.3f}, {share:.0%} of |{b}|)"
    return Check(key, text, estimate, bootstrap_p(draws, "above", -margin))


def _mean(values: np.ndarray) -> float:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else math.nan


def _claim(key: str, statement: str, drafts: list[Check]) -> Claim:
    """The claim's checks, Holm-corrected as one family."""
    adjusted = holm([c.p for c in drafts])
    checks = [replace(c, p_holm=q, passed=c.estimate.n > 0 and q < ALPHA)
              for c, q in zip(drafts, adjusted, strict=True)]  # fmt: skip
    return Claim(key, statement, verdict(checks), tuple(checks))


# ---- the claims ---------------------------------------------------------------------


def _c1(t: Table) -> Claim:
    checks = []
    if t.has(EVENT, FIXED):
        checks = [
            _compare(t, "C1", EVENT, FIXED, "n_osc", "below", "fewer oscillations per reach"),
            _compare(t, "C1", EVENT, FIXED, "n_osc_per_step", "below",
                     "fewer oscillations per step"),
            _compare(t, "C1", EVENT, FIXED, "final_error_m", "below", "closer convergence",
                     1000, " mm"),
            _compare(t, "C1", EVENT, FIXED, "success", "above", "higher success", 100, " pp"),
        ]  # fmt: skip
    return _claim("C1", "The event trigger suppresses chatter and improves convergence and "
                  "success over fixed-frequency progression", checks)  # fmt: skip


def _c2(t: Table) -> Claim:
    checks = [_compare(t, "C2", EVENT, other, "time", "above", "slower", unit=" s")
              for other in (FIXED, R1, R2) if t.has(EVENT, other)]  # fmt: skip
    return _claim("C2", "Event-triggered progression with a fixed model is slow", checks)


def _c3(t: Table) -> Claim:
    checks = []
    if t.has(R1, R2):
        checks = [
            _compare(t, "C3", R1, R2, "final_error_m", "below", "more accurate", 1000, " mm"),
            _bound(t, "C3", R1, "n_osc", NEAR_ZERO_OSCILLATIONS,
                   "near-zero chatter, oscillations per reach"),
            _compare(t, "C3", R1, R2, "time", "above", "longer execution", unit=" s"),
            _compare(t, "C3", R1, R2, "near_step_m", "below", "smaller steps within eps_g",
                     1000, " mm"),
        ]  # fmt: skip
    return _claim("C3", "Reward 1: accuracy, near-zero chatter, long execution, small steps "
                  "near the target", checks)  # fmt: skip


def _c4(t: Table) -> Claim:
    checks = []
    if t.has(R1, R2):
        checks = [
            _compare(t, "C4", R2, R1, "mid_step_m", "above",
                     "larger steps mid-to-late (eps_g to half the start distance)", 1000, " mm"),
            _compare(t, "C4", R2, R1, "time", "below", "faster", unit=" s"),
            _not_worse(t, "C4", R2, R1, "sparc", SMOOTHNESS_MARGIN,
                       "as smooth, SPARC not lower (non-inferiority)"),
        ]  # fmt: skip
    return _claim("C4", "Reward 2: larger steps mid-to-late in the reach, faster, smooth", checks)


def _c5(t: Table) -> Claim:
    checks = []
    for dammrl in (R1, R2):
        if t.has(dammrl, FIXED):
            checks += [
                _compare(t, "C5", dammrl, FIXED, "success", "above", "higher success", 100,
                         " pp"),
                _compare(t, "C5", dammrl, FIXED, "final_error_m", "below", "more precise",
                         1000, " mm"),
                _compare(t, "C5", dammrl, FIXED, "time", "below", "faster", unit=" s"),
            ]  # fmt: skip
    return _claim("C5", "Success, precision and time improve from the fixed-frequency "
                  "baseline to DAMMRL", checks)  # fmt: skip


def _c6(training: Curves) -> Claim:
    checks = [_settled(reward, agent, runs)
              for reward, runs in sorted(training.items()) if len(runs) > 1
              for agent in ("human", "robot")]  # fmt: skip
    # (one training seed has no interval: the claim is then not tested)
    return _claim(
        "C6", "Both agents converge during training (their Q-value curves settle)", checks
    )


def _settled(reward: str, agent: str, runs: list[dict[str, np.ndarray]]) -> Check:
    """TOST over training seeds: the move over the last tenth within +-SETTLED_SHARE of the
    curve's fastest move."""
    moves = np.array([settling(run[f"q_{agent}"]) for run in runs])
    p, estimate = tost_mean(moves, -SETTLED_SHARE, SETTLED_SHARE)
    text = (
        f"{agent} agent settled in {reward} ({len(runs)} training seeds): last-tenth move "
        f"/ fastest move = {estimate.text(1, 3)} (within +-{SETTLED_SHARE})"
    )
    return Check(f"C6/{reward}/{agent}", text, estimate, p)


def settling(curve: np.ndarray, window: float = TRAINING_WINDOW) -> float:
    """How fast a training curve still moves at its end, as a share of its fastest move:
    the change of its mean from the one-but-last window to the last, over the largest such
    change between consecutive windows (0: settled; about 1: still moving as fast as it
    ever did, as a straight line does; NaN entries, before the first update, left out)."""
    q = np.asarray(curve, dtype=float)
    n = max(1, round(window * q.size))
    means = []
    for start in range(0, q.size - n + 1, n):
        part = q[start : start + n]
        finite = part[np.isfinite(part)]
        means.append(float(finite.mean()) if finite.size else math.nan)
    moves = np.diff(np.array(means))
    moves = moves[np.isfinite(moves)]
    fastest = float(np.max(np.abs(moves))) if moves.size else 0.0
    return float(moves[-1]) / fastest if fastest > 0 else math.nan


def p_text(check: Check) -> str:
    return f"p = {check.p:.4f}, Holm {check.p_holm:.4f}"
