"""Policy settings: one class, environment prefix ``DAMMRL_POLICY_``."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from dammrl.models import ModelSet


class PolicySettings(BaseSettings):
    """The fixed multi-model M_ij published until the learned policy exists."""

    model_config = SettingsConfigDict(
        env_prefix="DAMMRL_POLICY_", env_nested_delimiter="__", frozen=True, extra="forbid"
    )

    human_model: int = Field(1, ge=1, le=2)
    """i: 1 = E_big, 2 = E_small."""
    robot_model: int = Field(1, ge=1, le=8)
    """j: the step vector (see dammrl.models)."""
    publish_period_s: float = Field(0.5, gt=0)
    """ModelChoice is repeated this often, so late joiners learn it [s]."""
    models: ModelSet = ModelSet()
