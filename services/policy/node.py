"""The policy node: answers each DecisionRequest with the ModelChoice M_ij.

The learned policy (a DAMMRL checkpoint) sees the end-effector, the goal and the model in
force; if its checkpoint is missing, corrupt or made for another layout, the node says so
(log and Health "degraded") and falls back to the safe fixed model of the settings.
When the human is real (intents from a sensor), their sub-model is not given: the node
scores each of their commands against the request it answered, updates the Bayesian
posterior, uses its MAP radius as i and publishes the posterior with every choice.
The adaptive policy (``DAMMRL_POLICY_KIND=adaptive``) also hears each reach's steps,
result and the participant's comfort ratings, hands them to the posterior over M_ij as the
in-process runner does, and says every switch (log, Health).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

import numpy as np

from dammrl_core.coadaptation import DecisionEvidence, ReachRecord, robot_model_of
from dammrl_core.human import HumanModel, direction_to_goal
from dammrl_core.models import ModelSet
from dammrl_core.policy import ModelChoice as CoreChoice
from dammrl_core.policy.adaptive import AdaptivePolicy
from dammrl_core.policy.loading import load_policy
from dammrl_core.policy.settings import PolicySettings
from dammrl_core.posterior import HumanModelPosterior, carried_prior
from schemas import (
    ComfortRating,
    DecisionRequest,
    EpisodeResult,
    Intent,
    ModelChoice,
    StepEvent,
    TaskGoal,
)
from schemas.messages import OPERATOR
from services.common.bus import Bus
from services.common.entry import run_service

log = logging.getLogger("dammrl.policy")


class PolicyNode:
    def __init__(
        self, settings: PolicySettings, human: HumanModel, models: ModelSet, bus: Bus
    ) -> None:
        self.settings = settings
        self.bus = bus
        self.models = models
        self.policy, self.health, self.description = load_policy(settings, models, human)
        log.info("policy: %s", self.description)
        self.adaptive = self.policy if isinstance(self.policy, AdaptivePolicy) else None
        self.record = ReachRecord()  # what the adaptive policy hears of this episode
        self.latest: CoreChoice = self.policy.decide(np.zeros(3), np.zeros(3))
        self.episode = 0
        self.real_human = False
        self.answers: dict[tuple[int, int], CoreChoice] = {}  # this episode's choices
        self._new_episode(0)
        self.publisher = bus.publisher(ModelChoice)
        self.posterior = HumanModelPosterior(human, log_prior=carried_prior(settings.prior))
        self.requests: dict[tuple[int, int], DecisionRequest] = {}
        if self.adaptive is not None:  # a result is taken before the next episode's request
            bus.subscribe(EpisodeResult, StepEvent, ComfortRating)
            bus.expect(EpisodeResult, "controller")
            bus.expect(StepEvent, "controller")
        bus.subscribe(DecisionRequest, TaskGoal, Intent)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(Intent, "intent")

    def run(self, stop: threading.Event) -> None:
        self._publish(-1)
        while not stop.is_set():
            message = self.bus.receive(self.settings.publish_period_s)
            if isinstance(message, DecisionRequest):
                self._answer(message)
            elif isinstance(message, Intent):
                self._observe_human(message)
            elif isinstance(message, TaskGoal):
                self._new_episode(message.episode)
            elif isinstance(message, (EpisodeResult, StepEvent, ComfortRating)):
                self._adapt(message)
            else:
                self._publish(-1)
            self.bus.report_health(self.health, self.description)

    def _answer(self, message: DecisionRequest) -> None:
        """Choose M_ij for a request; a re-sent request gets the same choice again."""
        self._new_episode(message.episode)
        request = (message.episode, message.request)
        if request not in self.answers:
            self.requests[request] = message
            ee, goal = np.array(message.ee_pos_m), np.array(message.goal_m)
            human = self.posterior.map_model if self.estimating else None
            self.answers[request] = self.policy.decide(ee, goal, human)
            self.record.asked_s.append(message.t_s)
            choice = self.answers[request]
            self.record.choices.append((choice.human_model, choice.robot_model))
        self.latest = self.answers[request]
        self._publish(message.request)

    @property
    def estimating(self) -> bool:
        mode = self.settings.estimate_human
        return mode == "always" or (mode == "auto" and self.real_human)

    def _observe_human(self, intent: Intent) -> None:
        """Score a command against the request it answered; update the posterior."""
        self.real_human = self.real_human or intent.person
        request = self.requests.pop((intent.episode, intent.request), None)
        if request is None or intent.source == OPERATOR:
            return  # a therapist's decision says nothing of the participant
        toward = direction_to_goal(request.ee_pos_m, request.goal_m, request.primary_axis)
        correct = intent.u_h == toward
        if self.estimating:
            self.posterior.update(correct, intent.decision_s, intent.confidence)
        confidence = intent.confidence if intent.person else 1.0
        if intent.episode == self.episode:
            self.record.decisions.append(
                DecisionEvidence(intent.human_model, correct, intent.decision_s, confidence)
            )

    def _adapt(self, message: EpisodeResult | StepEvent | ComfortRating) -> None:
        """The adaptive policy's evidence: this episode's steps, its result, a rating."""
        assert self.adaptive is not None
        if isinstance(message, StepEvent) and message.episode == self.episode:
            j = robot_model_of(self.models, np.array(message.steps_m))
            length = float(np.linalg.norm(message.dx_m))
            self.record.steps.append((j, length, message.radius_m, message.start_s))
        elif isinstance(message, ComfortRating):
            self.adaptive.rating(message.rating)
        elif isinstance(message, EpisodeResult) and message.episode == self.episode:
            evidence = self.record.evidence(message.success, message.t_total_s,
                                            message.final_error_m, message.sparc,
                                            message.model)  # fmt: skip
            self.record = ReachRecord()
            held = len(self.adaptive.held)
            if (switch := self.adaptive.observe(evidence)) is not None:
                log.warning("adaptive: %s", switch.line)
                self.description = f"adaptive: {switch.line}"
            for line in self.adaptive.held[held:]:
                log.info("adaptive: %s", line)

    def _new_episode(self, episode: int) -> None:
        """A new episode starts with no model in force (as in training)."""
        if episode != self.episode or episode == 0:
            self.episode = episode
            self.policy.reset()
            self.answers.clear()
            self.record = ReachRecord()

    def _publish(self, request: int) -> None:
        choice = self.latest
        self.publisher.send(
            ModelChoice(
                header=self.publisher.stamp(),
                episode=self.episode,
                request=request,
                human_model=choice.human_model,
                robot_model=choice.robot_model,
                radius_m=choice.radius_m,
                steps_m=tuple(float(v) for v in choice.steps_m),
                posterior=tuple(float(p) for p in self.posterior.probabilities)
                if self.estimating
                else None,
            )
        )


def main(argv: Sequence[str] | None = None) -> int:
    """Policy service: answers decision requests with the multi-model choice M_ij."""
    return run_service(
        "policy",
        "Policy service: answers decision requests with the multi-model choice M_ij.",
        "DAMMRL_POLICY_* (KIND, CHECKPOINT, HUMAN_MODEL, ROBOT_MODEL, FALLBACK_*), "
        "DAMMRL_HUMAN_*, DAMMRL_MODELS_*",
        lambda bus, _: PolicyNode(PolicySettings(), HumanModel(), ModelSet(), bus),
        argv,
    )
