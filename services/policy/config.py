"""The policy service's settings: the library's ``PolicySettings`` (DAMMRL_POLICY_) and what it
shares."""

from __future__ import annotations

from dammrl_core.human import HumanModel
from dammrl_core.models import ModelSet
from dammrl_core.policy.settings import PolicySettings
from dammrl_core.settings import Settings

SETTINGS: tuple[type[Settings], ...] = (PolicySettings, HumanModel, ModelSet)
"""Every settings class this service reads (the launcher checks them before a start)."""
