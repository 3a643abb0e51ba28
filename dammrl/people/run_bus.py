"""One stack run's messages on its bus, for a session: what it hears (the reach the
controller announced, the policy's posterior of the person, the recorder's
acknowledgements, emergency stops) and what it sends (the console's controls, the stop and
its release until every arm confirms them, the participant's comfort rating), one
sequence per key and publisher, as the recorder counts loss."""

from __future__ import annotations

import contextlib
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dammrl.stack.recorded import RecordedEpisodes
from dammrl.stack.stop import StopConsole
from dammrl_core.protocol import Trial
from schemas import (
    DEFAULT_NAMESPACE,
    ComfortRating,
    DecisionRequest,
    DecodeError,
    EmergencyStop,
    EpisodeRecorded,
    Header,
    Message,
    ModelChoice,
    SessionControl,
    TaskGoal,
    decode,
    encode,
    key,
)
from services.common.security import DISPLAY, OPERATOR

STOP_CONFIRM_S = 2.0
"""The console's stop (or release) is sent until every arm confirms it, this long at most."""


class RunBus:
    """The bus of one stack run, as the session hears and speaks on it."""

    def __init__(self, part: Path) -> None:
        self.hub: Any = None  # the stack's bus session (the operator's), once it is up
        self.display_bus: Any = None  # the participant display's own (its role), once up
        self.stopper: StopConsole | None = None  # the console's stop, once the stack is up
        self.sent: Counter[type[Message]] = Counter()  # per message type (its key): its seq
        self.announced = 0  # the last reach the controller announced
        self.posterior: tuple[float, float] | None = None  # the policy's, last heard
        self.recorded = RecordedEpisodes(part)  # what the recorder holds on disk
        self.listening = False  # to the recorder's acknowledgements
        self.subscribers: list[Any] = []

    def listen(self, hub: Any, on_stop: Callable[[EmergencyStop], None]) -> None:
        """Follow the run on the stack's hub (the operator's session); ``on_stop`` hears
        every emergency stop and release, from the console or anyone."""
        self.hub = hub
        ns = DEFAULT_NAMESPACE
        # a reach runs from its goal, or from its first request (its goal may have gone out
        # before the run listened)
        self.subscribers = [
            hub.declare_subscriber(key(ns, ModelChoice), self._choice),
            hub.declare_subscriber(key(ns, EpisodeRecorded), self._recorded),
            hub.declare_subscriber(key(ns, EmergencyStop), lambda s: self._stop(s, on_stop)),
            hub.declare_subscriber(key(ns, TaskGoal), self._announced(TaskGoal)),
            hub.declare_subscriber(key(ns, DecisionRequest), self._announced(DecisionRequest)),
        ]

    def close(self) -> None:
        self.hub, self.display_bus, self.subscribers = None, None, []
        if self.stopper is not None:
            self.stopper.close()
            self.stopper = None

    def _choice(self, sample: Any) -> None:
        """The policy's posterior of this person, as it learns (kept after the run)."""
        with contextlib.suppress(DecodeError):
            choice = decode(ModelChoice, sample.payload.to_bytes())
            if choice.posterior is not None and len(choice.posterior) == 2:
                self.posterior = (choice.posterior[0], choice.posterior[1])

    def _recorded(self, sample: Any) -> None:
        with contextlib.suppress(DecodeError):
            self.recorded.take(decode(EpisodeRecorded, sample.payload.to_bytes()))

    def _announced(self, message_type: type[TaskGoal | DecisionRequest]) -> Callable[[Any], None]:
        def take(sample: Any) -> None:
            with contextlib.suppress(DecodeError):
                message = decode(message_type, sample.payload.to_bytes())
                if message.header.source == "controller":
                    self.announced = max(self.announced, message.episode)

        return take

    @staticmethod
    def _stop(sample: Any, on_stop: Callable[[EmergencyStop], None]) -> None:
        with contextlib.suppress(DecodeError):
            on_stop(decode(EmergencyStop, sample.payload.to_bytes()))

    def header(self, message_type: type[Message], source: str = OPERATOR) -> Header:
        """The next header of ``message_type``: one sequence per key and publisher, as
        the recorder counts loss."""
        self.sent[message_type] += 1
        seq = self.sent[message_type] - 1
        return Header(stamp_ns=time.time_ns(), seq=seq, source=source)

    def send(self, message: Message, session: Any = None) -> None:
        """Publish ``message`` on ``session`` (default: the operator's, the hub)."""
        session = self.hub if session is None else session
        if session is not None:
            session.put(key(DEFAULT_NAMESPACE, type(message)), encode(message))

    def control(self, episode: int, action: str, who: str, why: str, **decision: int) -> None:
        """The console's command on the reach ``episode`` (the controller carries it out)."""
        self.send(SessionControl(header=self.header(SessionControl), episode=episode,
                                 action=action, who=who, why=why, **decision))  # fmt: skip

    def stop(self, engaged: bool, reason: str, say: Callable[[str], None]) -> None:
        """The emergency stop (or its release), sent until every arm confirms it (as
        ``dammrl stop --console`` does: no start-up, repeated while unconfirmed)."""
        action = "stop" if engaged else "release"
        if self.stopper is None:  # the stack is not up yet
            self.send(EmergencyStop(header=self.header(EmergencyStop), engaged=engaged,
                                    reason=reason))  # fmt: skip
            return
        report = self.stopper.send(engaged, reason, STOP_CONFIRM_S)
        for service, seconds in sorted(report.acknowledged.items()):
            say(f"console: {action} confirmed by {service} after {seconds * 1000:.0f} ms")
        for service in report.silent or ([] if report.acknowledged else ["no arm"]):
            say(f"console: {service} did not confirm the {action} within "
                f"{STOP_CONFIRM_S:.0f} s: use the hardware stop")  # fmt: skip

    def comfort(self, participant: str, trial: Trial, rating: int, asked_s: float) -> None:
        """The participant's comfort rating, sent with the display's role (the recording
        keeps it)."""
        rated = ComfortRating(header=self.header(ComfortRating, DISPLAY), participant=participant,
                              block=trial.block, trial=trial.number, rating=rating,
                              asked_s=asked_s)  # fmt: skip
        self.send(rated, self.display_bus)
