"""The simulated human (Agent_0): binary commands on the primary axis, with errors.

Pure: it perceives the end-effector position and the goal when asked, and answers with a
decision and how long that decision took. The caller (in-process runner or intent node)
makes the decision available only after that time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dammrl.core.human import HumanModel, direction_to_goal
from dammrl.core.models import ModelSet
from dammrl.core.state import Intent


@dataclass(frozen=True)
class Decision:
    intent: Intent  # t_s of the intent is when the decision becomes available
    correct: bool  # whether u_h points toward the goal (known only in simulation)
    decision_s: float  # how long the human took [s]


class SimulatedHuman:
    """Samples decisions from the human model (accuracy and decision time per radius)."""

    def __init__(
        self,
        human: HumanModel,
        models: ModelSet,
        seed: int | np.random.Generator | None = None,
    ) -> None:
        self.human = human
        self.models = models
        self.rng = np.random.default_rng(seed)  # a Generator passes through unchanged

    def decide(
        self, t_s: float, ee_pos: np.ndarray, goal: np.ndarray, axis: int, human_model: int
    ) -> Decision:
        """Decide at ``t_s`` from the perceived error along the primary ``axis``."""
        toward_goal = direction_to_goal(ee_pos, goal, axis)
        correct, decision_s = self.human.sample(self.rng, human_model)
        intent = Intent(
            t_s=t_s + decision_s,
            u_h=toward_goal if correct else -toward_goal,
            radius_m=self.models.radius_m(human_model),
            human_model=human_model,
        )
        return Decision(intent, correct, decision_s)
