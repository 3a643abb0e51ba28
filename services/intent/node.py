"""The intent node (virtual mode): the simulated human answers decision requests.

Each DecisionRequest is decided at once from what it shows (end-effector and goal) and
published after the decision time the human took, in real time. A TaskGoal reseeds the
human with the episode's seed, so a seed draws the same decisions as in-process.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from dammrl.task import seed_streams
from schemas import DecisionRequest, Intent, Message, TaskGoal
from services.common.bus import Bus
from services.common.entry import run_service
from services.intent.config import HumanSettings
from services.intent.core import SimulatedHuman

log = logging.getLogger("dammrl.intent")


class IntentNode:
    def __init__(self, settings: HumanSettings, bus: Bus) -> None:
        self.bus = bus
        self.human = SimulatedHuman(settings)
        self.due: list[tuple[float, int, dict[str, Any]]] = []  # (wall time, tiebreak, fields)
        self.publisher = bus.publisher(Intent)
        bus.subscribe(DecisionRequest, TaskGoal)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            wait = 0.05 if not self.due else max(0.0, min(0.05, self.due[0][0] - time.monotonic()))
            message = self.bus.receive(wait)
            if message is not None:
                self._dispatch(message)
            while self.due and self.due[0][0] <= time.monotonic():
                self.publisher.publish(**heapq.heappop(self.due)[2])
            self.bus.report_health()

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, TaskGoal):
            self.human.rng = seed_streams(message.seed)[1]
            self.due.clear()
        elif isinstance(message, DecisionRequest):
            self._decide(message)

    def _decide(self, request: DecisionRequest) -> None:
        decision = self.human.decide(
            request.t_s,
            np.array(request.ee_pos_m),
            np.array(request.goal_m),
            request.primary_axis,
            request.human_model,
        )
        fields = {
            "episode": request.episode,
            "request": request.request,
            "u_h": decision.intent.u_h,
            "human_model": request.human_model,
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
        lambda bus, _: IntentNode(HumanSettings(), bus),
        argv,
    )
