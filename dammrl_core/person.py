"""How a simulated person departs from the human sub-model they use.

The policy scores people with the nominal sub-models (:class:`dammrl_core.human.HumanModel`);
a real person is rarely exactly one of them. These settings make the *simulated* person
differ, so the policy's posterior can be tried on people unlike its model:

* ``behaviour="model"``: the nominal lognormal sub-model, optionally with another accuracy
  and every decision time scaled (a slower or quicker person).
* ``behaviour="ddm"``: a drift-diffusion decider. Evidence accumulates at drift ``v`` with
  unit noise between two boundaries ``a`` apart, starting midway; the radius sets ``a``
  (E_big: narrow, hurried; E_small: wide, careful). One mechanism gives both the
  accuracy, ``1 / (1 + exp(-v a))``, and the decision time, a first passage plus a
  non-decision time, so speed and accuracy trade off as in people.

Either behaviour can change with practice: fatigue within a session and learning across
sessions scale the person's skill, the log-odds of a correct command (a DDM person's
drift, which scales the same log-odds ``v a``), and fatigue can slow every decision. A
person may find large steps uncomfortable: after a reach they rate it 1-5 from the share
of steps longer than they like (``comfort_rating``).

A kind of person can be written down in a YAML file (``load_person``): any field below,
with a ``name`` and the ``source`` of its numbers.

The defaults leave the person identical to the model (bit for bit: same draws).
"""

from __future__ import annotations

import difflib
import functools
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.settings import FINITE

_GRID_POINTS = 4096  # of the first-passage CDF that samples are drawn from
# NOTE: v a <= 40 by the bounds below, so the series (weighted by cosh(v a / 2)) keeps
# eight significant digits where the survival is near 1
_TAIL = 1e-10  # survival probability where the grid ends


class SimulatedPerson(BaseModel):
    """The simulated person (``DAMMRL_HUMAN_PERSON__*``); defaults: exactly the model."""

    model_config = FINITE

    behaviour: Literal["model", "ddm"] = "model"
    """``model``: the nominal sub-model (with the overrides below); ``ddm``: drift diffusion."""
    accuracy: float | None = Field(None, gt=0, lt=1)
    """Probability of a correct command under either radius, in place of the sub-model's
    (``model`` only; a DDM person's accuracy follows from its drift and boundaries)."""
    accuracy_big: float | None = Field(None, gt=0, lt=1)
    """Probability of a correct command under E_big (i = 1) only, in place of the
    sub-model's (``model`` only; not with ``accuracy``)."""
    accuracy_small: float | None = Field(None, gt=0, lt=1)
    """Probability of a correct command under E_small (i = 2) only (as ``accuracy_big``)."""
    decision_time_factor: float = Field(1.0, gt=0, le=10)
    """Every decision time multiplied by this (1.5: a person 50 % slower than modelled)."""
    ddm_drift_per_s: float = Field(2.0, gt=0, le=10)
    """Drift rate v of the evidence toward the correct command [1/s] (unit noise)."""
    ddm_boundary_big: float = Field(0.7, gt=0, le=4)
    """Boundary separation a under E_big (i = 1): narrow, so fast and error-prone."""
    ddm_boundary_small: float = Field(1.1, gt=0, le=4)
    """Boundary separation a under E_small (i = 2): wide, so slow and accurate."""
    ddm_non_decision_s: float = Field(0.15, ge=0, le=10)
    """Perception and motor time added to every first passage [s]."""
    fatigue_per_reach: float = Field(0.0, ge=0, le=0.1)
    """Skill lost per reach within a session: after n reaches the log-odds of a correct
    command (a DDM person's drift) are x(1 - f)^n (0.02: 0.85 falls to 0.74 in 25 reaches)."""
    slowing_per_reach: float = Field(0.0, ge=0, le=0.1)
    """Decision times grow by this share per reach within a session: x(1 + k n)."""
    learning_per_session: float = Field(0.0, ge=0, le=1)
    """Skill gained per session after the first: in session s the log-odds of a correct
    command (a DDM person's drift) are x(1 + l)^(s - 1)."""
    comfort_step_max_m: float | None = Field(None, gt=0, le=0.1)
    """The longest step on any axis the person finds comfortable [m] (None: any step)."""
    comfort_rating_sd: float = Field(0.5, ge=0, le=2)
    """Noise of the person's comfort rating before it is rounded to 1-5."""

    @model_validator(mode="after")
    def _accuracy_only_for_the_model(self) -> SimulatedPerson:
        per_radius = self.accuracy_big is not None or self.accuracy_small is not None
        if self.behaviour == "ddm" and (self.accuracy is not None or per_radius):
            raise ValueError(
                "accuracy cannot be set for behaviour 'ddm': it follows from "
                "ddm_drift_per_s and the boundaries"
            )
        if self.accuracy is not None and per_radius:
            raise ValueError("accuracy is for both radii: set it or accuracy_big/accuracy_small")
        return self

    def accuracy_under(self, i: int, model_accuracy: float) -> float:
        """The ``model`` person's probability of a correct command under radius ``i``, the
        sub-model's being ``model_accuracy``."""
        own = self.accuracy_big if i == 1 else self.accuracy_small
        if own is not None:
            return own
        return model_accuracy if self.accuracy is None else self.accuracy

    @property
    def changes_with_practice(self) -> bool:
        return bool(self.fatigue_per_reach or self.slowing_per_reach or self.learning_per_session)

    def skill(self, session: int, reach: int) -> float:
        """The factor on the log-odds of a correct command in ``session`` (from 1) after
        ``reach`` reaches of it (from 0)."""
        return (1.0 - self.fatigue_per_reach) ** reach * (1.0 + self.learning_per_session) ** (
            session - 1
        )

    def practised(self, session: int, reach: int, model_accuracy: tuple[float, float]
                  ) -> SimulatedPerson:  # fmt: skip
        """This person in ``session`` after ``reach`` of its reaches, fatigue and learning
        folded in (a person that no longer changes); ``model_accuracy``: the sub-models'
        (E_big, E_small) accuracies the ``model`` person starts from."""
        if session < 1 or reach < 0:
            raise ValueError(f"session counts from 1 and reach from 0, got {session}, {reach}")
        g = self.skill(session, reach)
        update: dict[str, Any] = {"fatigue_per_reach": 0.0, "slowing_per_reach": 0.0,
                                  "learning_per_session": 0.0,
                                  "decision_time_factor": min(10.0, self.decision_time_factor
                                                              * (1 + self.slowing_per_reach
                                                                 * reach))}  # fmt: skip
        if self.behaviour == "ddm":
            update["ddm_drift_per_s"] = min(10.0, max(1e-6, g * self.ddm_drift_per_s))
        else:
            update["accuracy"] = None
            for i, name in ((1, "accuracy_big"), (2, "accuracy_small")):
                a = self.accuracy_under(i, model_accuracy[i - 1])
                update[name] = _logistic(g * math.log(a / (1 - a)))
        return self.model_copy(update=update)

    def comfort_rating(self, steps_m: np.ndarray, rng: np.random.Generator) -> int:
        """The person's rating (1-5) of a reach whose steps were ``steps_m`` (n, 3) [m]:
        5 less 4 x the share of steps longer than ``comfort_step_max_m`` on any axis, with
        noise, rounded (one normal draw)."""
        steps = np.abs(np.asarray(steps_m, dtype=float)).reshape(-1, 3)
        share = 0.0
        if self.comfort_step_max_m is not None and len(steps):
            share = float(np.mean(steps.max(axis=1) > self.comfort_step_max_m + 1e-9))
        rating = 5.0 - 4.0 * share + self.comfort_rating_sd * rng.standard_normal()
        return int(min(5, max(1, round(rating))))

    def boundary(self, i: int) -> float:
        return self.ddm_boundary_big if i == 1 else self.ddm_boundary_small

    def ddm_accuracy(self, i: int) -> float:
        """Probability that the DDM person commands toward the goal under sub-model ``i``."""
        return ddm_correct_probability(self.ddm_drift_per_s, self.boundary(i))

    def ddm_mean_decision_s(self, i: int) -> float:
        """Mean decision time of the DDM person under sub-model ``i`` [s] (time factor in)."""
        passage = ddm_mean_passage_s(self.ddm_drift_per_s, self.boundary(i))
        return self.decision_time_factor * (self.ddm_non_decision_s + passage)

    def sample_ddm(self, rng: np.random.Generator, i: int) -> tuple[bool, float]:
        """One DDM decision: (correct, decision time [s]); a uniform for each, in that order.

        NOTE: with the start midway the passage time does not depend on which boundary is
        hit, so the choice and the time can be drawn apart, each exactly.
        """
        v, a = self.ddm_drift_per_s, self.boundary(i)
        correct = bool(rng.random() < ddm_correct_probability(v, a))
        grid_s, cdf = _passage_cdf(v, a)
        passage = float(np.interp(rng.random(), cdf, grid_s))
        return correct, self.decision_time_factor * (self.ddm_non_decision_s + passage)


def _logistic(log_odds: float) -> float:
    """The probability of ``log_odds``, kept inside (0, 1) as a setting must be."""
    return min(1 - 1e-6, max(1e-6, 1.0 / (1.0 + math.exp(-log_odds))))


# ---- a kind of person, in a file ---------------------------------------------------
class PersonFile(BaseModel):
    """A kind of simulated person as written down: its name, where its numbers come from,
    and the person."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str
    source: str
    """Where the parameters come from (a published range, or the rationale)."""
    person: SimulatedPerson


def load_person(path: Path) -> PersonFile:
    """A person file (YAML): any ``SimulatedPerson`` field, and optionally ``name``
    (default: the file's stem) and ``source``; a ConfigurationError of one line naming
    the file, the field, its value and what was expected."""
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigurationError(f"person {path}: cannot read it: {_one_line(exc)}") from exc
    if not isinstance(raw, dict):
        raise ConfigurationError(f"person {path}: not a mapping of SimulatedPerson fields")
    name = raw.pop("name", path.stem)
    source = raw.pop("source", "not stated")
    fields = set(SimulatedPerson.model_fields)
    for key in raw:
        if key not in fields:
            near = difflib.get_close_matches(str(key), fields, n=1)
            hint = f"; did you mean {near[0]}?" if near else ""
            raise ConfigurationError(f"person {path}: unknown field {key!r}{hint}")
    if not isinstance(name, str) or not name.strip() or not isinstance(source, str):
        raise ConfigurationError(f"person {path}: name and source must be text")
    try:
        person = SimulatedPerson.model_validate(raw)
    except ValidationError as exc:
        raise ConfigurationError(f"person {path}: {_field_errors(exc)}") from None
    return PersonFile(name=name.strip(), source=" ".join(source.split()), person=person)


def _field_errors(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors(include_url=False):
        message = str(error["msg"]).removeprefix("Value error, ")
        if error["loc"]:
            where = ".".join(map(str, error["loc"]))
            parts.append(f"{where}={error.get('input')!r}: {message}")
        else:
            parts.append(message)
    return "; ".join(parts)


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())[:300]


def ddm_correct_probability(drift_per_s: float, boundary: float) -> float:
    """P(upper boundary first) for drift v, separation a, start a/2, unit noise."""
    return 1.0 / (1.0 + math.exp(-drift_per_s * boundary))


def ddm_mean_passage_s(drift_per_s: float, boundary: float) -> float:
    """Mean first-passage time from a/2 to either boundary [s]: (a / 2v) tanh(v a / 2)."""
    v, a = drift_per_s, boundary
    return a / (2.0 * v) * math.tanh(v * a / 2.0)


def ddm_survival(t_s: np.ndarray, drift_per_s: float, boundary: float, terms: int) -> np.ndarray:
    """P(no boundary reached by ``t_s``) from the large-time series (Feller; Navarro &
    Fuss 2009), both boundaries together; accurate where ``terms`` are enough."""
    v, a = drift_per_s, boundary
    k = np.arange(1, 2 * terms, 2)[:, None]  # odd k only: sin(k pi / 2) = 0 for even k
    sign = np.where((k - 1) // 2 % 2 == 0, 1.0, -1.0)
    rate = v * v / 2.0 + (k * math.pi / a) ** 2 / 2.0  # (terms, 1) [1/s]
    series = (sign * k / rate * np.exp(-rate * np.asarray(t_s)[None, :])).sum(axis=0)
    return np.asarray(math.pi / a**2 * 2.0 * math.cosh(v * a / 2.0) * series)


@functools.lru_cache(maxsize=32)
def _passage_cdf(drift_per_s: float, boundary: float) -> tuple[np.ndarray, np.ndarray]:
    """First-passage CDF on a grid (times [s], probabilities), for inverse sampling."""
    v, a = drift_per_s, boundary
    slowest = v * v / 2.0 + (math.pi / a) ** 2 / 2.0  # decay rate of the leading term
    leading = math.pi / a**2 * 2.0 * math.cosh(v * a / 2.0) / slowest  # its weight
    end_s = math.log(leading / _TAIL) / slowest
    grid_s = np.linspace(0.0, end_s, _GRID_POINTS)
    # enough terms that the last one has decayed to e^-40 at the first grid step
    terms = math.ceil(a / math.pi * math.sqrt(80.0 / grid_s[1])) + 1
    cdf = 1.0 - np.clip(ddm_survival(grid_s[1:], v, a, terms), 0.0, 1.0)
    cdf = np.maximum.accumulate(np.concatenate(([0.0], cdf)))
    cdf[-1] = 1.0
    return grid_s, cdf
