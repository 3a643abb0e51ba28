"""DQN for the two agents: replay buffer, Q-networks with targets, epsilon-greedy.

Agent_0 (human model) maps the observation to Q-values of the two radii; Agent_1 (robot)
sees the observation plus Agent_0's choice (one-hot) and scores the eight step vectors.
Both learn from the shared reward: Huber loss on the one-step target with a target
network, Adam, gradient clipping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dammrl.learning.rl.config import TrainSettings
from dammrl_core.policy.learned import DualQNetwork


class ReplayBuffer:
    """A ring buffer of (obs, i, j, reward, next_obs, done)."""

    def __init__(self, capacity: int, obs_size: int, seed: int) -> None:
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_size), dtype=np.float32)
        self.next_obs = np.zeros((capacity, obs_size), dtype=np.float32)
        self.actions = np.zeros((capacity, 2), dtype=np.int64)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.dones = np.zeros(capacity, dtype=np.float32)
        self.size = 0
        self._next = 0
        self.rng = np.random.default_rng(seed)

    def add(self, obs: np.ndarray, action: tuple[int, int], reward: float,
            next_obs: np.ndarray, done: bool) -> None:  # fmt: skip
        k = self._next
        self.obs[k], self.next_obs[k] = obs, next_obs
        self.actions[k] = action
        self.rewards[k], self.dones[k] = reward, float(done)
        self._next = (k + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch: int) -> tuple[np.ndarray, ...]:
        idx = self.rng.integers(0, self.size, batch)
        return (
            self.obs[idx],
            self.actions[idx],
            self.rewards[idx],
            self.next_obs[idx],
            self.dones[idx],
        )


@dataclass
class UpdateStats:
    loss_human: float
    loss_robot: float
    q_human: float
    q_robot: float


class DualAgentDQN:
    """Agent_0 chooses i (2 actions), Agent_1 chooses j (8 actions) given i."""

    def __init__(self, obs_size: int, actions: tuple[int, int], settings: TrainSettings,
                 device: torch.device) -> None:  # fmt: skip
        self.settings, self.device, self.actions = settings, device, actions
        self.online = DualQNetwork(settings.hidden, device)
        self.target = DualQNetwork(settings.hidden, device)
        self.q_human, self.q_robot = self.online.human, self.online.robot
        self.target_human, self.target_robot = self.target.human, self.target.robot
        self.sync_targets()
        self.parameters = [*self.q_human.parameters(), *self.q_robot.parameters()]
        self.optimizer = torch.optim.Adam(self.parameters, lr=settings.learning_rate)
        self.updates = 0

    def sync_targets(self) -> None:
        self.target_human.load_state_dict(self.q_human.state_dict())
        self.target_robot.load_state_dict(self.q_robot.state_dict())

    def robot_input(self, obs: torch.Tensor, human: torch.Tensor) -> torch.Tensor:
        return self.online.robot_input(obs, human)

    @torch.no_grad()
    def act(self, obs: np.ndarray, epsilon: float, rng: np.random.Generator) -> tuple[int, int]:
        """Epsilon-greedy for each agent; Agent_1 sees Agent_0's choice."""
        explore_human = rng.random() < epsilon
        human = int(rng.integers(self.actions[0])) if explore_human else None
        if rng.random() < epsilon:
            human = self.online.greedy(obs)[0] if human is None else human
            return human, int(rng.integers(self.actions[1]))
        return self.online.greedy(obs, human)

    def update(self, batch: tuple[np.ndarray, ...], conservative: float = 0.0) -> UpdateStats:
        """One double-DQN step; ``conservative`` > 0 adds CQL(H)'s term for each agent,
        alpha * (logsumexp_a Q(s, a) - Q(s, a_data)) (per-person refinement,
        dammrl.learning.adapt)."""
        obs, actions, rewards, next_obs, dones = (
            torch.as_tensor(b, device=self.device) for b in batch
        )
        gamma = self.settings.gamma
        with torch.no_grad():
            next_human = self.q_human(next_obs).argmax(1)
            target_h = self.target_human(next_obs).max(1).values
            target_r = self.target_robot(self.robot_input(next_obs, next_human)).max(1).values
            y_h = rewards + gamma * (1 - dones) * target_h
            y_r = rewards + gamma * (1 - dones) * target_r
        all_h = self.q_human(obs)
        all_r = self.q_robot(self.robot_input(obs, actions[:, 0]))
        q_h = all_h.gather(1, actions[:, :1]).squeeze(1)
        q_r = all_r.gather(1, actions[:, 1:]).squeeze(1)
        loss_h = nn.functional.smooth_l1_loss(q_h, y_h)
        loss_r = nn.functional.smooth_l1_loss(q_r, y_r)
        if conservative > 0:
            loss_h = loss_h + conservative * (torch.logsumexp(all_h, 1) - q_h).mean()
            loss_r = loss_r + conservative * (torch.logsumexp(all_r, 1) - q_r).mean()
        self.optimizer.zero_grad()
        (loss_h + loss_r).backward()  # type: ignore[no-untyped-call]
        nn.utils.clip_grad_norm_(self.parameters, self.settings.grad_clip)
        self.optimizer.step()
        self.updates += 1
        if self.updates % self.settings.target_update_every == 0:
            self.sync_targets()
        return UpdateStats(loss_h.item(), loss_r.item(), q_h.mean().item(), q_r.mean().item())

    def state_dict(self) -> dict[str, object]:
        return {
            "q_human": self.q_human.state_dict(), "q_robot": self.q_robot.state_dict(),
            "target_human": self.target_human.state_dict(),
            "target_robot": self.target_robot.state_dict(),
            "optimizer": self.optimizer.state_dict(), "updates": self.updates,
        }  # fmt: skip

    def load_state_dict(self, state: dict[str, object]) -> None:
        self.q_human.load_state_dict(state["q_human"])  # type: ignore[arg-type]
        self.q_robot.load_state_dict(state["q_robot"])  # type: ignore[arg-type]
        self.target_human.load_state_dict(state["target_human"])  # type: ignore[arg-type]
        self.target_robot.load_state_dict(state["target_robot"])  # type: ignore[arg-type]
        self.optimizer.load_state_dict(state["optimizer"])  # type: ignore[arg-type]
        self.updates = int(state["updates"])  # type: ignore[call-overload]
