"""Indexing of the multi-model set M_ij."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl_core.errors import ConfigurationError
from dammrl_core.models import ModelSet, parse_model, radius_name


def test_robot_model_index_is_binary_large_flags_on_xyz() -> None:
    models = ModelSet(step_small_m=(0.01, 0.01, 0.01), step_large_m=(0.03, 0.03, 0.03))
    np.testing.assert_allclose(models.steps_m(1), [0.01, 0.01, 0.01])
    np.testing.assert_allclose(models.steps_m(3), [0.01, 0.03, 0.01])
    np.testing.assert_allclose(models.steps_m(5), [0.03, 0.01, 0.01])
    np.testing.assert_allclose(models.steps_m(8), [0.03, 0.03, 0.03])


def test_human_model_one_is_the_big_sphere() -> None:
    models = ModelSet()
    assert models.radius_m(1) == models.e_big_m > models.radius_m(2) == models.e_small_m
    assert radius_name(1) == "E_big"


def test_parse_model() -> None:
    assert parse_model("1,3") == (1, 3)
    assert parse_model(" 2, 8") == (2, 8)


@pytest.mark.parametrize("text", ["3,1", "1,9", "1", "a,b", "1,2,3", "0,0"])
def test_bad_model_names_what_is_allowed(text: str) -> None:
    with pytest.raises(ConfigurationError, match="must be"):
        parse_model(text)


def test_model_set_rejects_unknown_fields_and_negative_radii() -> None:
    with pytest.raises(ValueError):
        ModelSet(e_big_m=-0.01)
    with pytest.raises(ValueError):
        ModelSet(e_huge_m=0.1)  # type: ignore[call-arg]
