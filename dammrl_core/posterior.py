"""Bayesian multiple-model estimate of the human sub-model (Algorithm 1, step f).

Each human sub-model i predicts how often a command is correct (toward the goal) and how
long a decision takes (lognormal). Every observed decision multiplies the prior by the
likelihood of what was seen; the posterior tells which sub-model the real human behaves
like when their admission radius is not given.

The commands are scored one by one. The times are scored together, with the person's own
time scale unknown (``HumanModel.decision_scale_sd``): a person slower than the model
looks careful, and nothing in one radius's times can tell the two apart, so the time
evidence is bounded and the accuracy evidence decides in the long run. Times at the floor
``decision_min_s`` (where the lognormal is censored) are left out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dammrl_core.human import HumanModel
from dammrl_core.models import HUMAN_MODELS


@dataclass
class HumanModelPosterior:
    human: HumanModel
    use_decision_time: bool = True
    log_accuracy: np.ndarray = field(default_factory=lambda: np.zeros(len(HUMAN_MODELS)))
    timed: int = 0  # decisions whose time is scored
    log_time_sum: float = 0.0  # sum of their log decision times [log s]
    decisions: int = 0
    map_history: list[int] = field(default_factory=list)
    log_prior: np.ndarray = field(default_factory=lambda: np.zeros(len(HUMAN_MODELS)))
    """What earlier runs and sessions of the same person said (``carried_prior``); flat
    by default."""

    def update(self, correct: bool, decision_s: float | None = None,
               confidence: float = 1.0) -> np.ndarray:  # fmt: skip
        """Fold in one decision (decoded with ``confidence``: a wearable's classifier may
        doubt it); return the posterior probabilities (one per model)."""
        confidence = min(1.0, max(0.0, confidence))
        for k, model in enumerate(HUMAN_MODELS):
            self.log_accuracy[k] += self.human.accuracy_log_likelihood(model, correct, confidence)
        self.log_accuracy -= self.log_accuracy.max()  # keep the numbers tame
        if self.use_decision_time and decision_s is not None:
            self._time(decision_s)
        self.decisions += 1
        self.map_history.append(self.map_model)
        return self.probabilities

    def _time(self, decision_s: float) -> None:
        """Keep the sufficient statistics of the scored times (not those at the floor)."""
        if decision_s > self.human.decision_min_s:
            self.timed += 1
            self.log_time_sum += math.log(decision_s)

    @property
    def log_probability(self) -> np.ndarray:
        """Unnormalised log posterior, one per model, largest 0."""
        evidence = self.human.times_log_evidence
        times = [evidence(m, self.timed, self.log_time_sum) for m in HUMAN_MODELS]
        log_p = self.log_prior + self.log_accuracy + np.array(times)
        return np.asarray(log_p - log_p.max())

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


PRIOR_CAP = 0.9
"""A carried prior is never surer than this of one model: a person may change between
sessions (practice, fatigue), and new evidence must be able to overturn the old."""


def carried_prior(probabilities: tuple[float, ...] | None) -> np.ndarray:
    """The log prior from a posterior carried from earlier runs or sessions, each model's
    probability clipped to [1 - PRIOR_CAP, PRIOR_CAP]; flat when there is none."""
    if probabilities is None:
        return np.zeros(len(HUMAN_MODELS))
    p = np.asarray(probabilities, dtype=float)
    if p.shape != (len(HUMAN_MODELS),) or not np.all(np.isfinite(p)) or p.sum() <= 0:
        raise ValueError(f"a prior is one probability per human model, got {probabilities}")
    p = np.clip(p / p.sum(), 1 - PRIOR_CAP, PRIOR_CAP)
    log_p = np.log(p / p.sum())
    return np.asarray(log_p - log_p.max())
