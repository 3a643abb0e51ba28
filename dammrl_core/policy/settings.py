"""Which policy chooses M_ij: one class, environment prefix ``DAMMRL_POLICY_``."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.coadaptation import Targets
from dammrl_core.settings import Settings

SHIPPED_POLICY = Path(
    str(resources.files("dammrl_core").joinpath("policies/reward2/checkpoint.pt"))
)


Probability = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]


class PolicySettings(Settings):
    """Which policy chooses the multi-model M_ij at each decision."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_POLICY_")

    kind: Literal["learned", "fixed", "adaptive"] = "learned"
    """'learned': the DQN of ``checkpoint``; 'fixed': always M_{human_model,robot_model};
    'adaptive': the DQN with the posterior over M_ij and the re-selection when
    ``targets`` are missed (dammrl_core.policy.adaptive)."""
    targets: Targets = Field(default_factory=Targets)
    """What the adaptive policy asks of the last ``window`` reaches
    (``DAMMRL_POLICY_TARGETS__SUCCESS_MIN=0.9``, ``__TIME_MAX_S``, ``__COMFORT_MIN``, ...)."""
    checkpoint: Path = SHIPPED_POLICY
    """Training run directory or checkpoint file (default: the shipped Reward 2 policy).
    The model set M_ij is the stack's one ``DAMMRL_MODELS_*`` setting."""
    human_model: int = Field(1, ge=1, le=2)
    """i of the fixed policy: 1 = E_big, 2 = E_small."""
    robot_model: int = Field(1, ge=1, le=8)
    """j of the fixed policy (see dammrl_core.models)."""
    fallback_human_model: int = Field(2, ge=1, le=2)
    """See ``fallback_robot_model``."""
    fallback_robot_model: int = Field(1, ge=1, le=8)
    """The safe fixed model used when the checkpoint cannot be loaded: M_2,1, the careful
    human's small sphere with all-small steps (the most accurate, never large moves)."""
    estimate_human: Literal["auto", "always", "never"] = "auto"
    """Estimate the human sub-model from their decisions (posterior) and use its MAP
    radius: 'auto' when the intents come from a real sensor, or always, or never."""
    prior: tuple[Probability, Probability] | None = None
    """The person's posterior from their earlier runs and sessions (P(E_big), P(E_small)),
    carried by ``dammrl session run``; capped at 0.9 (see dammrl_core.posterior). None:
    flat."""
    publish_period_s: float = Field(0.5, ge=0.05, le=10)
    """The latest ModelChoice is repeated this often, so late joiners learn it [s]."""
