"""One study: search the best fixed models on tuning seeds, run every configuration on
the evaluation seeds (with and without domain randomisation), judge the claims."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.study.claims import Claim, judge
from dammrl.study.configs import (
    Configuration,
    adaptive_configuration,
    best_fixed_candidates,
    paper_configurations,
    reviewer_configurations,
    variant_configurations,
)
from dammrl.study.run import (
    Job,
    Progress,
    Record,
    map_jobs,
    ordered,
    run_local,
    run_ray,
    run_session,
)
from dammrl_core.errors import ConfigurationError

TUNING_START = 7_900_000  # the best-fixed search's seeds start here: never evaluated on
TUNING_SEEDS = range(TUNING_START, TUNING_START + 20)


@dataclass(frozen=True)
class StudyOptions:
    seeds: range
    randomize: tuple[bool, ...] = (False, True)
    tuning_seeds: range = TUNING_SEEDS
    reward1: tuple[Path, ...] = ()
    reward2: tuple[Path, ...] = ()
    workers: int = 1
    ray: str | None = None  # a Ray address ("local": a local instance); None: this machine
    recording: Path | None = None  # a semi-virtual session (MCAP): its figure in the report
    adaptive: bool = False  # also configuration 4 inside the adaptive mode (sessions)

    def check(self) -> None:
        overlap = set(self.seeds) & set(self.tuning_seeds)
        if overlap:
            raise ConfigurationError(
                f"evaluation seeds overlap the tuning seeds of the best-fixed search "
                f"({min(overlap):,}...): choose seeds outside {self.tuning_seeds.start:,}-"
                f"{self.tuning_seeds.stop - 1:,}"
            )


@dataclass
class StudyResult:
    options: StudyOptions
    configurations: list[Configuration]
    records: list[Record]
    best: dict[str, tuple[int, int]]  # best-fixed row key -> the M_ij the search chose
    claims: dict[bool, list[Claim]]  # per randomisation setting
    wall_s: dict[str, float] = field(default_factory=dict)

    @property
    def rows(self) -> list[dict[str, Any]]:
        return [r.row for r in self.records]


def run_study(options: StudyOptions, progress: Callable[[int, str], Progress]) -> StudyResult:
    """The whole study; ``progress(total, description)`` makes a progress callback."""
    options.check()

    def execute(jobs: Sequence[Job], description: str) -> list[Record]:
        tick = progress(len(jobs), description)
        if options.ray is not None:
            return ordered(run_ray(jobs, options.ray, tick))
        return ordered(run_local(jobs, options.workers, tick))

    wall: dict[str, float] = {}
    start = time.perf_counter()
    best = search_best_fixed(options, execute)
    wall["best-fixed search"] = time.perf_counter() - start
    configurations = [
        *paper_configurations(options.reward1, options.reward2),
        *variant_configurations(),
        *reviewer_configurations(),
        *(c for c in best_fixed_candidates() if best.get(c.key) == c.policy.model),
    ]
    jobs = [
        Job(c, seed, randomize, index)
        for randomize in options.randomize
        for c in configurations
        for index, seed in enumerate(options.seeds)
    ]
    start = time.perf_counter()
    records = execute(jobs, "study")
    if options.adaptive:  # sessions: each in one process, its seeds in order
        adaptive = adaptive_configuration(options.reward2)
        configurations.append(adaptive)
        sessions = [(adaptive, tuple(options.seeds), r) for r in options.randomize]
        tick = progress(len(sessions), "adaptive sessions")
        for session in map_jobs(run_session, sessions, options.workers, progress=tick):
            records += session
    wall["evaluation"] = time.perf_counter() - start
    rng = np.random.default_rng(0)
    claims = {
        randomize: judge([r.row for r in records if r.row["randomize"] == randomize], rng)
        for randomize in options.randomize
    }
    return StudyResult(options, configurations, records, best, claims, wall)


def search_best_fixed(
    options: StudyOptions, execute: Callable[[Sequence[Job], str], list[Record]]
) -> dict[str, tuple[int, int]]:
    """The M_ij with the highest success (then the shortest time) under each progression,
    on the tuning seeds without randomisation."""
    candidates = best_fixed_candidates()
    jobs = [Job(c, s, False, k) for c in candidates for k, s in enumerate(options.tuning_seeds)]
    scores: dict[tuple[str, tuple[int, int]], list[dict[str, Any]]] = {}
    for record in execute(jobs, "best-fixed search"):
        i, j = (int(v) for v in record.row["model"].split(","))
        scores.setdefault((record.row["configuration"], (i, j)), []).append(record.row)
    best: dict[str, tuple[int, int]] = {}
    for key in {c.key for c in candidates}:
        ranked = sorted(
            ((model, rows) for (k, model), rows in scores.items() if k == key),
            key=lambda item: (-np.mean([r["success"] for r in item[1]]),
                              np.mean([r["t_total_s"] for r in item[1]])),
        )  # fmt: skip
        best[key] = ranked[0][0]
    return best
