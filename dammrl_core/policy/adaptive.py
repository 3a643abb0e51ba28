"""The adaptive policy: S2's narrowing and S3's re-selection around a base policy.

Until a target is missed the base policy (the shipped DQN) chooses, with the person's
estimated radius when one is given (S2: the posterior over the human sub-model narrows i).
After every reach the posterior over the options (:mod:`dammrl_core.coadaptation`) takes
in what the reach said: the person's decisions and the arm's steps move every option's
prediction, the reach's outcome moves the option in force (the base policy, or the
selected model). When the last ``targets.window`` reaches since the last switch miss a
target, the policy chooses by **Thompson sampling**: one joint draw of the posterior, and
the option that meets most targets in it (then the least short of the comfort target,
then the shortest time to success, a failure counting the whole horizon). An
option likely better is chosen often, one only possibly better now and then (exploration),
one surely worse never. Safety bounds the exploration:

* never an option whose success lower bound (one-sided 95 %) is below
  ``selection.success_floor`` (the base policy, what runs without adaptation, stays
  allowed);
* at most ``selection.max_switches`` switches in a block of ``selection.block_reaches``
  reaches, and at least ``targets.window`` reaches between two;
* a selected model runs exactly as that M_ij (or as the interpolated step vector), so its
  reaches say what it gives.

With ``selection.interpolate`` the options also include the paper's named extension,
bounded online interpolation: for each radius, the step vector halfway between two
neighbouring models' (one axis halfway between its small and large step; 24 more options,
never outside the model set's range). Their prediction is the mean of their neighbours'
until their own reaches say otherwise. The admission radius is not interpolated: it is the
person's choice, carried by every intent source as the sub-model's index.

Every switch is kept with its reason: the targets missed, the rule, and what the posterior
predicted for the new option.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from dammrl_core.coadaptation import (
    BASE,
    MIDPOINTS,
    OPTIONS,
    ModelPosterior,
    ReachEvidence,
    Selection,
    Targets,
)
from dammrl_core.human import HumanModel
from dammrl_core.model_table import ModelTable, Option, option_name
from dammrl_core.models import ModelSet
from dammrl_core.policy import ModelChoice, Policy, model_choice


@dataclass(frozen=True)
class Switch:
    """One re-selection: after which reach, from and to which option, and why."""

    reach: int  # reaches observed when it happened
    from_model: Option
    to_model: Option
    reasons: tuple[str, ...]  # the targets missed
    p_meets: float  # the new option's probability of meeting every target
    success: float  # its predicted success for this person (the table's, mean over draws)
    success_lower: float  # its success lower bound (with its own reaches)
    time_s: float  # its predicted median reach time [s]
    to_success_s: float  # its predicted mean time to success (a failure: the horizon) [s]
    left_out: int  # options below the success floor

    @property
    def line(self) -> str:
        return (
            f"after reach {self.reach}: {option_name(self.from_model)} -> "
            f"{option_name(self.to_model)} (Thompson draw; P(meets targets) "
            f"{self.p_meets:.2f}; predicted success {self.success:.2f}, lower bound "
            f"{self.success_lower:.2f}; median {self.time_s:.1f} s, time to success "
            f"{self.to_success_s:.1f} s; {self.left_out} options "
            f"below the success floor left out): " + "; ".join(self.reasons)
        )


class AdaptivePolicy:
    """A base policy with the posterior over the options and the target-driven,
    safely exploring re-selection."""

    def __init__(self, base: Policy, models: ModelSet, posterior: ModelPosterior,
                 targets: Targets, selection: Selection | None = None) -> None:  # fmt: skip
        self.base = base
        self.models = models
        self.posterior = posterior
        self.targets = targets
        self.selection = selection or Selection()
        self.rng = np.random.default_rng([self.selection.seed, 7])  # the Thompson picks
        self.selected: Option = BASE
        self.switches: list[Switch] = []
        self.held: list[str] = []  # switches the block's budget held back
        self.recent: list[ReachEvidence] = []  # since the last switch
        self.ratings: list[float] = []  # since the last switch
        self.unrated: list[Option] = []  # the option of each reach since the last rating

    @classmethod
    def around(cls, base: Policy, models: ModelSet, human: HumanModel, targets: Targets,
               selection: Selection | None = None, table: ModelTable | None = None
               ) -> AdaptivePolicy:  # fmt: skip
        """The adaptive mode around ``base`` for a person scored with ``human``'s
        sub-models, predicting from ``table`` (default: the packaged model table)."""
        selection = selection or Selection()
        options = (*OPTIONS, *MIDPOINTS) if selection.interpolate else OPTIONS
        posterior = ModelPosterior(table or ModelTable.load(), human, models, selection.seed,
                                   options)  # fmt: skip
        return cls(base, models, posterior, targets, selection)

    def reset(self) -> None:
        self.base.reset()

    def decide(
        self, ee_pos: np.ndarray, goal: np.ndarray, human_model: int | None = None
    ) -> ModelChoice:
        if self.selected == BASE:
            return self.base.decide(ee_pos, goal, human_model)
        return option_choice(self.models, self.selected)

    def observe(self, reach: ReachEvidence, rating: float | None = None) -> Switch | None:
        """Fold in a finished reach (and the person's comfort ``rating`` of it, 1-5, when
        they gave one); when the targets are missed, choose again (the switch, else None)."""
        self.posterior.observe(reach, self.selected)
        self.unrated.append(self.selected)
        if rating is not None:
            self.unrated = []
            self.posterior.rating(self.selected, rating)
            self.ratings.append(float(rating))
        self.recent.append(reach)
        if len(self.recent) < self.targets.window:
            return None
        reasons = self.targets.unmet(self.recent[-self.targets.window :], self.ratings)
        return self._choose(reasons) if reasons else None

    def rating(self, rating: float) -> None:
        """The participant's comfort rating (1-5) of the reaches since the last one (a
        block's, from the session display), credited to the option in force for most of
        them, even when the policy has switched since."""
        if self.unrated:
            self.posterior.rating(Counter(self.unrated).most_common(1)[0][0], rating)
        self.unrated = []
        self.ratings.append(float(rating))

    def allowed(self) -> tuple[Option, ...]:
        """The options the selection may take: the base policy, and every other whose
        success lower bound reaches the floor."""
        options = self.posterior.options
        lower = self.posterior.success_lower(self.targets)
        floor = self.selection.success_floor
        return tuple(o for o, b in zip(options, lower, strict=True) if o == BASE or b >= floor)

    def _choose(self, reasons: list[str]) -> Switch | None:
        allowed = self.allowed()
        chosen = self.posterior.thompson(self.targets, allowed, self.rng)
        if chosen == self.selected:
            return None
        reach = self.posterior.reaches
        block = (reach - 1) // self.selection.block_reaches
        used = sum((s.reach - 1) // self.selection.block_reaches == block for s in self.switches)
        if used >= self.selection.max_switches:
            self.held.append(f"after reach {reach}: {option_name(chosen)} held back "
                             f"({used} switches in this block): " + "; ".join(reasons))  # fmt: skip
            return None
        draws = self.posterior.draws(self.targets)
        row = draws.row(chosen)
        switch = Switch(
            reach=reach,
            from_model=self.selected,
            to_model=chosen,
            reasons=tuple(reasons),
            p_meets=float(self.posterior.meets(self.targets, (chosen,))[0]),
            success=float(draws.predicted_success[row]),
            success_lower=float(self.posterior.success_lower(self.targets, (chosen,))[0]),
            time_s=float(draws.predicted_time_s[row]),
            to_success_s=float(draws.predicted_to_success_s[row]),
            left_out=len(self.posterior.options) - len(allowed),
        )
        self.selected = chosen
        self.switches.append(switch)
        self.recent, self.ratings = [], []
        return switch


def option_choice(models: ModelSet, option: Option) -> ModelChoice:
    """What a selected option chooses: M_ij, or radius i with the steps halfway between
    M_ij's and M_ik's (reported as j)."""
    if len(option) == 2:
        return model_choice(models, *option)
    i, j, k = option
    halfway = (models.steps_m(j) + models.steps_m(k)) / 2
    return ModelChoice(i, j, models.radius_m(i), halfway)
