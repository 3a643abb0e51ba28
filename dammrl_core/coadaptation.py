"""Co-adaptation: the posterior over the model set M_ij and the paper's S3 re-selection.

Algorithm 1 step (f) updates "the model posterior probability using online estimates of
the human's effective error rate and decision frequency, alongside the observed execution
time of the robot"; S3 updates it "based on real-world task performance and user comfort"
and, "if task targets are unmet, ... selects alternative matched models".

Here each option (the 16 M_ij and the base policy) has a predictive belief about what a
reach under it gives *this* person on *this* arm: its success probability, its mean log
reach time, its log final error and its comfort. Two sources move them
(docs/guide/coadaptation.md states each likelihood):

* **the person and the arm**, estimated from every decision and step whatever the option
  in force: per radius i the person's accuracy a_i (Beta, prior at the sub-model's
  accuracy, ``PERSON_PRIOR_DECISIONS`` pseudo-decisions; a wearable's confidence c counts
  as c of a decision) and their decision-time ratio r_i to the sub-model (lognormal times,
  normal prior on log r_i, sd ``decision_scale_sd``); the arm's step-time factor s (each
  step's execution time lognormal around s tau(L, eps), log s ~ N(0, 0.3^2)). Evidence is
  discounted with a half-life of ``HALF_LIFE_DECISIONS`` decisions of the same radius, so
  a person who tires or learns is followed.
  Every option's prediction comes from these: persons drawn from this posterior are run
  through the model table (:mod:`dammrl_core.model_table`: each option simulated on a grid
  of persons), so an option never tried moves with what is learned about the person;
* **the option's own reaches**: success is Bernoulli(p), with the prediction p as prior
  worth ``PRIOR_REACHES`` reaches of this person, Beta(n0 p + 1/2, n0 (1 - p) + 1/2) (on
  Jeffreys' Beta(1/2, 1/2): a 100 % prediction has prior mean 10.5 / 11 = 0.95); log time
  and log error normal around the prediction with an offset of the option's own (prior
  N(0, 0.3^2)); comfort: the participant's ratings (1-5), regressed on the options' step
  sizes (so a rating of large steps says something of every option with large steps), or
  the reach's SPARC (a smoothness proxy).

``draws`` samples all of it jointly (``DRAWS`` draws, seeded by the evidence seen): per
option and draw its success probability, mean log time, ... and how many targets it
meets. From them: ``meets`` (P(option meets every target)), ``success_lower`` (the 5 %
quantile of its success probability, the selection's floor), ``probabilities`` (P(M_ij is
the person's best model: most targets met, fastest among ties)) and ``thompson`` (one
draw's best option: Thompson sampling).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from dammrl_core.human import HumanModel
from dammrl_core.model_table import (
    BASE,
    MIDPOINTS,
    MODELS,
    OPTIONS,
    TABLE,
    ModelTable,
    Option,
    Persons,
    Prediction,
    halfway,
    option_name,
)
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS, ModelSet

__all__ = ["BASE", "MIDPOINTS", "MODELS", "OPTIONS", "TABLE", "ModelTable", "Option",
           "option_name"]  # fmt: skip

PRIOR_REACHES = 10.0
"""Reaches of this person the table's prediction for them weighs as (per option)."""
PERSON_PRIOR_DECISIONS = 4.0
"""Pseudo-decisions behind the sub-model's accuracy in the person's accuracy prior."""
HALF_LIFE_DECISIONS = 300.0
"""The person's evidence halves in weight after this many later decisions of the same
radius (about 15 reaches): a person who tires within a session or learns across sessions
is followed; a steady one is estimated from ~430 decisions' worth (accuracy sd ~0.02)."""
ARM_SCALE_PRIOR_SD = 0.3
"""Prior sd of log s, this arm's step-time factor against the nominal arm (x1.8 at 2 sd)."""
OFFSET_PRIOR_SD = 0.3
"""Prior sd of an option's own log-time (and log-error) offset from its prediction."""
DRAWS = 1000
"""Joint draws behind every answer (seeded: the same evidence, the same answer)."""
LOWER_QUANTILE = 0.05
"""The success lower bound is this quantile of the success draws (one-sided 95 %)."""
COMFORT_PRIOR_MEAN = (4.0, 0.0, 0.0, 0.0, 0.0)
COMFORT_PRIOR_SD = (1.0, 2.0, 1.0, 1.0, 1.0)
"""The comfort regression rating = b . (1, largest axis scale, x, y, z scales): a prior
rating of 4 +- 1 for small steps, large steps anywhere (+- 2) or on an axis (+- 1) not
known to matter until rated."""
COMFORT_NOISE_SD = 0.8
"""One rating's sd around the option's mean (1-5 ratings, rounded)."""


# ---- what one reach tells --------------------------------------------------------------
@dataclass(frozen=True)
class DecisionEvidence:
    human_model: int  # the radius i the person decided under
    correct: bool  # toward the goal (scored against the request)
    decision_s: float | None  # how long it took [s] (None: not known)
    confidence: float = 1.0  # the source's probability of the command


@dataclass(frozen=True)
class StepEvidence:
    robot_model: int  # j whose step vector the step used
    length_m: float  # ||dx|| [m]
    radius_m: float  # the admission radius that ended it [m]
    execution_s: float  # reference start to the trigger that admitted it [s]


@dataclass(frozen=True)
class ReachEvidence:
    """Everything one finished reach says (in-process from ReachResult; on the bus from
    its Intents, StepEvents, DecisionRequests and EpisodeResult: the same numbers)."""

    model: tuple[int, int]  # the M_ij in force for most of its decisions
    success: bool
    t_total_s: float
    final_error_m: float
    sparc: float | None  # the smoothness proxy of comfort (None: not measurable)
    decisions: tuple[DecisionEvidence, ...] = ()
    steps: tuple[StepEvidence, ...] = ()


@dataclass
class ReachRecord:
    """What one reach's decisions, requests and steps say, collected as they come: by the
    in-process runner from its result, by the policy service from the bus (one place, so
    both compositions hand the posterior the same evidence)."""

    choices: list[tuple[int, int]] = field(default_factory=list)  # one per decision
    decisions: list[DecisionEvidence] = field(default_factory=list)
    asked_s: list[float] = field(default_factory=list)  # robot clock of each request
    steps: list[tuple[int, float, float, float]] = field(default_factory=list)
    """(j, ||dx|| [m], admission radius [m], reference start [s]) of each step."""

    def evidence(
        self,
        success: bool,
        t_total_s: float,
        final_error_m: float,
        sparc: float | None,
        model: tuple[int, int],
    ) -> ReachEvidence:
        """The reach's evidence, ``model`` being the one in force when no decision was."""
        starts = [start for _, _, _, start in self.steps]
        steps = tuple(
            StepEvidence(j, length, radius, t)
            for (j, length, radius, _), t in zip(
                self.steps, execution_times(starts, self.asked_s), strict=True
            )
            if t is not None
        )
        return ReachEvidence(
            model=model_in_force(self.choices) or model,
            success=success,
            t_total_s=t_total_s,
            final_error_m=final_error_m,
            sparc=sparc if sparc is not None and math.isfinite(sparc) else None,
            decisions=tuple(self.decisions),
            steps=steps,
        )


def model_in_force(choices: list[tuple[int, int]]) -> tuple[int, int] | None:
    """The M_ij of most decisions (the first such among ties), None without one."""
    if not choices:
        return None
    counts = Counter(choices)
    best = max(counts.values())
    return next(c for c in choices if counts[c] == best)


def robot_model_of(models: ModelSet, steps_m: np.ndarray) -> int:
    """The j whose step vector ``steps_m`` is (the nearest, for a rounded copy)."""
    distances = [float(np.abs(models.steps_m(j) - steps_m).sum()) for j in ROBOT_MODELS]
    return ROBOT_MODELS[int(np.argmin(distances))]


def execution_times(step_starts_s: list[float], asked_s: list[float]) -> list[float | None]:
    """Each step's execution time: its reference starting to the next decision request
    (the event trigger admitting it); None for a step no request followed (the last)."""
    asked = sorted(asked_s)
    times: list[float | None] = []
    for start in step_starts_s:
        after = next((t for t in asked if t >= start - 1e-9), None)
        times.append(None if after is None else max(0.0, after - start))
    return times


# ---- targets ---------------------------------------------------------------------------
class Targets(BaseModel):
    """What the protocol asks of the last ``window`` reaches (S3's "task targets");
    a target left None is not asked."""

    model_config = ConfigDict(
        frozen=True, extra="forbid", allow_inf_nan=False, use_attribute_docstrings=True
    )

    window: int = Field(5, ge=1, le=100)
    """Reaches the targets are judged over (and the fewest between two switches)."""
    success_min: float | None = Field(0.8, ge=0, le=1)
    """Share of successful reaches."""
    time_max_s: float | None = Field(20.0, gt=0, le=600)
    """Median reach time [s]."""
    final_error_max_m: float | None = Field(None, gt=0, le=1)
    """Median final error [m]."""
    comfort_min: float | None = Field(None, ge=1, le=5)
    """Mean comfort rating (1-5, from the participant display)."""
    sparc_min: float | None = Field(None, ge=-50, le=0)
    """Mean SPARC of the reaches (the smoothness proxy; closer to 0 is smoother)."""

    def unmet(self, recent: list[ReachEvidence], ratings: list[float]) -> list[str]:
        """The targets the last reaches miss, each as a short reason ([] when all met)."""
        reasons = []
        if self.success_min is not None:
            rate = float(np.mean([r.success for r in recent]))
            if rate < self.success_min:
                reasons.append(f"success {rate:.0%} < {self.success_min:.0%}")
        if self.time_max_s is not None:
            median = float(np.median([r.t_total_s for r in recent]))
            if median > self.time_max_s:
                reasons.append(f"median time {median:.1f} s > {self.time_max_s:g} s")
        if self.final_error_max_m is not None:
            error = float(np.median([r.final_error_m for r in recent]))
            if error > self.final_error_max_m:
                reasons.append(
                    f"median error {error * 1000:.0f} mm > {self.final_error_max_m * 1000:g} mm"
                )
        if self.comfort_min is not None and ratings:
            comfort = float(np.mean(ratings))
            if comfort < self.comfort_min:
                reasons.append(f"comfort {comfort:.1f} < {self.comfort_min:g}")
        if self.sparc_min is not None:
            values = [r.sparc for r in recent if r.sparc is not None]
            if values and (sparc := float(np.mean(values))) < self.sparc_min:
                reasons.append(f"SPARC {sparc:.2f} < {self.sparc_min:g}")
        return reasons


class Selection(BaseModel):
    """How the adaptive policy chooses when targets are missed
    (``DAMMRL_POLICY_SELECTION__*``)."""

    model_config = ConfigDict(
        frozen=True, extra="forbid", allow_inf_nan=False, use_attribute_docstrings=True
    )

    success_floor: float = Field(0.5, ge=0, le=1)
    """Never an option whose success lower bound (one-sided 95 %) is below this; the base
    policy, what runs without adaptation, stays allowed."""
    max_switches: int = Field(3, ge=0, le=50)
    """Switches allowed per block of ``block_reaches`` reaches."""
    block_reaches: int = Field(20, ge=1, le=1000)
    """Reaches per block (counted from the policy's start; a protocol block restarts it)."""
    interpolate: bool = False
    """Also offer steps between neighbouring models' (bounded online interpolation)."""
    seed: int = Field(0, ge=0, le=2**31 - 1)
    """Seed of the Thompson draws (the same evidence and seed, the same choices)."""


# ---- beliefs ---------------------------------------------------------------------------
@dataclass
class NormalMean:
    """A normal belief about a mean with known observation sd (conjugate), its evidence
    kept as weighted sums (so older evidence can be discounted)."""

    prior_mean: float
    prior_sd: float
    noise_sd: float
    n: float = 0.0  # sum of weights
    total: float = 0.0  # sum of weight x value

    def add(self, value: float, weight: float = 1.0, discount: float = 1.0) -> None:
        """One observation of ``weight``, the earlier ones first multiplied by ``discount``."""
        if math.isfinite(value) and weight > 0:
            self.n = self.n * discount + weight
            self.total = self.total * discount + weight * value

    @classmethod
    def of(cls, prior_mean: float, prior_sd: float, noise_sd: float,
           values: list[float]) -> NormalMean:  # fmt: skip
        """The belief after ``values``, each a whole observation."""
        return cls(prior_mean, prior_sd, noise_sd, float(len(values)), float(sum(values)))

    def posterior(self, shift: float = 0.0) -> tuple[float, float]:
        """(mean, sd) of the mean, for observations each minus ``shift``."""
        precision = self.prior_sd**-2 + self.n * self.noise_sd**-2
        total = self.total - shift * self.n
        mean = (self.prior_mean * self.prior_sd**-2 + total * self.noise_sd**-2) / precision
        return mean, precision**-0.5


@dataclass
class Accuracy:
    """A Beta belief about the share of correct commands, data discounted as they age."""

    prior_good: float
    prior_bad: float
    good: float = 0.0
    bad: float = 0.0

    def add(self, correct: bool, weight: float, discount: float) -> None:
        self.good, self.bad = self.good * discount, self.bad * discount
        if correct:
            self.good += weight
        else:
            self.bad += weight

    @property
    def alpha(self) -> float:
        return self.prior_good + self.good

    @property
    def beta(self) -> float:
        return self.prior_bad + self.bad

    @property
    def mean(self) -> float:
        return self.alpha / (self.alpha + self.beta)


@dataclass
class OptionBelief:
    """What the reaches under one option said."""

    successes: float = 0.0
    failures: float = 0.0
    log_times: list[float] = field(default_factory=list)
    log_errors: list[float] = field(default_factory=list)
    sparcs: list[float] = field(default_factory=list)


@dataclass(frozen=True)
class Draws:
    """Joint draws of every option's belief (arrays (options, DRAWS), ``options`` order)."""

    options: tuple[Option, ...]
    success: np.ndarray  # success probability
    log_time: np.ndarray  # mean log reach time [log s]
    met: np.ndarray  # targets met
    shortfall: np.ndarray  # how far short of the comfort, error and SPARC targets missed
    to_success_s: np.ndarray  # mean time to success, a failure counting the horizon [s]
    asked: int  # targets asked (those that can be judged)
    predicted_success: np.ndarray  # (options,) the table's mean prediction for the person
    predicted_time_s: np.ndarray  # (options,) its median reach time [s]
    predicted_to_success_s: np.ndarray  # (options,) its mean time to success [s]

    def row(self, option: Option) -> int:
        return self.options.index(option)

    @property
    def score(self) -> np.ndarray:
        """The rule (each term below the one before it): most targets met; then the least
        short of the comfort, error and SPARC targets; then the shortest time to success
        (success and speed in one number: a failure counts the whole horizon)."""
        short = 0.5 * np.tanh(self.shortfall)
        return np.asarray(self.met - short - 0.01 * np.tanh(self.to_success_s / 60.0))


def shortfalls(targets: Targets, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per target asked (and judged: ``values`` has its measure), how far short of it
    ``values`` are, 0 where met, in comparable units: the success and comfort shortfall
    as a share of the target, time and error in log units, SPARC as a share of |target|
    (at least 1). ``values``: success, log_time, and optionally log_error, comfort, sparc."""
    out = {}
    if targets.success_min is not None:
        out["success"] = (np.maximum(0.0, targets.success_min - values["success"])
                          / max(targets.success_min, 0.01))  # fmt: skip
    if targets.time_max_s is not None:
        out["time"] = np.maximum(0.0, values["log_time"] - math.log(targets.time_max_s))
    if targets.final_error_max_m is not None and "log_error" in values:
        out["error"] = np.maximum(0.0, values["log_error"] - math.log(targets.final_error_max_m))
    if targets.comfort_min is not None and "comfort" in values:
        out["comfort"] = (np.maximum(0.0, targets.comfort_min - values["comfort"])
                          / targets.comfort_min)  # fmt: skip
    if targets.sparc_min is not None and "sparc" in values:
        out["sparc"] = (np.maximum(0.0, targets.sparc_min - values["sparc"])
                        / max(abs(targets.sparc_min), 1.0))  # fmt: skip
    return out


GRADED = ("comfort", "error", "sparc")
"""The targets whose shortfall ranks options that meet as many targets (success and time
are ranked by the time to success instead)."""


def comfort_features(scale: np.ndarray) -> np.ndarray:
    """(1, largest axis scale, x, y, z scales) of a step-scale vector (3,) (0 small, 1 large)."""
    scale = np.asarray(scale, dtype=float)
    return np.concatenate(([1.0, float(scale.max())], scale))


class ModelPosterior:
    """The posterior over the options for one person on one arm (see the module)."""

    def __init__(self, table: ModelTable, human: HumanModel, models: ModelSet,
                 seed: int = 0, options: tuple[Option, ...] = OPTIONS) -> None:  # fmt: skip
        self.table = table
        self.options = options  # those the posterior answers for (OPTIONS, and MIDPOINTS)
        self.human = human
        self.models = models
        self.seed = seed
        self.accuracy = {
            i: Accuracy(human.accuracy(i) * PERSON_PRIOR_DECISIONS,
                        (1 - human.accuracy(i)) * PERSON_PRIOR_DECISIONS)
            for i in HUMAN_MODELS
        }  # fmt: skip
        self.log_decision = {
            i: NormalMean(
                math.log(human.decision_median_s(i)),
                max(human.decision_scale_sd, 0.05),
                human.decision_sigma,
            )
            for i in HUMAN_MODELS
        }
        self.arm = NormalMean(0.0, ARM_SCALE_PRIOR_SD, table.step_time_log_sd)
        self.beliefs = {m: OptionBelief() for m in options}
        self.ratings: list[tuple[Option, float]] = []
        self.reaches = 0
        self._decisions = 0  # evidence seen: the draws' seed and cache key
        self._cache: dict[Targets, Draws] = {}

    # ---- evidence -------------------------------------------------------------------
    def observe(self, reach: ReachEvidence, option: Option | None = None) -> None:
        """Fold in one finished reach, run under ``option`` (default: its model in force;
        ``BASE``: the base policy)."""
        for d in reach.decisions:
            self.decision(d)
        for s in reach.steps:
            self.step(s)
        belief = self.beliefs[reach.model if option is None else option]
        if reach.success:
            belief.successes += 1
        else:
            belief.failures += 1
        belief.log_times.append(math.log(max(reach.t_total_s, 1e-3)))
        belief.log_errors.append(math.log(max(reach.final_error_m, 1e-4)))
        if reach.sparc is not None and math.isfinite(reach.sparc):
            belief.sparcs.append(reach.sparc)
        self.reaches += 1
        self._cache.clear()

    def decision(self, d: DecisionEvidence) -> None:
        confidence = min(1.0, max(0.0, d.confidence))
        discount = 0.5 ** (1.0 / HALF_LIFE_DECISIONS)
        self.accuracy[d.human_model].add(d.correct, confidence, discount)
        if d.decision_s is not None and d.decision_s > self.human.decision_min_s:
            self.log_decision[d.human_model].add(math.log(d.decision_s), confidence, discount)
        self._decisions += 1
        self._cache.clear()

    def step(self, s: StepEvidence) -> None:
        predicted = self.table.step_time_s(s.length_m, s.radius_m)
        if s.execution_s > 0 and predicted > 0:
            self.arm.add(math.log(s.execution_s / predicted))
            self._cache.clear()

    def rating(self, option: Option, rating: float) -> None:
        """The participant's comfort rating (1-5) of reaches mostly under ``option``."""
        self.ratings.append((option, float(rating)))
        self._cache.clear()

    # ---- the person and the arm -----------------------------------------------------
    def person_accuracy(self, i: int) -> float:
        return self.accuracy[i].mean

    def decision_ratio(self, i: int) -> float:
        """The person's median decision time under i over the sub-model's."""
        mean, _ = self.log_decision[i].posterior()
        return math.exp(mean - math.log(self.human.decision_median_s(i)))

    @property
    def arm_scale(self) -> float:
        """This arm's step-time factor s against the nominal arm."""
        return math.exp(self.arm.posterior()[0])

    def persons(self, rng: np.random.Generator, n: int = DRAWS) -> Persons:
        """``n`` draws of the person and the arm from their posterior."""
        ratios = []
        for i in HUMAN_MODELS:
            mean, sd = self.log_decision[i].posterior()
            ratios.append(np.exp(rng.normal(mean - math.log(self.human.decision_median_s(i)),
                                            sd, n)))  # fmt: skip
        arm_mean, arm_sd = self.arm.posterior()
        return Persons(
            accuracy_big=rng.beta(self.accuracy[1].alpha, self.accuracy[1].beta, n),
            accuracy_small=rng.beta(self.accuracy[2].alpha, self.accuracy[2].beta, n),
            time_ratio_big=ratios[0],
            time_ratio_small=ratios[1],
            arm_scale=np.exp(rng.normal(arm_mean, arm_sd, n)),
        )

    # ---- every option, for this person ----------------------------------------------
    def draws(self, targets: Targets) -> Draws:
        """Joint draws of every option's belief (cached until new evidence)."""
        if targets not in self._cache:
            self._cache[targets] = self._draw(targets, self.options)
        return self._cache[targets]

    def _draw(self, targets: Targets, options: tuple[Option, ...]) -> Draws:
        rng = np.random.default_rng([self.seed, self.reaches, self._decisions, len(self.ratings)])
        persons = self.persons(rng)
        predictions = self._predictions(options, persons)
        comfort = self._comfort_draws(predictions, rng) if targets.comfort_min else None
        success, log_time, to_success, met, short = [], [], [], [], []
        asked = 0
        horizon = self.table.horizon_s
        for k, (option, p) in enumerate(zip(options, predictions, strict=True)):
            belief = self.beliefs[option]
            s = rng.beta(PRIOR_REACHES * p.success + 0.5 + belief.successes,
                         PRIOR_REACHES * (1 - p.success) + 0.5 + belief.failures)  # fmt: skip
            t = self._time_draws(p, belief, rng)
            # a success takes the table's time of successes, moved by the option's own offset
            took = np.minimum(np.exp(p.log_time_success + t - p.log_time), horizon)
            checks = self._checks(targets, p, belief, s, t, rng,
                                  None if comfort is None else comfort[k])  # fmt: skip
            asked = len(checks)
            success.append(s)
            log_time.append(t)
            to_success.append(s * took + (1 - s) * horizon)
            met.append(np.sum([c <= 0 for c in checks.values()], axis=0))
            graded = [checks[name] for name in GRADED if name in checks]
            short.append(np.sum(graded, axis=0) if graded else np.zeros(DRAWS))
        return Draws(
            options=options,
            success=np.array(success),
            log_time=np.array(log_time),
            met=np.array(met),
            shortfall=np.array(short),
            to_success_s=np.array(to_success),
            asked=asked,
            predicted_success=np.array([float(p.success.mean()) for p in predictions]),
            predicted_time_s=np.exp([float(np.median(p.log_time)) for p in predictions]),
            predicted_to_success_s=np.array([float(p.to_success_s.mean()) for p in predictions]),
        )

    def _predictions(self, options: tuple[Option, ...], persons: Persons) -> list[Prediction]:
        """Each option's prediction; a midpoint's from its neighbours' (each made once)."""
        made: dict[Option, Prediction] = {}

        def of(option: Option) -> Prediction:
            if option not in made:
                if len(option) == 3:
                    i, j, k = option
                    made[option] = halfway(of((i, j)), of((i, k)))
                else:
                    made[option] = self.table.predict(option, persons)
            return made[option]

        return [of(o) for o in options]

    def _time_draws(self, p: Prediction, belief: OptionBelief,
                    rng: np.random.Generator) -> np.ndarray:  # fmt: skip
        """The option's mean log time: prior N(prediction, OFFSET_PRIOR_SD^2) per person
        draw, its own reaches' log times around it (sd: the table's spread)."""
        n, total = len(belief.log_times), sum(belief.log_times)
        precision = OFFSET_PRIOR_SD**-2 + n * p.log_time_sd**-2
        mean = (p.log_time * OFFSET_PRIOR_SD**-2 + total * p.log_time_sd**-2) / precision
        return np.asarray(rng.normal(mean, precision**-0.5))

    def _checks(self, targets: Targets, p: Prediction, belief: OptionBelief, success: np.ndarray,
                log_time: np.ndarray, rng: np.random.Generator,
                comfort: np.ndarray | None) -> dict[str, np.ndarray]:  # fmt: skip
        """Per target asked, each draw's shortfall (0: met; see ``shortfalls``)."""
        draws: dict[str, np.ndarray] = {"success": success, "log_time": log_time}
        if targets.final_error_max_m is not None:
            errors = NormalMean.of(p.log_error, OFFSET_PRIOR_SD, p.log_error_sd, belief.log_errors)
            draws["log_error"] = rng.normal(*errors.posterior(), DRAWS)
        if comfort is not None:
            draws["comfort"] = comfort
        if targets.sparc_min is not None:
            sparcs = NormalMean.of(p.sparc, p.sparc_sd, p.sparc_sd, belief.sparcs)
            draws["sparc"] = rng.normal(*sparcs.posterior(), DRAWS)
        return shortfalls(targets, draws)

    def _comfort_draws(self, predictions: list[Prediction],
                       rng: np.random.Generator) -> np.ndarray | None:  # fmt: skip
        """Each option's mean rating per draw (options, DRAWS); None before any rating."""
        if not self.ratings:
            return None
        mean, cov = self.comfort_posterior()
        coefficients = rng.multivariate_normal(mean, cov, DRAWS)  # (DRAWS, 5)
        features = np.array([comfort_features(p.scale) for p in predictions])
        return np.asarray(features @ coefficients.T)

    def comfort_posterior(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean, covariance) of the comfort regression's coefficients (conjugate normal)."""
        prior_precision = np.diag(np.asarray(COMFORT_PRIOR_SD) ** -2.0)
        precision, weighted = prior_precision.copy(), prior_precision @ COMFORT_PRIOR_MEAN
        for option, rating in self.ratings:
            x = comfort_features(self._scale(option))
            precision += np.outer(x, x) / COMFORT_NOISE_SD**2
            weighted += x * rating / COMFORT_NOISE_SD**2
        cov = np.linalg.inv(precision)
        return cov @ weighted, cov

    def _scale(self, option: Option) -> np.ndarray:
        if len(option) == 3:
            halves = self._scale(option[:2]) + self._scale((option[0], option[2]))
            return np.asarray(halves / 2)
        reaches = self.table.reaches(option)
        return np.array([reaches.array(f"scale_{a}").mean() for a in "xyz"])

    # ---- the answers ----------------------------------------------------------------
    def meets(self, targets: Targets, options: tuple[Option, ...] = MODELS) -> np.ndarray:
        """Each option's probability of meeting every target asked (``options`` order)."""
        draws = self.draws(targets)
        met = draws.met[[draws.row(o) for o in options]]
        return np.asarray((met >= draws.asked).mean(axis=1))

    def success_lower(self, targets: Targets, options: tuple[Option, ...] | None = None
                      ) -> np.ndarray:  # fmt: skip
        """Each option's success lower bound (the LOWER_QUANTILE of its draws; default:
        every option of the posterior, in its order)."""
        options = self.options if options is None else options
        draws = self.draws(targets)
        rows = [draws.row(o) for o in options]
        return np.asarray(np.quantile(draws.success[rows], LOWER_QUANTILE, axis=1))

    def probabilities(self, targets: Targets) -> np.ndarray:
        """P(M_ij is the best model for this person): the one meeting most targets,
        fastest among ties (MODELS order)."""
        draws = self.draws(targets)
        rows = [draws.row(m) for m in MODELS]
        best = np.argmax(draws.score[rows], axis=0)
        return np.bincount(best, minlength=len(MODELS)) / DRAWS

    def thompson(self, targets: Targets, allowed: tuple[Option, ...],
                 rng: np.random.Generator) -> Option:  # fmt: skip
        """Thompson sampling: the best of ``allowed`` in one draw of the posterior."""
        draws = self.draws(targets)
        k = int(rng.integers(DRAWS))
        scores = [draws.score[draws.row(o), k] for o in allowed]
        return allowed[int(np.argmax(scores))]

    def summary(self, targets: Targets) -> dict[str, Any]:
        """The estimates and the per-option answers (for logs, reports and tests)."""
        draws = self.draws(targets)
        return {
            "reaches": self.reaches,
            "accuracy": {i: round(self.person_accuracy(i), 4) for i in HUMAN_MODELS},
            "decision_ratio": {i: round(self.decision_ratio(i), 4) for i in HUMAN_MODELS},
            "arm_scale": round(self.arm_scale, 4),
            "meets": dict(zip(MODELS, np.round(self.meets(targets), 4).tolist(), strict=True)),
            "meets_base": round(float(self.meets(targets, (BASE,))[0]), 4),
            "success_lower": _by_option(self.options, self.success_lower(targets), 4),
            "predicted_success": _by_option(draws.options, draws.predicted_success, 4),
            "predicted_time_s": _by_option(draws.options, draws.predicted_time_s, 2),
            "predicted_to_success_s": _by_option(draws.options, draws.predicted_to_success_s, 2),
            "posterior": dict(zip(MODELS, self.probabilities(targets).tolist(), strict=True)),
        }


def _by_option(options: tuple[Option, ...], values: np.ndarray, digits: int) -> dict[Option, float]:
    return dict(zip(options, np.round(values, digits).tolist(), strict=True))
