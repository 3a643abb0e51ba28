"""The finite multi-model set M = {M_ij} of the paper.

Indexing (1-based, as in the paper):

* ``i`` picks the human sub-model, the admission-sphere radius epsilon:
  ``i = 1`` is E_big (fast, less accurate human), ``i = 2`` is E_small (careful human).
* ``j`` picks the robot sub-model, the step-magnitude vector delta = (dx, dy, dz). Its
  binary digits, most significant first, say which axes take the large step:
  ``j - 1 = 4 bx + 2 by + bz`` with ``b = 0`` small and ``b = 1`` large. So ``j = 1`` is
  all-small, ``j = 8`` all-large, ``j = 3`` is (small, large, small).
"""

from __future__ import annotations

from typing import Annotated, Literal, Self

import numpy as np
from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError
from dammrl_core.settings import Settings, ordered

HUMAN_MODELS = (1, 2)
ROBOT_MODELS = tuple(range(1, 9))
RadiusName = Literal["E_big", "E_small"]
_Step = Annotated[float, Field(gt=0, le=0.1)]


class ModelSet(Settings):
    """Numbers behind each M_ij: admission radii [m] and step magnitudes [m] per axis.

    One setting for the whole stack (environment prefix ``DAMMRL_MODELS_``): the human,
    the policy and the controller all read it, so the radius the policy plans with is
    the one the trigger uses.
    """

    model_config = SettingsConfigDict(env_prefix="DAMMRL_MODELS_")

    e_big_m: float = Field(0.010, gt=0, le=0.05, description="admission radius E_big [m]")
    e_small_m: float = Field(0.004, gt=0, le=0.05,
                             description="admission radius E_small [m], below E_big")  # fmt: skip
    step_small_m: tuple[_Step, _Step, _Step] = Field(
        (0.010, 0.010, 0.010), description="small step (x_s, y_s, z_s) [m], each (0, 0.1]"
    )
    step_large_m: tuple[_Step, _Step, _Step] = Field(
        (0.030, 0.030, 0.030), description="large step (x_b, y_b, z_b) [m], each at least the small"
    )

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """E_small below E_big, each small step at most its large one (the paper's set)."""
        ordered(self, "e_small_m", "e_big_m")
        ordered(self, "step_small_m", "step_large_m", strict=False)
        return self

    def radius_m(self, i: int) -> float:
        """Admission radius epsilon of human model ``i`` [m]."""
        _check_index("human model i", i, HUMAN_MODELS)
        return self.e_big_m if i == 1 else self.e_small_m

    def steps_m(self, j: int) -> np.ndarray:
        """Step magnitudes (dx, dy, dz) of robot model ``j`` [m], shape (3,)."""
        _check_index("robot model j", j, ROBOT_MODELS)
        large = [(j - 1) >> bit & 1 for bit in (2, 1, 0)]
        return np.where(large, self.step_large_m, self.step_small_m).astype(float)


def radius_name(i: int) -> RadiusName:
    """'E_big' for i = 1, 'E_small' for i = 2."""
    _check_index("human model i", i, HUMAN_MODELS)
    return "E_big" if i == 1 else "E_small"


def parse_model(text: str) -> tuple[int, int]:
    """Parse ``"I,J"`` (e.g. ``"1,3"``) into a checked (i, j) pair."""
    parts = text.replace(" ", "").split(",")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise ConfigurationError(f"model must be 'I,J' with I in 1..2 and J in 1..8, got {text!r}")
    i, j = int(parts[0]), int(parts[1])
    _check_index("human model i", i, HUMAN_MODELS)
    _check_index("robot model j", j, ROBOT_MODELS)
    return i, j


def _check_index(what: str, value: int, allowed: tuple[int, ...]) -> None:
    if value not in allowed:
        raise ConfigurationError(f"{what} must be one of {list(allowed)}, got {value}")
