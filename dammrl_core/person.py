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

The defaults leave the person identical to the model (bit for bit: same draws).
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import numpy as np
from pydantic import BaseModel, Field, model_validator

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

    @model_validator(mode="after")
    def _accuracy_only_for_the_model(self) -> SimulatedPerson:
        if self.behaviour == "ddm" and self.accuracy is not None:
            raise ValueError(
                "accuracy cannot be set for behaviour 'ddm': it follows from "
                "ddm_drift_per_s and the boundaries"
            )
        return self

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
