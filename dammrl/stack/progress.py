"""What a run says as it goes: each episode's result counted once and reported
(``EpisodeTally``), the services' progress and silences (``Progress``), and the prompts
for a person at the pad (``PatientPrompts``)."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable

import zenoh
from zenoh.handlers import RingChannel

from dammrl.stack.options import StackOptions
from dammrl.stack.stop import ARM_SERVICES
from dammrl_core.errors import (
    Exit,
    JobFailedError,
)
from schemas import (
    DecisionRequest,
    DecodeError,
    EpisodeResult,
    Health,
    Intent,
    Message,
    ModelChoice,
    RobotState,
    decode,
    key,
)
from services.intent.config import IntentSettings

FIRST_STATE_S = 30.0
"""The arm publishes its first state this soon after every service is alive [s]."""
QUIET_S = 30.0
"""Without an episode result this long, ``dammrl up`` says what each service reports [s]."""
SWITCH = "adaptive: after reach"
"""How the policy's Health detail begins after a switch (services.policy.node)."""


class EpisodeTally:
    """The run's episodes: each result counted once and only from the controller, reported
    as it comes, and the run's verdict on the person's input."""

    def __init__(self, options: StackOptions, out: Callable[[str], None],
                 info: Callable[[str], None],
                 on_result: Callable[[EpisodeResult], None] | None = None) -> None:  # fmt: skip
        self.options = options
        self.out = out
        self.info = info
        self.on_result = on_result
        self.results: list[EpisodeResult] = []
        self.ignored = 0  # messages on task/result that were not an episode's result

    def count(self, payload: bytes) -> EpisodeResult | None:
        """An episode's result counted and reported (None: not one to count)."""
        result = self.accept(payload)
        if result is None:
            return None
        self.results.append(result)
        if self.on_result is not None:
            self.on_result(result)
        self._report(result)
        if undecided(result):  # whose input never answered, and what to check, at once
            self.info(f"episode {result.episode} could not be done: in {result.t_total_s:.0f} s "
                      f"no decision came from {self.input_of_the_person()}")  # fmt: skip
        return result

    def done(self) -> bool:
        """Every episode asked for has ended (never, for an open-ended run)."""
        total = self.options.episodes
        return total is not None and len(self.results) >= total

    def accept(self, payload: bytes) -> EpisodeResult | None:
        """An episode result to count, or None (logged): undecodable, not from the
        controller (on a secured bus the ACL already drops those), or an episode already
        counted (a replay)."""
        try:
            result = decode(EpisodeResult, payload)
        except DecodeError as exc:
            self._ignored(f"a message on task/result: {exc}")
            return None
        counted = {r.episode for r in self.results}
        if result.header.source != "controller" or result.episode in counted:
            why = "a repeat" if result.episode in counted else f"from {result.header.source!r}"
            self._ignored(f"an episode result ({why})")
            return None
        return result

    def _ignored(self, what: str) -> None:
        """Say the first few, then every 1000th (a flood must not flood the terminal)."""
        self.ignored += 1
        if self.ignored <= 3 or self.ignored % 1000 == 0:
            self.info(f"ignored {what} ({self.ignored} so far)")

    def _report(self, result: EpisodeResult) -> None:
        if self.options.json:
            self.out(json.dumps(result_dict(result)))
            return
        total = self.options.episodes or "?"
        self.out(
            f"episode {result.episode}/{total}: {result.outcome} in {result.t_total_s:.1f} s, "
            f"N_osc {result.n_osc}, final error {result.final_error_m * 1000:.1f} mm"
            + ("" if result.success else f" ({result.reason})")
        )

    def verdict(self) -> int:
        """Exit FAILED when the person's input never joined: episodes ended without a
        decision and no episode of the run had one (one line says so)."""
        lacking = [r for r in self.results if undecided(r)]
        if not lacking or any(r.n_decisions > 0 for r in self.results):
            return Exit.OK
        self.info(f"dammrl: {len(lacking)} of {len(self.results)} episodes could not be done: "
                  f"no decision ever came from {self.input_of_the_person()}")  # fmt: skip
        return Exit.FAILED

    def input_of_the_person(self) -> str:
        """Whose decisions the run waits for, and how that input joins this run."""
        o, port = self.options, self.options.port
        if o.pad_port is not None:
            return (f"the pad at {o.pad_port} (is someone pressing it? an emulated patient "
                    f"joins by itself: `dammrl sensor emulate --link {o.pad_port} --pattern "
                    f"patient`, or give it --bus-port {port})")  # fmt: skip
        if o.lsl_stream is not None:
            return (f"the wearable's stream {o.lsl_stream!r} (is the person moving? an "
                    "emulated armband joins by itself: `dammrl intent emulate --stream "
                    f"{o.lsl_stream} --pattern patient`, or --bus-port {port})")  # fmt: skip
        named = o.intent or IntentSettings().source
        return f"the intent source {named!r} (what does `dammrl status --bus-port {port}` say?)"


class Progress:
    """``dammrl up`` never waits silently: the arm's first state must come within
    ``FIRST_STATE_S`` of the services being alive (else the run fails, with what the
    services' Health says), and every ``QUIET_S`` without an episode result prints what
    each service reports."""

    def __init__(self, session: zenoh.Session, namespace: str, out: Callable[[str], None]):
        self.out = out
        self.health: dict[str, Health] = {}
        self.first_state = False
        self.since = time.monotonic()
        self.said = self.since
        self.stopped: dict[str, bool] = {}
        self.switch = ""  # the adaptive policy's last switch said
        self._healths = session.declare_subscriber(f"{namespace}/health/*", RingChannel(256))
        self._states = session.declare_subscriber(key(namespace, RobotState), RingChannel(1))

    def _take(self) -> None:
        """What arrived (rings filled by Zenoh without Python: a flood costs nothing here)."""
        while (sample := self._healths.try_recv()) is not None:
            with contextlib.suppress(DecodeError):
                health = decode(Health, sample.payload.to_bytes())
                self.health[health.service] = health
        if not self.first_state and self._states.try_recv() is not None:
            self.first_state = True
            self._states.undeclare()  # type: ignore[no-untyped-call]

    def advanced(self) -> None:
        self.since = self.said = time.monotonic()

    def check(self) -> None:
        self._take()
        self._say_stops()
        self._say_switch()
        now = time.monotonic()
        if not self.first_state and now - self.since > FIRST_STATE_S:
            raise JobFailedError(
                f"no robot state {FIRST_STATE_S:.0f} s after the start: {self.report()}"
            )
        if now - self.said > QUIET_S:
            self.said = now
            self.out(f"no episode ended for {now - self.since:.0f} s: {self.report()}")

    def _say_stops(self) -> None:
        """An arm that stops (an emergency stop, a fault) is said at once, once."""
        arms = [h for h in self.health.values() if h.service in ARM_SERVICES]
        for health in arms:
            stopped = health.state == "stopped"
            if stopped and not self.stopped.get(health.service):
                reason = health.detail.split(";")[0]
                self.out(f"{health.service} stopped: {reason} (it holds; Ctrl-C ends the run)")
            self.stopped[health.service] = stopped

    def _say_switch(self) -> None:
        """The adaptive policy re-selected its models (S3): said once, with its reason."""
        policy = self.health.get("policy")
        if policy is not None and policy.detail.startswith(SWITCH) and policy.detail != self.switch:
            self.switch = policy.detail
            self.out(f"policy {policy.detail}")

    def report(self) -> str:
        """What each service's last Health says, on one line."""
        healths = sorted(self.health.values(), key=lambda h: h.service)
        if not healths:
            return "no service reported its health"
        return "; ".join(
            f"{h.service} {h.state}" + (f" ({h.detail})" if h.detail else "") for h in healths
        )


class PatientPrompts:
    """Semi-virtual: tell the person at the pad when the arm waits for them, where the goal
    is, what their press was read as, and which sub-model the policy thinks they follow."""

    def __init__(self, session: zenoh.Session, namespace: str, out: Callable[[str], None]):
        self.out = out
        self.subscribers = [
            (t, session.declare_subscriber(key(namespace, t)))
            for t in (DecisionRequest, ModelChoice, Intent)
        ]
        self.estimate = ""
        self.prompted = -1

    def show(self) -> None:
        for message_type, subscriber in self.subscribers:
            while (sample := subscriber.try_recv()) is not None:
                with contextlib.suppress(DecodeError):  # the services count bad messages
                    self._say(decode(message_type, sample.payload.to_bytes()))

    def _say(self, message: Message) -> None:
        if isinstance(message, ModelChoice) and message.posterior and message.request >= 0:
            p_small = message.posterior[1]
            likely, p = ("E_small", p_small) if p_small >= 0.5 else ("E_big", 1 - p_small)
            self.estimate = f"  [policy: you decide like {likely}, p {p:.2f}]"
        elif isinstance(message, DecisionRequest) and message.request != self.prompted:
            self.prompted = message.request  # a re-sent request is not a new prompt
            axis = "xyz"[message.primary_axis]
            ahead_mm = (
                message.goal_m[message.primary_axis] - message.ee_pos_m[message.primary_axis]
            ) * 1000
            where = f"{abs(ahead_mm):.0f} mm {'ahead' if ahead_mm >= 0 else 'behind'} on {axis}"
            self.out(f"  request {message.request}: press now - the goal is {where} "
                     "(firm = forward, light = back)")  # fmt: skip
        elif isinstance(message, Intent) and message.person:
            direction = "+1 forward" if message.u_h > 0 else "-1 back"
            radius = "quick -> E_big" if message.human_model == 1 else "held -> E_small"
            self.out(f"  read {direction}, {radius}, after {message.decision_s:.2f} s"
                     f"{self.estimate}")  # fmt: skip


def undecided(result: EpisodeResult) -> bool:
    """An episode that timed out without any decision: the person's input could not do it.
    A hold ends a reach for the arm's or the controller's reason (its own line says which),
    however early: not the person's input, so not blamed on it."""
    return result.n_decisions == 0 and result.outcome == "timeout"


def result_dict(result: EpisodeResult) -> dict[str, object]:
    """The JSON object of one episode: the keys of ``dammrl reach --json``."""
    fields = result.model_dump(mode="json", exclude={"header", "episode"})
    return fields | {"episode": result.episode}


def summary(results: list[EpisodeResult]) -> str:
    n = len(results)
    if n == 0:
        return "no episode ended"
    wins = sum(r.success for r in results)
    mean_t = sum(r.t_total_s for r in results) / n
    mean_osc = sum(r.n_osc for r in results) / n
    return (
        f"{wins}/{n} successful ({wins / n:.0%}), mean time {mean_t:.1f} s, "
        f"mean N_osc {mean_osc:.1f}"
    )
