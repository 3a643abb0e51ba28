"""The intent node: any intent source answering the controller's decision requests.

The source is a plug-in (``DAMMRL_INTENT_SOURCE``: ``simulated``, ``pad``, or an installed
package's), made from its own settings. The bookkeeping is here, once, whatever decides:
a request is asked of the source once (a re-sent request gets the answer already given,
never a new decision); a source that decides with the policy's radius (the simulated
human) waits for the policy's ModelChoice of the same request, at most ``policy_wait_s``
(then the request's own radius); a new episode (its TaskGoal, or a request of a later
episode whose announcement was missed) closes an older episode's open request and tells
the source. Raw samples go out as SensorSample; what keeps the source from deciding goes
into Health ("degraded").
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from dammrl_core.human import HumanModel
from dammrl_core.intent.source import (
    Ask,
    Chunk,
    Decided,
    Evidence,
    IntentSource,
    SourceContext,
    StreamingSource,
    source_plugin,
)
from dammrl_core.models import ModelSet
from schemas import (
    DecisionRequest,
    Intent,
    IntentEvidence,
    Message,
    ModelChoice,
    SensorSample,
    SessionControl,
    SignalChunk,
    TaskGoal,
)
from schemas.messages import OPERATOR, HealthState, samples_per_chunk
from services.common import security
from services.common.bus import Bus
from services.common.entry import run_service
from services.intent.config import IntentSettings

MAX_REMEMBERED = 256  # answers kept for re-sent requests
OPERATOR_HOLD_S = 2.0
"""A therapist's decision typed before its request opened answers it if it opens this soon
[s] (later, it is dropped: it was meant for a moment that has passed)."""
log = logging.getLogger("dammrl.intent")
Key = tuple[int, int]  # (episode, request)


class IntentNode:
    def __init__(self, settings: IntentSettings, source: IntentSource, name: str,
                 models: ModelSet, bus: Bus) -> None:  # fmt: skip
        self.source = source
        self.name = name
        self.models = models
        self.bus = bus
        lockstep = bus.settings.lockstep  # then the robot clock waits: only a dead policy is late
        self.policy_wait_s = (
            bus.settings.lockstep_timeout_s / 4 if lockstep else settings.policy_wait_s
        )
        self.episode = 0
        self.open: DecisionRequest | None = None  # the request the source is asked
        self.waiting: dict[Key, tuple[float, DecisionRequest]] = {}  # for the policy's i
        self.choices: dict[Key, int] = {}  # the policy's i per request, which may come first
        self.seen: set[Key] = set()
        self.answered: OrderedDict[Key, Intent] = OrderedDict()
        self.health_state: HealthState = "ok"
        self.intents = bus.publisher(Intent)
        self.samples = bus.publisher(SensorSample)
        self.streaming = source if isinstance(source, StreamingSource) else None
        self.chunks = bus.publisher(SignalChunk)
        self.raw = RawBacklog()
        self.evidence = bus.publisher(IntentEvidence)
        bus.subscribe(DecisionRequest, TaskGoal, ModelChoice, SessionControl)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")
        bus.expect(ModelChoice, "policy")
        bus.expect(SessionControl, security.OPERATOR)  # the session's console: a takeover
        self.taken_by: str | None = None  # the therapist deciding for the participant
        self.operator_early: tuple[SessionControl, float] | None = None  # before its request
        self.asked_s = 0.0  # when the open request was asked

    def run(self, stop: threading.Event) -> None:
        self.source.open()
        try:
            while not stop.is_set():
                for message in self.bus.receive_all(0.005):
                    self._dispatch(message)
                self._ask_unanswered_by_the_policy()
                if (decided := self.source.poll(time.monotonic())) is not None:
                    self._answer(decided)
                self._publish_readings()
                self._publish_stream()
                self._report()
        finally:
            self.source.close()

    # ---- requests ------------------------------------------------------------------------
    def _dispatch(self, message: Message) -> None:
        if isinstance(message, TaskGoal):
            self._new_episode(message.episode, message.seed)
        elif isinstance(message, DecisionRequest):
            self._take_request(message)
        elif isinstance(message, ModelChoice) and message.request > 0:
            self.choices[(message.episode, message.request)] = message.human_model
            self._ask_if_chosen((message.episode, message.request))
        elif isinstance(message, SessionControl):
            self._take_control(message)

    # ---- the therapist's takeover --------------------------------------------------------
    def _take_control(self, control: SessionControl) -> None:
        """``take``: the therapist decides (the source is not asked, its decisions are
        dropped); ``decide``: their answer to the open request; ``give``: back to the
        participant, who is asked the open request afresh."""
        if control.action == "take" and self.taken_by is None:
            self.taken_by = control.who
            self.source.cancel()
            log.warning("decisions taken over by %s", control.who)
        elif control.action == "give" and self.taken_by is not None:
            self.taken_by, self.operator_early = None, None
            log.warning("decisions handed back by %s", control.who)
            if self.open is not None:
                self._ask(self.open, self.open.human_model)
        elif control.action == "decide":
            self._decide_for(control)

    def _decide_for(self, control: SessionControl) -> None:
        """The therapist's answer to the open request; one that comes before its request
        (the console and the request travel apart) answers the next one of the episode,
        if it opens within OPERATOR_HOLD_S."""
        if self.taken_by is None or control.episode != self.episode:
            log.info("an operator's decision while not taken over: ignored")
            return
        request = self.open
        if request is None:
            self.operator_early = (control, time.monotonic())
            return
        assert control.u_h is not None and control.human_model is not None  # the schema's
        decided = Decided(control.u_h, control.human_model, 1.0,
                          time.monotonic() - self.asked_s)  # fmt: skip
        self.open, self.operator_early = None, None
        self._send_answer(request, decided, OPERATOR, person=False)

    def _take_request(self, request: DecisionRequest) -> None:
        if request.episode > self.episode:  # its announcement was missed (never an older one)
            self._new_episode(request.episode, request.seed)
        key = (request.episode, request.request)
        if (answer := self.answered.get(key)) is not None:
            self._publish(answer)  # the answer was lost: the same again, never a new one
            return
        if key in self.seen:
            return
        self.seen.add(key)
        if self.source.waits_for_model_choice:
            self.waiting[key] = (time.monotonic(), request)
            self._ask_if_chosen(key)
        else:
            self._ask(request, request.human_model)

    def _new_episode(self, episode: int, seed: int) -> None:
        """Once per episode (repeats of the announcement change nothing; a restarted
        controller counts from 1 again): another episode's open request closes, never the
        new one's (the goal and its first request come on two subscriptions, in either
        order)."""
        if episode == self.episode:
            return
        self.episode = episode
        self.source.new_episode(episode, seed)
        if self.open is not None and self.open.episode != episode:
            self.open = None
            self.source.cancel()
        for pending in (self.waiting, self.choices, self.answered):
            for key in [k for k in pending if k[0] != episode]:  # a choice may come first
                del pending[key]
        self.seen = {k for k in self.seen if k[0] == episode}

    def _ask_if_chosen(self, key: Key) -> None:
        if key in self.waiting and key in self.choices:
            self._ask(self.waiting.pop(key)[1], self.choices.pop(key))

    def _ask_unanswered_by_the_policy(self) -> None:
        """Requests the policy did not answer in time are asked with their own i."""
        now = time.monotonic()
        for key, (since, request) in list(self.waiting.items()):
            if now - since > self.policy_wait_s:
                del self.waiting[key]
                self._ask(request, request.human_model)

    def _ask(self, request: DecisionRequest, human_model: int) -> None:
        self.open, self.asked_s = request, time.monotonic()
        if self.taken_by is not None:  # the therapist answers it
            early = self.operator_early
            if early is not None and time.monotonic() - early[1] <= OPERATOR_HOLD_S:
                self._decide_for(early[0])
            return
        ask = Ask(request.episode, request.request, request.seed, request.t_s,
                  np.array(request.ee_pos_m), np.array(request.goal_m), request.primary_axis,
                  human_model)  # fmt: skip
        self.source.ask(ask, time.monotonic())

    # ---- answers -------------------------------------------------------------------------
    def _answer(self, decided: Decided) -> None:
        """The source's decision for the open request (dropped while taken over)."""
        if self.taken_by is not None:
            return
        request, self.open = self.open, None
        if request is None:
            return
        self._send_answer(request, decided, self.name, self.source.person)

    def _send_answer(self, request: DecisionRequest, decided: Decided, source: str,
                     person: bool) -> None:  # fmt: skip
        answer = Intent(
            header=self.intents.stamp(),
            episode=request.episode,
            request=request.request,
            u_h=1 if decided.u_h > 0 else -1,
            human_model=decided.human_model,
            radius_m=self.models.radius_m(decided.human_model),
            confidence=decided.confidence,
            source=source,
            person=person,
            decision_s=decided.decision_s,
            correct=decided.correct,
        )
        self.answered[(request.episode, request.request)] = answer
        while len(self.answered) > MAX_REMEMBERED:  # bounded: the oldest answer goes first
            self.answered.popitem(last=False)
        self.intents.send(answer)

    def _publish(self, answer: Intent) -> None:
        self.intents.send(answer.model_copy(update={"header": self.intents.stamp()}))

    def _publish_readings(self) -> None:
        for reading in self.source.readings():
            sample = SensorSample(header=self.samples.stamp(), device_seq=reading.device_seq,
                                  raw=reading.raw, level=reading.level,
                                  pressed=reading.active)  # fmt: skip
            self.samples.send(sample)

    def _publish_stream(self) -> None:
        """A streaming source's raw samples (paced: see RawBacklog) and the evidence of
        its decisions."""
        if self.streaming is None:
            return
        for chunk in self.streaming.chunks():
            self.raw.add(chunk)
        if (due := self.raw.take(time.monotonic())) is not None:
            self.chunks.send(self._chunk(due))
        for evidence in self.streaming.evidence():
            self.evidence.send(self._evidence(evidence))

    def _chunk(self, chunk: Chunk) -> SignalChunk:
        rows = [[float(v) if np.isfinite(v) else None for v in row] for row in chunk.samples]
        return SignalChunk(header=self.chunks.stamp(), stream=chunk.stream, rate_hz=chunk.rate_hz,
                           stamps_ns=[bus_ns(t) for t in chunk.times_s],
                           samples=rows)  # fmt: skip

    def _evidence(self, e: Evidence) -> IntentEvidence:
        return IntentEvidence(
            header=self.evidence.stamp(), episode=self.episode, request=e.request,
            source=self.name, u_h=1 if e.u_h > 0 else -1, human_model=e.human_model,
            confidence=min(1.0, max(0.0, e.confidence)), onset_ns=bus_ns(e.onset_s),
            decided_ns=bus_ns(e.decided_s),
            duration_s=max(0.0, e.duration_s), windows=e.windows,
            features=tuple(e.features[:1024]), acted=e.acted, reason=e.reason[:200],
        )  # fmt: skip

    def _report(self) -> None:
        problem = self.source.problem()
        state: HealthState = "ok" if problem is None else "degraded"
        dropped = f"{self.raw.dropped} raw samples dropped" if self.raw.dropped else None
        detail = "; ".join(filter(None, (self.source.detail(), problem, dropped)))
        self.bus.report_health(state, detail, force=state != self.health_state)
        self.health_state = state


CHUNK_PERIOD_S = 0.02
"""Raw samples go out at most this often: a tenth of the key's rate limit, which drops a
message that follows another too soon on a link (``schemas.keys.LIMITS``), so network
jitter never bunches two legitimate ones into a drop."""
MAX_BACKLOG_S = 5.0
"""Raw samples waiting longer than this (a stream faster than the bus may carry) are
dropped, oldest first, and counted in Health."""


class RawBacklog:
    """A streaming source's raw samples waiting for the bus: one message at most every
    ``CHUNK_PERIOD_S`` with at most ``samples_per_chunk`` samples."""

    def __init__(self) -> None:
        self.waiting: list[Chunk] = []
        self.last_s = -np.inf
        self.dropped = 0

    def add(self, chunk: Chunk) -> None:
        self.waiting.append(chunk)
        while sum(len(c.times_s) for c in self.waiting) > MAX_BACKLOG_S * chunk.rate_hz:
            self.dropped += len(self.waiting.pop(0).times_s)

    def take(self, now_s: float) -> Chunk | None:
        """The next message's samples, when one is due."""
        if not self.waiting or now_s - self.last_s < CHUNK_PERIOD_S:
            return None
        self.last_s = now_s
        first = self.waiting[0]
        stream = [c for c in self.waiting if c.stream == first.stream]
        samples = np.concatenate([c.samples for c in stream])
        times = np.concatenate([c.times_s for c in stream])
        size = samples_per_chunk(samples.shape[1])
        now, later = slice(0, size), slice(size, None)
        self.waiting = [c for c in self.waiting if c.stream != first.stream]
        if len(times) > size:
            self.waiting.insert(0, Chunk(first.stream, first.rate_hz, samples[later], times[later]))
        return Chunk(first.stream, first.rate_hz, samples[now], times[now])


def bus_ns(monotonic_s: float) -> int:
    """A time on this machine's monotonic clock (LSL's local clock) on the bus clock."""
    return max(0, time.time_ns() - round((time.monotonic() - monotonic_s) * 1e9))


def main(argv: Sequence[str] | None = None) -> int:
    """Intent service: the human agent's decisions, from the configured source."""
    return run_service(
        "intent",
        "Intent service: the human agent's decisions (a simulated human, the pad, a plug-in).",
        "DAMMRL_INTENT_*, the source's own (e.g. DAMMRL_PAD_*), DAMMRL_HUMAN_*, DAMMRL_MODELS_*",
        lambda bus, _: make_node(IntentSettings(), bus),
        argv,
    )


def make_node(settings: IntentSettings, bus: Bus) -> IntentNode:
    """The node of the source ``settings.source``, made from its own settings."""
    plugin = source_plugin(settings.source)
    models = ModelSet()
    context = SourceContext(models, HumanModel(), bus.settings.lockstep)
    source = plugin.create(plugin.settings(), context)
    return IntentNode(settings, source, plugin.name, models, bus)
