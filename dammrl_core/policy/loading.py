"""Policy core: the policy the settings ask for, with a safe fallback.

A missing, corrupt or mismatched checkpoint never stops the service: it is reported and
the safe fixed model of the settings takes over.
"""

from __future__ import annotations

import logging
from typing import Literal

from dammrl_core.errors import DammrlError
from dammrl_core.human import HumanModel
from dammrl_core.models import ModelSet
from dammrl_core.policy import FixedPolicy, Policy
from dammrl_core.policy.settings import PolicySettings

log = logging.getLogger("dammrl.policy")


def load_policy(
    settings: PolicySettings, models: ModelSet, human: HumanModel | None = None
) -> tuple[Policy, Literal["ok", "degraded"], str]:
    """(policy, health state, description); never raises for a bad checkpoint or table."""
    policy, health, description = _load_base(settings, models)
    if settings.kind != "adaptive":
        return policy, health, description
    from dammrl_core.policy.adaptive import AdaptivePolicy

    try:
        adaptive = AdaptivePolicy.around(policy, models, human or HumanModel(), settings.targets,
                                         settings.selection)  # fmt: skip
    except DammrlError as exc:
        log.error("cannot adapt (%s); the base policy alone chooses", exc)
        return policy, "degraded", f"{description}; not adaptive: {exc}"
    return adaptive, health, f"adaptive around the {description}"


def _load_base(
    settings: PolicySettings, models: ModelSet
) -> tuple[Policy, Literal["ok", "degraded"], str]:
    if settings.kind == "fixed":
        policy = FixedPolicy(models, settings.human_model, settings.robot_model)
        return policy, "ok", f"fixed M_{settings.human_model},{settings.robot_model}"
    try:
        from dammrl_core.policy.learned import LearnedPolicy  # torch only for a learned policy

        learned = LearnedPolicy(models, settings.checkpoint)
    except DammrlError as exc:
        i, j = settings.fallback_human_model, settings.fallback_robot_model
        log.error(
            "cannot use the learned policy (%s); falling back to the fixed M_%d,%d", exc, i, j
        )
        return FixedPolicy(models, i, j), "degraded", f"fallback M_{i},{j}: {exc}"
    return learned, "ok", f"learned (Reward {learned.reward}) from {settings.checkpoint}"
