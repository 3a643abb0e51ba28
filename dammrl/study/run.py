"""Run a study's reaches: one process, every core, or a Ray cluster, with the same result.

A reach is a pure function of (configuration, condition, seed): every random draw comes
from the seed's named streams. So the reaches can run anywhere, in any order, and the
records, sorted, are identical whichever executor ran them. A condition whose IK latencies
are measured is the exception until its latencies are saved: a job that carries them
replays them, and is pure again.
"""

from __future__ import annotations

import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl.study.configs import CONDITIONS, Condition, Configuration
from dammrl.study.rows import reach_row, steps_of
from dammrl_core.errors import JobFailedError
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
    condition that times each solve) the IK latencies that entered its simulated time."""

    row: dict[str, Any]
    steps: np.ndarray  # (n, 2) per micro-step: distance to the goal [m], mean step [m]
    ik_latencies: tuple[float, ...] | None = None


def run_job(job: Job) -> Record:
    """One reach, in whatever process this is (cores and policies built once per process)."""
    result = reach(job)
    tolerance = _runner(CONDITIONS[job.condition], job.configuration).settings.task.goal_tolerance_m
    timed = CONDITIONS[job.condition].solves_timed  # each solve's own time: kept
    latencies = tuple(result.ik_latencies_s) if timed else None
    return Record(reach_row(result, identity(job), job.configuration.policy.runs, tolerance),
                  steps_of(result), latencies)  # fmt: skip


def identity(job: Job) -> dict[str, Any]:
    """What names a reach in a study's rows."""
    return {
        "configuration": job.configuration.key,
        "condition": job.condition,
        "seed_set": job.seed_set,
        "seed": job.seed,
        "randomize": CONDITIONS[job.condition].randomize,
        "run": _run_index(job),
    }


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
    from dammrl.stack.runner import evidence_of
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
        row = reach_row(result, identity(reach_job), 0, tolerance)  # one adapting policy
        records.append(Record(row, steps_of(result)))
    return records


def _run_index(job: Job) -> int:
    """Which of a learned configuration's training runs chose (0 for any other)."""
    checkpoints = job.configuration.policy.checkpoints
    return job.index % len(checkpoints) if job.configuration.policy.kind == "learned" else 0


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
    in_order: bool = True,
) -> Iterator[R]:
    """``function`` of every job, in the jobs' order (``in_order=False``: as each batch
    finishes): on a Ray cluster when ``ray`` is an address ("local": a local instance),
    else on ``workers`` processes of this machine (1: in this process). ``progress`` hears
    of each batch as it finishes. Jobs must be pure: the results do not depend on where
    they ran. A ``kill`` (SIGTERM) or Ctrl-C ends every worker before this process ends;
    a worker whose parent died ends itself."""
    if ray is not None:
        yield from _map_ray(function, jobs, ray, progress, batch, in_order)
    elif workers <= 1:
        for job in jobs:
            yield _tick(function(job), progress)
    else:
        yield from _map_processes(function, jobs, workers, progress, batch, in_order)


def _map_processes(
    function: Callable[[J], R],
    jobs: Sequence[J],
    workers: int,
    progress: Progress | None,
    batch: int,
    in_order: bool,
) -> Iterator[R]:
    # batches small enough that progress moves (a first estimate from one batch of 16 slow
    # reaches was hours off), large enough that a reach's process start-up is amortised
    size = max(1, min(batch, len(jobs) // (workers * 16)))
    # spawn, not fork: a forked child would inherit torch's and MuJoCo's thread state
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_start,
                               initargs=(os.getpid(),))  # fmt: skip
    try:
        with _terminate_raises():
            futures = {pool.submit(_run_batch, function, list(chunk)): k
                       for k, chunk in enumerate(_batches(jobs, size))}  # fmt: skip
            yield from _collect(futures, lambda f: f.result(), _wait_first, progress, in_order)
    except BaseException:  # a kill, Ctrl-C, a failed job, or the caller stopped early
        _end_workers(pool)
        raise
    pool.shutdown(wait=True)


def _wait_first(pending: set[Any]) -> tuple[set[Any], set[Any]]:
    done, left = wait(pending, return_when=FIRST_COMPLETED)
    return set(done), set(left)


def _collect(
    futures: dict[Any, int],
    result: Callable[[Any], list[R]],
    wait_first: Callable[[set[Any]], tuple[set[Any], set[Any]]],
    progress: Progress | None,
    in_order: bool,
) -> Iterator[R]:
    """The batches' results in their order (or as they finish), each batch's progress told
    when it finishes."""
    finished: dict[int, list[R]] = {}
    pending, next_batch = set(futures), 0
    while pending:
        done, pending = wait_first(pending)
        for future in done:
            finished[futures[future]] = results = result(future)
            if progress is not None:
                progress(len(results))
            if not in_order:
                yield from finished.pop(futures[future])
        while next_batch in finished:
            yield from finished.pop(next_batch)
            next_batch += 1


@contextmanager
def _terminate_raises() -> Iterator[None]:
    """A ``kill`` (SIGTERM) raises SystemExit in the main thread while workers run, so they
    are ended first: its default action would end this process alone and leave them
    running, adopted by init."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _end_workers(pool: ProcessPoolExecutor) -> None:
    """Terminate every worker now, running jobs included (shutdown alone waits for them)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())  # the pool's own
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=5)
        if process.is_alive():
            process.kill()
    pool.shutdown(wait=False, cancel_futures=True)


def _worker_start(parent: int) -> None:
    """A worker: one thread (the workers are the parallelism), Ctrl-C left to the parent
    (the terminal sends it to the whole group; the parent ends the workers), and ended with
    its parent however that ends (kill -9 included)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _end_with_parent(parent)
    os.environ["OMP_NUM_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)


def _end_with_parent(parent: int) -> None:
    if sys.platform == "linux":
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    else:  # no parent-death signal: watch for being adopted

        def watch() -> None:
            while os.getppid() == parent:
                time.sleep(1.0)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent:  # the parent died before the signal was asked for
        os._exit(1)


def _tick(result: R, progress: Progress | None, n: int = 1) -> R:
    if progress is not None:
        progress(n)
    return result


def _map_ray(function: Callable[[J], R], jobs: Sequence[J], address: str,
             progress: Progress | None, batch: int, in_order: bool) -> Iterator[R]:  # fmt: skip
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
        futures = {remote.remote(function, list(chunk)): k
                   for k, chunk in enumerate(_batches(jobs, batch))}  # fmt: skip

        def wait_first(pending: set[Any]) -> tuple[set[Any], set[Any]]:
            done, left = ray.wait(list(pending), num_returns=1)
            return set(done), set(left)

        yield from _collect(futures, ray.get, wait_first, progress, in_order)
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
