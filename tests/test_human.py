"""The simulated human is right as often as its setting says, faster under E_big; a
simulated person unlike the model differs as set, and by default not at all."""

from __future__ import annotations

import re

import numpy as np
import pytest
from pydantic import ValidationError

from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel
from dammrl_core.intent.simulated import SimulatedHuman
from dammrl_core.models import ModelSet
from dammrl_core.person import (
    SimulatedPerson,
    ddm_correct_probability,
    ddm_mean_passage_s,
    ddm_survival,
)

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


# Drawn with seed 2024 by the code before simulated persons existed (sub-models 1, 2, 1, ...).
BEFORE_PERSONS = [
    (True, 0.40913162675040166),
    (True, 0.29872119866784447),
    (False, 0.2550908673885333),
    (True, 0.46601628821305213),
    (True, 0.31315991161646123),
    (True, 0.32120122334604195),
    (True, 0.39024806209036267),
    (True, 0.5102600931063237),
]
NEXT_DRAW_BEFORE = 0.9756221976285376


def _decisions(person: SimulatedPerson, i: int, n: int, seed: int = 5) -> np.ndarray:
    """(correct, decision time [s]) of ``n`` decisions, shape (n, 2)."""
    human = SimulatedHuman(HumanModel(person=person), ModelSet(), seed=seed)
    out = [human.decide(0.0, np.zeros(3), GOAL, 0, i) for _ in range(n)]
    return np.array([(d.correct, d.decision_s) for d in out])


def test_the_default_person_draws_exactly_what_the_model_drew_before() -> None:
    human = SimulatedHuman(HumanModel(), ModelSet(), seed=2024)
    drawn = [human.decide(0.0, np.zeros(3), GOAL, 0, 1 + k % 2) for k in range(8)]
    assert [(d.correct, d.decision_s) for d in drawn] == BEFORE_PERSONS
    assert human.rng.random() == NEXT_DRAW_BEFORE  # no draw added or skipped


@pytest.mark.parametrize("i", [1, 2])
def test_an_accuracy_override_holds_under_either_radius(i: int) -> None:
    correct = _decisions(SimulatedPerson(accuracy=0.85), i, 10_000)[:, 0]
    assert correct.mean() == pytest.approx(0.85, abs=0.015)


@pytest.mark.parametrize(("i", "factor"), [(1, 1.5), (2, 1.5), (2, 0.7)])
def test_the_time_factor_scales_the_median_decision_time(i: int, factor: float) -> None:
    times = _decisions(SimulatedPerson(decision_time_factor=factor), i, 10_000)[:, 1]
    assert np.median(times) == pytest.approx(factor * HumanModel().decision_median_s(i), rel=0.02)


def test_a_ddm_person_is_quicker_and_less_accurate_under_e_big_from_one_parameter_set() -> None:
    person = SimulatedPerson(behaviour="ddm")
    big, small = _decisions(person, 1, 5000), _decisions(person, 2, 5000)
    assert big[:, 0].mean() < small[:, 0].mean() - 0.05
    assert np.mean(big[:, 1]) < np.mean(small[:, 1]) - 0.05
    assert big[:, 1].min() >= person.ddm_non_decision_s


@pytest.mark.parametrize("i", [1, 2])
def test_ddm_samples_match_the_analytic_accuracy_and_mean_time(i: int) -> None:
    person = SimulatedPerson(behaviour="ddm", decision_time_factor=1.2)
    drawn = _decisions(person, i, 20_000)
    assert drawn[:, 0].mean() == pytest.approx(person.ddm_accuracy(i), abs=0.01)
    assert drawn[:, 1].mean() == pytest.approx(person.ddm_mean_decision_s(i), rel=0.01)


def test_ddm_closed_forms_match_a_simulated_diffusion() -> None:
    """Euler-Maruyama paths from a/2 with drift v and unit noise, stopped at 0 or a."""
    v, a, dt = 2.0, 0.7, 1e-4
    rng = np.random.default_rng(0)
    x, t = np.full(4000, a / 2), np.zeros(4000)
    running = np.ones(4000, dtype=bool)
    while running.any():
        x[running] += v * dt + np.sqrt(dt) * rng.standard_normal(running.sum())
        t[running] += dt
        running &= (x > 0) & (x < a)
    assert np.mean(x >= a) == pytest.approx(ddm_correct_probability(v, a), abs=0.02)
    assert t.mean() == pytest.approx(ddm_mean_passage_s(v, a), rel=0.04)  # Euler overshoots


def test_a_survival_series_starts_at_one_and_decays() -> None:
    survival = ddm_survival(np.array([1e-3, 0.1, 1.0]), 2.0, 1.1, terms=200)
    assert survival[0] == pytest.approx(1.0, abs=1e-6)
    assert np.all(np.diff(survival) < 0) and survival[-1] < 0.01


@pytest.mark.parametrize(
    ("person", "variable"),
    [
        ({"decision_time_factor": -1.5}, "DAMMRL_HUMAN_PERSON__DECISION_TIME_FACTOR"),
        ({"accuracy": 1.2}, "DAMMRL_HUMAN_PERSON__ACCURACY"),
        ({"accuracy": 0.0}, "DAMMRL_HUMAN_PERSON__ACCURACY"),
        ({"behaviour": "bayes"}, "DAMMRL_HUMAN_PERSON__BEHAVIOUR"),
        (
            {"behaviour": "ddm", "accuracy": 0.85},
            "DAMMRL_HUMAN_PERSON__ACCURACY cannot be set for DAMMRL_HUMAN_PERSON__BEHAVIOUR 'ddm'",
        ),
    ],
)
def test_a_bad_person_setting_is_refused_naming_it(
    person: dict[str, object], variable: str
) -> None:
    with pytest.raises(ConfigurationError, match=re.escape(variable)):
        HumanModel(person=person)
    with pytest.raises(ValidationError):
        SimulatedPerson.model_validate(person)


def test_the_person_is_set_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DAMMRL_HUMAN_PERSON__BEHAVIOUR", "ddm")
    monkeypatch.setenv("DAMMRL_HUMAN_PERSON__DECISION_TIME_FACTOR", "1.5")
    person = HumanModel().person
    assert person.behaviour == "ddm" and person.decision_time_factor == 1.5
