"""The human sub-models of the paper (section 3.4): how accurate and how fast a human is
under each admission radius. One object gives both what the simulated human samples and
the likelihood the policy's posterior scores real decisions with.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl.core.settings import Settings


class HumanModel(Settings):
    """Accuracy and decision time per human sub-model i (``DAMMRL_HUMAN_``).

    Decision times are lognormal: median ``decision_median_*_s``, log-sd
    ``decision_sigma``, never below ``decision_min_s`` (choice reaction times of healthy
    adults are 0.3-0.6 s; a hurried choice under E_big is faster and less accurate).
    """

    model_config = SettingsConfigDict(env_prefix="DAMMRL_HUMAN_")

    accuracy_big: float = Field(0.8, gt=0, lt=1)
    """Probability of a correct command (toward the goal) under E_big (i = 1)."""
    accuracy_small: float = Field(0.9, gt=0, lt=1)
    """Probability of a correct command under E_small (i = 2)."""
    decision_median_big_s: float = Field(0.25, gt=0, le=60)
    """Median decision time under E_big [s]."""
    decision_median_small_s: float = Field(0.40, gt=0, le=60)
    """Median decision time under E_small [s]."""
    decision_sigma: float = Field(0.3, gt=0, le=3)
    """Log-standard deviation of the decision time."""
    decision_min_s: float = Field(0.1, ge=0, le=10)
    """Shortest possible decision [s]."""

    def accuracy(self, i: int) -> float:
        """Probability that sub-model ``i`` commands toward the goal."""
        return self.accuracy_big if i == 1 else self.accuracy_small

    def decision_median_s(self, i: int) -> float:
        return self.decision_median_big_s if i == 1 else self.decision_median_small_s

    def sample(self, rng: np.random.Generator, i: int) -> tuple[bool, float]:
        """One decision of sub-model ``i``: (correct, decision time [s]), in that draw order."""
        correct = bool(rng.random() < self.accuracy(i))
        drawn = self.decision_median_s(i) * np.exp(self.decision_sigma * rng.standard_normal())
        return correct, float(max(self.decision_min_s, drawn))

    def log_likelihood(self, i: int, correct: bool, decision_s: float | None = None) -> float:
        """log p(correct, decision time | sub-model i); the time is left out when None or
        at the floor ``decision_min_s`` (where the lognormal is censored)."""
        accuracy = self.accuracy(i)
        log_l = math.log(accuracy if correct else 1.0 - accuracy)
        if decision_s is not None and decision_s > self.decision_min_s:
            z = (math.log(decision_s) - math.log(self.decision_median_s(i))) / self.decision_sigma
            log_l += -0.5 * z * z - math.log(decision_s * self.decision_sigma)
        return log_l


def direction_to_goal(
    ee_pos: Sequence[float] | np.ndarray, goal: Sequence[float] | np.ndarray, axis: int
) -> int:
    """The correct binary command: +1 when the goal lies ahead along ``axis``, else -1."""
    return 1 if goal[axis] - ee_pos[axis] >= 0 else -1
