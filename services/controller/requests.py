"""The controller's decision requests on the bus: one request open at a time, sent again
while unanswered, matched with the human's answer (an Intent) and the policy's choice of
the same request (a ModelChoice), whichever comes first."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dammrl_core.control.reach import Answer
from dammrl_core.human import direction_to_goal
from dammrl_core.models import ModelSet
from dammrl_core.state import Intent as CoreIntent
from schemas import DecisionRequest, Header, Intent, ModelChoice

log = logging.getLogger("dammrl.controller")
RESENDS_SAID = 10
"""An unanswered request's resends are warned about on the first and every tenth."""


@dataclass(frozen=True)
class Timing:
    resend_s: float  # an unanswered request is sent again this often [s]
    choice_wait_s: float  # the human's answer waits this long for the policy's choice [s]


class Requests:
    """The open request and its answers, for one episode."""

    def __init__(self, episode: int, seed: int, models: ModelSet, timing: Timing) -> None:
        self.episode, self.seed = episode, seed
        self.models = models
        self.timing = timing
        self.number = 0  # the open (or last) request
        self.t_s = 0.0  # robot time it was made [s]
        self.open: DecisionRequest | None = None  # to send it again
        self.sent_s = 0.0  # when it was last sent (monotonic)
        self.first_sent_s = 0.0  # when it was first sent (monotonic)
        self.resent = 0  # how often the open request went out again
        self.choices: dict[int, ModelChoice] = {}  # the policy's answer per request
        self.intent: Intent | None = None  # the human's answer, until matched with a choice
        self.intent_wall_s = 0.0

    def make(self, header_from: Callable[[], Header], t_s: float, ee_pos: np.ndarray,
             goal: np.ndarray, axis: int, human_model: int) -> DecisionRequest:  # fmt: skip
        """The next request, at robot time ``t_s``."""
        self.number += 1
        self.t_s = t_s
        self.open = DecisionRequest(
            header=header_from(), episode=self.episode, seed=self.seed, request=self.number,
            t_s=t_s, ee_pos_m=tuple(float(v) for v in ee_pos),
            goal_m=tuple(float(v) for v in goal), primary_axis=axis, human_model=human_model,
        )  # fmt: skip
        self.sent_s = self.first_sent_s = time.monotonic()
        self.resent = 0
        return self.open

    def again(self, header_from: Callable[[], Header], asked: bool) -> DecisionRequest | None:
        """The open request once more, when nobody answered it for ``resend_s`` (a service
        that joined late or restarted: they answer a repeat with their first answer)."""
        waiting = asked and self.intent is None and self.open is not None
        if not waiting or time.monotonic() - self.sent_s <= self.timing.resend_s:
            return None
        assert self.open is not None
        self.resent += 1
        waited = time.monotonic() - self.first_sent_s
        # said once, then every tenth time: a person who does not answer is no flood
        level = logging.WARNING if self.resent % RESENDS_SAID == 1 else logging.INFO
        log.log(level, "request %d unanswered for %.1f s: sending it again (sent %d times)",
                self.number, waited, self.resent + 1)  # fmt: skip
        self.sent_s = time.monotonic()
        self.open = self.open.model_copy(update={"header": header_from()})
        return self.open

    def take_choice(self, message: ModelChoice) -> None:
        """The policy's answer to a request of this episode (its periodic repeats only say
        the policy is alive); it may come before or after the human's."""
        if message.episode == self.episode and message.request > 0:
            self.choices[message.request] = message

    def take_intent(self, message: Intent, asked: bool) -> None:
        """The human's answer to the open request (an answer to an older one is late)."""
        if message.episode == self.episode and message.request == self.number and asked:
            self.intent, self.intent_wall_s = message, time.monotonic()

    def answer(self) -> tuple[Answer, tuple[int, int] | None] | None:
        """The human's answer with the step vector the policy chose for the same request,
        once both are in (or the human's alone after ``choice_wait_s``: the steps in force
        stay, the human decided under the request's own i); and the choice (i, j)."""
        message = self.intent
        if message is None:
            return None
        choice = self.choices.get(message.request)
        if choice is None and time.monotonic() - self.intent_wall_s <= self.timing.choice_wait_s:
            return None
        due_s = self.t_s + message.decision_s  # a late answer is due on arrival
        # radius and steps come from the stack's model set by index, never as free numbers
        # from a message (the schema alone would allow 0.1 m steps)
        radius_m = self.models.radius_m(message.human_model)
        intent = CoreIntent(due_s, message.u_h, radius_m, message.human_model, message.confidence)
        steps = None if choice is None else self.models.steps_m(choice.robot_model)
        self.intent = None
        chosen = None if choice is None else (choice.human_model, choice.robot_model)
        return Answer(intent, steps, self._correct(message)), chosen

    def _correct(self, message: Intent) -> bool | None:
        """Toward the goal from where the hand was when asked: a simulated human says so
        itself; a person's command is scored here, as the posterior scores it."""
        if message.correct is not None or self.open is None:
            return message.correct
        ask = self.open
        return message.u_h == direction_to_goal(ask.ee_pos_m, ask.goal_m, ask.primary_axis)
