"""Kinds of simulated person in files (``dammrl coadapt compare --person FILE.yaml``):
every field, every bad value refused in one line, and what practice and comfort do."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel
from dammrl_core.person import SimulatedPerson, load_person

PERSONS = Path(__file__).parents[1] / "dammrl" / "study" / "persons"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "person.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("path", sorted(PERSONS.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_shipped_person_loads_with_a_name_and_a_source(path: Path) -> None:
    person = load_person(path)
    assert person.name and len(person.source) > 80  # a stated source or rationale


def test_every_field_of_a_simulated_person_can_be_set_in_a_file(tmp_path: Path) -> None:
    text = """name: everything
source: a test
behaviour: model
accuracy_big: 0.6
accuracy_small: 0.95
decision_time_factor: 1.5
ddm_drift_per_s: 1.5
ddm_boundary_big: 0.5
ddm_boundary_small: 0.9
ddm_non_decision_s: 0.2
fatigue_per_reach: 0.02
slowing_per_reach: 0.01
learning_per_session: 0.3
comfort_step_max_m: 0.015
comfort_rating_sd: 0.4
"""
    loaded = load_person(write(tmp_path, text))
    given = {k for k in SimulatedPerson.model_fields if k != "accuracy"}
    assert loaded.person.model_fields_set == given  # every field but one (exclusive of two)
    assert (loaded.name, loaded.source) == ("everything", "a test")
    assert load_person(write(tmp_path, "accuracy: 0.7\n")).name == "person"  # the file's stem


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("accuracy: 1.0", "accuracy=1.0: Input should be less than 1"),
        ("accuracy_big: 0", "accuracy_big=0: Input should be greater than 0"),
        ("accuracy_small: -0.1", "accuracy_small=-0.1: Input should be greater than 0"),
        ("decision_time_factor: 11", "decision_time_factor=11: Input should be less than or"),
        ("ddm_drift_per_s: 0", "ddm_drift_per_s=0: Input should be greater than 0"),
        ("ddm_boundary_big: 5", "ddm_boundary_big=5: Input should be less than or equal to 4"),
        ("ddm_boundary_small: 0", "ddm_boundary_small=0: Input should be greater than 0"),
        ("ddm_non_decision_s: -1", "ddm_non_decision_s=-1: Input should be greater than or"),
        ("fatigue_per_reach: 0.2", "fatigue_per_reach=0.2: Input should be less than or equal"),
        ("slowing_per_reach: -0.01", "slowing_per_reach=-0.01: Input should be greater than"),
        ("learning_per_session: 2", "learning_per_session=2: Input should be less than or equal"),
        ("comfort_step_max_m: 0.5", "comfort_step_max_m=0.5: Input should be less than or equal"),
        ("comfort_rating_sd: 3", "comfort_rating_sd=3: Input should be less than or equal to 2"),
        ("behaviour: lba", "behaviour='lba': Input should be 'model' or 'ddm'"),
        ("accuracy: .nan", "accuracy=nan: Input should be a finite number"),
        ("accuracy: high", "accuracy='high': Input should be a valid number"),
        ("acuracy: 0.7", "unknown field 'acuracy'; did you mean accuracy?"),
        ("behaviour: ddm\naccuracy: 0.7", "accuracy cannot be set for behaviour 'ddm'"),
        ("accuracy: 0.7\naccuracy_big: 0.6", "accuracy is for both radii"),
        ("name: [a, b]", "name and source must be text"),
        ("- accuracy", "not a mapping of SimulatedPerson fields"),
        ("accuracy: [", "cannot read it"),
    ],
)
def test_a_bad_value_is_refused_in_one_line_naming_the_file_and_field(
    tmp_path: Path, line: str, expected: str
) -> None:
    path = write(tmp_path, line + "\n")
    with pytest.raises(ConfigurationError) as caught:
        load_person(path)
    message = str(caught.value)
    assert message.startswith(f"person {path}: ") and "\n" not in message
    assert expected in message


def test_a_missing_file_is_refused_in_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigurationError, match=r"^person .*nowhere.yaml: cannot read it"):
        load_person(tmp_path / "nowhere.yaml")


# ---- practice and comfort ---------------------------------------------------------------
def logit(p: float) -> float:
    return math.log(p / (1 - p))


def test_fatigue_scales_the_log_odds_within_a_session_and_slows_decisions() -> None:
    human = HumanModel(person=SimulatedPerson(fatigue_per_reach=0.03, slowing_per_reach=0.02))
    tired = human.practised(session=3, reach=25).person
    assert logit(tired.accuracy_under(1, 0.8)) == pytest.approx(logit(0.8) * 0.97**25)
    assert logit(tired.accuracy_under(2, 0.9)) == pytest.approx(logit(0.9) * 0.97**25)
    assert tired.decision_time_factor == pytest.approx(1.5)
    assert human.practised(session=3, reach=0).person.accuracy_under(1, 0.8) == pytest.approx(0.8)


def test_learning_scales_the_log_odds_per_session_and_a_ddm_persons_drift_alike() -> None:
    human = HumanModel(person=SimulatedPerson(accuracy=0.6, learning_per_session=0.5))
    for session, factor in ((1, 1.0), (2, 1.5), (4, 3.375)):
        a = human.practised(session, reach=7).person.accuracy_under(1, 0.8)
        assert logit(a) == pytest.approx(logit(0.6) * factor)
    ddm = HumanModel(person=SimulatedPerson(behaviour="ddm", learning_per_session=0.5))
    later = ddm.practised(2, 0).person
    assert later.ddm_drift_per_s == pytest.approx(3.0)  # 2 /s x 1.5
    assert logit(later.ddm_accuracy(1)) == pytest.approx(1.5 * logit(ddm.person.ddm_accuracy(1)))


def test_a_person_who_does_not_change_is_the_same_model_at_any_point() -> None:
    human = HumanModel(person=SimulatedPerson(accuracy=0.7))
    assert human.practised(5, 40) is human


def test_the_comfort_rating_falls_with_the_share_of_steps_too_long() -> None:
    person = SimulatedPerson(comfort_step_max_m=0.015, comfort_rating_sd=0.0)
    rng = np.random.default_rng(0)
    small, large = [0.01, 0.01, 0.01], [0.03, 0.01, 0.01]
    assert person.comfort_rating(np.array([small] * 4), rng) == 5
    assert person.comfort_rating(np.array([small, small, large, large]), rng) == 3
    assert person.comfort_rating(np.array([large] * 4), rng) == 1
    anyone = SimulatedPerson(comfort_rating_sd=0.0)
    assert anyone.comfort_rating(np.array([large] * 4), rng) == 5
    noisy = SimulatedPerson(comfort_step_max_m=0.015)
    ratings = [noisy.comfort_rating(np.array([small, large]), rng) for _ in range(400)]
    assert set(ratings) <= {1, 2, 3, 4, 5} and np.mean(ratings) == pytest.approx(3.0, abs=0.1)
