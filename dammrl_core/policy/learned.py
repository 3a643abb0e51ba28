"""The learned DAMMRL policy: observation, the two Q-networks, checkpoints, greedy choice.

Observation (16,): the end-effector position and the goal, normalised to the workspace
([-1, 1] per axis), and the model in force as one-hots (i: 2, j: 8). Agent_0 (human
model) scores the two radii from the observation; Agent_1 (robot) sees the observation
plus Agent_0's choice (one-hot) and scores the eight step vectors. Training
(``dammrl.learning.rl``) builds on these networks; this module only needs them to act.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dammrl_core.errors import DammrlError
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS, ModelSet
from dammrl_core.policy import ModelChoice, model_choice

OBSERVATION_SIZE = 3 + 3 + len(HUMAN_MODELS) + len(ROBOT_MODELS)
ACTIONS = (len(HUMAN_MODELS), len(ROBOT_MODELS))
WORKSPACE_CENTRE = np.array([0.45, 0.0, -0.10])
WORKSPACE_HALF = np.array([0.25, 0.25, 0.20])
CHECKPOINT = "checkpoint.pt"
SHIPPED_RUNS = ("reward1", "reward2")
"""The policies shipped in the package (dammrl_core/policies/<name>)."""
FORMAT = 1


class CheckpointError(DammrlError):
    """A checkpoint that is missing, corrupt or made for something else."""


def observe(x: np.ndarray, goal: np.ndarray, model: tuple[int, int] | None) -> np.ndarray:
    """The observation of end-effector ``x`` and ``goal`` [m] (3,) with M_ij in force."""
    obs = np.zeros(OBSERVATION_SIZE, dtype=np.float32)
    obs[0:3] = (x - WORKSPACE_CENTRE) / WORKSPACE_HALF
    obs[3:6] = (goal - WORKSPACE_CENTRE) / WORKSPACE_HALF
    if model is not None:
        obs[6 + model[0] - 1] = 1.0
        obs[8 + model[1] - 1] = 1.0
    return obs


def mlp(inputs: int, outputs: int, hidden: int) -> nn.Module:
    return nn.Sequential(
        nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
        nn.Linear(hidden, outputs),
    )  # fmt: skip


class DualQNetwork:
    """Q-networks of both agents: ``human`` (2 radii) and ``robot`` (8 step vectors | i)."""

    def __init__(self, hidden: int, device: torch.device) -> None:
        self.device = device
        self.human = mlp(OBSERVATION_SIZE, ACTIONS[0], hidden).to(device)
        self.robot = mlp(OBSERVATION_SIZE + ACTIONS[0], ACTIONS[1], hidden).to(device)

    def robot_input(self, obs: torch.Tensor, human: torch.Tensor) -> torch.Tensor:
        """Agent_1's input: the observation and Agent_0's choice as a one-hot."""
        one_hot = nn.functional.one_hot(human, ACTIONS[0]).float()
        return torch.cat([obs, one_hot], dim=1)

    @torch.no_grad()
    def greedy(self, obs: np.ndarray, human: int | None = None) -> tuple[int, int]:
        """Greedy 0-based (i, j); with ``human`` given, only j is chosen (for that i)."""
        x = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        i = int(self.human(x).argmax(1).item()) if human is None else human
        q = self.robot(self.robot_input(x, torch.tensor([i], device=self.device)))
        return i, int(q.argmax(1).item())


def resolve_run(run: Path) -> Path:
    """A run directory or checkpoint file as given; a shipped policy by its name
    (``reward1``, ``reward2``, or the repository path ``dammrl_core/policies/reward2``
    the docs write), found in the installed package from any directory."""
    if run.exists() or run.name not in SHIPPED_RUNS:
        return run
    if len(run.parts) == 1 or run.parts[-2] == "policies":
        return Path(str(resources.files("dammrl_core").joinpath("policies", run.name)))
    return run


def load_checkpoint(run: Path) -> dict[str, Any]:
    """The checkpoint of a run directory (or file, or shipped name), checked for format and
    shapes.

    Loaded with ``weights_only=True``: tensors and plain containers only, so a crafted
    file cannot run code.
    """
    run = resolve_run(run)
    path = run / CHECKPOINT if run.is_dir() else run
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path} (give a run directory, a .pt file or "
                              f"a shipped policy: {', '.join(SHIPPED_RUNS)})")  # fmt: skip
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a damaged or unsafe file
        raise CheckpointError(f"checkpoint {path} is corrupt: {exc}") from exc
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a dammrl checkpoint (format {FORMAT})")
    if (
        checkpoint.get("observation_size") != OBSERVATION_SIZE
        or tuple(checkpoint.get("actions", ())) != ACTIONS
    ):
        raise CheckpointError(f"{path} was trained for another observation/action layout")
    return checkpoint


class LearnedPolicy:
    """The greedy dual-agent DQN of a training run: s = [x; x_g; M_ij in force] -> (i, j)."""

    def __init__(self, models: ModelSet, checkpoint: Path) -> None:
        state = load_checkpoint(checkpoint)  # CheckpointError names what is wrong
        try:
            self.reward = int(state["reward"])
            self.network = DualQNetwork(int(state["settings"]["hidden"]), torch.device("cpu"))
            agent = state["agent"]
            self.network.human.load_state_dict(agent["q_human"])
            self.network.robot.load_state_dict(agent["q_robot"])
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise CheckpointError(
                f"checkpoint {checkpoint} does not fit the policy: {exc}"
            ) from exc
        self.models = models
        self.previous: tuple[int, int] | None = None

    def reset(self) -> None:
        """A new episode: no model in force yet."""
        self.previous = None

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        """Greedy (i, j); with ``human_model`` (a real human's estimated radius) Agent_1
        chooses j for that i instead of Agent_0's choice."""
        obs = observe(ee_pos, goal, self.previous)
        i, j = self.network.greedy(obs, None if human_model is None else human_model - 1)
        self.previous = (i + 1, j + 1)
        return model_choice(self.models, i + 1, j + 1)
