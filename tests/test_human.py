"""The simulated human is right as often as its setting says, faster under E_big."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl.core.human import HumanModel
from dammrl.core.models import ModelSet
from services.intent.core import SimulatedHuman

GOAL = np.array([0.5, 0.0, -0.2])


@pytest.mark.parametrize(("human_model", "accuracy"), [(1, 0.8), (2, 0.9)])
def test_accuracy_over_10000_decisions_is_within_2_percent(
    human_model: int, accuracy: float
) -> None:
    human = SimulatedHuman(HumanModel(), ModelSet(), seed=11)
    rng = np.random.default_rng(3)
    right = 0
    for _ in range(10_000):
        x = GOAL + rng.uniform(-0.2, 0.2, 3)
        decision = human.decide(0.0, x, GOAL, 0, human_model)
        right += decision.intent.u_h == np.sign(GOAL[0] - x[0])
        assert decision.correct == (decision.intent.u_h == np.sign(GOAL[0] - x[0]))
    assert right / 10_000 == pytest.approx(accuracy, abs=0.02)


def test_configured_accuracy_is_honoured() -> None:
    human = SimulatedHuman(HumanModel(accuracy_big=0.6), ModelSet(), seed=1)
    correct = [human.decide(0.0, np.zeros(3), GOAL, 0, 1).correct for _ in range(10_000)]
    assert np.mean(correct) == pytest.approx(0.6, abs=0.02)


def test_decisions_are_faster_under_e_big() -> None:
    human = SimulatedHuman(HumanModel(), ModelSet(), seed=2)
    big = [human.decide(0.0, np.zeros(3), GOAL, 0, 1).decision_s for _ in range(2000)]
    small = [human.decide(0.0, np.zeros(3), GOAL, 0, 2).decision_s for _ in range(2000)]
    assert np.median(big) < np.median(small)
    assert min(big + small) >= HumanModel().decision_min_s


def test_intent_arrives_after_the_decision_time_with_the_chosen_radius() -> None:
    decision = SimulatedHuman(HumanModel(), ModelSet(), seed=0).decide(5.0, np.zeros(3), GOAL, 0, 2)
    assert decision.intent.t_s == pytest.approx(5.0 + decision.decision_s)
    assert decision.intent.radius_m == ModelSet().e_small_m


def test_same_seed_same_decisions() -> None:
    a = SimulatedHuman(HumanModel(), ModelSet(), seed=9)
    b = SimulatedHuman(HumanModel(), ModelSet(), seed=9)
    assert [a.decide(0, np.zeros(3), GOAL, 0, 1) for _ in range(20)] == [
        b.decide(0, np.zeros(3), GOAL, 0, 1) for _ in range(20)
    ]
