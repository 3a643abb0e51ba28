"""The simulated human (Agent_0): binary commands on the primary axis, with errors.

Pure: it perceives the end-effector position and the goal when asked, and answers with a
decision and how long that decision took. The caller (in-process runner or intent node)
makes the decision available only after that time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dammrl.state import Intent
from services.intent.config import HumanSettings


@dataclass(frozen=True)
class Decision:
    intent: Intent  # t_s of the intent is when the decision becomes available
    correct: bool  # whether u_h points toward the goal (known only in simulation)
    decision_s: float  # how long the human took [s]


def direction_to_goal(
    ee_pos: Sequence[float] | np.ndarray, goal: Sequence[float] | np.ndarray, axis: int
) -> int:
    """The correct binary command: +1 when the goal lies ahead along ``axis``, else -1."""
    return 1 if goal[axis] - ee_pos[axis] >= 0 else -1


class SimulatedHuman:
    """Correct with probability 0.8 under E_big and 0.9 under E_small (settings)."""

    def __init__(
        self, settings: HumanSettings, seed: int | np.random.Generator | None = None
    ) -> None:
        self.settings = settings
        self.rng = np.random.default_rng(seed)  # a Generator passes through unchanged

    def accuracy(self, human_model: int) -> float:
        return self.settings.accuracy_big if human_model == 1 else self.settings.accuracy_small

    def decision_time_s(self, human_model: int) -> float:
        s = self.settings
        median = s.decision_median_big_s if human_model == 1 else s.decision_median_small_s
        drawn = median * np.exp(s.decision_sigma * self.rng.standard_normal())
        return float(max(s.decision_min_s, drawn))

    def decide(
        self, t_s: float, ee_pos: np.ndarray, goal: np.ndarray, axis: int, human_model: int
    ) -> Decision:
        """Decide at ``t_s`` from the perceived error along the primary ``axis``."""
        toward_goal = direction_to_goal(ee_pos, goal, axis)
        correct = bool(self.rng.random() < self.accuracy(human_model))
        decision_s = self.decision_time_s(human_model)
        intent = Intent(
            t_s=t_s + decision_s,
            u_h=toward_goal if correct else -toward_goal,
            radius_m=self.settings.models.radius_m(human_model),
            human_model=human_model,
        )
        return Decision(intent, correct, decision_s)
