"""The intent node of the semi-virtual mode: a real human pressing a pressure pad.

It reads the sensor's frames from the serial port (reopening it with back-off when it
disappears), publishes every sample as a SensorSample, decodes presses into decisions,
and answers the open DecisionRequest with each decision (source "sensor"). A press with
no open request is ignored (the arm only moves when asked). While the sensor is silent,
unplugged or stuck pressed the service reports it (Health "degraded"); no intent means the
controller takes no step: it holds. A press the decoder did not see whole (the sensor was
lost, frames went missing) never becomes a decision.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from dammrl.core.errors import ConfigurationError
from dammrl.core.models import ModelSet
from schemas import DecisionRequest, Intent, Message, SensorSample, TaskGoal
from services.common.bus import Bus
from services.intent.calibration import load_calibration
from services.intent.config import IntentSettings
from services.intent.decoder import PressDecision, PressDecoder
from services.intent.serial_sensor import Arrival, SerialSensor

MAX_REMEMBERED = 256  # answers kept for re-sent requests


class SensorIntentNode:
    def __init__(self, settings: IntentSettings, models: ModelSet, bus: Bus) -> None:
        if settings.port is None:
            raise ConfigurationError("DAMMRL_INTENT_PORT (the sensor's serial device) is not set")
        self.settings = settings
        self.models = models
        self.bus = bus
        self.calibration = load_calibration(settings.calibration_file)
        self.decoder = PressDecoder(self.calibration, settings.decoder)
        self.sensor = SerialSensor(settings.port, settings.baud_rate, settings.reconnect_max_s)
        self.request: DecisionRequest | None = None
        self.seen_requests: set[tuple[int, int]] = set()  # the controller re-sends unanswered
        # the intents published, by (episode, request): a re-sent request (the controller
        # heard no answer: it was lost) gets the same answer again, never a new press
        self.answered: dict[tuple[int, int], dict[str, Any]] = {}
        self.request_wall_s = 0.0
        self.ignored_presses = 0
        self.health_state = ""  # the last reported: a change is reported at once
        self.samples = bus.publisher(SensorSample)
        self.intents = bus.publisher(Intent)
        bus.subscribe(DecisionRequest, TaskGoal)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")

    def run(self, stop: threading.Event) -> None:
        with self.sensor:
            while not stop.is_set():
                while (message := self.bus.receive(0)) is not None:
                    self._dispatch(message)
                for arrival in self.sensor.read():  # waits a few ms for bytes
                    self._sample(arrival)
                if not self.sensor.connected:
                    self.decoder.reset()  # a press spanning a disconnect is never a decision
                self._report()

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, DecisionRequest):
            key = (message.episode, message.request)
            if (answer := self.answered.get(key)) is not None:
                self.intents.publish(**answer)  # the answer was lost: the same again
            elif key not in self.seen_requests:
                self.seen_requests.add(key)  # not a repeat
                self.request, self.request_wall_s = message, time.monotonic()
        elif (
            isinstance(message, TaskGoal)
            and self.request is not None
            and self.request.episode < message.episode
        ):
            # a new episode closes an older episode's request; never its own: the goal and
            # the first request come on two subscriptions and may arrive in either order
            self.request = None

    def _sample(self, arrival: Arrival) -> None:
        decision = self.decoder.update(arrival.t_s, arrival.frame.raw, arrival.lost_frames)
        self.samples.publish(
            device_seq=arrival.frame.seq,
            raw=arrival.frame.raw,
            level=self.decoder.level,
            pressed=self.decoder.pressing_since is not None,
        )
        if decision is not None:
            self._answer(decision)

    def _answer(self, decision: PressDecision) -> None:
        request = self.request
        if request is None:
            self.ignored_presses += 1
            return
        self.request = None
        models = self.models
        onset_s = decision.t_s - decision.duration_s  # the decision is made when pressing starts
        answer: dict[str, Any] = {
            "episode": request.episode,
            "request": request.request,
            "u_h": decision.u_h,
            "human_model": decision.human_model,
            "radius_m": models.radius_m(decision.human_model),
            "confidence": decision.confidence,
            "source": "sensor",
            "decision_s": max(0.0, onset_s - self.request_wall_s),
        }
        if len(self.answered) >= MAX_REMEMBERED:  # bounded: the oldest answer goes first
            del self.answered[next(iter(self.answered))]
        self.answered[(request.episode, request.request)] = answer
        self.intents.publish(**answer)

    def _report(self) -> None:
        sensor = self.sensor
        counts = f"{sensor.parser.frames} frames, {sum(sensor.parser.errors.values())} bad"
        problem = self._problem()
        state = "ok" if problem is None else "degraded"
        detail = counts if problem is None else f"{counts}; {problem}"
        self.bus.report_health(state, detail, force=state != self.health_state)
        self.health_state = state

    def _problem(self) -> str | None:
        """What keeps the sensor from deciding, if anything."""
        sensor = self.sensor
        if not sensor.connected:
            return f"sensor {sensor.device} not connected: {sensor.last_error}"
        if sensor.silent_for() > self.settings.sensor_stale_s:
            return f"sensor silent: no valid frame for {sensor.silent_for():.1f} s"
        if (since := self.decoder.stuck_since) is not None:
            held_s = time.monotonic() - since
            wall = time.strftime("%H:%M:%S", time.localtime(time.time() - held_s))
            return (
                f"sensor stuck pressed (level {self.decoder.level:.2f}) since {wall}, "
                f"{held_s:.0f} s: no decision until it returns to rest"
            )
        return None
