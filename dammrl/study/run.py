"""Run a study's reaches: one process, every core, or a Ray cluster, with the same result.

A reach is a pure function of (configuration, condition, seed): every random draw comes
from the seed's named streams. So the reaches can run anywhere, in any order, and the
records, sorted, are identical whichever executor ran them. A condition whose IK latencies
are measured is the exception until its latencies are saved: a job that carries them
replays them, and is pure again.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from dammrl.runner import ReachResult, ReachRunner, ReachSettings
from dammrl.study.claims import step_windows
from dammrl.study.configs import CONDITIONS, Condition, Configuration
from dammrl_core.errors import JobFailedError
from dammrl_core.metrics import decisions_until_stable, n_oscillations
from dammrl_core.policy import FixedPolicy, Policy, RandomPolicy
from dammrl_core.task import seed_streams

Progress = Callable[[int], None]  # called with the number of jobs just finished
J = TypeVar("J")
R = TypeVar("R")


@dataclass(frozen=True)
class Job:
    """One reach of a study."""

    configuration: Configuration
    seed: int
    condition: str = "nominal"  # a key of CONDITIONS
    index: int = 0  # the seed's position in the study: picks one of several checkpoints
    seed_set: int = 0  # which of the study's disjoint seed sets the seed belongs to
    ik_latencies: tuple[float, ...] | None = None  # a measured run's, replayed

    @property
    def latency_key(self) -> str:
        """Names the job's IK latencies in a study's saved latencies."""
        return f"{self.condition}/{self.configuration.key}/{self.seed}"


@dataclass(frozen=True)
class Record:
    """What a study keeps of one reach: a flat row of numbers, the decisions, and (a
    measured condition) the IK latencies that entered its simulated time."""

    row: dict[str, Any]
    steps: np.ndarray  # (n, 2) per micro-step: distance to the goal [m], mean step [m]
    ik_latencies: tuple[float, ...] | None = None


def run_job(job: Job) -> Record:
    """One reach, in whatever process this is (cores and policies built once per process)."""
    result = reach(job)
    tolerance = _runner(CONDITIONS[job.condition], job.configuration).settings.task.goal_tolerance_m
    measured = CONDITIONS[job.condition].measured
    latencies = tuple(result.ik_latencies_s) if measured else None
    return Record(_row(job, result, tolerance), _steps(result), latencies)


def reach(job: Job) -> ReachResult:
    """The reach of a job, whole (trajectory included)."""
    runner = _runner(CONDITIONS[job.condition], job.configuration)
    configuration = job.configuration
    return runner.run(job.seed, configuration.policy.model, configuration.trigger,
                      policy=_policy(runner, job), ik_latencies=job.ik_latencies)  # fmt: skip


_RUNNERS: dict[tuple[Any, ...], ReachRunner] = {}
_POLICIES: dict[str, Policy] = {}


def _runner(condition: Condition, configuration: Configuration) -> ReachRunner:
    controller_overrides = {**condition.controller, **configuration.controller}
    key = (condition.randomize, tuple(sorted(condition.randomization.items())),
           tuple(sorted(controller_overrides.items())))  # fmt: skip
    if key not in _RUNNERS:
        base = ReachSettings().randomized(condition.randomize)
        randomization = base.sim.randomization.model_copy(update=condition.randomization)
        sim = base.sim.model_copy(update={"randomization": randomization})
        controller = base.controller.model_copy(update=controller_overrides)
        settings = base.model_copy(update={"controller": controller, "sim": sim})
        _RUNNERS[key] = ReachRunner(settings)
    return _RUNNERS[key]


def _policy(runner: ReachRunner, job: Job) -> Policy:
    spec, models = job.configuration.policy, runner.settings.models
    if spec.kind == "fixed":
        return FixedPolicy(models, *spec.model)
    if spec.kind == "random":
        return RandomPolicy(models, seed_streams(job.seed).policy)
    checkpoint = spec.checkpoints[job.index % len(spec.checkpoints)]
    if str(checkpoint) not in _POLICIES:
        from dammrl_core.policy.learned import LearnedPolicy  # torch: only when needed

        _POLICIES[str(checkpoint)] = LearnedPolicy(models, checkpoint)
    return _POLICIES[str(checkpoint)]


def run_session(job: tuple[Configuration, tuple[int, ...], str]) -> list[Record]:
    """An adaptive configuration's reaches: its seeds in order as one session, the
    posterior over M_ij carried from reach to reach (one job: the order matters)."""
    from dammrl.runner import evidence_of
    from dammrl_core.policy.adaptive import AdaptivePolicy
    from dammrl_core.policy.learned import LearnedPolicy
    from dammrl_core.policy.settings import PolicySettings

    configuration, seeds, condition = job
    runner = _runner(CONDITIONS[condition], configuration)
    models = runner.settings.models
    base = LearnedPolicy(models, configuration.policy.checkpoints[0])
    settings = PolicySettings()
    policy = AdaptivePolicy.around(base, models, runner.settings.human, settings.targets,
                                   settings.selection)  # fmt: skip
    records, tolerance = [], runner.settings.task.goal_tolerance_m
    for index, seed in enumerate(seeds):
        result = runner.run(seed, trigger=configuration.trigger, policy=policy)
        policy.observe(evidence_of(result, models))
        reach_job = Job(configuration, seed, condition, index)
        records.append(Record(_row(reach_job, result, tolerance), _steps(result)))
    return records


def _row(job: Job, result: ReachResult, tolerance_m: float) -> dict[str, Any]:
    """The reach as a flat row; ``tolerance_m``: the paper's eps_g."""
    metrics = result.metrics.as_dict()
    human = [c.human_model for c in result.choices]
    robot = [c.robot_model for c in result.choices]
    n = len(result.choices)
    windows = step_windows(tolerance_m, float(np.linalg.norm(result.task.goal - result.task.start)))
    return {
        "configuration": job.configuration.key,
        "condition": job.condition,
        "seed_set": job.seed_set,
        "seed": job.seed,
        "randomize": CONDITIONS[job.condition].randomize,
        "run": _run_index(job),
        "model": f"{result.model[0]},{result.model[1]}",  # in force at the end
        **metrics,
        "t_success_s": metrics["t_total_s"] if metrics["success"] else None,
        "t_reached_s": _first_within(result, tolerance_m),
        "n_osc_true": _n_osc_true(result),
        "human_stable_after": decisions_until_stable(human),
        "robot_stable_after": decisions_until_stable(robot),
        "stable_share": 1 - decisions_until_stable(list(zip(human, robot, strict=True))) / n
        if n
        else None,
        "step_mean_m": _mean_step(result, 0.0, np.inf),
        "near_step_m": _mean_step(result, *windows["near"]),
        "mid_step_m": _mean_step(result, *windows["mid"]),
        "ik_latency_median_s": float(np.median(result.ik_latencies_s))
        if result.ik_latencies_s
        else None,
    }


def _run_index(job: Job) -> int:
    """Which of a learned configuration's training runs chose (0 for any other)."""
    checkpoints = job.configuration.policy.checkpoints
    return job.index % len(checkpoints) if job.configuration.policy.kind == "learned" else 0


def _first_within(result: ReachResult, tolerance_m: float) -> float | None:
    """When the measured end-effector first came within ``tolerance_m`` of the goal (the
    paper's success criterion), before the reach ended; None if it never did."""
    traj = result.trajectory
    kept = traj.t <= result.metrics.t_total_s + 1e-9
    within = np.linalg.norm(traj.x[kept] - result.task.goal, axis=1) <= tolerance_m
    return float(traj.t[kept][np.argmax(within)]) if within.any() else None


def _n_osc_true(result: ReachResult) -> int | None:
    """N_osc on the noise-free path (simulation's ground truth), beside N_osc on the
    measured one: how much of the count is motion."""
    traj = result.trajectory
    kept = traj.t <= result.metrics.t_total_s + 1e-9
    x = traj.x_true[kept]
    if len(x) == 0 or not np.all(np.isfinite(x)):
        return None
    subgoals = np.array([s.subgoal for s in result.steps]).reshape(-1, 3)
    radii = np.array([s.radius_m for s in result.steps])
    rate = 1.0 / float(traj.t[1] - traj.t[0]) if len(traj.t) > 1 else 1.0
    return n_oscillations(x, subgoals, radii, rate)


def _mean_step(result: ReachResult, nearest_m: float, farthest_m: float) -> float | None:
    """Mean step magnitude [m] of the steps planned at a goal distance in the range."""
    sizes = [s.steps_m.mean() for s in result.steps if nearest_m <= s.goal_error_m < farthest_m]
    return float(np.mean(sizes)) if sizes else None


def _steps(result: ReachResult) -> np.ndarray:
    rows = [(s.goal_error_m, float(s.steps_m.mean())) for s in result.steps]
    return np.array(rows, dtype=float).reshape(-1, 2)


def run_local(jobs: Sequence[Job], workers: int, progress: Progress | None = None) -> list[Record]:
    """Every job, on ``workers`` processes of this machine (1: in this process)."""
    return list(map_jobs(run_job, jobs, workers, None, progress))


def run_ray(
    jobs: Sequence[Job], address: str | None, progress: Progress | None = None
) -> list[Record]:
    """Every job on a Ray cluster (``address``; None or "local": a local Ray instance)."""
    return list(map_jobs(run_job, jobs, 1, address or "local", progress))


def map_jobs(
    function: Callable[[J], R],
    jobs: Sequence[J],
    workers: int,
    ray: str | None = None,
    progress: Progress | None = None,
    batch: int = 16,
) -> Iterator[R]:
    """``function`` of every job, as each finishes: on a Ray cluster when ``ray`` is an
    address ("local": a local instance), else on ``workers`` processes of this machine (1:
    in this process). Jobs must be pure: the results do not depend on where they ran."""
    if ray is not None:
        yield from _map_ray(function, jobs, ray, progress, batch)
    elif workers <= 1:
        for job in jobs:
            yield _tick(function(job), progress)
    else:
        yield from _map_processes(function, jobs, workers, progress, batch)


def _map_processes(function: Callable[[J], R], jobs: Sequence[J], workers: int,
                   progress: Progress | None, batch: int) -> Iterator[R]:  # fmt: skip
    chunk = max(1, min(batch, len(jobs) // (workers * 8)))
    # spawn, not fork: a forked child would inherit torch's and MuJoCo's thread state
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_quiet_worker) as pool:
        for result in pool.map(function, jobs, chunksize=chunk):
            yield _tick(result, progress)


def _quiet_worker() -> None:
    """One thread per worker process: the workers are the parallelism."""
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


def _tick(result: R, progress: Progress | None, n: int = 1) -> R:
    if progress is not None:
        progress(n)
    return result


def _map_ray(function: Callable[[J], R], jobs: Sequence[J], address: str,
             progress: Progress | None, batch: int) -> Iterator[R]:  # fmt: skip
    try:
        import ray
    except ImportError as exc:  # an optional dependency
        raise ImportError("--ray needs Ray: pip install 'dammrl[ray]'") from exc
    started = not ray.is_initialized()
    if started:
        where = None if address == "local" else address
        if where is not None:
            check_reachable(where)
        ray.init(address=where, include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {"OMP_NUM_THREADS": "1"}})  # fmt: skip
    try:
        remote: Any = ray.remote(num_cpus=1)(_run_batch)
        pending = [remote.remote(function, list(chunk)) for chunk in _batches(jobs, batch)]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            results = ray.get(done[0])
            if progress is not None:
                progress(len(results))
            yield from results
    finally:
        if started:
            ray.shutdown()


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in one line when a ``host:port`` Ray address does not answer (Ray itself
    would retry for minutes); other forms ("auto", none) are left to Ray."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout_s).close()
    except OSError as exc:
        raise JobFailedError(f"cannot reach the Ray cluster at {address}: {exc}") from None


def _run_batch(function: Callable[[J], R], jobs: list[J]) -> list[R]:
    return [function(job) for job in jobs]


def _batches(jobs: Sequence[J], size: int) -> Iterator[Sequence[J]]:
    for start in range(0, len(jobs), size):
        yield jobs[start : start + size]


def ordered(records: Iterable[Record]) -> list[Record]:
    """Records in one canonical order, whichever executor produced them."""
    return sorted(
        records,
        key=lambda r: (r.row["configuration"], r.row["condition"], r.row["seed"], r.row["model"]),
    )
