"""The same training with stable-baselines3's DQN, for comparison (benchmark-only extra).

SB3's DQN is single-agent: it gets the joint action (i, j) as one of 16 discrete actions,
on the same environment, reward and seeds; dammrl's dual-agent DQN runs beside it with the
same number of episodes. Prints wall time and greedy success on the same evaluation seeds.

    pip install -e '.[bench]'
    python benchmarks/bench_sb3.py [--reward 2] [--episodes 300] [--eval 50]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3 import DQN

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.env import ACTIONS, OBSERVATION_SIZE, ReachEnv
from dammrl.learning.rl.train import evaluate, train
from dammrl.stack.runner import ReachRunner, ReachSettings
from dammrl_core.task import HELD_OUT_START, held_out_seeds


class JointActionEnv(gym.Env):  # type: ignore[misc]
    """ReachEnv with the 2 x 8 actions flattened into Discrete(16)."""

    def __init__(self, reward: int, max_decisions: int, seed_base: int = 0,
                 randomize: bool = True) -> None:  # fmt: skip
        runner = ReachRunner(ReachSettings().randomized(randomize))  # as dammrl trains
        self.env = ReachEnv(runner, RewardWeights.preset(reward), max_decisions)  # type: ignore[arg-type]
        self.observation_space = gym.spaces.Box(-5.0, 5.0, (OBSERVATION_SIZE,), np.float32)
        self.action_space = gym.spaces.Discrete(ACTIONS[0] * ACTIONS[1])
        self.episode = 0
        self.seed_base = seed_base
        self.episodes_done = 0
        self.successes: list[bool] = []

    def reset(
        self, *, seed: int | None = None, options: Any = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        self.episode += 1
        return self.env.reset(seed=self.seed_base + self.episode - 1)

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(divmod(int(action), ACTIONS[1]))
        if terminated or truncated:
            self.episodes_done += 1
            self.successes.append(bool(info["metrics"].success))
        return obs, reward, terminated, truncated, {}


def sb3_success(model: DQN, reward: int, episodes: int) -> float:
    env = JointActionEnv(reward, TrainSettings().max_decisions, seed_base=HELD_OUT_START)
    wins = 0
    for _ in range(episodes):
        obs, _ = env.reset()
        while True:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, _ = env.step(int(action))
            if terminated or truncated:
                wins += env.successes[-1]
                break
    return wins / episodes


def sb3_model(reward: int, settings: TrainSettings, decisions: int) -> DQN:
    """SB3's DQN with dammrl's hyper-parameters on the joint-action environment."""
    env = JointActionEnv(reward, settings.max_decisions, randomize=settings.randomize)
    return DQN(
        "MlpPolicy", env, learning_rate=settings.learning_rate, buffer_size=settings.buffer_size,
        learning_starts=settings.learning_starts, batch_size=settings.batch_size,
        gamma=settings.gamma, train_freq=settings.train_every,
        target_update_interval=settings.target_update_every,
        exploration_fraction=min(1.0, settings.epsilon_decay_decisions / decisions),
        exploration_final_eps=settings.epsilon_end, max_grad_norm=settings.grad_clip,
        policy_kwargs={"net_arch": [settings.hidden, settings.hidden]}, seed=settings.seed,
        device="cpu",
    )  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reward", type=int, choices=[1, 2], default=2)
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--eval", type=int, default=50)
    args = parser.parse_args()
    settings = TrainSettings(episodes=args.episodes)

    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        logs = train(args.reward, Path(out), settings, "cpu", progress=lambda _: None)
        ours_s = time.perf_counter() - start
        decisions = sum(log.decisions for log in logs)
        ours = evaluate(Path(out), held_out_seeds(args.eval))["success_rate"]
    print(f"dammrl dual-agent DQN: {args.episodes} episodes ({decisions} decisions), "
          f"{ours_s:.0f} s, greedy success {ours:.0%} on {args.eval} unseen seeds")  # fmt: skip

    model = sb3_model(args.reward, settings, decisions)
    env = model.get_env().envs[0].unwrapped  # type: ignore[union-attr]
    start = time.perf_counter()
    model.learn(total_timesteps=decisions)
    sb3_s = time.perf_counter() - start
    print(f"stable-baselines3 DQN (joint action): {decisions} decisions "
          f"({env.episodes_done} episodes) in {sb3_s:.0f} s, greedy success "
          f"{sb3_success(model, args.reward, args.eval):.0%} on the same seeds")  # fmt: skip


if __name__ == "__main__":
    main()
