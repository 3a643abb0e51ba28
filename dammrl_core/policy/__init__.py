"""Who chooses the multi-model M_ij: the one policy interface of every composition.

The in-process runner, the RL environment's evaluation, ``dammrl evaluate``, ``dammrl
replay --into-policy`` and the policy service all call a :class:`Policy` the same way:
``reset()`` when an episode starts, ``decide(ee_pos, goal)`` at every decision.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS, ModelSet, radius_name


@dataclass(frozen=True)
class ModelChoice:
    human_model: int  # i: 1 = E_big, 2 = E_small
    robot_model: int  # j: 1..8, see dammrl_core.models
    radius_m: float  # epsilon of model i [m]
    steps_m: np.ndarray  # delta of model j (3,) [m]

    @property
    def label(self) -> str:
        return f"M_{self.human_model},{self.robot_model} ({radius_name(self.human_model)})"


def model_choice(models: ModelSet, human_model: int, robot_model: int) -> ModelChoice:
    return ModelChoice(
        human_model, robot_model, models.radius_m(human_model), models.steps_m(robot_model)
    )


class Policy(Protocol):
    """Chooses M_ij at each decision of an episode."""

    def reset(self) -> None:
        """A new episode starts: no model in force yet."""

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        """M_ij for the decision the human is asked for at ``ee_pos`` [m] (3,) toward
        ``goal`` [m] (3,); ``human_model``, when given, is the human's known (estimated)
        sub-model i, and only j is chosen."""
        ...


class FixedPolicy:
    """Always the same M_ij (with the human's own i when it is given)."""

    def __init__(self, models: ModelSet, human_model: int, robot_model: int) -> None:
        self.models = models
        self.choice = model_choice(models, human_model, robot_model)

    def reset(self) -> None:
        """Nothing to forget."""

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        if human_model is None:
            return self.choice
        return model_choice(self.models, human_model, self.choice.robot_model)


class RandomPolicy:
    """A uniformly random (i, j) at every decision (the study's chance-level row); with the
    human's own i given, only j is drawn."""

    def __init__(self, models: ModelSet, rng: np.random.Generator) -> None:
        self.models = models
        self.rng = rng

    def reset(self) -> None:
        """Nothing to forget (the stream goes on)."""

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        i = int(self.rng.choice(HUMAN_MODELS))
        j = int(self.rng.choice(ROBOT_MODELS))
        return model_choice(self.models, i if human_model is None else human_model, j)
