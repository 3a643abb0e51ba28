"""The adaptive policy: S2's narrowing and S3's re-selection around a base policy.

Until a target is missed the base policy (the shipped DQN) chooses, with the person's
estimated radius when one is given (S2: the posterior over the human sub-model narrows i).
After every reach the posterior over M_ij (:mod:`dammrl_core.coadaptation`) takes in what
the reach said, credited to what was in force (the base policy, or the selected model);
when the last ``targets.window`` reaches since the last switch miss a target, the policy
switches to the option most likely to meet every target (S3): a model M_ij, or the base
policy again. Under a model it chooses only among the matched models: the selected
radius i and the step vectors j whose chance of meeting the targets is within
``KEEP_WITHIN`` of the best one's (a learned base still picks among them per state;
another base takes the best).
An alternative must be at least ``SWITCH_GAIN`` likelier to meet the targets than the
model in force: targets no model can meet leave the policy as it is instead of churning
through models no better.
Every switch is kept with its reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from dammrl_core.coadaptation import (
    BASE,
    OPTIONS,
    ModelPosterior,
    ReachEvidence,
    Targets,
)
from dammrl_core.models import ModelSet
from dammrl_core.policy import ModelChoice, Policy, model_choice

KEEP_WITHIN = 0.05
"""A step vector stays allowed when its P(meets every target) is within this of the
selected model's (the learned base then chooses among near-equals per state)."""


SWITCH_GAIN = 0.05
"""How much likelier to meet every target an alternative must be than the model in force
(a design choice: below it a switch is a coin toss between near-equals)."""


class Restrictable(Protocol):
    def decide_within(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int, robot_models: frozenset[int]
    ) -> ModelChoice: ...


@dataclass(frozen=True)
class Switch:
    """One re-selection: after which reach, from and to which model, and why."""

    reach: int  # reaches observed when it happened
    from_model: tuple[int, int]
    to_model: tuple[int, int]
    allowed: tuple[int, ...]  # the step vectors j allowed with to_model's radius
    reasons: tuple[str, ...]  # the targets missed
    p_meets: float  # the new model's probability of meeting every target

    @property
    def line(self) -> str:
        allowed = f"j in {list(self.allowed)}; " if self.to_model != BASE else ""
        return (
            f"after reach {self.reach}: {_name(self.from_model)} -> {_name(self.to_model)} "
            f"({allowed}P(meets targets) {self.p_meets:.2f}): " + "; ".join(self.reasons)
        )


def _name(option: tuple[int, int]) -> str:
    return "the base policy" if option == BASE else f"M_{option[0]},{option[1]}"


class AdaptivePolicy:
    """A base policy with the posterior over M_ij and the target-driven re-selection."""

    def __init__(
        self, base: Policy, models: ModelSet, posterior: ModelPosterior, targets: Targets
    ) -> None:
        self.base = base
        self.models = models
        self.posterior = posterior
        self.targets = targets
        self.selected: tuple[int, int] | None = None  # None: the base chooses freely
        self.allowed: frozenset[int] = frozenset()
        self.switches: list[Switch] = []
        self.recent: list[ReachEvidence] = []  # since the last switch
        self.ratings: list[float] = []  # since the last switch

    def reset(self) -> None:
        self.base.reset()

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        if self.selected is None:
            return self.base.decide(ee_pos, goal, human_model)
        i, j = self.selected
        if len(self.allowed) > 1 and hasattr(self.base, "decide_within"):
            restricted: Restrictable = self.base  # type: ignore[assignment]
            return restricted.decide_within(ee_pos, goal, i, self.allowed)
        return model_choice(self.models, i, j)

    def observe(self, reach: ReachEvidence) -> Switch | None:
        """Fold in a finished reach; switch when the targets are missed and an alternative
        is more likely to meet them (the switch, else None)."""
        current = self.selected or BASE
        self.posterior.observe(reach, current)
        self.recent.append(reach)
        if len(self.recent) < self.targets.window:
            return None
        reasons = self.targets.unmet(self.recent[-self.targets.window :], self.ratings)
        return self._switch(current, reasons) if reasons else None

    def rating(self, rating: float) -> None:
        """The participant's comfort rating (1-5) of the reaches since the last one."""
        if self.recent:
            self.posterior.rating(self.selected or BASE, rating)
        self.ratings.append(float(rating))

    def _switch(self, current: tuple[int, int], reasons: list[str]) -> Switch | None:
        meets = self.posterior.meets(self.targets, OPTIONS)
        ranked = sorted(range(len(OPTIONS)), key=lambda k: (-meets[k], k))
        chosen = next(k for k in ranked if OPTIONS[k] != current)
        if meets[chosen] < meets[OPTIONS.index(current)] + SWITCH_GAIN:
            return None  # no alternative is likelier to meet the targets
        if OPTIONS[chosen] == BASE:
            self.selected, self.allowed = None, frozenset()
        else:
            i, j = OPTIONS[chosen]
            allowed = {
                jj
                for (ii, jj), p in zip(OPTIONS, meets, strict=True)
                if ii == i and p >= meets[chosen] - KEEP_WITHIN
            }
            self.selected, self.allowed = (i, j), frozenset(allowed | {j})
        switch = Switch(
            self.posterior.reaches,
            current,
            OPTIONS[chosen],
            tuple(sorted(self.allowed)),
            tuple(reasons),
            float(meets[chosen]),
        )
        self.switches.append(switch)
        self.recent, self.ratings = [], []
        return switch
