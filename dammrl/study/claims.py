"""The paper's claims C1-C6, each judged from a study's per-reach rows.

Every claim is split into checks fixed before any result was seen; each check is a paired
comparison on the same seeds (a 95 % bootstrap interval that excludes zero) or a rate
with its Wilson interval. A claim *holds* when every check passes, holds *partly* when
some do, and *does not hold* when none does. The thresholds are the ones written here;
they are never tuned to a result.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Literal

import numpy as np

from dammrl.study.stats import Estimate, bootstrap_mean, paired_difference, wilson

Verdict = Literal["holds", "partly", "does not hold", "not tested"]
Rows = Sequence[dict[str, Any]]

FIXED, EVENT, R1, R2 = "1-fixed", "2-event", "3-dammrl-r1", "4-dammrl-r2"
NEAR_ZERO_CHATTER = 0.05  # oscillations per step: "~zero chatter" (C3)
CONVERGED_SHARE = 0.5  # a reach converged when its choice held over its last half (C6)


@dataclass(frozen=True)
class Check:
    text: str  # what is compared, with the numbers
    passed: bool


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


class Table:
    """Rows by configuration, values aligned by seed (NaN where a value is missing)."""

    def __init__(self, rows: Rows, rng: np.random.Generator) -> None:
        self.rng = rng
        self.by_config: dict[str, dict[int, dict[str, Any]]] = {}
        for row in rows:
            self.by_config.setdefault(row["configuration"], {})[row["seed"]] = row

    def has(self, *configs: str) -> bool:
        return all(c in self.by_config for c in configs)

    def values(self, config: str, metric: str, seeds: Sequence[int]) -> np.ndarray:
        rows = self.by_config[config]
        return np.array([_number(rows[s].get(metric)) if s in rows else np.nan for s in seeds])

    def seeds(self, a: str, b: str) -> list[int]:
        return sorted(set(self.by_config[a]) & set(self.by_config[b]))

    def difference(self, a: str, b: str, metric: str) -> Estimate:
        """Paired mean of a - b over the seeds both ran."""
        seeds = self.seeds(a, b)
        return paired_difference(self.values(a, metric, seeds), self.values(b, metric, seeds),
                                 self.rng)  # fmt: skip

    def rate(self, config: str, flag: Callable[[dict[str, Any]], bool | None]) -> Estimate:
        flags = [f for row in self.by_config[config].values() if (f := flag(row)) is not None]
        return wilson(sum(flags), len(flags))


def _number(value: Any) -> float:
    return float("nan") if value is None else float(value)


def _lower(table: Table, a: str, b: str, metric: str, what: str, scale: float = 1.0,
           unit: str = "") -> Check:  # fmt: skip
    d = table.difference(a, b, metric)
    return Check(f"{what}: {a} - {b} = {d.text(scale)}{unit}", d.n > 0 and d.high < 0)


def _higher(table: Table, a: str, b: str, metric: str, what: str, scale: float = 1.0,
            unit: str = "") -> Check:  # fmt: skip
    d = table.difference(a, b, metric)
    return Check(f"{what}: {a} - {b} = {d.text(scale)}{unit}", d.n > 0 and d.low > 0)


def judge(rows: Rows, rng: np.random.Generator) -> list[Claim]:
    """C1-C6 from the rows of one condition (one randomisation setting)."""
    table = Table(rows, rng)
    return [_c1(table), _c2(table), _c3(table), _c4(table), _c5(table), _c6(table)]


def _claim(key: str, statement: str, checks: list[Check]) -> Claim:
    return Claim(key, statement, verdict(checks), tuple(checks))


def _c1(t: Table) -> Claim:
    checks = []
    if t.has(EVENT, FIXED):
        checks = [
            _lower(t, EVENT, FIXED, "n_osc_per_step", "fewer oscillations per step"),
            _higher(t, EVENT, FIXED, "success", "higher success", 100, " pp"),
        ]
    return _claim("C1", "The event trigger suppresses chatter and improves convergence and "
                  "success over fixed-frequency progression", checks)  # fmt: skip


def _c2(t: Table) -> Claim:
    checks = [
        _higher(t, EVENT, other, "t_total_s", "slower", unit=" s")
        for other in (FIXED, R1, R2)
        if t.has(EVENT, other)
    ]
    return _claim("C2", "Event-triggered progression with a fixed model is slow", checks)


def _c3(t: Table) -> Claim:
    checks = []
    if t.has(R1, R2):
        chatter = _mean_estimate(t, R1, "n_osc_per_step")
        checks = [
            _lower(t, R1, R2, "final_error_m", "more accurate", 1000, " mm"),
            Check(
                f"~zero chatter: {R1} oscillations per step {chatter.text(1, 3)} "
                f"(upper bound < {NEAR_ZERO_CHATTER})",
                chatter.n > 0 and chatter.high < NEAR_ZERO_CHATTER,
            ),
            _higher(t, R1, R2, "t_total_s", "longer execution", unit=" s"),
            _lower(t, R1, R2, "near_step_m", "smaller steps within 4 cm", 1000, " mm"),
        ]
    return _claim("C3", "Reward 1: accuracy, near-zero chatter, long execution, small steps "
                  "near the target", checks)  # fmt: skip


def _c4(t: Table) -> Claim:
    checks = []
    if t.has(R1, R2):
        sparc = t.difference(R2, R1, "sparc")
        checks = [
            _higher(t, R2, R1, "mid_step_m", "larger steps 4-16 cm out", 1000, " mm"),
            _lower(t, R2, R1, "t_total_s", "faster", unit=" s"),
            Check(f"as smooth (SPARC not lower): {R2} - {R1} = {sparc.text(1, 3)}",
                  sparc.n > 0 and sparc.high >= 0),
        ]  # fmt: skip
    return _claim("C4", "Reward 2: larger steps mid-to-late in the reach, faster, smooth", checks)


def _c5(t: Table) -> Claim:
    checks = []
    for dammrl in (R1, R2):
        if t.has(dammrl, FIXED):
            checks += [
                _higher(t, dammrl, FIXED, "success", "higher success", 100, " pp"),
                _lower(t, dammrl, FIXED, "final_error_m", "more precise", 1000, " mm"),
                _lower(t, dammrl, FIXED, "t_total_s", "faster", unit=" s"),
            ]
    return _claim("C5", "Success, precision and time improve from the fixed-frequency "
                  "baseline to DAMMRL", checks)  # fmt: skip


def _c6(t: Table) -> Claim:
    checks = []
    for dammrl in (R1, R2):
        if not t.has(dammrl):
            continue
        for agent in ("human", "robot"):
            share = t.rate(dammrl, partial(_converged, agent=agent))
            checks.append(Check(
                f"{agent} agent converged (choice held over the last half of the decisions)"
                f" in {dammrl}: {share.text(100, 0)} % of reaches (lower bound >= 50 %)",
                share.n > 0 and share.low >= CONVERGED_SHARE,
            ))  # fmt: skip
    return _claim("C6", "Both agents converge (the chosen M_ij stops changing)", checks)


def _converged(row: dict[str, Any], *, agent: str) -> bool | None:
    n = row.get("n_decisions") or 0
    if n < 2:
        return None
    return float(row[f"{agent}_stable_after"]) <= CONVERGED_SHARE * n


def _mean_estimate(t: Table, config: str, metric: str) -> Estimate:
    seeds = sorted(t.by_config[config])
    return bootstrap_mean(t.values(config, metric, seeds), t.rng)
