"""The intent node: any intent source answering the controller's decision requests.

The source is a plug-in (``DAMMRL_INTENT_SOURCE``: ``simulated``, ``pad``, or an installed
package's), made from its own settings. The bookkeeping is here, once, whatever decides:
a request is asked of the source once (a re-sent request gets the answer already given,
never a new decision), a person's source with the time its controller opened it (its
stamp: a late delivery here does not make a prompt contraction early); a source that
decides with the policy's radius (the simulated human) waits for the policy's
ModelChoice of the same request, at most ``policy_wait_s`` (then the request's own
radius); a new episode (its TaskGoal, or a request of a later episode whose announcement
was missed) closes an older episode's open request and tells the source. Raw samples go
out as SensorSample; what keeps the source from deciding goes into Health ("degraded"),
and stays in its detail for ``PROBLEM_HOLD_S`` after it cleared (a fault of a tenth of a
second is seen by `dammrl status` too). A source that fails (an error it did not catch)
is reported so and retried: the service lives, nothing is decided.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from dammrl_core.human import HumanModel
from dammrl_core.intent.source import (
    Ask,
    Chunk,
    Decided,
    Evidence,
    IntentSource,
    Rebaselining,
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
T = TypeVar("T")


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
        # each request's robot time: a request known by its number but asked at another time
        # is a restarted controller's (it counts from 1 again), never one to answer from memory
        self.asked_at: dict[Key, float] = {}
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
        self.failures: dict[str, str] = {}  # the source's errors, per call, while they last
        self.retry_at: dict[str, float] = {}  # when a failed call is tried again
        self.problems = RecentProblems()

    def run(self, stop: threading.Event) -> None:
        self._guarded("opening", self.source.open)
        try:
            while not stop.is_set():
                for message in self.bus.receive_all(0.005):
                    self._dispatch(message)
                self.step()
        finally:
            self._guarded("closing", self.source.close)

    def step(self) -> None:
        """One turn after the messages: the source read, its decision answered, its
        samples and evidence published, Health."""
        self._ask_unanswered_by_the_policy()
        decided = self._guarded("reading", lambda: self.source.poll(time.monotonic()))
        if decided is not None:
            self._answer(decided)
        self._publish_readings()
        self._publish_stream()
        self._report()

    def _guarded(self, what: str, call: Callable[[], T]) -> T | None:
        """``call()``, a source's error stated (once per kind, in the log and in Health)
        instead of ending the service: nothing is decided, the arm holds at its request."""
        if what in self.failures and time.monotonic() < self.retry_at.get(what, 0.0):
            return None  # retried later: meanwhile the loop serves the bus (a takeover)
        try:
            result = call()
        except Exception as exc:  # a plug-in's bug or a device's: the service lives
            problem = f"the source failed {what}: {type(exc).__name__}: {exc}"
            if problem != self.failures.get(what):
                log.exception("%s (retrying)", problem)
            self.failures[what] = problem
            self.retry_at[what] = time.monotonic() + SOURCE_RETRY_S
            return None
        self.failures.pop(what, None)
        return result

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
        if control.action == "rebaseline":
            self._rebaseline(control.who)
        elif control.action == "take" and self.taken_by is None:
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

    def _rebaseline(self, who: str) -> None:
        if isinstance(self.source, Rebaselining):
            log.warning("%s, asked by %s", self.source.rebaseline(), who)
        else:
            log.warning("a rest level asked by %s: %s tracks none", who, self.name)

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
        if self.asked_at.setdefault(key, request.t_s) != request.t_s:
            self._forget(request.episode)  # another controller's: the old answers are not its
            self.asked_at[key] = request.t_s
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
            self._ask(request, request.human_model, opened_s(request.header.stamp_ns))

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
        self._drop(lambda e: e != episode)  # a choice may come first: the new one's stay

    def _forget(self, episode: int) -> None:
        """Everything of ``episode`` so far (a restarted controller's episode of that
        number is another): its open request, answers, choices and requests seen."""
        if self.open is not None and self.open.episode == episode:
            self.open = None
            self.source.cancel()
        self._drop(lambda e: e == episode)

    def _drop(self, of: Callable[[int], bool]) -> None:
        """What is kept per request, for the episodes ``of`` picks."""
        for pending in (self.waiting, self.choices, self.answered, self.asked_at):
            for key in [k for k in pending if of(k[0])]:
                del pending[key]
        self.seen = {k for k in self.seen if not of(k[0])}

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

    def _ask(self, request: DecisionRequest, human_model: int,
             since_s: float | None = None) -> None:  # fmt: skip
        """Ask the source ``request`` (open since ``since_s``, this machine's monotonic
        clock; default now: a request handed back to the participant is asked afresh)."""
        self.open, self.asked_s = request, time.monotonic()
        if self.taken_by is not None:  # the therapist answers it
            early = self.operator_early
            if early is not None and time.monotonic() - early[1] <= OPERATOR_HOLD_S:
                self._decide_for(early[0])
            return
        ask = Ask(request.episode, request.request, request.seed, request.t_s,
                  np.array(request.ee_pos_m), np.array(request.goal_m), request.primary_axis,
                  human_model)  # fmt: skip
        self.source.ask(ask, time.monotonic() if since_s is None else since_s)

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
                           stamps_ns=[bus_ns(t) for t in chunk.times_s], samples=rows,
                           missing=chunk.missing,
                           clock_corrected_s=chunk.clock_corrected_s)  # fmt: skip

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
        problem = self._guarded("stating its problem", self.source.problem)
        problem = next(iter(self.failures.values()), None) or problem
        now = time.monotonic()
        self.problems.see(problem, now)
        state: HealthState = "ok" if problem is None else "degraded"
        dropped = f"{self.raw.dropped} raw samples dropped" if self.raw.dropped else None
        detail = self._guarded("stating its detail", self.source.detail)
        lines = (detail, problem, dropped, self.problems.recent(now))
        self.bus.report_health(state, "; ".join(filter(None, lines)),
                               force=state != self.health_state)  # fmt: skip
        self.health_state = state


SOURCE_RETRY_S = 0.5
"""A source that failed is called again after this long [s]."""
PROBLEM_HOLD_S = 15.0
"""A problem stays in Health's detail this long after it cleared [s]: a status query
takes 2.5 s and a fault may last a tenth of one."""
HELD_PROBLEMS = 3


@dataclass
class _Problem:
    text: str
    since_s: float
    until_s: float


class RecentProblems:
    """The problems a source stated, each from when it began to when it cleared: logged
    as they begin and end, and the recent ones said in Health for ``PROBLEM_HOLD_S``."""

    def __init__(self) -> None:
        self.current: _Problem | None = None
        self.ended: deque[_Problem] = deque(maxlen=HELD_PROBLEMS)

    def see(self, problem: str | None, now_s: float) -> None:
        current = self.current
        if current is not None and problem is not None and _kind(problem) == _kind(current.text):
            current.text, current.until_s = problem, now_s  # the same, its numbers updated
            return
        if current is not None:
            current.until_s = now_s
            self.ended.append(current)
            log.info("cleared after %.1f s: %s", now_s - current.since_s, current.text)
        self.current = None if problem is None else _Problem(problem, now_s, now_s)
        if problem is not None:
            log.warning("%s", problem)

    def recent(self, now_s: float) -> str | None:
        """The problems that cleared in the last PROBLEM_HOLD_S, newest first."""
        held = [p for p in reversed(self.ended) if now_s - p.until_s <= PROBLEM_HOLD_S]
        if not held:
            return None
        return "recently: " + "; ".join(
            f"{p.text} (for {p.until_s - p.since_s:.1f} s, {now_s - p.until_s:.0f} s ago)"
            for p in held
        )


def _kind(problem: str) -> str:
    """A problem without its numbers ("silent for 1.2 s" is one problem as it grows)."""
    return re.sub(r"[-+]?\d[\d.]*", "#", problem)


CHUNK_PERIOD_S = 0.02
"""Raw samples go out at most this often: a tenth of the key's rate limit, which drops a
message that follows another too soon on a link (``schemas.keys.LIMITS``), so network
jitter never bunches two legitimate ones into a drop."""
MAX_BACKLOG_S = 5.0
"""Raw samples waiting longer than this (a stream faster than the bus may carry) are
dropped, oldest first, and counted in Health."""


class RawBacklog:
    """A streaming source's raw samples waiting for the bus: one message at most every
    ``CHUNK_PERIOD_S`` with at most ``samples_per_chunk`` samples; samples dropped here
    count as missing before the next ones (the recording's loss metadata)."""

    def __init__(self) -> None:
        self.waiting: list[Chunk] = []
        self.last_s = -np.inf
        self.dropped = 0

    def add(self, chunk: Chunk) -> None:
        self.waiting.append(chunk)
        while sum(len(c.times_s) for c in self.waiting) > MAX_BACKLOG_S * chunk.rate_hz:
            oldest = self.waiting.pop(0)
            self.dropped += len(oldest.times_s)
            after = next(k for k, c in enumerate(self.waiting) if c.stream == oldest.stream)
            missing = self.waiting[after].missing + oldest.missing + len(oldest.times_s)
            self.waiting[after] = replace(self.waiting[after], missing=missing)

    def take(self, now_s: float) -> Chunk | None:
        """The next message's samples, when one is due."""
        if not self.waiting or now_s - self.last_s < CHUNK_PERIOD_S:
            return None
        self.last_s = now_s
        first = self.waiting[0]
        room = samples_per_chunk(first.samples.shape[1])
        taken, left = [], []
        for chunk in self.waiting:
            if chunk.stream != first.stream or room <= 0:
                left.append(chunk)
            elif len(chunk.times_s) <= room:
                taken.append(chunk)
                room -= len(chunk.times_s)
            else:
                taken.append(replace(chunk, samples=chunk.samples[:room],
                                     times_s=chunk.times_s[:room]))  # fmt: skip
                left.append(replace(chunk, samples=chunk.samples[room:],
                                    times_s=chunk.times_s[room:], missing=0))  # fmt: skip
                room = 0
        self.waiting = left
        return Chunk(first.stream, first.rate_hz, np.concatenate([c.samples for c in taken]),
                     np.concatenate([c.times_s for c in taken]),
                     sum(c.missing for c in taken), taken[-1].clock_corrected_s)  # fmt: skip


MAX_TRANSIT_S = 1.0
"""A request's publisher stamp counts as its opening at most this long before it arrived
(beyond, the two machines' clocks disagree) [s]."""


def opened_s(stamp_ns: int) -> float:
    """When a request opened, on this machine's monotonic clock: its publisher's stamp (the
    participant may see it from then on: a loaded machine delivers it here later, and a
    contraction begun in between is theirs), never after its arrival, nor more than
    ``MAX_TRANSIT_S`` before it."""
    now = time.monotonic()
    stamped = now - (time.time_ns() - stamp_ns) / 1e9
    return min(now, max(stamped, now - MAX_TRANSIT_S))


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
