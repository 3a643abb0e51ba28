"""Co-adaptation: the posterior over the model set M_ij and the paper's S3 re-selection.

Algorithm 1 step (f) updates "the model posterior probability using online estimates of
the human's effective error rate and decision frequency, alongside the observed execution
time of the robot"; S3 updates it "based on real-world task performance and user comfort"
and, "if task targets are unmet, ... selects alternative matched models".

Here each M_ij has a predictive belief about what a reach under it gives *this* person on
*this* arm: its success probability, its (log) reach time, its (log) final error and its
comfort. The beliefs start from the model table (what each M_ij gave the nominal
simulated person on the nominal arm, ``dammrl adapt table``) and are moved by four kinds
of evidence, each with a stated likelihood (docs/guide/coadaptation.md):

* **the person** (per radius i): each command is Bernoulli(a_i) with a Beta prior at the
  sub-model's accuracy, a wearable's confidence c counting as c of an observation; each
  decision time is lognormal around the person's median under i, with a normal prior at
  the sub-model's (sd ``decision_scale_sd``) and known log-sd ``decision_sigma``;
* **the robot**: each step's execution time (its reference starting to the trigger that
  admits it) is lognormal around ``s * tau(L, eps)``, the nominal arm's time for a step
  of that length and admission radius, scaled by this arm's unknown factor s (log s
  normal, prior sd 0.3);
* **the task**: each reach's success is Bernoulli(p_ij) (Beta prior at the table's rate,
  ``PRIOR_REACHES`` pseudo-reaches), its log time and log final error normal around the
  model's prediction with a per-model offset (normal prior);
* **comfort**: the participant's rating after a block (1-5, from the session display)
  where present, else a smoothness proxy (SPARC of the reach: both a rating and a jerk
  measure are what the paper calls comfort; the proxy is what a simulation has).

The person's and the arm's estimates reach *every* model, not only the one in force: a
model's predicted time is its table time with the decision share scaled by the person's
decision-time ratio, the execution share by s, and the step count by how far the person's
accuracy is from the sub-model's (net progress per decision is 2a - 1). The task and
comfort evidence reach the model in force.

``probabilities`` is the posterior probability that M_ij is the best model for the person
(the one meeting most targets, fastest among ties), by a seeded Monte Carlo over the
beliefs; ``meets`` is each model's probability of meeting every target.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import stats

from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS, ModelSet

MODELS: tuple[tuple[int, int], ...] = tuple((i, j) for i in HUMAN_MODELS for j in ROBOT_MODELS)
"""Every M_ij, in the posterior's order (i major)."""
BASE = (0, 0)
"""The base policy itself (the learned DQN, choosing M_ij per state): an option of the
re-selection beside the 16 models, with beliefs of its own. Its reaches are credited to
it, not to the M_ij it chose most: a policy that changes j along a reach is faster than
any fixed M_ij, and crediting its reaches to one would make that model look better than
it is."""
OPTIONS: tuple[tuple[int, int], ...] = (BASE, *MODELS)
PRIOR_REACHES = 4.0
"""Pseudo-reaches behind a model's table success rate: four real reaches weigh as much."""
ARM_SCALE_PRIOR_SD = 0.3
"""Prior sd of log s, this arm's step-time factor against the nominal arm (x1.8 at 2 sd)."""
OFFSET_PRIOR_SD = 0.3
"""Prior sd of a model's own log-time (and log-error, comfort) offset from its prediction."""
DRAWS = 2000
"""Monte Carlo draws behind ``probabilities`` (seeded: the same evidence, the same answer)."""
MIN_NET_PROGRESS = 0.1
"""2a - 1 is bounded below by this in the step-count scaling (a person at chance would
need unboundedly many steps; the episode timeout bounds it in fact)."""
TABLE = Path(str(resources.files("dammrl_core").joinpath("policies", "model_table.json")))


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


# ---- the model table: what each M_ij gave the nominal person ----------------------------
class ModelRow(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    human_model: int = Field(ge=0, le=2)  # (0, 0): the base policy
    robot_model: int = Field(ge=0, le=8)
    reaches: int = Field(ge=1)
    big_share: float = Field(ge=0, le=1)  # of decisions under E_big (i = 1)
    success_rate: float = Field(ge=0, le=1)
    log_time_mean: float  # mean log t_total [log s]
    log_time_sd: float = Field(gt=0)
    log_error_mean: float  # mean log final error [log m]
    log_error_sd: float = Field(gt=0)
    sparc_mean: float
    sparc_sd: float = Field(gt=0)
    decision_share: float = Field(ge=0, le=1)  # of t_total spent waiting for decisions
    execution_share: float = Field(ge=0, le=1)  # of t_total spent executing steps


class ModelTable(BaseModel):
    """Per M_ij, what a reach gave the nominal simulated person on the nominal arm, and
    the nominal arm's step time, log tau = c + b_L log L + b_eps log eps (a step of length
    L to within an admission radius eps), with its log-sd."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    seeds: str
    step_time_log_intercept: float
    step_time_log_length: float
    step_time_log_radius: float
    step_time_log_sd: float = Field(gt=0)
    rows: tuple[ModelRow, ...]  # one per M_ij, and the base policy's (0, 0)

    def row(self, model: tuple[int, int]) -> ModelRow:
        for row in self.rows:
            if (row.human_model, row.robot_model) == model:
                return row
        raise ConfigurationError(f"the model table has no row for M_{model[0]},{model[1]}")

    def step_time_s(self, length_m: float, radius_m: float) -> float:
        """The nominal arm's execution time of a step [s]."""
        log_tau = (self.step_time_log_intercept
                   + self.step_time_log_length * math.log(max(length_m, 1e-4))
                   + self.step_time_log_radius * math.log(max(radius_m, 1e-4)))  # fmt: skip
        return math.exp(log_tau)

    @classmethod
    def load(cls, path: Path = TABLE) -> ModelTable:
        try:
            table = cls.model_validate(json.loads(path.read_text()))
        except (OSError, ValueError) as exc:
            raise ConfigurationError(f"model table {path}: {exc}") from exc
        if sorted((r.human_model, r.robot_model) for r in table.rows) != sorted(OPTIONS):
            raise ConfigurationError(
                f"model table {path} must have one row per M_ij and the base policy's"
            )
        return table


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


# ---- beliefs ---------------------------------------------------------------------------
@dataclass
class NormalMean:
    """A normal belief about a mean with known observation sd (conjugate)."""

    prior_mean: float
    prior_sd: float
    noise_sd: float
    values: list[float] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)

    def add(self, value: float, weight: float = 1.0) -> None:
        if math.isfinite(value) and weight > 0:
            self.values.append(value)
            self.weights.append(weight)

    @classmethod
    def of(cls, prior_mean: float, prior_sd: float, noise_sd: float,
           values: list[float]) -> NormalMean:  # fmt: skip
        """The belief after ``values``, each a whole observation."""
        return cls(prior_mean, prior_sd, noise_sd, list(values), [1.0] * len(values))

    @property
    def n(self) -> float:
        return float(sum(self.weights))

    def posterior(self, shift: float = 0.0) -> tuple[float, float]:
        """(mean, sd) of the mean, for observations each minus ``shift``."""
        precision = self.prior_sd**-2 + self.n * self.noise_sd**-2
        total = sum(w * (v - shift) for v, w in zip(self.values, self.weights, strict=True))
        mean = (self.prior_mean * self.prior_sd**-2 + total * self.noise_sd**-2) / precision
        return mean, precision**-0.5


@dataclass
class ModelBelief:
    """What the reaches under one M_ij said (its offsets from the prediction)."""

    successes: float = 0.0
    failures: float = 0.0
    log_times: list[float] = field(default_factory=list)
    log_errors: list[float] = field(default_factory=list)
    sparcs: list[float] = field(default_factory=list)
    ratings: list[float] = field(default_factory=list)


class ModelPosterior:
    """The posterior over M_ij for one person on one arm (see the module's docstring)."""

    def __init__(self, table: ModelTable, human: HumanModel, models: ModelSet) -> None:
        self.table = table
        self.human = human
        self.models = models
        self.accuracy = {
            i: [human.accuracy(i) * PRIOR_REACHES, (1 - human.accuracy(i)) * PRIOR_REACHES]
            for i in HUMAN_MODELS
        }
        self.log_decision = {
            i: NormalMean(
                math.log(human.decision_median_s(i)),
                max(human.decision_scale_sd, 0.05),
                human.decision_sigma,
            )
            for i in HUMAN_MODELS
        }
        self.arm = NormalMean(0.0, ARM_SCALE_PRIOR_SD, table.step_time_log_sd)
        self.beliefs = {m: ModelBelief() for m in OPTIONS}
        self.reaches = 0

    # ---- evidence -------------------------------------------------------------------
    def observe(self, reach: ReachEvidence, option: tuple[int, int] | None = None) -> None:
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

    def decision(self, d: DecisionEvidence) -> None:
        confidence = min(1.0, max(0.0, d.confidence))
        self.accuracy[d.human_model][0 if d.correct else 1] += confidence
        if d.decision_s is not None and d.decision_s > self.human.decision_min_s:
            self.log_decision[d.human_model].add(math.log(d.decision_s), confidence)

    def step(self, s: StepEvidence) -> None:
        predicted = self.table.step_time_s(s.length_m, s.radius_m)
        if s.execution_s > 0 and predicted > 0:
            self.arm.add(math.log(s.execution_s / predicted))

    def rating(self, model: tuple[int, int], rating: float) -> None:
        """The participant's comfort rating (1-5) for a block mostly under ``model``."""
        self.beliefs[model].ratings.append(float(rating))

    # ---- what the evidence says -----------------------------------------------------
    def person_accuracy(self, i: int) -> float:
        good, bad = self.accuracy[i]
        return good / (good + bad)

    def decision_ratio(self, i: int) -> float:
        """The person's median decision time under i over the sub-model's."""
        mean, _ = self.log_decision[i].posterior()
        return math.exp(mean - math.log(self.human.decision_median_s(i)))

    @property
    def arm_scale(self) -> float:
        """This arm's step-time factor s against the nominal arm."""
        return math.exp(self.arm.posterior()[0])

    def predicted_log_time(self, model: tuple[int, int]) -> float:
        """The model's table log time, its decision share scaled by the person's speed,
        its execution share by the arm's, and its step count by the person's accuracy
        (each radius weighted by its share of the model's decisions)."""
        row = self.table.row(model)
        weights = {1: row.big_share, 2: 1.0 - row.big_share}
        steps = sum(
            w
            * (2 * self.human.accuracy(i) - 1)
            / max(2 * self.person_accuracy(i) - 1, MIN_NET_PROGRESS)
            for i, w in weights.items()
        )
        deciding = sum(w * self.decision_ratio(i) for i, w in weights.items())
        other = max(0.0, 1.0 - row.decision_share - row.execution_share)
        factor = other + steps * (
            row.decision_share * deciding + row.execution_share * self.arm_scale
        )
        return row.log_time_mean + math.log(max(factor, 1e-3))

    def success_belief(self, model: tuple[int, int]) -> tuple[float, float]:
        """Beta(alpha, beta) of the model's success probability."""
        row, belief = self.table.row(model), self.beliefs[model]
        prior = row.success_rate * PRIOR_REACHES
        return (prior + belief.successes + 0.5, PRIOR_REACHES - prior + belief.failures + 0.5)

    def time_belief(self, model: tuple[int, int]) -> tuple[float, float]:
        """(mean, sd) of the model's mean log reach time for this person."""
        row, belief = self.table.row(model), self.beliefs[model]
        offset = NormalMean.of(0.0, OFFSET_PRIOR_SD, row.log_time_sd, belief.log_times)
        predicted = self.predicted_log_time(model)
        mean, sd = offset.posterior(shift=predicted)
        return predicted + mean, sd

    def error_belief(self, model: tuple[int, int]) -> tuple[float, float]:
        row, belief = self.table.row(model), self.beliefs[model]
        errors = NormalMean.of(
            row.log_error_mean, OFFSET_PRIOR_SD, row.log_error_sd, belief.log_errors
        )
        return errors.posterior()

    def comfort_belief(self, model: tuple[int, int]) -> tuple[float, float] | None:
        """(mean, sd) of the option's mean rating; None before any rating of any option."""
        if not any(b.ratings for b in self.beliefs.values()):
            return None
        ratings = self.beliefs[model].ratings
        return NormalMean.of(3.0, 1.0, 1.0, ratings).posterior()

    def sparc_belief(self, model: tuple[int, int]) -> tuple[float, float]:
        row, belief = self.table.row(model), self.beliefs[model]
        sparcs = NormalMean.of(row.sparc_mean, row.sparc_sd, row.sparc_sd, belief.sparcs)
        return sparcs.posterior()

    def meets(self, targets: Targets, options: tuple[tuple[int, int], ...] = MODELS) -> np.ndarray:
        """Each option's probability of meeting every target (default: per M_ij, MODELS
        order), the terms taken as independent."""
        return np.array([math.prod(self._meets_each(m, targets)) for m in options])

    def _meets_each(self, model: tuple[int, int], targets: Targets) -> list[float]:
        p = []
        if targets.success_min is not None:
            p.append(float(stats.beta.sf(targets.success_min, *self.success_belief(model))))
        if targets.time_max_s is not None:
            mean, sd = self.time_belief(model)
            p.append(float(stats.norm.cdf(math.log(targets.time_max_s), mean, sd)))
        if targets.final_error_max_m is not None:
            mean, sd = self.error_belief(model)
            p.append(float(stats.norm.cdf(math.log(targets.final_error_max_m), mean, sd)))
        if targets.comfort_min is not None and (c := self.comfort_belief(model)) is not None:
            p.append(float(stats.norm.sf(targets.comfort_min, *c)))
        if targets.sparc_min is not None:
            p.append(float(stats.norm.sf(targets.sparc_min, *self.sparc_belief(model))))
        return p

    def probabilities(self, targets: Targets) -> np.ndarray:
        """P(M_ij is the best model for this person): the one meeting most targets,
        fastest among ties, by ``DRAWS`` seeded draws from the beliefs."""
        rng = np.random.default_rng(self.reaches)
        met = np.zeros((DRAWS, len(MODELS)))
        times = np.zeros((DRAWS, len(MODELS)))
        for k, model in enumerate(MODELS):
            draws = self._draws(model, targets, rng)
            met[:, k] = draws["met"]
            times[:, k] = draws["log_time"]
        score = met - 1e-3 * np.tanh(times / 10)  # most targets met; then the faster
        best = np.argmax(score, axis=1)
        return np.bincount(best, minlength=len(MODELS)) / DRAWS

    def _draws(
        self, model: tuple[int, int], targets: Targets, rng: np.random.Generator
    ) -> dict[str, np.ndarray]:
        mean, sd = self.time_belief(model)
        log_time = rng.normal(mean, sd, DRAWS)
        met = np.zeros(DRAWS)
        if targets.success_min is not None:
            met += rng.beta(*self.success_belief(model), DRAWS) >= targets.success_min
        if targets.time_max_s is not None:
            met += log_time <= math.log(targets.time_max_s)
        if targets.final_error_max_m is not None:
            e_mean, e_sd = self.error_belief(model)
            met += rng.normal(e_mean, e_sd, DRAWS) <= math.log(targets.final_error_max_m)
        if targets.comfort_min is not None and (c := self.comfort_belief(model)) is not None:
            met += rng.normal(*c, DRAWS) >= targets.comfort_min
        if targets.sparc_min is not None:
            met += rng.normal(*self.sparc_belief(model), DRAWS) >= targets.sparc_min
        return {"met": met, "log_time": log_time}

    def summary(self, targets: Targets) -> dict[str, Any]:
        """The estimates and both per-model answers (for logs, reports and tests)."""
        return {
            "reaches": self.reaches,
            "accuracy": {i: round(self.person_accuracy(i), 4) for i in HUMAN_MODELS},
            "decision_ratio": {i: round(self.decision_ratio(i), 4) for i in HUMAN_MODELS},
            "arm_scale": round(self.arm_scale, 4),
            "meets": dict(zip(MODELS, np.round(self.meets(targets), 4).tolist(), strict=True)),
            "meets_base": round(float(self.meets(targets, (BASE,))[0]), 4),
            "posterior": dict(zip(MODELS, self.probabilities(targets).tolist(), strict=True)),
        }
