"""The human sub-models of the paper (section 3.4): how accurate and how fast a human is
under each admission radius.

One settings object, two concepts kept apart: its own fields are the policy's model of
people (the nominal sub-models, and how much people's speed may differ from them), which
the posterior scores decisions with; ``person`` says how the *simulated* person departs
from that model (by default not at all). The simulated human samples from both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.person import SimulatedPerson
from dammrl_core.settings import Settings


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
    decision_scale_sd: float = Field(0.15, ge=0, le=3)
    """Between-person log-sd of the decision-time scale, for the posterior: a person may be
    slower or quicker than the sub-model (0.15: within a factor 1.35 for 95 % of people;
    more for a slowed patient group, see docs/posterior.md). With one radius in use a
    person's speed and radius are confounded, so time evidence saturates instead of
    growing without bound. 0: everyone times exactly like a sub-model (the original
    posterior)."""
    person: SimulatedPerson = Field(default_factory=SimulatedPerson)
    """How the simulated person departs from the sub-models (defaults: not at all)."""

    def accuracy(self, i: int) -> float:
        """Probability that sub-model ``i`` commands toward the goal."""
        return self.accuracy_big if i == 1 else self.accuracy_small

    def decision_median_s(self, i: int) -> float:
        return self.decision_median_big_s if i == 1 else self.decision_median_small_s

    def sample(self, rng: np.random.Generator, i: int) -> tuple[bool, float]:
        """One decision of the simulated person using sub-model ``i``: (correct, decision
        time [s]), in that draw order (a uniform, then a normal; a uniform for a DDM)."""
        person = self.person
        if person.behaviour == "ddm":
            return person.sample_ddm(rng, i)
        accuracy = person.accuracy_under(i, self.accuracy(i))
        correct = bool(rng.random() < accuracy)
        median = self.decision_median_s(i) * person.decision_time_factor  # x 1.0 is exact
        drawn = median * np.exp(self.decision_sigma * rng.standard_normal())
        return correct, float(max(self.decision_min_s, drawn))

    def practised(self, session: int, reach: int) -> HumanModel:
        """The simulated person in ``session`` (from 1) after ``reach`` of its reaches
        (from 0): fatigue and learning folded in (the same model when they are unset)."""
        if not self.person.changes_with_practice:
            return self
        accuracies = (self.accuracy(1), self.accuracy(2))
        person = self.person.practised(session, reach, accuracies)
        return self.model_copy(update={"person": person})

    def accuracy_log_likelihood(self, i: int, correct: bool, confidence: float = 1.0) -> float:
        """log p(correct | sub-model i) of a command the source decoded with ``confidence``:
        with that probability the command is the person's, otherwise the classifier's coin
        (a mixture: a doubtful command says less about who the person is)."""
        accuracy = self.accuracy(i)
        intended = accuracy if correct else 1.0 - accuracy
        return math.log(confidence * intended + (1.0 - confidence) * 0.5)

    def times_log_evidence(self, i: int, timed: int, log_time_sum: float) -> float:
        """log p(log decision times | sub-model i), up to a term equal for every i.

        ``timed`` times with ``sum(log t) = log_time_sum``. Each is log median_i + b + noise
        (sd ``decision_sigma``), with the person's own scale b ~ N(0, decision_scale_sd^2)
        integrated out; what depends on i is the mean log time's distance from the
        sub-model's. NOTE: the variance never falls below decision_scale_sd^2, so a person
        who is simply slow cannot make the posterior certain of the careful radius.
        """
        if timed == 0:
            return 0.0
        mean = log_time_sum / timed
        variance = self.decision_scale_sd**2 + self.decision_sigma**2 / timed
        return -0.5 * (mean - math.log(self.decision_median_s(i))) ** 2 / variance


def direction_to_goal(
    ee_pos: Sequence[float] | np.ndarray, goal: Sequence[float] | np.ndarray, axis: int
) -> int:
    """The correct binary command: +1 when the goal lies ahead along ``axis``, else -1."""
    return 1 if goal[axis] - ee_pos[axis] >= 0 else -1
