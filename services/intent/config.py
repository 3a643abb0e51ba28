"""The intent service's settings: which source decides (``DAMMRL_INTENT_``); each source has
settings of its own (``DAMMRL_PAD_*`` for the pad; the simulated human is ``DAMMRL_HUMAN_*``)."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.human import HumanModel
from dammrl_core.models import ModelSet
from dammrl_core.settings import Settings


class IntentSettings(Settings):
    """Where the human agent's decisions come from (``DAMMRL_INTENT_``)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_INTENT_")

    source: str = Field("simulated", min_length=1, max_length=64)
    """Who decides: ``simulated`` (virtual mode), ``pad`` (the pressure pad, semi-virtual),
    ``lsl`` (a wearable sensor's stream on Lab Streaming Layer), or a source an installed
    package registers under the entry-point group
    ``dammrl.intent_sources`` (``dammrl intent sources`` lists them)."""
    policy_wait_s: float = Field(0.2, gt=0, le=5.0)
    """How long a request waits for the policy's ModelChoice, for a source that decides
    with the policy's radius (the simulated human) [s]."""


SETTINGS: tuple[type[Settings], ...] = (IntentSettings, HumanModel, ModelSet)
"""Every settings class this service reads (the launcher checks them before a start; the
source's own too, see ``dammrl.stack.launch``)."""
