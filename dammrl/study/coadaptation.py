"""Co-adaptation measured: shipped, adaptive, refined and oracle policy for kinds of
simulated person whose needs differ (``dammrl coadapt compare``).

The rules below were committed before the run they judge (docs/coadaptation/registration.md
states them in words, with the commit). For each kind of person (a person file):

* the **oracle** is the best fixed M_ij for that person by the adaptive mode's own rule
  (most targets met; then the least short of the comfort target; then the shortest mean
  time to success, a failure counting the 60 s horizon),
  searched on ``ORACLE_SEEDS`` (every M_ij, ``len(ORACLE_SEEDS)`` seeds each), then run
  on the test seeds; its search and its test-seed success are reported side by side;
* the **shipped** policy (the Reward 2 DQN) on the test seeds;
* the **adaptive** mode around it: the test seeds in order as the person's sessions, the
  posterior carried from reach to reach and session to session, ``replicates`` times with
  different Thompson seeds (and ``interpolated_replicates`` times with the bounded
  interpolation on);
* the **refined** policy: ``dammrl adapt``'s update on the person's first session with the
  shipped policy (``SESSION_SEEDS``), judged by its gate on the person fitted from that
  session; the candidate runs on the test seeds, and the policy the person would use is the
  candidate when the gate deployed it, else the shipped policy.

The test seeds are the person's sessions 2, 3, ... of ``SESSION_REACHES`` reaches each
(session 1 is the refinement's): a person who tires does so within each, one who learns
does so from one to the next, and every arm meets the same person at the same reach. Each
reach's comfort is the simulated person's rating of its steps (its own noise per seed,
the same in every arm).

Judged (paired by seed, bootstrap 95 % intervals; a bound is the interval's end):

* time to success restricted at the horizon (a failed reach counts 60 s: one measure for
  success and speed), success, median time and comfort;
* "an alternative is better" when, on the oracle's own seeds, the oracle ranks above the
  shipped policy by the rule and its time to success is shorter by ``MARGIN_S`` or more, or
  its mean comfort higher by ``MARGIN_COMFORT`` or more (the interval's bound past 0);
  "the shipped policy is best" when the oracle does not rank above it;
* goal 1 (an alternative better): after ``SETTLE_REACHES`` reaches, the adaptive mode's
  time to success is within ``MARGIN_S`` of the oracle's (upper bound) and its comfort
  within ``MARGIN_COMFORT`` (lower bound);
* goal 2 (the shipped policy best): the adaptive mode is equivalent to it over every test
  reach, time to success within +-``MARGIN_S`` (both bounds);
* goal 3: a refined policy deployed by the gate is never measurably worse than the
  shipped policy on the test seeds (the upper bound of its loss below ``MARGIN_S``).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dammrl.learning.adapt import RefineSettings
from dammrl.study.coadaptation_jobs import (
    HORIZON_S,
    SESSION_REACHES,
    FixedJob,
    Jobs,
    Kind,
    RefinedRun,
    Row,
    Session,
    adaptive_job,
    fixed_job,
    refined_job,
)
from dammrl.study.stats import Estimate, paired_difference
from dammrl_core.coadaptation import GRADED, Targets, shortfalls
from dammrl_core.model_table import BASE, MODELS, Option

__all__ = ["HORIZON_S", "SESSION_REACHES", "Kind", "Row"]

PERSONS_DIR = Path(__file__).parent / "persons"
REGISTERED = (
    "nominal", "low-accuracy", "hurried-errors", "careful-errors", "narrow-boundaries",
    "slow-decisions", "fatigue", "learner", "small-steps",
)  # fmt: skip
"""The registered kinds of person (files in ``PERSONS_DIR``), in the report's order."""


def registered_kinds() -> list[Kind]:
    return [Kind.of(PERSONS_DIR / f"{key}.yaml") for key in REGISTERED]


TARGETS = Targets(window=5, success_min=0.9, time_max_s=20.0, comfort_min=3.0)
"""The targets of every kind (the issue's positive control's, and comfort)."""
ORACLE_SEEDS = range(7_600_000, 7_600_030)
SESSION_SEEDS = range(7_650_000, 7_650_025)
TEST_SEEDS = range(7_700_000, 7_700_100)
"""Held-out seeds used by no training, study or table; disjoint."""
REPLICATES = 2
INTERPOLATED_REPLICATES = 1
MARGIN_S = 2.5
"""Time to success [s]: about 5 pp of success (a failure costs ~50 s more than a success)."""
MARGIN_COMFORT = 0.5
"""Mean comfort rating (1-5): half a step of the scale."""
SETTLE_REACHES = 25
"""Goal 1 is judged on the reaches after these (the first test session)."""
REFINE = RefineSettings(sim_reaches=50, gate_seeds=40)
"""The refinement of the comparison: ``dammrl adapt``'s defaults but 50 simulated reaches
and a gate on 40 reaches per policy (the machine is shared: the defaults' 100 and 60 would
add a fifth to the run)."""


# ---- the comparison -------------------------------------------------------------------------
@dataclass(frozen=True)
class Plan:
    """What ``compare`` runs."""

    kinds: list[Kind]
    oracle_seeds: range = ORACLE_SEEDS
    test_seeds: range = TEST_SEEDS
    session_seeds: range = SESSION_SEEDS
    replicates: int = REPLICATES
    interpolated_replicates: int = INTERPOLATED_REPLICATES  # 0: not run
    refine: RefineSettings = field(default_factory=lambda: REFINE)

    def reaches(self) -> int:
        """Reaches ``compare`` runs (its progress unit; a refinement counts its simulated
        reaches, its gate's and its session's)."""
        per_kind = (len(MODELS) + 1) * len(self.oracle_seeds) + 2 * len(self.test_seeds)
        per_kind += (self.replicates + self.interpolated_replicates) * len(self.test_seeds)
        per_kind += self.refine_reaches()
        return per_kind * len(self.kinds)

    def refine_reaches(self) -> int:
        return (len(self.session_seeds) + self.refine.sim_reaches + 2 * self.refine.gate_seeds
                + len(self.test_seeds))  # fmt: skip


@dataclass(frozen=True)
class PersonResult:
    kind: Kind
    oracle: Option
    search: dict[Option, list[Row]]  # every option (and BASE) on the oracle's seeds
    arms: dict[str, list[Row]]  # on the test seeds; adaptive arms: every replicate
    sessions: list[Session]
    refined: RefinedRun

    @property
    def deployed(self) -> list[Row]:
        """What the person would run after the gate: the candidate, or the shipped policy."""
        return self.arms["refined"] if self.refined.gate.deployed else self.arms["shipped"]


def compare(plan: Plan, workers: int = 1, progress: Callable[[int], None] | None = None,
            cache: Path | None = None) -> list[PersonResult]:  # fmt: skip
    """Every arm for every kind of person (see the module). With ``cache``, every finished
    job is kept there and a later run with the same job and the same code reuses it (a
    long comparison resumes after an interruption)."""
    tick = progress or (lambda n: None)
    runs = Jobs(workers, tick, cache)
    test = tuple(plan.test_seeds)
    indices = tuple(range(len(test)))
    oracle_seeds = tuple(plan.oracle_seeds)
    search_jobs: list[FixedJob] = [
        (kind, "search", option, oracle_seeds, tuple(range(len(oracle_seeds))))
        for kind in plan.kinds
        for option in (BASE, *MODELS)
    ]
    search_jobs += [(kind, "shipped", BASE, test, indices) for kind in plan.kinds]
    rows = [r for done in runs.map(fixed_job, search_jobs, len) for r in done]
    search = {k.key: _searched(rows, k.key) for k in plan.kinds}
    oracles = {k.key: best_fixed(search[k.key]) for k in plan.kinds}
    oracle_jobs: list[FixedJob] = [(k, "oracle", oracles[k.key], test, indices) for k in plan.kinds]
    rows += [r for done in runs.map(fixed_job, oracle_jobs, len) for r in done]
    # the candidates' checkpoints: beside the cache, else in a folder of their own (never
    # among the report's files)
    candidates = cache / "refined" if cache is not None else Path(tempfile.mkdtemp("-refined"))
    refine_jobs = [(k, tuple(plan.session_seeds), test, candidates / k.key, plan.refine)
                   for k in plan.kinds]  # fmt: skip
    refined = runs.map(refined_job, refine_jobs, lambda _: plan.refine_reaches())
    session_jobs = [(k, test, TARGETS, r, False) for k in plan.kinds
                    for r in range(plan.replicates)]  # fmt: skip
    session_jobs += [(k, test, TARGETS, r, True) for k in plan.kinds
                     for r in range(plan.interpolated_replicates)]  # fmt: skip
    sessions = runs.map(adaptive_job, session_jobs, lambda s: len(s.rows))
    return [_result(k, oracles[k.key], search[k.key], rows, sessions, refined) for k in plan.kinds]


def _searched(rows: list[Row], kind: str) -> dict[Option, list[Row]]:
    mine = [r for r in rows if r.person == kind and r.arm == "search"]
    return {o: [r for r in mine if r.option == o] for o in (BASE, *MODELS)}


def _result(kind: Kind, oracle: Option, search: dict[Option, list[Row]], rows: list[Row],
            sessions: list[Session], refined: list[RefinedRun]) -> PersonResult:  # fmt: skip
    mine = [s for s in sessions if s.kind == kind.key]
    arms = {arm: sorted((r for r in rows if r.person == kind.key and r.arm == arm),
                        key=lambda r: r.index) for arm in ("shipped", "oracle")}  # fmt: skip
    arms["adaptive"] = [r for s in mine if not s.interpolate for r in s.rows]
    arms["interpolated"] = [r for s in mine if s.interpolate for r in s.rows]
    run = next(r for r in refined if r.kind == kind.key)
    arms["refined"] = run.rows
    return PersonResult(kind, oracle, search, arms, mine, run)


# ---- the rule, the oracle and the goals ----------------------------------------------------
@dataclass(frozen=True)
class LongRun:
    """An arm's long-run statistics, as the targets judge them."""

    success: float
    median_time_s: float
    comfort: float
    to_success_s: float  # mean time to success, a failure counting the horizon

    @classmethod
    def of(cls, rows: Sequence[Row]) -> LongRun:
        return cls(float(np.mean([r.success for r in rows])),
                   float(np.median([r.t_total_s for r in rows])),
                   float(np.mean([r.comfort for r in rows])),
                   float(np.mean([r.restricted_s for r in rows])))  # fmt: skip

    def rank(self, targets: Targets = TARGETS) -> tuple[float, float, float]:
        """The adaptive mode's rule as a sort key (smaller is better): most targets met,
        then the least short of the comfort (error, SPARC) targets, then the shortest time
        to success."""
        values = {"success": np.array([self.success]),
                  "log_time": np.array([math.log(max(self.median_time_s, 1e-3))]),
                  "comfort": np.array([self.comfort])}  # fmt: skip
        short = {k: float(v[0]) for k, v in shortfalls(targets, values).items()}
        graded = sum(short.get(name, 0.0) for name in GRADED)
        return (-float(sum(v <= 0 for v in short.values())), graded, self.to_success_s)

    def targets_met(self, targets: Targets = TARGETS) -> int:
        return int(-self.rank(targets)[0])


def best_fixed(search: dict[Option, list[Row]]) -> Option:
    """The oracle: the fixed M_ij that ranks first by the rule on its own seeds."""
    return min(MODELS, key=lambda m: LongRun.of(search[m]).rank())


def restricted(rows: Sequence[Row]) -> np.ndarray:
    return np.array([r.restricted_s for r in rows])


def per_seed(rows: Sequence[Row], value: Callable[[Row], float], seeds: Sequence[int],
             after: int = 0) -> np.ndarray:  # fmt: skip
    """Each seed's mean of ``value`` over its rows (replicates), reaches from ``after`` on."""
    by_seed: dict[int, list[float]] = {}
    for r in rows:
        if r.index >= after:
            by_seed.setdefault(r.seed, []).append(value(r))
    return np.array([np.mean(by_seed[s]) if s in by_seed else np.nan for s in seeds])


def difference(a: Sequence[Row], b: Sequence[Row], value: Callable[[Row], float],
               seeds: Sequence[int], after: int = 0, stream: int = 0) -> Estimate:  # fmt: skip
    """Mean of a - b paired by seed (replicates averaged within a seed), 95 % interval."""
    rng = np.random.default_rng([stream, after])
    return paired_difference(
        per_seed(a, value, seeds, after), per_seed(b, value, seeds, after), rng
    )


@dataclass(frozen=True)
class Verdict:
    """What the registered rules say of one kind of person."""

    case: str  # 'alternative better', 'shipped best', 'neither'
    why: str
    goal: str  # 'goal 1', 'goal 2' or 'none'
    passed: bool | None  # None: no goal for this kind
    detail: str
    goal3: bool | None  # None: the gate deployed nothing
    goal3_detail: str


def verdict(result: PersonResult) -> Verdict:
    search = result.search
    oracle, shipped = LongRun.of(search[result.oracle]), LongRun.of(search[BASE])
    seeds = sorted({r.seed for r in search[BASE]})
    time_gain = difference(search[BASE], search[result.oracle], _restricted, seeds, stream=1)
    comfort_gain = difference(search[result.oracle], search[BASE], _comfort, seeds, stream=2)
    ranks_above = oracle.rank() < shipped.rank()
    by_time = time_gain.value >= MARGIN_S and time_gain.low > 0
    by_comfort = comfort_gain.value >= MARGIN_COMFORT and comfort_gain.low > 0
    why = (f"on the oracle's seeds: rank {_rank(oracle)} vs the shipped policy's "
           f"{_rank(shipped)}; time to success shorter by {time_gain.text(1, 2)} s, comfort "
           f"higher by {comfort_gain.text(1, 2)}")  # fmt: skip
    goal3, goal3_detail = _goal3(result)
    if ranks_above and (by_time or by_comfort):
        passed, detail = _goal1(result)
        return Verdict("alternative better", why, "goal 1", passed, detail, goal3, goal3_detail)
    if not ranks_above:
        passed, detail = _goal2(result)
        return Verdict("shipped best", why, "goal 2", passed, detail, goal3, goal3_detail)
    return Verdict("neither", why, "none", None, "no goal: the oracle ranks above the shipped "
                   "policy, but by less than a margin", goal3, goal3_detail)  # fmt: skip


def _restricted(r: Row) -> float:
    return r.restricted_s


def _comfort(r: Row) -> float:
    return r.comfort


def _rank(run: LongRun) -> str:
    return (f"{run.targets_met()} targets met (success {run.success:.0%}, median "
            f"{run.median_time_s:.1f} s, comfort {run.comfort:.1f})")  # fmt: skip


def _goal1(result: PersonResult) -> tuple[bool, str]:
    seeds = [r.seed for r in result.arms["shipped"]]
    arms = result.arms
    time = difference(arms["adaptive"], arms["oracle"], _restricted, seeds, SETTLE_REACHES, 3)
    comfort = difference(arms["adaptive"], arms["oracle"], _comfort, seeds, SETTLE_REACHES, 4)
    passed = time.high < MARGIN_S and comfort.low > -MARGIN_COMFORT
    return passed, (f"after {SETTLE_REACHES} reaches, adaptive - oracle: time to success "
                    f"{time.text(1, 2)} s (margin < {MARGIN_S:g}), comfort {comfort.text(1, 2)} "
                    f"(margin > -{MARGIN_COMFORT:g})")  # fmt: skip


def _goal2(result: PersonResult) -> tuple[bool, str]:
    seeds = [r.seed for r in result.arms["shipped"]]
    time = difference(result.arms["adaptive"], result.arms["shipped"], _restricted, seeds,
                      stream=5)  # fmt: skip
    passed = time.low > -MARGIN_S and time.high < MARGIN_S
    return passed, (f"adaptive - shipped over every test reach: time to success "
                    f"{time.text(1, 2)} s (equivalence margin +-{MARGIN_S:g})")  # fmt: skip


def _goal3(result: PersonResult) -> tuple[bool | None, str]:
    seeds = [r.seed for r in result.arms["shipped"]]
    loss = difference(result.arms["refined"], result.arms["shipped"], _restricted, seeds,
                      stream=6)  # fmt: skip
    gate_line = "deployed" if result.refined.gate.deployed else "kept the shipped policy"
    detail = (f"the gate {gate_line} ({result.refined.gate.reason}); on the test seeds the "
              f"candidate - shipped: time to success {loss.text(1, 2)} s")  # fmt: skip
    if not result.refined.gate.deployed:
        return None, detail
    return bool(loss.high < MARGIN_S), detail


def regret_curve(result: PersonResult, arm: str) -> np.ndarray:
    """Cumulative restricted-time regret against the oracle over the test reaches, mean over
    the arm's replicates (reaches,)."""
    oracle = {r.index: r.restricted_s for r in result.arms["oracle"]}
    rows = result.arms[arm]
    curves = []
    for replicate in sorted({r.replicate for r in rows}):
        mine = sorted((r for r in rows if r.replicate == replicate), key=lambda r: r.index)
        curves.append(np.cumsum([r.restricted_s - oracle[r.index] for r in mine]))
    return np.asarray(np.mean(curves, axis=0))


def arm_rows(result: PersonResult) -> Iterator[tuple[str, list[Row]]]:
    """The arms in the report's order ('refined' is the candidate; 'as deployed' after
    the gate)."""
    for arm in ("shipped", "oracle", "adaptive", "interpolated", "refined"):
        if result.arms.get(arm):
            yield arm, result.arms[arm]
    yield "as deployed", result.deployed
