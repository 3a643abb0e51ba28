"""Bayesian multiple-model estimate of the human sub-model (Algorithm 1, step f).

Each human sub-model i predicts how often a command is correct (toward the goal) and how
long a decision takes (lognormal). Every observed decision multiplies the prior by the
likelihood of what was seen; the posterior tells which sub-model the real human behaves
like when their admission radius is not given.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dammrl.core.human import HumanModel
from dammrl.core.models import HUMAN_MODELS


@dataclass
class HumanModelPosterior:
    human: HumanModel
    use_decision_time: bool = True
    log_probability: np.ndarray = field(default_factory=lambda: np.zeros(len(HUMAN_MODELS)))
    decisions: int = 0
    map_history: list[int] = field(default_factory=list)

    def update(self, correct: bool, decision_s: float | None = None) -> np.ndarray:
        """Fold in one decision; return the posterior probabilities (one per model)."""
        for k, model in enumerate(HUMAN_MODELS):
            time_s = decision_s if self.use_decision_time else None
            self.log_probability[k] += self.human.log_likelihood(model, correct, time_s)
        self.log_probability -= self.log_probability.max()  # keep the numbers tame
        self.decisions += 1
        self.map_history.append(self.map_model)
        return self.probabilities

    @property
    def probabilities(self) -> np.ndarray:
        p = np.exp(self.log_probability)
        return np.asarray(p / p.sum())

    @property
    def map_model(self) -> int:
        return HUMAN_MODELS[int(np.argmax(self.log_probability))]

    def settled_after(self) -> int:
        """Decisions until the MAP model stopped changing (the convergence figure)."""
        history = self.map_history
        for k in range(len(history) - 1, -1, -1):
            if history[k] != history[-1]:
                return k + 2
        return 1 if history else 0
