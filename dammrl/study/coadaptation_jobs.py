"""The jobs of the co-adaptation comparison (``dammrl/study/coadaptation.py``): one reach of
a kind of person under a policy, a fixed option over seeds, an adaptive session, the
refinement on a first session and its gate; and the runner of jobs that keeps each
finished one (so a long comparison resumes). Nothing here judges a result.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import pickle
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from dammrl.learning.adapt import (
    Decision,
    Gate,
    PersonFit,
    RefineSettings,
    Transition,
    fit_person,
    gate,
    refine_transitions,
)
from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.env import ReachEnv
from dammrl.stack.runner import ReachResult, ReachRunner, evidence_of
from dammrl.study.run import map_jobs
from dammrl_core.coadaptation import Selection, Targets
from dammrl_core.human import HumanModel
from dammrl_core.model_table import BASE, Option
from dammrl_core.person import PersonFile, load_person
from dammrl_core.policy import FixedPolicy, Policy
from dammrl_core.policy.adaptive import AdaptivePolicy
from dammrl_core.policy.learned import LearnedPolicy, load_checkpoint

SESSION_REACHES = 25
"""Test reaches per session of the person (the first test session is their second)."""
HORIZON_S = 60.0
SHIPPED = Path("reward2")
RATING_STREAM = 2039


@dataclass(frozen=True)
class Kind:
    """A kind of person: its file's name, the person and the source of its numbers."""

    key: str
    name: str
    source: str
    human: HumanModel

    @classmethod
    def of(cls, path: Path) -> Kind:
        loaded: PersonFile = load_person(path)
        return cls(path.stem, loaded.name, loaded.source, HumanModel(person=loaded.person))


@dataclass(frozen=True)
class Row:
    """One reach of the comparison."""

    person: str
    arm: str  # 'search', 'oracle', 'shipped', 'adaptive', 'interpolated', 'refined'
    replicate: int
    seed: int
    index: int  # its place in the test seeds (the person's practice)
    option: Option  # the option in force (BASE: the shipped policy, or the adaptive base)
    success: bool
    t_total_s: float
    final_error_m: float
    comfort: float

    @property
    def restricted_s(self) -> float:
        """Time to success restricted at the horizon (a failure counts all of it)."""
        return self.t_total_s if self.success else HORIZON_S


def practice(index: int) -> tuple[int, int]:
    """(session, reach) of the person at test reach ``index`` (sessions from 2)."""
    return index // SESSION_REACHES + 2, index % SESSION_REACHES


# ---- one process's runner ----------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _runner() -> ReachRunner:
    return ReachRunner()


@functools.lru_cache(maxsize=2)
def _shipped() -> LearnedPolicy:
    return LearnedPolicy(_runner().settings.models, SHIPPED)


def _reach(kind: Kind, arm: str, seed: int, index: int, policy: Policy, option: Option,
           replicate: int = 0) -> tuple[Row, ReachResult]:  # fmt: skip
    result = _runner().run(seed, policy=policy, human=kind.human.practised(*practice(index)))
    steps = np.array([s.steps_m for s in result.steps]).reshape(-1, 3)
    rating = kind.human.person.comfort_rating(steps, np.random.default_rng([seed, RATING_STREAM]))
    m = result.metrics
    row = Row(kind.key, arm, replicate, seed, index, option, m.success, m.t_total_s,
              m.final_error_m, float(rating))  # fmt: skip
    return row, result


FixedJob = tuple[Kind, str, Option, tuple[int, ...], tuple[int, ...]]
"""kind, arm, option (BASE: the shipped policy), seeds, their indices."""


def fixed_job(job: FixedJob) -> list[Row]:
    kind, arm, option, seeds, indices = job
    runner = _runner()
    policy: Policy = _shipped() if option == BASE else FixedPolicy(runner.settings.models, *option)
    return [_reach(kind, arm, s, k, policy, option)[0] for s, k in zip(seeds, indices, strict=True)]


# ---- the adaptive session ----------------------------------------------------------------
@dataclass(frozen=True)
class Session:
    """The adaptive mode over the test seeds, the person's sessions in order."""

    kind: str
    replicate: int
    interpolate: bool
    rows: list[Row]
    switches: list[str]
    held: list[str]
    summary: dict[str, Any]


def adaptive_session(kind: Kind, seeds: Sequence[int], targets: Targets, replicate: int,
                     interpolate: bool = False) -> Session:  # fmt: skip
    """The adaptive mode around the shipped policy over ``seeds`` in order, the person's
    comfort rating of each reach handed to it with the reach."""
    models = _runner().settings.models
    selection = Selection(seed=replicate, interpolate=interpolate)
    policy = AdaptivePolicy.around(_shipped(), models, HumanModel(), targets, selection)
    arm = "interpolated" if interpolate else "adaptive"
    rows = []
    for index, seed in enumerate(seeds):
        row, result = _reach(kind, arm, seed, index, policy, policy.selected, replicate)
        policy.observe(evidence_of(result, models), rating=row.comfort)
        rows.append(row)
    summary = policy.posterior.summary(targets)
    return Session(kind.key, replicate, interpolate, rows, [s.line for s in policy.switches],
                   policy.held, summary)  # fmt: skip


def adaptive_job(job: tuple[Kind, tuple[int, ...], Targets, int, bool]) -> Session:
    return adaptive_session(*job)


# ---- the refined policy --------------------------------------------------------------------
@dataclass(frozen=True)
class RefinedRun:
    kind: str
    rows: list[Row]  # the candidate on the test seeds
    fit: PersonFit
    gate: Gate


def refined_run(kind: Kind, session_seeds: Sequence[int], test_seeds: Sequence[int],
                out: Path, settings: RefineSettings) -> RefinedRun:  # fmt: skip
    """The person's first session with the shipped policy, the refinement on it, its gate
    on the fitted person, and the candidate on the test seeds."""
    runner = _runner()
    checkpoint = load_checkpoint(SHIPPED)
    env = ReachEnv(runner, RewardWeights(**checkpoint["weights"]),
                   TrainSettings(**checkpoint["settings"]).max_decisions)  # fmt: skip
    transitions: list[Transition] = []
    decisions: list[Decision] = []
    for reach, seed in enumerate(session_seeds):
        transitions += _shipped_episode(env, seed, kind.human.practised(1, reach))
        episode = env.episode
        median = kind.human.decision_median_s
        decisions += [(c.human_model, d.correct, d.decision_s / median(c.human_model))
                      for d, c in zip(episode.decisions, episode.choices, strict=True)]  # fmt: skip
    fit = fit_person(decisions)
    candidate = refine_transitions(transitions, fit, SHIPPED, out, settings).out
    verdict = gate(candidate, SHIPPED, fit, settings, transitions)
    policy = LearnedPolicy(runner.settings.models, candidate)
    rows = [_reach(kind, "refined", s, k, policy, BASE)[0] for k, s in enumerate(test_seeds)]
    return RefinedRun(kind.key, rows, fit, verdict)


def _shipped_episode(env: ReachEnv, seed: int, human: HumanModel) -> list[Transition]:
    policy = _shipped()
    obs, _ = env.reset(seed=seed, human=human)
    policy.reset()
    out, done = [], False
    while not done:
        choice = policy.decide(env.episode.last_state.ee_pos, env.episode.task.goal)
        action = (choice.human_model - 1, choice.robot_model - 1)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        out.append(Transition(obs, action, reward, next_obs, done))
        obs = next_obs
    return out


def refined_job(job: tuple[Kind, tuple[int, ...], tuple[int, ...], Path, RefineSettings]
                 ) -> RefinedRun:  # fmt: skip
    return refined_run(*job)


J = TypeVar("J")
R = TypeVar("R")
REACHES = ("dammrl/stack/runner.py", "dammrl_core/person.py", "dammrl_core/human.py", "Kind", "Row",
           "practice", "_runner", "_shipped", "_reach")  # fmt: skip
SOURCES = {
    "fixed_job": (*REACHES, "fixed_job"),
    "refined_job": (*REACHES, "dammrl/learning/adapt.py", "refined_job", "refined_run",
                    "RefinedRun", "_shipped_episode"),
    "adaptive_job": (*REACHES, "dammrl_core/coadaptation.py", "dammrl_core/model_table.py",
                     "dammrl_core/policy/adaptive.py", "dammrl_core/policies/model_table.json.gz",
                     "adaptive_job", "adaptive_session", "Session"),
    "table_job": ("dammrl/stack/runner.py", "dammrl_core/person.py", "dammrl_core/human.py",
                  "dammrl/study/coadaptation_table.py"),
}  # fmt: skip
"""What a cached job's result depends on beyond the simulation itself (files, and the
functions and classes of this module): a change to any of them makes the job run again."""


@dataclass
class Jobs:
    """Runs jobs on ``workers`` processes, ticking the progress by each result's reaches,
    reusing a result kept in ``cache`` for the same job and the same code."""

    workers: int
    tick: Callable[[int], None]
    cache: Path | None

    def map(self, function: Callable[[J], R], jobs: Sequence[J],
            reaches: Callable[[R], int]) -> list[R]:  # fmt: skip
        keys = [self._key(function, job) for job in jobs]
        done: dict[int, R] = {}
        for k, key in enumerate(keys):
            if (kept := self._kept(key)) is not None:
                done[k] = kept
                self.tick(reaches(kept))
        todo = [k for k in range(len(jobs)) if k not in done]
        # one job at a time to a worker: each is kept as soon as it is done
        results = map_jobs(function, [jobs[k] for k in todo], self.workers, batch=1)
        for k, result in zip(todo, results, strict=True):
            done[k] = result
            self._keep(keys[k], result)
            self.tick(reaches(result))
        return [done[k] for k in range(len(jobs))]

    def _key(self, function: Callable[..., Any], job: Any) -> str:
        digest = hashlib.sha256(function.__name__.encode())
        digest.update(_code_digest(function).encode())
        digest.update(repr(_plain_job(job)).encode())
        return digest.hexdigest()[:32]

    def _kept(self, key: str) -> Any:
        if self.cache is None or not (self.cache / f"{key}.pickle").is_file():
            return None
        return pickle.loads((self.cache / f"{key}.pickle").read_bytes())  # our own files

    def _keep(self, key: str, result: Any) -> None:
        if self.cache is not None:
            self.cache.mkdir(parents=True, exist_ok=True)
            partial = self.cache / f"{key}.partial"
            partial.write_bytes(pickle.dumps(result))
            partial.replace(self.cache / f"{key}.pickle")


@functools.lru_cache(maxsize=4)
def _code_digest(function: Callable[..., Any]) -> str:
    """The digest of what ``function``'s results depend on (``SOURCES``; another
    function: its own source)."""
    root = Path(__file__).parents[2]
    if function.__name__ not in SOURCES:
        return hashlib.sha256(inspect.getsource(function).encode()).hexdigest()
    digest = hashlib.sha256()
    for name in SOURCES[function.__name__]:
        if "/" not in name:  # a function or class of this module
            digest.update(inspect.getsource(globals()[name]).encode())
            continue
        path = root / name
        digest.update(path.read_bytes() if path.is_file() else b"missing")
    return digest.hexdigest()


def _plain_job(job: Any) -> Any:
    """A job as plain values (a kind by its person's fields, paths as text)."""
    if isinstance(job, tuple):
        return tuple(_plain_job(v) for v in job)
    if isinstance(job, Kind):
        return (job.key, job.human.model_dump_json())
    if isinstance(job, RefineSettings | Targets):
        return job.model_dump_json()
    if isinstance(job, Path):
        return str(job)
    return job
