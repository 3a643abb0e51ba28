"""The human-model posterior finds the person it models and is not sure of the wrong
sub-model when the person is slower or quicker than its model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dammrl_core.human import HumanModel
from dammrl_core.intent.simulated import SimulatedHuman
from dammrl_core.models import ModelSet
from dammrl_core.person import SimulatedPerson
from dammrl_core.posterior import HumanModelPosterior

GOAL = np.array([0.5, 0.0, -0.2])
DECISIONS = [
    (True, 0.40913162675040166),
    (True, 0.29872119866784447),
    (False, 0.2550908673885333),
    (True, 0.46601628821305213),
    (True, 0.31315991161646123),
    (True, 0.32120122334604195),
    (True, 0.39024806209036267),
    (True, 0.5102600931063237),
    (False, 0.1),  # at the floor: the time is not scored
    (True, 0.05),
]
# p(E_small) after each decision above, from the posterior before decision_scale_sd existed
P_SMALL_BEFORE = [
    0.8119762980091473, 0.7830054895050902, 0.3700865335869693, 0.8335377941371623,
    0.8426107589081583, 0.8672730536837199, 0.9566108994299911, 0.9966969615925793,
    0.9934156714751629, 0.9941429785831241,
]  # fmt: skip


def _final_probabilities(person: SimulatedPerson, truth: int, scale_sd: float) -> np.ndarray:
    """p(model) after 20 decisions, one row per seeded sequence, shape (200, 2)."""
    rows = []
    for seed in range(200):
        human = SimulatedHuman(HumanModel(person=person), ModelSet(), seed)
        posterior = HumanModelPosterior(HumanModel(decision_scale_sd=scale_sd))
        for _ in range(20):
            decision = human.decide(0.0, np.zeros(3), GOAL, 0, truth)
            p = posterior.update(decision.correct, decision.decision_s)
        rows.append(p)
    return np.array(rows)


def test_without_a_scale_spread_the_posterior_is_the_original_one() -> None:
    posterior = HumanModelPosterior(HumanModel(decision_scale_sd=0.0))
    p_small = [posterior.update(correct, t)[1] for correct, t in DECISIONS]
    np.testing.assert_allclose(p_small, P_SMALL_BEFORE, rtol=1e-12)
    assert posterior.timed == 8 and posterior.settled_after() == 4


def test_a_slow_e_big_person_does_not_make_the_posterior_sure_of_e_small() -> None:
    slow = SimulatedPerson(decision_time_factor=1.5)
    sure_wrong = _final_probabilities(slow, 1, HumanModel().decision_scale_sd)[:, 1] > 0.99
    assert sure_wrong.mean() < 0.25
    original = _final_probabilities(slow, 1, 0.0)[:, 1] > 0.99
    assert original.mean() > 0.9  # the failure the spread mends


@pytest.mark.parametrize("truth", [1, 2])
def test_the_posterior_still_finds_the_person_it_models(truth: int) -> None:
    p_truth = _final_probabilities(SimulatedPerson(), truth, HumanModel().decision_scale_sd)
    assert np.mean(p_truth[:, truth - 1] > 0.5) >= 0.98
    assert np.mean(p_truth[:, truth - 1]) >= 0.9


def test_time_evidence_is_bounded_by_the_scale_spread() -> None:
    human = HumanModel()
    log_small = 1000 * math.log(human.decision_median_small_s)  # 1000 times at E_small's median
    evidence = [human.times_log_evidence(i, 1000, log_small) for i in (1, 2)]
    odds = evidence[1] - evidence[0]
    gap = math.log(human.decision_median_small_s / human.decision_median_big_s)
    assert 0 < odds <= gap**2 / (2 * human.decision_scale_sd**2)


def test_a_carried_prior_starts_the_posterior_where_the_person_was_but_never_certain() -> None:
    from dammrl_core.human import HumanModel
    from dammrl_core.posterior import PRIOR_CAP, HumanModelPosterior, carried_prior

    fresh = HumanModelPosterior(HumanModel(), log_prior=carried_prior((0.3, 0.7)))
    np.testing.assert_allclose(fresh.probabilities, [0.3, 0.7])
    sure = HumanModelPosterior(HumanModel(), log_prior=carried_prior((0.0, 1.0)))
    np.testing.assert_allclose(sure.probabilities, [1 - PRIOR_CAP, PRIOR_CAP])
    for _ in range(30):  # a person who changed: 30 quick, inaccurate decisions
        sure.update(correct=False, decision_s=0.4)
    assert sure.map_model == 1  # the evidence overturns the carried belief
