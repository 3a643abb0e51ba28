"""Policy core: chooses the multi-model M_ij (human radius i, robot step vector j).

Until the learned DAMMRL policy exists, a fixed choice from settings.
"""

from __future__ import annotations

from dataclasses import dataclass

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


class FixedPolicy:
    """Always the same M_ij."""

    def __init__(self, models: ModelSet, human_model: int, robot_model: int) -> None:
        self.choice = ModelChoice(
            human_model, robot_model, models.radius_m(human_model), models.steps_m(robot_model)
        )

    def choose(self) -> ModelChoice:
        return self.choice
