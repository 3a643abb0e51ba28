"""One study: find the best fixed models on tuning seeds (the shipped search when it was
made with these settings), run every configuration under every condition on K disjoint
sets of evaluation seeds, judge the claims on each set and on all of them, under both
success criteria, and under the paper's criterion at every eps_g of the range."""

from __future__ import annotations

import gzip
import hashlib
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from dammrl.study.claims import (
    CRITERIA,
    EPS_G_RANGE_MM,
    Claim,
    Criterion,
    Curves,
    Stability,
    judge,
    stability,
)
from dammrl.study.configs import (
    CONDITIONS,
    DEFAULT_CONDITIONS,
    PAPER_KEYS,
    R1,
    R2,
    Configuration,
    adaptive_configuration,
    best_fixed_candidates,
    paper_configurations,
    reviewer_configurations,
    variant_configurations,
)
from dammrl.study.rows import read_training
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
SEARCHES_FORMAT = 1
SHIPPED_SEARCHES = Path(__file__).with_name("best_fixed.json")  # searches made, by settings
Verdicts = dict[tuple[str, Criterion, int | None], list[Claim]]  # (condition, criterion, set)
Sensitivity = dict[tuple[str, int], list[Claim]]  # (condition, eps_g mm): eps_g, every seed


@dataclass(frozen=True)
class StudyOptions:
    seeds: range  # every evaluation seed; split into ``sets`` disjoint sets in order
    sets: int = 1
    conditions: tuple[str, ...] = DEFAULT_CONDITIONS
    tuning_seeds: range | None = None  # None: a shipped search made with these settings,
    # else one on as many tuning seeds as evaluation seeds (at most 20)
    reward1: tuple[Path, ...] = ()
    reward2: tuple[Path, ...] = ()
    workers: int = 1
    ray: str | None = None  # a Ray address ("local": a local instance); None: this machine
    recording: Path | None = None  # a semi-virtual session (MCAP): its figure in the report
    adaptive: bool = False  # also configuration 4 inside the adaptive mode (sessions)
    rows: Literal["all", "paper"] = "all"  # "paper": configurations 1-4 only (every verdict)
    ik_latencies: dict[str, tuple[float, ...]] | None = None  # a measured study's, replayed

    @property
    def search_seeds(self) -> range:
        """The tuning seeds of a search this study would make."""
        if self.tuning_seeds is not None:
            return self.tuning_seeds
        return range(TUNING_START, TUNING_START + min(len(TUNING_SEEDS), len(self.seeds)))

    def check(self) -> None:
        overlap = set(self.seeds) & set(TUNING_SEEDS if self.tuning_seeds is None
                                        else self.tuning_seeds)  # fmt: skip
        if overlap:
            tuning = self.search_seeds if self.tuning_seeds is not None else TUNING_SEEDS
            raise ConfigurationError(
                f"evaluation seeds overlap the tuning seeds of the best-fixed search "
                f"({min(overlap):,}...): choose seeds outside {tuning.start:,}-"
                f"{tuning.stop - 1:,}"
            )
        if not 1 <= self.sets <= len(self.seeds):
            raise UsageError(f"{self.sets} seed sets need at least {self.sets} seeds, got "
                             f"{len(self.seeds)}")  # fmt: skip
        unknown = [c for c in self.conditions if c not in CONDITIONS]
        if unknown or not self.conditions:
            raise UsageError(f"unknown condition {', '.join(unknown) or '(none)'}: choose from "
                             f"{', '.join(CONDITIONS)}")  # fmt: skip
        runs = [c.policy.runs for c in paper_configurations(self.reward1, self.reward2)[2:4]]
        if min(runs) > 1 and runs[0] != runs[1]:
            raise UsageError(f"{runs[0]} Reward 1 runs and {runs[1]} Reward 2 runs: the claims "
                             "compare run k of each, so give as many of each")  # fmt: skip

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
    sensitivity: Sensitivity = field(default_factory=dict)  # eps_g over its range
    search: Search | None = None  # the best-fixed search used (shipped or made)

    @property
    def rows(self) -> list[dict[str, Any]]:
        return [r.row for r in self.records]

    def claims(self, condition: str, criterion: Criterion = "press",
               seed_set: int | None = None) -> list[Claim]:  # fmt: skip
        return self.verdicts[(condition, criterion, seed_set)]

    def stability(self, condition: str, criterion: Criterion, index: int) -> Stability:
        """Claim ``index`` on each disjoint seed set: stable when every check agrees."""
        return stability([self.claims(condition, criterion, k)[index]
                          for k in range(self.options.sets)])  # fmt: skip

    def stable(self, condition: str, criterion: Criterion, index: int) -> bool:
        return self.stability(condition, criterion, index).stable

    @property
    def latencies(self) -> dict[str, tuple[float, ...]]:
        """The IK latencies of every reach of a condition measured on this computer (to
        save and replay; the reference machine's are the same on any)."""
        measured = [r for r in self.records if CONDITIONS[r.row["condition"]].measured]
        return {_latency_key(r.row): r.ik_latencies for r in measured
                if r.ik_latencies is not None}  # fmt: skip


def run_study(options: StudyOptions, progress: Callable[[int, str], Progress],
              searches_in: Sequence[Path] = ()) -> StudyResult:  # fmt: skip
    """The whole study; ``progress(total, description)`` makes a progress callback;
    ``searches_in``: files of earlier best-fixed searches to reuse beside the shipped one."""
    options.check()

    def execute(jobs: Sequence[Job], description: str) -> list[Record]:
        tick = progress(len(jobs), description)
        shuffled = shuffle(jobs)  # early progress stands for the whole, not one configuration
        if options.ray is not None:
            return ordered(run_ray(shuffled, options.ray, tick))
        return ordered(run_local(shuffled, options.workers, tick))

    wall: dict[str, float] = {}
    paper = paper_configurations(options.reward1, options.reward2)
    search, configurations = None, [c for c in paper if c.key in PAPER_KEYS]
    if options.rows == "all":
        start = time.perf_counter()
        search = shipped_search(options, (SHIPPED_SEARCHES, *searches_in))
        if search is None:
            search = search_best_fixed(options, execute)
            wall["best-fixed search"] = time.perf_counter() - start
        configurations = [
            *paper,
            *variant_configurations(),
            *reviewer_configurations(),
            *(c for c in best_fixed_candidates() if search.best.get(c.key) == c.policy.model),
        ]
    best = search.best if search is not None else {}
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
    sensitivity: Sensitivity = {}
    for condition in options.conditions:
        rows = [r.row for r in records if r.row["condition"] == condition]
        for criterion in CRITERIA:
            for seed_set in (None, *range(options.sets)):
                chosen = [r for r in rows if seed_set is None or r["seed_set"] == seed_set]
                verdicts[(condition, criterion, seed_set)] = judge(chosen, criterion, training)
        for eps_mm in EPS_G_RANGE_MM:
            sensitivity[(condition, eps_mm)] = judge(rows, "eps_g", training, eps_mm)
    return StudyResult(options, configurations, records, best, verdicts, wall, sensitivity,
                       search)  # fmt: skip


def shuffle(jobs: Sequence[Job]) -> list[Job]:
    """The jobs in a fixed pseudo-random order (the results are sorted afterwards)."""
    order = np.random.default_rng(len(jobs)).permutation(len(jobs))
    return [jobs[k] for k in order]


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
    for session in map_jobs(run_session, sessions, options.workers):  # in the sessions' order
        records += session
        tick(len(session))  # in reaches, as every other bar, a session at a time
    first = {seed: i for i, seed in enumerate(options.seeds)}
    for record in records:
        record.row["seed_set"] = options.seed_set(first[record.row["seed"]])
    return records


@dataclass(frozen=True)
class Search:
    """A best-fixed search: the M_ij with the highest success (then the shortest time)
    under each progression, on tuning seeds on the nominal arm."""

    fingerprint: str  # the settings and candidates it was made with
    tuning_seeds: range
    best: dict[str, tuple[int, int]]
    shipped: bool = False  # read from the package (or an earlier run), not made now

    def to_json(self) -> dict[str, Any]:
        return {"fingerprint": self.fingerprint,
                "tuning_seeds": [self.tuning_seeds.start, self.tuning_seeds.stop],
                "best": {k: list(v) for k, v in sorted(self.best.items())}}  # fmt: skip


def search_fingerprint(tuning_seeds: range) -> str:
    """What decides a search's result besides the code: every default setting of a reach
    (the model set, arm, controller, human, task; DAMMRL_* overrides included), the
    candidates and the tuning seeds."""
    from dammrl.stack.runner import ReachSettings

    settings = ReachSettings().model_dump(mode="json")
    # the arm by its description's content, not by where this checkout keeps the file
    urdf = Path(settings["robot"].pop("urdf_path"))
    settings["robot"]["urdf_sha256"] = hashlib.sha256(urdf.read_bytes()).hexdigest()
    document = {
        "settings": settings,
        "candidates": [[c.key, c.trigger, c.controller, list(c.policy.model)]
                       for c in best_fixed_candidates()],
        "tuning_seeds": [tuning_seeds.start, tuning_seeds.stop],
    }  # fmt: skip
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


def shipped_search(options: StudyOptions, places: Sequence[Path] = (SHIPPED_SEARCHES,)
                   ) -> Search | None:  # fmt: skip
    """A search already made with these settings on the tuning seeds asked (default: the
    shipped 20, else those a search would use now), or None."""
    wanted = [search_fingerprint(options.tuning_seeds or TUNING_SEEDS),
              search_fingerprint(options.search_seeds)]  # fmt: skip
    for fingerprint in wanted:
        for place in places:
            for entry in load_searches(place):
                if entry.fingerprint == fingerprint:
                    return Search(entry.fingerprint, entry.tuning_seeds, entry.best, True)
    return None


def load_searches(path: Path) -> list[Search]:
    """The searches saved in ``path`` (none when it is missing); a file that is not one
    fails in one line."""
    if not path.exists():
        return []
    try:
        document = json.loads(path.read_text())
        if document.get("format") != SEARCHES_FORMAT:
            raise ValueError(f"format {document.get('format')!r}, expected {SEARCHES_FORMAT}")
        return [Search(e["fingerprint"], range(*e["tuning_seeds"]),
                       {k: (int(v[0]), int(v[1])) for k, v in e["best"].items()})
                for e in document["searches"]]  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise UsageError(f"{path} is not a file of best-fixed searches: {exc}") from None


def save_search(search: Search, path: Path) -> None:
    """Add ``search`` to the searches in ``path`` (replacing one with its fingerprint)."""
    kept = [s for s in load_searches(path) if s.fingerprint != search.fingerprint]
    document = {"format": SEARCHES_FORMAT,
                "searches": [s.to_json() for s in (*kept, search)]}  # fmt: skip
    path.write_text(json.dumps(document, indent=1) + "\n")


def search_best_fixed(
    options: StudyOptions, execute: Callable[[Sequence[Job], str], list[Record]]
) -> Search:
    """The M_ij with the highest success (then the shortest time) under each progression,
    on the tuning seeds on the nominal arm."""
    candidates = best_fixed_candidates()
    tuning = options.search_seeds
    jobs = [Job(c, s, "nominal", k) for c in candidates for k, s in enumerate(tuning)]
    scores: dict[tuple[str, tuple[int, int]], list[dict[str, Any]]] = {}
    for record in execute(jobs, f"best-fixed search ({len(tuning)} tuning seeds)"):
        i, j = (int(v) for v in record.row["model"].split(","))
        scores.setdefault((record.row["configuration"], (i, j)), []).append(record.row)
    best: dict[str, tuple[int, int]] = {}
    for key in sorted({c.key for c in candidates}):
        ranked = sorted(
            ((model, rows) for (k, model), rows in scores.items() if k == key),
            key=lambda item: (-np.mean([r["success"] for r in item[1]]),
                              np.mean([r["t_total_s"] for r in item[1]])),
        )  # fmt: skip
        best[key] = ranked[0][0]
    return Search(search_fingerprint(tuning), tuning, best)


# ---- training curves (C6) -----------------------------------------------------------


def training_curves(configurations: Sequence[Configuration]) -> Curves:
    """The per-episode Q-value curves of every training seed of configurations 3 and 4
    (each checkpoint's ``training.csv``; a checkpoint without one is left out)."""
    curves: Curves = {}
    for c in configurations:
        if c.key in (R1, R2):
            runs = [read_training(p.parent / "training.csv") for p in c.policy.checkpoints]
            curves[c.key] = [run for run in runs if run is not None]
    return curves


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
