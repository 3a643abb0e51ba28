"""``dammrl train`` and ``dammrl evaluate``: the dual-agent DQN on the reach environment.

A run directory holds ``checkpoint.pt`` (networks, optimiser, counters and the settings
that produced them; training resumes from it), ``training.csv`` (one row per episode),
``training.png`` (returns, success rate, Q-values and losses of both agents) and
``tensorboard/`` (``tensorboard --logdir DIR``).
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter

from dammrl.learning.rl.config import RewardWeights, TrainSettings
from dammrl.learning.rl.dqn import DualAgentDQN, ReplayBuffer, UpdateStats
from dammrl.learning.rl.env import ACTIONS, OBSERVATION_SIZE, ReachEnv
from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl_core.errors import DammrlError
from dammrl_core.policy.learned import (
    CHECKPOINT,
    FORMAT,
    CheckpointError,
    LearnedPolicy,
    load_checkpoint,
)
from dammrl_core.task import training_seed

__all__ = ["CheckpointError", "evaluate", "load_checkpoint", "train"]


@dataclass
class EpisodeLog:
    episode: int
    ret: float
    success: bool
    decisions: int
    epsilon: float
    t_total_s: float
    loss_human: float
    loss_robot: float
    q_human: float
    q_robot: float
    small_steps: float  # share of decisions with the all-small step vector (j = 1)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise DammrlError("--device cuda: no CUDA device is available here")
    return torch.device(name)


def epsilon_at(decisions: int, s: TrainSettings) -> float:
    fraction = min(1.0, decisions / s.epsilon_decay_decisions)
    return s.epsilon_start + fraction * (s.epsilon_end - s.epsilon_start)


def train(
    reward: Literal[1, 2],
    out: Path,
    settings: TrainSettings,
    device: str = "auto",
    progress: Callable[[list[EpisodeLog]], None] | None = None,
    weights: RewardWeights | None = None,
) -> list[EpisodeLog]:
    """Train (or resume) both agents; return the per-episode log. ``progress`` is called
    with the log after every episode; ``weights`` (default: the ``reward`` preset) sets the
    reward's terms, e.g. another time weight beta."""
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(settings.seed)
    torch.set_num_threads(1)  # small networks: threads only contend with the simulation
    rng = np.random.default_rng(settings.seed)
    weights = weights or RewardWeights.preset(reward)
    runner = ReachRunner(ReachSettings().randomized(settings.randomize))
    env = ReachEnv(runner, weights, settings.max_decisions)
    agent = DualAgentDQN(OBSERVATION_SIZE, ACTIONS, settings, pick_device(device))
    buffer = ReplayBuffer(settings.buffer_size, OBSERVATION_SIZE, settings.seed)
    logs, decisions = _resume(out, agent, reward, settings)
    board = SummaryWriter(str(out / "tensorboard"), purge_step=len(logs) + 1)
    for episode in range(len(logs), settings.episodes):
        log, decisions = _run_episode(env, agent, buffer, rng, episode, decisions, settings)
        logs.append(log)
        _to_tensorboard(board, log)
        if progress is not None:
            progress(logs)
        if (episode + 1) % 50 == 0 or episode + 1 == settings.episodes:
            save(out, agent, reward, weights, settings, logs, decisions)
    board.close()
    plot_training(logs, out / "training.png", reward)
    return logs


def _to_tensorboard(board: SummaryWriter, log: EpisodeLog) -> None:
    """The per-episode figures, under the names of the curves in training.png."""
    for name, value in asdict(log).items():
        if name != "episode" and np.isfinite(float(value)):
            board.add_scalar(f"train/{name}", float(value), log.episode)


def _run_episode(
    env: ReachEnv,
    agent: DualAgentDQN,
    buffer: ReplayBuffer,
    rng: np.random.Generator,
    episode: int,
    decisions: int,
    s: TrainSettings,
) -> tuple[EpisodeLog, int]:
    obs, _ = env.reset(seed=training_seed(s.seed, episode))
    total, stats, small, n = 0.0, [], 0, 0
    while True:
        epsilon = epsilon_at(decisions, s)
        action = agent.act(obs, epsilon, rng)
        next_obs, reward, terminated, truncated, info = env.step(action)
        buffer.add(obs, action, reward, next_obs, terminated)
        obs, total, decisions, n = next_obs, total + reward, decisions + 1, n + 1
        small += action[1] == 0
        if buffer.size >= max(s.learning_starts, s.batch_size) and decisions % s.train_every == 0:
            stats.append(agent.update(buffer.sample(s.batch_size)))
        if terminated or truncated:
            metrics = info["metrics"]
            break
    mean = _mean_stats(stats)
    return EpisodeLog(episode + 1, total, metrics.success, n, epsilon, metrics.t_total_s,
                      mean.loss_human, mean.loss_robot, mean.q_human, mean.q_robot,
                      small / n), decisions  # fmt: skip


def _mean_stats(stats: list[UpdateStats]) -> UpdateStats:
    if not stats:
        return UpdateStats(float("nan"), float("nan"), float("nan"), float("nan"))
    return UpdateStats(*(float(np.mean([getattr(s, f) for s in stats])) for f in
                         ("loss_human", "loss_robot", "q_human", "q_robot")))  # fmt: skip


def progress_summary(logs: list[EpisodeLog]) -> str:
    """The last 50 episodes in one short line (return, success, epsilon, Q of both agents)."""
    recent, last = logs[-50:], logs[-1]
    return (
        f"return {np.mean([r.ret for r in recent]):.2f}, "
        f"success {np.mean([r.success for r in recent]):.0%}, epsilon {last.epsilon:.2f}, "
        f"Q {last.q_human:.2f}/{last.q_robot:.2f}"
    )


def save(out: Path, agent: DualAgentDQN, reward: Literal[1, 2], weights: RewardWeights,
         settings: TrainSettings, logs: list[EpisodeLog], decisions: int) -> None:  # fmt: skip
    checkpoint = {
        "format": FORMAT, "reward": reward, "weights": weights.model_dump(),
        "settings": settings.model_dump(), "agent": agent.state_dict(), "decisions": decisions,
        "observation_size": OBSERVATION_SIZE, "actions": ACTIONS,
    }  # fmt: skip
    torch.save(checkpoint, out / CHECKPOINT)
    with open(out / "training.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, list(asdict(logs[0])))
        writer.writeheader()
        writer.writerows(asdict(log) for log in logs)
    (out / "settings.json").write_text(json.dumps(checkpoint["settings"], indent=2))


def _resume(out: Path, agent: DualAgentDQN, reward: int, settings: TrainSettings
            ) -> tuple[list[EpisodeLog], int]:  # fmt: skip
    if not (out / CHECKPOINT).exists():
        return [], 0
    checkpoint = load_checkpoint(out)
    if checkpoint["reward"] != reward:
        raise CheckpointError(
            f"{out} holds a Reward {checkpoint['reward']} run, not Reward {reward}"
        )
    agent.load_state_dict(checkpoint["agent"])
    with open(out / "training.csv") as handle:
        logs = [EpisodeLog(**_typed(row)) for row in csv.DictReader(handle)]
    return logs, int(checkpoint["decisions"])


def _typed(row: dict[str, str]) -> dict[str, Any]:
    types = {f: t for f, t in EpisodeLog.__annotations__.items()}
    return {k: (v == "True" if types[k] == "bool" else int(v) if types[k] == "int" else float(v))
            for k, v in row.items()}  # fmt: skip


@dataclass(frozen=True)
class Rollout:
    """One greedy episode: its metrics and, per decision, (distance to goal [m], i, j)."""

    metrics: Any
    decisions: list[tuple[float, int, int]]


def greedy_rollouts(run: Path, seeds: range, randomize: bool = False,
                    done: Callable[[], None] | None = None) -> list[Rollout]:  # fmt: skip
    """The run's greedy policy on ``seeds`` (held out from training), stochastic human,
    on the nominal arm or on randomised ones; ``done`` is called after each reach."""
    checkpoint = load_checkpoint(run)
    settings = TrainSettings(**checkpoint["settings"])
    runner = ReachRunner(ReachSettings().randomized(randomize))
    policy = LearnedPolicy(runner.settings.models, run)
    env = ReachEnv(runner, RewardWeights(**checkpoint["weights"]), settings.max_decisions)
    rollouts = []
    for seed in seeds:
        env.reset(seed=seed)
        policy.reset()
        decisions = []
        while True:
            x, goal = env.episode.last_state.ee_pos, env.episode.task.goal
            choice = policy.decide(x, goal)
            i, j = choice.human_model, choice.robot_model
            decisions.append((float(np.linalg.norm(x - goal)), i, j))
            _, _, terminated, truncated, info = env.step((i - 1, j - 1))
            if terminated or truncated:
                break
        rollouts.append(Rollout(info["metrics"], decisions))
        if done is not None:
            done()
    return rollouts


def adaptive_rollouts(run: Path, seeds: range, randomize: bool = False,
                      done: Callable[[], None] | None = None
                      ) -> tuple[list[Rollout], list[str]]:  # fmt: skip
    """The run's greedy policy inside the adaptive mode (``DAMMRL_POLICY_TARGETS__*``):
    ``seeds`` in order as one session of one simulated person, the posterior over M_ij
    carried from reach to reach; the rollouts and every switch."""
    from dammrl.stack.runner import evidence_of
    from dammrl_core.policy.adaptive import AdaptivePolicy
    from dammrl_core.policy.settings import PolicySettings

    runner = ReachRunner(ReachSettings().randomized(randomize))
    models = runner.settings.models
    settings = PolicySettings()
    policy = AdaptivePolicy.around(LearnedPolicy(models, run), models, runner.settings.human,
                                   settings.targets, settings.selection)  # fmt: skip
    rollouts = []
    for seed in seeds:
        result = runner.run(seed, policy=policy)
        policy.observe(evidence_of(result, models))
        rollouts.append(Rollout(result.metrics, _decisions(result)))
        if done is not None:
            done()
    return rollouts, [s.line for s in policy.switches]


def _decisions(result: ReachResult) -> list[tuple[float, int, int]]:
    """(distance to the goal when asked [m], i, j) of each decision of a reach."""
    traj = result.trajectory
    out = []
    for d, c in zip(result.decisions, result.choices, strict=True):
        row = min(int(np.searchsorted(traj.t, d.intent.t_s - d.decision_s - 1e-9)), len(traj.t) - 1)
        distance = float(np.linalg.norm(traj.x[row] - result.task.goal))
        out.append((distance, c.human_model, c.robot_model))
    return out


def evaluate(
    run: Path,
    seeds: range,
    randomize: bool = False,
    done: Callable[[], None] | None = None,
    adaptive: bool = False,
) -> dict[str, Any]:
    """Summary of :func:`greedy_rollouts` (the ``dammrl evaluate`` JSON); ``adaptive``: of
    :func:`adaptive_rollouts`, with its switches."""
    switches: list[str] = []
    if adaptive:
        rollouts, switches = adaptive_rollouts(run, seeds, randomize, done)
    else:
        rollouts = greedy_rollouts(run, seeds, randomize, done)
    metrics = [r.metrics for r in rollouts]
    choices = [d for r in rollouts for d in r.decisions]
    return {
        "checkpoint": str(run), "reward": load_checkpoint(run)["reward"],
        "episodes": len(seeds), "seeds": f"{seeds.start}:{seeds.stop}", "randomize": randomize,
        "success_rate": float(np.mean([m.success for m in metrics])),
        "t_total_s": float(np.mean([m.t_total_s for m in metrics])),
        "final_error_m": float(np.mean([m.final_error_m for m in metrics])),
        "n_osc": float(np.mean([m.n_osc for m in metrics])),
        "share_e_small": float(np.mean([i == 2 for _, i, _ in choices])),
        "share_all_small_steps": float(np.mean([j == 1 for _, _, j in choices])),
        **({"adaptive": True, "switches": switches} if adaptive else {}),
    }  # fmt: skip


def plot_training(logs: list[EpisodeLog], path: Path, reward: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    episodes = np.array([r.episode for r in logs])

    def smooth(values: list[float], width: int = 25) -> np.ndarray:
        """Centred moving mean that averages only over the samples it has at the edges."""
        v = np.asarray(values, dtype=float)
        kernel = np.ones(min(width, len(v)))
        return np.convolve(v, kernel, mode="same") / np.convolve(
            np.ones_like(v), kernel, mode="same"
        )

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    axes[0, 0].plot(episodes, [r.ret for r in logs], alpha=0.3)
    axes[0, 0].plot(episodes, smooth([r.ret for r in logs]))
    axes[0, 0].set(title="episode return", xlabel="episode", ylabel="return")
    axes[0, 1].plot(
        episodes, smooth([float(r.success) for r in logs]), label="success (moving mean)"
    )
    axes[0, 1].plot(episodes, [r.epsilon for r in logs], label="epsilon")
    axes[0, 1].set(title="success rate and exploration", xlabel="episode", ylim=(0, 1.05))
    axes[0, 1].legend()
    axes[1, 0].plot(episodes, [r.q_human for r in logs], label="Agent_0 (human radius)")
    axes[1, 0].plot(episodes, [r.q_robot for r in logs], label="Agent_1 (robot steps)")
    axes[1, 0].set(title="mean Q of the actions taken", xlabel="episode", ylabel="Q")
    axes[1, 0].legend()
    axes[1, 1].semilogy(episodes, [r.loss_human for r in logs], label="Agent_0")
    axes[1, 1].semilogy(episodes, [r.loss_robot for r in logs], label="Agent_1")
    axes[1, 1].set(title="Huber loss", xlabel="episode")
    axes[1, 1].legend()
    fig.suptitle(f"DAMMRL training, Reward {reward}")
    fig.savefig(path, dpi=110)
    plt.close(fig)
