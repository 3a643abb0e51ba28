"""RL benchmarks: environment decisions per second, and the wall time of a training run.

python benchmarks/bench_rl.py [--decisions 2000] [--train-episodes 200]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from dammrl.rl.config import RewardWeights, TrainSettings
from dammrl.rl.env import ACTIONS, ReachEnv
from dammrl.rl.train import train
from dammrl.runner import ReachRunner


def decisions_per_second(n: int) -> float:
    env = ReachEnv(ReachRunner(), RewardWeights.preset(2), max_decisions=150)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    done, episode, start = 0, 0, time.perf_counter()
    while done < n:
        *_, terminated, truncated, _ = env.step(
            (rng.integers(ACTIONS[0]), rng.integers(ACTIONS[1]))
        )
        done += 1
        if terminated or truncated:
            episode += 1
            env.reset(seed=episode)
    return n / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--decisions", type=int, default=2000)
    parser.add_argument("--train-episodes", type=int, default=200)
    args = parser.parse_args()
    print(f"environment: {decisions_per_second(args.decisions):.0f} decisions/s (random actions)")
    for reward in (1, 2):
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            logs = train(reward, Path(out), TrainSettings(episodes=args.train_episodes),
                         "cpu", progress=lambda _: None)  # fmt: skip
            wall = time.perf_counter() - start
        decisions = sum(log.decisions for log in logs)
        rate = decisions / wall
        print(
            f"Reward {reward}: {args.train_episodes} episodes, {decisions} decisions, {wall:.0f} s"
        )
        print(f"    {rate:.0f} decisions/s with learning")


if __name__ == "__main__":
    main()
