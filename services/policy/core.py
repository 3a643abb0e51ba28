"""Policy core: chooses the multi-model M_ij (human radius i, robot step vector j).

Until the learned DAMMRL policy exists, a fixed choice from settings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.models import ModelSet, radius_name


@dataclass(frozen=True)
class ModelChoice:
    human_model: int  # i: 1 = E_big, 2 = E_small
    robot_model: int  # j: 1..8, see dammrl.models
    radius_m: float  # epsilon of model i [m]
    steps_m: np.ndarray  # delta of model j (3,) [m]

    @property
    def label(self) -> str:
        return f"M_{self.human_model},{self.robot_model} ({radius_name(self.human_model)})"


def model_choice(models: ModelSet, human_model: int, robot_model: int) -> ModelChoice:
    return ModelChoice(
        human_model, robot_model, models.radius_m(human_model), models.steps_m(robot_model)
    )


class FixedPolicy:
    """Always the same M_ij."""

    def __init__(self, models: ModelSet, human_model: int, robot_model: int) -> None:
        self.choice = model_choice(models, human_model, robot_model)

    def choose(self) -> ModelChoice:
        return self.choice

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        """The fixed model (with ``human_model`` as i when the human's radius is known)."""
        if human_model is None:
            return self.choice
        return ModelChoice(
            human_model, self.choice.robot_model, self.choice.radius_m, self.choice.steps_m
        )


class LearnedPolicy:
    """The greedy dual-agent DQN of a training run: s = [x; x_g; M_ij in force] -> (i, j)."""

    def __init__(self, models: ModelSet, checkpoint: Path) -> None:
        import torch  # imported here: the fixed policy and the other services need no torch

        from dammrl.rl.config import TrainSettings
        from dammrl.rl.dqn import DualAgentDQN
        from dammrl.rl.env import ACTIONS, OBSERVATION_SIZE
        from dammrl.rl.train import load_checkpoint

        state = load_checkpoint(checkpoint)  # CheckpointError names what is wrong
        self.reward = int(state["reward"])
        self.agent = DualAgentDQN(
            OBSERVATION_SIZE, ACTIONS, TrainSettings(**state["settings"]), torch.device("cpu")
        )
        self.agent.load_state_dict(state["agent"])
        self.models = models
        self.previous: tuple[int, int] | None = None
        self.rng = np.random.default_rng(0)

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        """Greedy (i, j); with ``human_model`` (a real human's estimated radius) Agent_1
        chooses j for that i instead of Agent_0's choice."""
        import torch

        from dammrl.rl.env import observe

        obs = observe(ee_pos, goal, self.previous)
        i, j = self.agent.act(obs, 0.0, self.rng)
        if human_model is not None:
            i = human_model - 1
            with torch.no_grad():
                x = torch.as_tensor(obs).unsqueeze(0)
                q = self.agent.q_robot(self.agent.robot_input(x, torch.tensor([i])))
            j = int(q.argmax(1).item())
        self.previous = (i + 1, j + 1)
        return model_choice(self.models, i + 1, j + 1)

    def reset(self) -> None:
        """A new episode: no model in force yet."""
        self.previous = None
