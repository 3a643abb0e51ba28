"""Co-adaptation measured: the model table, and the oracle / shipped / adaptive comparison
on simulated persons unlike the training human.

``dammrl coadapt table`` runs every M_ij on the nominal simulated person and writes the
model table the posterior starts from (its seeds lie below the held-out range and apart
from training's). ``dammrl coadapt compare`` runs, for each kind of person:

* the **oracle**: the best fixed M_ij for that person, found by brute force on seeds of
  its own (most successes, then the shortest median time), then run on the test seeds;
* the **shipped** policy (the Reward 2 DQN) on the test seeds;
* the **adaptive** mode around the shipped policy: the test seeds as one session, in
  order, the posterior carried from reach to reach;
* the **refined** policy: the shipped one refined (``dammrl adapt``'s update) on a first
  session of that person with the shipped policy (seeds of its own), then run on the
  test seeds;

and reports success, time and error with paired 95 % intervals (by seed) against the
shipped policy, regret against the oracle, every switch, and the reaches until the
posterior's MAP model settled.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.adapt import PersonFit, RefineSettings, Transition, fit_person, refine_transitions
from dammrl.rl.config import RewardWeights, TrainSettings
from dammrl.rl.env import ReachEnv
from dammrl.runner import ReachResult, ReachRunner, ReachSettings, evidence_of
from dammrl.study.run import map_jobs
from dammrl.study.stats import Estimate, bootstrap_mean, paired_difference, wilson
from dammrl_core.coadaptation import (
    BASE,
    MODELS,
    OPTIONS,
    ModelPosterior,
    ModelRow,
    ModelTable,
    ReachEvidence,
    Targets,
)
from dammrl_core.human import HumanModel
from dammrl_core.person import SimulatedPerson
from dammrl_core.policy import FixedPolicy, Policy
from dammrl_core.policy.adaptive import AdaptivePolicy
from dammrl_core.policy.learned import LearnedPolicy, load_checkpoint

TABLE_SEEDS = range(6_900_000, 6_900_030)
"""The model table's seeds: below the held-out range, above every training run's."""
ORACLE_SEEDS = range(7_600_000, 7_600_020)
TEST_SEEDS = range(7_700_000, 7_700_040)
"""The comparison's held-out seeds: the oracle searches on its own, all policies are
measured on the test seeds (neither used by any study or training)."""
SESSION_SEEDS = range(7_650_000, 7_650_020)
"""The person's first session, with the shipped policy: the refinement's data."""
SHIPPED = Path("reward2")

PERSONS: dict[str, SimulatedPerson] = {
    "nominal": SimulatedPerson(),
    "slow (x1.6)": SimulatedPerson(decision_time_factor=1.6),
    "quick (x0.6)": SimulatedPerson(decision_time_factor=0.6),
    "error-prone (65 %)": SimulatedPerson(accuracy=0.65),
    "accurate (97 %)": SimulatedPerson(accuracy=0.97),
    "drift-diffusion": SimulatedPerson(behaviour="ddm"),
    "drift-diffusion, weak drift": SimulatedPerson(behaviour="ddm", ddm_drift_per_s=1.0),
}
"""The kinds of person (``DAMMRL_HUMAN_PERSON__*``); the first is the training human."""


# ---- one process's runners ----------------------------------------------------------
@functools.lru_cache(maxsize=8)
def _runner(person: str) -> ReachRunner:
    return ReachRunner(ReachSettings(human=HumanModel(person=PERSONS[person])))


def _policy(runner: ReachRunner, spec: tuple[int, int] | None) -> Policy:
    if spec is None:
        return LearnedPolicy(runner.settings.models, SHIPPED)
    return FixedPolicy(runner.settings.models, *spec)


@dataclass(frozen=True)
class Row:
    """One reach of the comparison."""

    person: str
    arm: str  # 'oracle-search', 'oracle', 'shipped', 'adaptive'
    seed: int
    model: tuple[int, int]
    success: bool
    t_total_s: float
    final_error_m: float


def _row(person: str, arm: str, result: ReachResult) -> Row:
    m = result.metrics
    return Row(person, arm, result.seed, result.model, m.success, m.t_total_s, m.final_error_m)


FixedJob = tuple[str, str, tuple[int, int] | None, int]  # person, arm, M_ij (None: shipped), seed


def _fixed_job(job: FixedJob) -> Row:
    person, arm, spec, seed = job
    runner = _runner(person)
    return _row(person, arm, runner.run(seed, policy=_policy(runner, spec)))


def _table_job(job: tuple[tuple[int, int], int]) -> tuple[ReachEvidence, float]:
    option, seed = job
    runner = _runner("nominal")
    if option == BASE:
        result = runner.run(seed, policy=_policy(runner, None))
    else:
        result = runner.run(seed, option)
    return evidence_of(result, runner.settings.models), _decision_time(result)


def _decision_time(result: ReachResult) -> float:
    end = result.metrics.t_total_s
    return float(sum(d.decision_s for d in result.decisions if d.intent.t_s <= end + 1e-6))


# ---- the model table ---------------------------------------------------------------
def build_table(
    seeds: range = TABLE_SEEDS, workers: int = 1, progress: Callable[[int], None] | None = None
) -> ModelTable:
    """Every M_ij, and the shipped policy (the adaptive policy's base), on ``seeds`` with
    the nominal person on the nominal arm."""
    jobs = [(m, s) for m in OPTIONS for s in seeds]
    done = list(map_jobs(_table_job, jobs, workers, progress=progress))
    steps = [s for evidence, _ in done for s in evidence.steps]
    timed = [s for s in steps if s.execution_s > 0 and s.length_m > 0]
    design = np.column_stack([np.ones(len(timed)), np.log([s.length_m for s in timed]),
                              np.log([s.radius_m for s in timed])])  # fmt: skip
    log_times = np.log([s.execution_s for s in timed])
    coefficients, *_ = np.linalg.lstsq(design, log_times, rcond=None)
    log_sd = float(np.std(log_times - design @ coefficients))
    rows = [
        _table_row(m, [d for (mm, _), d in zip(jobs, done, strict=True) if mm == m])
        for m in OPTIONS
    ]
    return ModelTable(
        seeds=f"{seeds.start}:{seeds.stop}",
        step_time_log_intercept=float(coefficients[0]),
        step_time_log_length=float(coefficients[1]),
        step_time_log_radius=float(coefficients[2]),
        step_time_log_sd=max(log_sd, 0.05),
        rows=tuple(rows),
    )


def _table_row(model: tuple[int, int], done: list[tuple[ReachEvidence, float]]) -> ModelRow:
    reaches = [evidence for evidence, _ in done]
    log_t = np.log([max(r.t_total_s, 1e-3) for r in reaches])
    log_e = np.log([max(r.final_error_m, 1e-4) for r in reaches])
    sparc = np.array([r.sparc for r in reaches if r.sparc is not None and math.isfinite(r.sparc)])
    total = sum(r.t_total_s for r in reaches)
    executing = sum(s.execution_s for r in reaches for s in r.steps)
    deciding = sum(d for _, d in done)
    decisions = [d for r in reaches for d in r.decisions]
    return ModelRow(
        human_model=model[0],
        robot_model=model[1],
        reaches=len(reaches),
        big_share=float(np.mean([d.human_model == 1 for d in decisions])) if decisions else 0.0,
        success_rate=float(np.mean([r.success for r in reaches])),
        log_time_mean=float(log_t.mean()),
        log_time_sd=max(float(log_t.std()), 0.05),
        log_error_mean=float(log_e.mean()),
        log_error_sd=max(float(log_e.std()), 0.05),
        sparc_mean=float(sparc.mean()) if sparc.size else -5.0,
        sparc_sd=max(float(sparc.std()), 0.1) if sparc.size else 2.0,
        decision_share=min(1.0, deciding / total),
        execution_share=min(1.0, executing / total),
    )


# ---- the adaptive session ------------------------------------------------------------
@dataclass(frozen=True)
class Session:
    """The adaptive mode over the test seeds as one session of one person."""

    rows: list[Row]
    switches: list[str]
    map_models: list[tuple[int, int]]  # the posterior's MAP model after each reach
    summary: dict[str, Any]


def adaptive_session(
    person: str, seeds: range, targets: Targets, table: ModelTable | None = None
) -> Session:
    runner = _runner(person)
    models = runner.settings.models
    posterior = ModelPosterior(table or ModelTable.load(), HumanModel(), models)
    policy = AdaptivePolicy(_policy(runner, None), models, posterior, targets)
    rows, map_models = [], []
    for seed in seeds:
        result = runner.run(seed, policy=policy)
        rows.append(_row(person, "adaptive", result))
        policy.observe(evidence_of(result, models))
        map_models.append(MODELS[int(np.argmax(posterior.probabilities(targets)))])
    return Session(rows, [s.line for s in policy.switches], map_models, posterior.summary(targets))


def _adaptive_job(job: tuple[str, range, Targets]) -> Session:
    return adaptive_session(*job)


# ---- the refined policy --------------------------------------------------------------
@dataclass(frozen=True)
class RefinedRun:
    rows: list[Row]
    fit: PersonFit


def refined_run(person: str, session_seeds: range, test_seeds: range, out: Path,
                settings: RefineSettings) -> RefinedRun:  # fmt: skip
    """A first session with the shipped policy, the refinement on it, the test seeds."""
    runner = _runner(person)
    checkpoint = load_checkpoint(SHIPPED)
    env = ReachEnv(runner, RewardWeights(**checkpoint["weights"]),
                   TrainSettings(**checkpoint["settings"]).max_decisions)  # fmt: skip
    policy = LearnedPolicy(runner.settings.models, SHIPPED)
    human = runner.settings.human
    transitions: list[Transition] = []
    decisions: list[tuple[bool, float]] = []
    for seed in session_seeds:
        obs, _ = env.reset(seed=seed)
        policy.reset()
        done = False
        while not done:
            state = env.episode.last_state
            choice = policy.decide(state.ee_pos, env.episode.task.goal)
            action = (choice.human_model - 1, choice.robot_model - 1)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
            transitions.append(Transition(obs, action, reward, next_obs, done))
            obs = next_obs
        episode = env.episode
        for d, c in zip(episode.decisions, episode.choices, strict=True):
            decisions.append((d.correct, d.decision_s / human.decision_median_s(c.human_model)))
    fit = fit_person(decisions)
    refined = refine_transitions(transitions, fit, SHIPPED, out, settings)
    mine = LearnedPolicy(runner.settings.models, refined.out)
    rows = [_row(person, "refined", runner.run(seed, policy=mine)) for seed in test_seeds]
    return RefinedRun(rows, fit)


def _refined_job(job: tuple[str, range, range, Path, RefineSettings]) -> RefinedRun:
    return refined_run(*job)


def settled_after(history: list[Any]) -> int:
    """Reaches until the last change of ``history`` (1: never changed; 0: empty)."""
    for k in range(len(history) - 1, 0, -1):
        if history[k] != history[k - 1]:
            return k + 1
    return 1 if history else 0


# ---- the comparison ------------------------------------------------------------------
@dataclass(frozen=True)
class PersonResult:
    person: str
    oracle: tuple[int, int]
    arms: dict[str, list[Row]]  # 'oracle', 'shipped', 'adaptive', 'refined' on the test seeds
    session: Session
    fit: PersonFit  # the simulated person fitted to the first session (the refinement's)


def compare(
    persons: list[str],
    targets: Targets,
    out: Path,
    workers: int = 1,
    oracle_seeds: range = ORACLE_SEEDS,
    test_seeds: range = TEST_SEEDS,
    refine: RefineSettings | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[PersonResult]:
    """The oracle search, the shipped and the adaptive policy for each person."""
    jobs: list[FixedJob] = [
        (p, "oracle-search", m, s) for p in persons for m in MODELS for s in oracle_seeds
    ]
    jobs += [(p, "shipped", None, s) for p in persons for s in test_seeds]
    fixed = list(map_jobs(_fixed_job, jobs, workers, progress=progress))
    oracles = {
        p: _best([r for r in fixed if r.person == p and r.arm == "oracle-search"]) for p in persons
    }
    oracle_jobs = [(p, "oracle", oracles[p], s) for p in persons for s in test_seeds]
    oracle_rows = list(map_jobs(_fixed_job, oracle_jobs, workers, progress=progress))
    sessions = list(
        map_jobs(
            _adaptive_job, [(p, test_seeds, targets) for p in persons], workers, progress=progress
        )
    )
    refine_jobs = [(p, SESSION_SEEDS, test_seeds, out / "refined" / _slug(p),
                    refine or RefineSettings()) for p in persons]  # fmt: skip
    refined = list(map_jobs(_refined_job, refine_jobs, workers, progress=progress))
    return [
        PersonResult(
            p,
            oracles[p],
            {
                "oracle": [r for r in oracle_rows if r.person == p],
                "shipped": [r for r in fixed if r.person == p and r.arm == "shipped"],
                "adaptive": session.rows,
                "refined": run.rows,
            },
            session,
            run.fit,
        )
        for p, session, run in zip(persons, sessions, refined, strict=True)
    ]


def _slug(person: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in person).strip("-")


def _best(rows: list[Row]) -> tuple[int, int]:
    """The model with most successes, then the shortest median time."""

    def score(model: tuple[int, int]) -> tuple[float, float]:
        mine = [r for r in rows if r.model == model]
        return (-sum(r.success for r in mine), float(np.median([r.t_total_s for r in mine])))

    return min(MODELS, key=score)


def figures(result: PersonResult) -> Iterator[tuple[str, str, Estimate]]:
    """(arm, measure, estimate): levels and paired differences against the shipped policy."""
    rng = np.random.default_rng(0)
    shipped = result.arms["shipped"]
    for arm, rows in result.arms.items():
        yield arm, "success", wilson(sum(r.success for r in rows), len(rows))
        yield arm, "time [s]", bootstrap_mean(np.array([r.t_total_s for r in rows]), rng)
        yield (
            arm,
            "error [mm]",
            bootstrap_mean(np.array([r.final_error_m * 1e3 for r in rows]), rng),
        )
        if arm == "shipped":
            continue
        for measure, value in (
            ("success", lambda r: float(r.success)),
            ("time [s]", lambda r: r.t_total_s),
            ("error [mm]", lambda r: r.final_error_m * 1e3),
        ):
            a = np.array([value(r) for r in rows])
            b = np.array([value(r) for r in shipped])
            yield arm, f"{measure} - shipped", paired_difference(a, b, rng)
