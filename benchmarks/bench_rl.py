"""RL throughput, side by side in one run: the environment on one core and on every core
against raw MuJoCo for the same simulated time, and training wall time against
stable-baselines3's DQN on the same environment (when the ``bench`` extra is installed).

    python benchmarks/bench_rl.py [--decisions 2000] [--train-episodes 200]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import mujoco
import numpy as np
from bench_core import RecordedPhysics

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.env import ACTIONS, ReachEnv
from dammrl.learning.rl.train import train
from dammrl.stack.runner import ReachRunner, ReachSettings


def environment(
    decisions: int, randomize: bool, seed: int = 0, fast_forward: bool = True,
    recorded: list[RecordedPhysics] | None = None,
) -> tuple[float, float, int]:  # fmt: skip
    """Random actions for ``decisions`` decisions: (processor time [s], simulated [s],
    physics steps). ``recorded``: tick every period and keep the physics there (see
    ``replayed_physics``)."""
    settings = ReachSettings(fast_forward=fast_forward and recorded is None)
    runner = ReachRunner(settings.randomized(randomize))
    if recorded is not None:
        recorded.append(RecordedPhysics(runner))
    env = ReachEnv(runner, RewardWeights.preset(2), max_decisions=150)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    episode, simulated = seed * 10_000, 0.0
    start = time.process_time()
    for _ in range(decisions):
        *_, terminated, truncated, _ = env.step(
            (rng.integers(ACTIONS[0]), rng.integers(ACTIONS[1]))
        )
        if terminated or truncated:
            simulated += runner.sim.data.time
            episode += 1
            env.reset(seed=episode)
    simulated += runner.sim.data.time
    spent = time.process_time() - start
    return spent, simulated, round(simulated / runner.sim.timestep_s)


def raw_physics(steps: int, randomize: bool) -> float:
    """Processor time of ``steps`` bare mj_step calls (10 per call, as the control loop) on
    the same model (randomised alike: joint friction adds constraints to solve): the
    ceiling for the environment."""
    runner = ReachRunner(ReachSettings().randomized(randomize))
    model, data = runner.sim.model, runner.sim.data
    start = runner.start_posture(runner.sample(0).start)
    runner.sim.reset(start, (0.5, 0.0), rng=np.random.default_rng(0))
    start = time.process_time()
    for _ in range(steps // 10):
        mujoco.mj_step(model, data, nstep=10)
    return time.process_time() - start


def replayed_physics(decisions: int, randomize: bool) -> tuple[float, int, bool]:
    """The same decisions' physics (the environment ticked every period, bit for bit the
    same episodes, every period's actuator inputs recorded) stepped again through bare
    mj_step: (processor time [s], physics steps, replayed bit for bit)."""
    recorded: list[RecordedPhysics] = []
    environment(decisions, randomize, recorded=recorded)
    return recorded[0].replay()


def _worker(args: tuple[int, bool, int]) -> tuple[float, float, int]:
    os.environ["OMP_NUM_THREADS"] = "1"
    return environment(*args)


def parallel_environment(decisions: int, workers: int) -> float:
    """Decisions per second of ``workers`` processes collecting at once (one env each)."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        list(pool.map(_worker, [(50, True, k) for k in range(workers)]))  # warm up
        start = time.perf_counter()
        list(pool.map(_worker, [(decisions, True, k + 1) for k in range(workers)]))
        return workers * decisions / (time.perf_counter() - start)


def training(episodes: int) -> tuple[float, int]:
    """dammrl's dual-agent DQN: (wall [s], decisions) for ``episodes`` episodes."""
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        logs = train(2, Path(out), TrainSettings(episodes=episodes), "cpu", progress=lambda _: None)
        return time.perf_counter() - start, sum(log.decisions for log in logs)


def sb3_training(decisions: int) -> float | None:
    """stable-baselines3's DQN with the same hyper-parameters for the same decisions."""
    try:
        from bench_sb3 import sb3_model  # the bench extra
    except ImportError:
        return None
    model = sb3_model(2, TrainSettings(), decisions)
    start = time.perf_counter()
    model.learn(total_timesteps=decisions)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--decisions", type=int, default=2000)
    parser.add_argument("--train-episodes", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=3, help="each timing, the best kept")
    parser.add_argument("--json", type=Path, help="write the figures here too")
    parser.add_argument("--no-training", action="store_true", help="the environment only")
    args = parser.parse_args()
    environment(100, True)  # warm up (imports, caches)
    figures: dict[str, float] = {}
    for randomize in (False, True):
        timings = []
        for _ in range(args.repeat):  # interleaved: the machine's load changes
            spent, simulated, steps = environment(args.decisions, randomize)
            # the same episodes, without the steps the shortcuts take past an episode's end
            replayed, _, bitwise = replayed_physics(args.decisions, randomize)
            timings.append((spent, raw_physics(steps, randomize), replayed, bitwise))
        spent, physics = min(t[0] for t in timings), min(t[1] for t in timings)
        replayed, bitwise = min(t[2] for t in timings), all(t[3] for t in timings)
        arm = "randomised" if randomize else "nominal"
        print(f"environment, 1 core, {arm} arm: {args.decisions / spent:.0f} decisions per "
              f"processor second ({simulated / spent:.0f}x real time); raw mj_step for the "
              f"same {simulated:.0f} s simulated: {args.decisions / physics:.0f} decisions/s "
              f"(environment at {physics / spent:.0%} of it; best of {args.repeat}); its own "
              f"physics replayed: {args.decisions / replayed:.0f} decisions/s (environment "
              f"at {replayed / spent:.0%} of it; {_bitwise(bitwise)})")  # fmt: skip
        figures[f"environment / raw mj_step, {arm}"] = physics / spent
        figures[f"environment / its physics replayed, {arm}"] = replayed / spent
        figures[f"replayed bit for bit, {arm}"] = bitwise
        figures[f"environment decisions/s, {arm}"] = args.decisions / spent
    if args.no_training:
        _write(args.json, figures)
        return
    cores = os.cpu_count() or 1
    started = time.perf_counter()  # wall time, as the processes' below
    environment(args.decisions, True, seed=1)
    one = args.decisions / (time.perf_counter() - started)
    many = parallel_environment(args.decisions, cores)
    print(f"environment, {cores} processes: {many:.0f} decisions/s in all "
          f"({many / one:.2f}x one core)")  # fmt: skip
    figures[f"environment, {cores} processes / 1"] = many / one
    training(2)  # warm: imports (TensorBoard, SciPy's filters) outside the timing, as SB3's
    wall, decisions = training(args.train_episodes)
    print(f"training (dammrl dual-agent DQN): {args.train_episodes} episodes, {decisions} "
          f"decisions in {wall:.1f} s ({decisions / wall:.0f}/s with learning)")  # fmt: skip
    sb3 = sb3_training(decisions)
    if sb3 is None:
        print("stable-baselines3: not installed (pip install -e '.[bench]')")
    else:
        print(f"training (stable-baselines3 DQN, joint action): {decisions} decisions in "
              f"{sb3:.1f} s; dammrl / sb3 wall time = {wall / sb3:.2f}")  # fmt: skip
        figures["training dammrl / sb3 wall time"] = wall / sb3
    _write(args.json, figures)


def _bitwise(same: bool) -> str:
    return "bit for bit" if same else "NOT bit for bit: the baseline is off"


def _write(path: Path | None, figures: dict[str, float]) -> None:
    if path is not None:
        path.write_text(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
