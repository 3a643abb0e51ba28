"""One study: search the best fixed models on tuning seeds, run every configuration under
every condition on K disjoint sets of evaluation seeds, judge the claims on each set and on
all of them, under both success criteria."""

from __future__ import annotations

import csv
import gzip
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.study.claims import CRITERIA, Claim, Criterion, Curves, judge
from dammrl.study.configs import (
    CONDITIONS,
    DEFAULT_CONDITIONS,
    R1,
    R2,
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
from dammrl_core.errors import ConfigurationError, UsageError

TUNING_START = 7_900_000  # the best-fixed search's seeds start here: never evaluated on
TUNING_SEEDS = range(TUNING_START, TUNING_START + 20)
LATENCIES_FORMAT = 1
Verdicts = dict[tuple[str, Criterion, int | None], list[Claim]]  # (condition, criterion, set)


@dataclass(frozen=True)
class StudyOptions:
    seeds: range  # every evaluation seed; split into ``sets`` disjoint sets in order
    sets: int = 1
    conditions: tuple[str, ...] = DEFAULT_CONDITIONS
    tuning_seeds: range = TUNING_SEEDS
    reward1: tuple[Path, ...] = ()
    reward2: tuple[Path, ...] = ()
    workers: int = 1
    ray: str | None = None  # a Ray address ("local": a local instance); None: this machine
    recording: Path | None = None  # a semi-virtual session (MCAP): its figure in the report
    adaptive: bool = False  # also configuration 4 inside the adaptive mode (sessions)
    ik_latencies: dict[str, tuple[float, ...]] | None = None  # a measured study's, replayed

    def check(self) -> None:
        overlap = set(self.seeds) & set(self.tuning_seeds)
        if overlap:
            raise ConfigurationError(
                f"evaluation seeds overlap the tuning seeds of the best-fixed search "
                f"({min(overlap):,}...): choose seeds outside {self.tuning_seeds.start:,}-"
                f"{self.tuning_seeds.stop - 1:,}"
            )
        if not 1 <= self.sets <= len(self.seeds):
            raise UsageError(f"{self.sets} seed sets need at least {self.sets} seeds, got "
                             f"{len(self.seeds)}")  # fmt: skip
        unknown = [c for c in self.conditions if c not in CONDITIONS]
        if unknown or not self.conditions:
            raise UsageError(f"unknown condition {', '.join(unknown) or '(none)'}: choose from "
                             f"{', '.join(CONDITIONS)}")  # fmt: skip

    def seed_set(self, index: int) -> int:
        """Which set the study's ``index``-th seed belongs to."""
        return index * self.sets // len(self.seeds)

    def set_seeds(self, k: int) -> range:
        indices = [i for i in range(len(self.seeds)) if self.seed_set(i) == k]
        return range(self.seeds[indices[0]], self.seeds[indices[-1]] + 1)


@dataclass
class StudyResult:
    options: StudyOptions
    configurations: list[Configuration]
    records: list[Record]
    best: dict[str, tuple[int, int]]  # best-fixed row key -> the M_ij the search chose
    verdicts: Verdicts  # per condition, criterion and seed set (None: every set)
    wall_s: dict[str, float] = field(default_factory=dict)

    @property
    def rows(self) -> list[dict[str, Any]]:
        return [r.row for r in self.records]

    def claims(self, condition: str, criterion: Criterion = "press",
               seed_set: int | None = None) -> list[Claim]:  # fmt: skip
        return self.verdicts[(condition, criterion, seed_set)]

    def stable(self, condition: str, criterion: Criterion, index: int) -> bool:
        """Claim ``index`` got one verdict on every seed set."""
        sets = {self.claims(condition, criterion, k)[index].verdict
                for k in range(self.options.sets)}  # fmt: skip
        return len(sets) == 1

    @property
    def latencies(self) -> dict[str, tuple[float, ...]]:
        """The IK latencies of every reach of a measured condition (to save and replay)."""
        return {_latency_key(r.row): r.ik_latencies for r in self.records
                if r.ik_latencies is not None}  # fmt: skip


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
    jobs = study_jobs(options, configurations)
    start = time.perf_counter()
    records = execute(jobs, "study")
    if options.adaptive:
        adaptive = adaptive_configuration(options.reward2)
        configurations.append(adaptive)
        records += adaptive_sessions(options, adaptive, progress)
    wall["evaluation"] = time.perf_counter() - start
    training = training_curves(configurations)
    verdicts: Verdicts = {}
    for condition in options.conditions:
        rows = [r.row for r in records if r.row["condition"] == condition]
        for criterion in CRITERIA:
            for seed_set in (None, *range(options.sets)):
                chosen = [r for r in rows if seed_set is None or r["seed_set"] == seed_set]
                verdicts[(condition, criterion, seed_set)] = judge(chosen, criterion, training)
    return StudyResult(options, configurations, records, best, verdicts, wall)


def study_jobs(options: StudyOptions, configurations: Sequence[Configuration]) -> list[Job]:
    """Every reach: each condition's configurations on every evaluation seed (replaying
    saved IK latencies where the options carry them; all or none of a measured condition's)."""
    jobs = []
    for key in options.conditions:
        condition = CONDITIONS[key]
        for c in configurations:
            if not condition.runs(c):
                continue
            for index, seed in enumerate(options.seeds):
                job = Job(c, seed, key, index, options.seed_set(index))
                jobs.append(_with_latencies(job, options.ik_latencies) if condition.measured
                            else job)  # fmt: skip
    return jobs


def _with_latencies(job: Job, saved: dict[str, tuple[float, ...]] | None) -> Job:
    if saved is None:
        return job
    if job.latency_key not in saved:
        raise UsageError(f"the saved IK latencies have none for {job.latency_key}: run the "
                         "study they came from, or measure again (no --ik-latencies)")  # fmt: skip
    return Job(job.configuration, job.seed, job.condition, job.index, job.seed_set,
               saved[job.latency_key])  # fmt: skip


def _latency_key(row: dict[str, Any]) -> str:
    return f"{row['condition']}/{row['configuration']}/{row['seed']}"


def adaptive_sessions(options: StudyOptions, adaptive: Configuration,
                       progress: Callable[[int, str], Progress]) -> list[Record]:  # fmt: skip
    """Configuration 4a: one session per seed set and randomisation, each in one process,
    its seeds in order (the posterior carried from reach to reach)."""
    conditions = [c for c in options.conditions if c in ("nominal", "randomised")]
    sessions = [(adaptive, tuple(options.set_seeds(k)), c)
                for c in conditions for k in range(options.sets)]  # fmt: skip
    tick = progress(sum(len(seeds) for _, seeds, _ in sessions), "adaptive sessions")
    records = []
    for session in map_jobs(run_session, sessions, options.workers):
        records += session
        tick(len(session))  # in reaches, as every other bar, a session at a time
    first = {seed: i for i, seed in enumerate(options.seeds)}
    for record in records:
        record.row["seed_set"] = options.seed_set(first[record.row["seed"]])
    return records


def search_best_fixed(
    options: StudyOptions, execute: Callable[[Sequence[Job], str], list[Record]]
) -> dict[str, tuple[int, int]]:
    """The M_ij with the highest success (then the shortest time) under each progression,
    on the tuning seeds on the nominal arm."""
    candidates = best_fixed_candidates()
    jobs = [Job(c, s, "nominal", k) for c in candidates for k, s in enumerate(options.tuning_seeds)]
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


# ---- training curves (C6) -----------------------------------------------------------

TRAINING_COLUMNS = ("q_human", "q_robot")


def training_curves(configurations: Sequence[Configuration]) -> Curves:
    """The per-episode Q-value curves of every training seed of configurations 3 and 4
    (each checkpoint's ``training.csv``; a checkpoint without one is left out)."""
    curves: Curves = {}
    for c in configurations:
        if c.key in (R1, R2):
            runs = [read_training(p.parent / "training.csv") for p in c.policy.checkpoints]
            curves[c.key] = [run for run in runs if run is not None]
    return curves


def read_training(path: Path) -> dict[str, np.ndarray] | None:
    """A run's training log: the Q-value columns by episode (None: no readable log)."""
    try:
        with path.open() as f:
            rows = list(csv.DictReader(f))
        return {k: np.array([float(r[k]) for r in rows]) for k in TRAINING_COLUMNS}
    except (OSError, KeyError, ValueError):
        return None


# ---- saved IK latencies ---------------------------------------------------------------


def save_latencies(latencies: dict[str, tuple[float, ...]], path: Path, command: str) -> None:
    """A measured study's IK latencies [s], by reach, gzip-compressed JSON (no name or
    time in the gzip header: the same latencies give the same bytes)."""
    document = {"format": LATENCIES_FORMAT, "command": command,
                "latencies": {k: list(v) for k, v in sorted(latencies.items())}}  # fmt: skip
    path.write_bytes(gzip.compress(json.dumps(document).encode(), mtime=0))


def load_latencies(path: Path) -> dict[str, tuple[float, ...]]:
    """Saved IK latencies (``save_latencies``); a file that is not one fails in one line."""
    try:
        document = json.loads(gzip.decompress(path.read_bytes()))
        if document.get("format") != LATENCIES_FORMAT:
            raise ValueError(f"format {document.get('format')!r}, expected {LATENCIES_FORMAT}")
        latencies = {str(k): tuple(float(x) for x in v)
                     for k, v in document["latencies"].items()}  # fmt: skip
    except (OSError, EOFError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise UsageError(f"{path} is not a study's saved IK latencies: {exc}") from None
    bad = [k for k, v in latencies.items() if not all(0.0 <= x < 60.0 for x in v)]
    if bad:
        raise UsageError(f"{path}: latencies outside 0-60 s for {bad[0]}")
    return latencies
