"""``dammrl coadapt table``: every option simulated on a grid of persons, the model table
the posterior over M_ij predicts every option from (:mod:`dammrl_core.model_table`).

Each M_ij runs with persons whose accuracy under its radius is each node of
``ACCURACY_NODES``; the base policy (the shipped DQN, which uses both radii) on the grid
``BASE_NODES`` x ``BASE_NODES`` of both accuracies. Every node runs the same task seeds
(``TABLE_SEEDS``: below the held-out range, apart from training's and every study's), with
the sub-models' decision times and a simulated timeout of ``SIMULATED_TIMEOUT_S`` (1.5 x
the task's: a person up to 1.5 times as quick as the sub-model still has their reach).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings, evidence_of
from dammrl.study.coadaptation_jobs import Jobs
from dammrl_core.coadaptation import ReachEvidence
from dammrl_core.human import HumanModel
from dammrl_core.model_table import (
    BASE,
    COLUMNS,
    OPTIONS,
    ModelTable,
    Option,
    OptionReaches,
    Radius,
    grid_persons,
)
from dammrl_core.models import ModelSet
from dammrl_core.person import SimulatedPerson
from dammrl_core.policy import Policy
from dammrl_core.policy.learned import LearnedPolicy
from dammrl_core.task import TaskSettings

TABLE_SEEDS = range(6_900_000, 6_900_012)
ACCURACY_NODES = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 0.99)
BASE_NODES = (0.5, 0.6, 0.7, 0.8, 0.9, 0.99)
HORIZON_S = float(TaskSettings.model_fields["episode_timeout_s"].default)
SIMULATED_TIMEOUT_S = 1.5 * HORIZON_S
SHIPPED = Path("reward2")


def option_grid(option: Option) -> tuple[tuple[Radius, ...], tuple[tuple[float, ...], ...]]:
    """The axes and nodes an option runs on."""
    if option == BASE:
        return ("big", "small"), (BASE_NODES, BASE_NODES)
    return ("big",) if option[0] == 1 else ("small",), (ACCURACY_NODES,)


TableJob = tuple[Option, int, int]  # option, node, seed


@functools.lru_cache(maxsize=1)
def _runner() -> ReachRunner:
    task = TaskSettings(episode_timeout_s=SIMULATED_TIMEOUT_S)
    return ReachRunner(ReachSettings(task=task))


@functools.lru_cache(maxsize=1)
def _shipped(models: ModelSet) -> Policy:
    return LearnedPolicy(models, SHIPPED)


def table_job(job: TableJob) -> tuple[list[float], ReachEvidence]:
    option, node, seed = job
    big, small = grid_persons(*option_grid(option))[node]
    runner = _runner()
    human = HumanModel(person=SimulatedPerson(accuracy_big=big, accuracy_small=small))
    policy = _shipped(runner.settings.models) if option == BASE else None
    model = (1, 1) if option == BASE else (option[0], option[1])
    result = runner.run(seed, model, policy=policy, human=human)
    evidence = evidence_of(result, runner.settings.models)
    return reach_columns(result, evidence, runner.settings.models), evidence


def _one(_: object) -> int:
    return 1


def reach_columns(result: ReachResult, evidence: ReachEvidence, models: ModelSet) -> list[float]:
    """COLUMNS of one reach."""
    m = result.metrics
    end = m.t_total_s + 1e-6
    pairs = zip(result.decisions, result.choices, strict=True)
    decided = [(c.human_model, d.decision_s) for d, c in pairs if d.intent.t_s <= end]
    scales = step_scales(np.array([s.steps_m for s in result.steps]).reshape(-1, 3), models)
    return [
        float(m.success),
        m.t_total_s,
        sum(t for i, t in decided if i == 1),
        sum(t for i, t in decided if i == 2),
        sum(s.execution_s for s in evidence.steps),
        math.log(max(m.final_error_m, 1e-4)),
        m.sparc if math.isfinite(m.sparc) else math.nan,
        *scales,
    ]


def step_scales(steps_m: np.ndarray, models: ModelSet) -> list[float]:
    """The mean step scale per axis (0: the small step, 1: the large) of steps (n, 3)."""
    if not len(steps_m):
        return [0.0, 0.0, 0.0]
    small, large = np.array(models.step_small_m), np.array(models.step_large_m)
    scale = (np.abs(steps_m) - small) / np.maximum(large - small, 1e-9)
    return [float(v) for v in np.clip(scale, 0.0, 1.0).mean(axis=0)]


def table_jobs(seeds: range = TABLE_SEEDS) -> list[TableJob]:
    return [
        (option, node, seed)
        for option in OPTIONS
        for node in range(len(grid_persons(*option_grid(option))))
        for seed in seeds
    ]


def build_table(seeds: range = TABLE_SEEDS, workers: int = 1,
                progress: Callable[[int], None] | None = None,
                cache: Path | None = None) -> ModelTable:  # fmt: skip
    """Every option on its grid of persons (see the module); with ``cache``, every
    finished reach is kept there for a later run (a long build resumes)."""
    jobs = table_jobs(seeds)
    results = Jobs(workers, progress or (lambda n: None), cache).map(table_job, jobs, _one)
    done = dict(zip(jobs, results, strict=True))
    options = []
    for option in OPTIONS:
        axes, grid = option_grid(option)
        nodes = range(len(grid_persons(axes, grid)))
        columns = {
            name: [[round(done[(option, n, s)][0][k], 5) for s in seeds] for n in nodes]
            for k, name in enumerate(COLUMNS)
        }
        options.append(OptionReaches(human_model=option[0], robot_model=option[1], axes=axes,
                                     grid=grid, columns=columns))  # fmt: skip
    intercept, length, radius, sd = _step_time_fit([e for _, e in done.values()])
    return ModelTable(seeds=f"{seeds.start}:{seeds.stop}", horizon_s=HORIZON_S,
                      simulated_timeout_s=SIMULATED_TIMEOUT_S, step_time_log_intercept=intercept,
                      step_time_log_length=length, step_time_log_radius=radius,
                      step_time_log_sd=sd, options=tuple(options))  # fmt: skip


def _step_time_fit(reaches: list[ReachEvidence]) -> tuple[float, float, float, float]:
    """log tau = c + b_L log L + b_eps log eps over every timed step, and its log-sd."""
    timed = [s for r in reaches for s in r.steps if s.execution_s > 0 and s.length_m > 0]
    design = np.column_stack([np.ones(len(timed)), np.log([s.length_m for s in timed]),
                              np.log([s.radius_m for s in timed])])  # fmt: skip
    log_times = np.log([s.execution_s for s in timed])
    coefficients, *_ = np.linalg.lstsq(design, log_times, rcond=None)
    log_sd = float(np.std(log_times - design @ coefficients))
    return (float(coefficients[0]), float(coefficients[1]), float(coefficients[2]),
            max(log_sd, 0.05))  # fmt: skip
