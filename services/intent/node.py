"""The intent node (virtual mode): the simulated human answers decision requests.

Each DecisionRequest is decided from what it shows (end-effector and goal) as soon as the
policy's ModelChoice for that request arrives (its i is the admission radius the human
works with; after ``policy_wait_s`` without an answer the request's own i is used). The
Intent is published at once with the decision time the human took: the controller
applies it when its robot clock reaches the request time plus that decision time, as the
in-process runner does, so the human is timed by the robot clock, not by bus latency.
The first message of a new episode, its TaskGoal or (for an intent service that joined
after the announcement) its first request, reseeds the human with the episode's seed, so a
seed draws the same decisions as in-process.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from dammrl.core.human import HumanModel
from dammrl.core.models import ModelSet
from dammrl.core.task import seed_streams
from schemas import DecisionRequest, Intent, Message, ModelChoice, TaskGoal
from services.common.bus import Bus
from services.common.entry import run_service
from services.intent.config import IntentSettings
from services.intent.core import SimulatedHuman

if TYPE_CHECKING:
    from services.intent.sensor_node import SensorIntentNode

log = logging.getLogger("dammrl.intent")


class IntentNode:
    def __init__(
        self, settings: IntentSettings, human: HumanModel, models: ModelSet, bus: Bus
    ) -> None:
        self.bus = bus
        self.human = SimulatedHuman(human, models)
        lockstep = bus.settings.lockstep  # then the robot clock waits: only a dead policy is late
        self.policy_wait_s = (
            bus.settings.lockstep_timeout_s / 4 if lockstep else settings.policy_wait_s
        )
        self.waiting: dict[tuple[int, int], tuple[float, DecisionRequest]] = {}
        self.choices: dict[tuple[int, int], int] = {}  # (episode, request) -> the policy's i
        self.answered: dict[tuple[int, int], dict[str, Any]] = {}  # the intents published
        self.episode = 0
        self.publisher = bus.publisher(Intent)
        bus.subscribe(DecisionRequest, TaskGoal, ModelChoice)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(ModelChoice, "policy")

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            message = self.bus.receive(0.01)
            if message is not None:
                self._dispatch(message)
            self._decide_unanswered()
            self.bus.report_health()

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, TaskGoal):
            self._new_episode(message.episode, message.seed)
        elif isinstance(message, DecisionRequest):
            if message.episode > self.episode:  # its announcement was missed (never an older one)
                self._new_episode(message.episode, message.seed)
            answered = self.answered.get((message.episode, message.request))
            if answered is not None:  # a re-sent request: the same answer again
                self.publisher.publish(**answered)
                return
            self.waiting[(message.episode, message.request)] = (time.monotonic(), message)
            self._decide_if_chosen((message.episode, message.request))
        elif isinstance(message, ModelChoice) and message.request > 0:
            # the policy's answer may overtake the request it answers: keep it
            self.choices[(message.episode, message.request)] = message.human_model
            self._decide_if_chosen((message.episode, message.request))

    def _new_episode(self, episode: int, seed: int) -> None:
        """Reseed the human once per episode (repeats of the announcement change nothing)."""
        if episode == self.episode:
            return
        self.episode = episode
        self.human.rng = seed_streams(seed).human
        for pending in (self.waiting, self.choices, self.answered):
            for key in [k for k in pending if k[0] != episode]:  # a choice may come first
                del pending[key]

    def _decide_if_chosen(self, key: tuple[int, int]) -> None:
        if key in self.waiting and key in self.choices:
            self._decide(self.waiting.pop(key)[1], self.choices.pop(key))

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
        fields: dict[str, Any] = {
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
        self.answered[(request.episode, request.request)] = fields
        self.publisher.publish(**fields)


def main(argv: Sequence[str] | None = None) -> int:
    """Intent service: the simulated human answers decision requests."""
    return run_service(
        "intent",
        "Intent service: the simulated human answers decision requests.",
        "DAMMRL_INTENT_*, DAMMRL_HUMAN_*, DAMMRL_MODELS_*",
        lambda bus, _: _node(IntentSettings(), bus),
        argv,
    )


def _node(settings: IntentSettings, bus: Bus) -> IntentNode | SensorIntentNode:
    """The simulated human (virtual mode) or the pressure sensor (semi-virtual mode)."""
    if settings.source == "serial":
        from services.intent.sensor_node import SensorIntentNode

        return SensorIntentNode(settings, ModelSet(), bus)
    return IntentNode(settings, HumanModel(), ModelSet(), bus)
