"""The intent node (virtual mode): the simulated human answers decision requests.

Each DecisionRequest is decided from what it shows (end-effector and goal) as soon as the
policy's ModelChoice for that request arrives (its i is the admission radius the human
works with; after ``policy_wait_s`` without an answer the request's own i is used), and
published after the decision time the human took, in real time. A TaskGoal reseeds the
human with the episode's seed, so a seed draws the same decisions as in-process.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from dammrl.task import seed_streams
from schemas import DecisionRequest, Intent, Message, ModelChoice, TaskGoal
from services.common.bus import Bus
from services.common.entry import run_service
from services.intent.config import HumanSettings
from services.intent.core import SimulatedHuman

if TYPE_CHECKING:
    from services.intent.sensor_node import SensorIntentNode

log = logging.getLogger("dammrl.intent")


class IntentNode:
    def __init__(self, settings: HumanSettings, bus: Bus) -> None:
        self.bus = bus
        self.human = SimulatedHuman(settings)
        self.policy_wait_s = settings.policy_wait_s
        self.due: list[tuple[float, int, dict[str, Any]]] = []  # (wall time, tiebreak, fields)
        self.waiting: dict[tuple[int, int], tuple[float, DecisionRequest]] = {}
        self.publisher = bus.publisher(Intent)
        bus.subscribe(DecisionRequest, TaskGoal, ModelChoice)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(ModelChoice, "policy")

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            wait = 0.01 if not self.due else max(0.0, min(0.01, self.due[0][0] - time.monotonic()))
            message = self.bus.receive(wait)
            if message is not None:
                self._dispatch(message)
            self._decide_unanswered()
            while self.due and self.due[0][0] <= time.monotonic():
                self.publisher.publish(**heapq.heappop(self.due)[2])
            self.bus.report_health()

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, TaskGoal):
            self.human.rng = seed_streams(message.seed)[1]
            self.due.clear()
            self.waiting.clear()
        elif isinstance(message, DecisionRequest):
            self.waiting[(message.episode, message.request)] = (time.monotonic(), message)
        elif isinstance(message, ModelChoice) and message.request >= 0:
            entry = self.waiting.pop((message.episode, message.request), None)
            if entry is not None:
                self._decide(entry[1], message.human_model)

    def _decide_unanswered(self) -> None:
        """Requests the policy did not answer in time are decided with their own i."""
        now = time.monotonic()
        for key, (since, request) in list(self.waiting.items()):
            if now - since > self.policy_wait_s:
                del self.waiting[key]
                self._decide(request, request.human_model)

    def _decide(self, request: DecisionRequest, human_model: int) -> None:
        decision = self.human.decide(
            request.t_s,
            np.array(request.ee_pos_m),
            np.array(request.goal_m),
            request.primary_axis,
            human_model,
        )
        fields = {
            "episode": request.episode,
            "request": request.request,
            "u_h": decision.intent.u_h,
            "human_model": human_model,
            "radius_m": decision.intent.radius_m,
            "confidence": 1.0,
            "source": "simulated",
            "decision_s": decision.decision_s,
            "correct": decision.correct,
        }
        heapq.heappush(self.due, (time.monotonic() + decision.decision_s, request.request, fields))


def main(argv: Sequence[str] | None = None) -> int:
    """Intent service: the simulated human answers decision requests."""
    return run_service(
        "intent",
        "Intent service: the simulated human answers decision requests.",
        "DAMMRL_INTENT_*",
        lambda bus, _: _node(HumanSettings(), bus),
        argv,
    )


def _node(settings: HumanSettings, bus: Bus) -> IntentNode | SensorIntentNode:
    """The simulated human (virtual mode) or the pressure sensor (semi-virtual mode)."""
    if settings.source == "serial":
        from services.intent.sensor_node import SensorIntentNode

        return SensorIntentNode(settings, bus)
    return IntentNode(settings, bus)
