"""The policy node: publishes the ModelChoice M_ij in force (fixed from settings)."""

from __future__ import annotations

import threading
from collections.abc import Sequence

from schemas import ModelChoice
from services.common.bus import Bus
from services.common.entry import run_service
from services.policy.config import PolicySettings
from services.policy.core import FixedPolicy


class PolicyNode:
    def __init__(self, settings: PolicySettings, bus: Bus) -> None:
        self.settings = settings
        self.bus = bus
        self.policy = FixedPolicy(settings.models, settings.human_model, settings.robot_model)
        self.publisher = bus.publisher(ModelChoice)

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            choice = self.policy.choose()
            self.publisher.publish(
                human_model=choice.human_model,
                robot_model=choice.robot_model,
                radius_m=choice.radius_m,
                steps_m=tuple(float(v) for v in choice.steps_m),
            )
            self.bus.report_health()
            stop.wait(self.settings.publish_period_s)


def main(argv: Sequence[str] | None = None) -> int:
    """Policy service: publishes the multi-model choice M_ij."""
    return run_service(
        "policy",
        "Policy service: publishes the multi-model choice M_ij.",
        "DAMMRL_POLICY_*",
        lambda bus, _: PolicyNode(PolicySettings(), bus),
        argv,
    )
