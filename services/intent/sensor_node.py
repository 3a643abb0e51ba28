"""The intent node of the semi-virtual mode: a real human pressing a pressure pad.

It reads the sensor's frames from the serial port (reopening it with back-off when it
disappears), publishes every sample as a SensorSample, decodes presses into decisions,
and answers the open DecisionRequest with each decision (source "sensor"). A press with
no open request is ignored (the arm only moves when asked). While the sensor is silent
or unplugged the service reports it (Health "degraded"); no intent means the controller
takes no step: it holds.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

import serial

from dammrl.errors import ConfigurationError
from schemas import DecisionRequest, Intent, Message, SensorSample, TaskGoal
from services.common.bus import Bus
from services.intent.config import HumanSettings
from services.intent.decoder import Calibration, PressDecision, PressDecoder
from services.intent.emulator import DEFAULT_CALIBRATION
from services.intent.protocol import FrameParser

log = logging.getLogger("dammrl.intent")


def load_calibration(settings: HumanSettings) -> Calibration:
    path = settings.calibration_file
    if path is None:
        return DEFAULT_CALIBRATION
    try:
        return Calibration.model_validate_json(path.read_text())
    except OSError as exc:
        raise ConfigurationError(f"cannot read the calibration file {path}: {exc}") from exc


class SensorIntentNode:
    def __init__(self, settings: HumanSettings, bus: Bus) -> None:
        if settings.port is None:
            raise ConfigurationError("DAMMRL_INTENT_PORT (the sensor's serial device) is not set")
        self.settings = settings
        self.bus = bus
        self.calibration = load_calibration(settings)
        self.decoder = PressDecoder(self.calibration)
        self.parser = FrameParser()
        self.port: serial.Serial | None = None
        self.retry_at, self.backoff_s = 0.0, 0.5
        self.last_frame_s = 0.0
        self.request: DecisionRequest | None = None
        self.request_wall_s = 0.0
        self.ignored_presses = 0
        self.samples = bus.publisher(SensorSample)
        self.intents = bus.publisher(Intent)
        bus.subscribe(DecisionRequest, TaskGoal)
        bus.expect(DecisionRequest, "controller")
        bus.expect(TaskGoal, "controller")

    def run(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                while (message := self.bus.receive(0)) is not None:
                    self._dispatch(message)
                self._read_sensor()
                self._report()
                time.sleep(0.002)
        finally:
            self._close()

    def _dispatch(self, message: Message) -> None:
        if isinstance(message, DecisionRequest):
            self.request, self.request_wall_s = message, time.monotonic()
        elif isinstance(message, TaskGoal):
            self.request = None

    def _read_sensor(self) -> None:
        port = self._open()
        if port is None:
            return
        try:
            data = port.read(port.in_waiting or 1)
        except (serial.SerialException, OSError) as exc:
            log.warning("sensor lost (%s): reconnecting", exc)
            self._close()
            return
        now = time.monotonic()
        for frame in self.parser.feed(data):
            self.last_frame_s = now
            self.samples.publish(device_seq=frame.seq, raw=frame.raw, pressure_kpa=None)
            decision = self.decoder.update(now, frame.raw)
            if decision is not None:
                self._answer(decision)

    def _answer(self, decision: PressDecision) -> None:
        request = self.request
        if request is None:
            self.ignored_presses += 1
            return
        self.request = None
        models = self.settings.models
        self.intents.publish(
            episode=request.episode,
            request=request.request,
            u_h=decision.u_h,
            human_model=decision.human_model,
            radius_m=models.radius_m(decision.human_model),
            confidence=decision.confidence,
            source="sensor",
            decision_s=max(0.0, decision.t_s - self.request_wall_s),
        )

    def _open(self) -> serial.Serial | None:
        if self.port is not None:
            return self.port
        now = time.monotonic()
        if now < self.retry_at:
            return None
        try:
            self.port = serial.Serial(self.settings.port, self.settings.baud_rate, timeout=0)
        except (serial.SerialException, OSError) as exc:
            self.retry_at = now + self.backoff_s
            log.warning(
                "cannot open %s (%s); next try in %.1f s", self.settings.port, exc, self.backoff_s
            )
            self.backoff_s = min(self.backoff_s * 2, self.settings.reconnect_max_s)
            return None
        log.info("sensor connected on %s", self.settings.port)
        self.backoff_s, self.last_frame_s = 0.5, now
        return self.port

    def _close(self) -> None:
        if self.port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self.port.close()
        self.port = None

    def _report(self) -> None:
        if self.port is None:
            self.bus.report_health("degraded", f"sensor {self.settings.port} not connected")
        elif time.monotonic() - self.last_frame_s > self.settings.sensor_stale_s:
            self.bus.report_health("degraded", "sensor silent: no valid frame")
        else:
            errors = sum(self.parser.errors.values())
            self.bus.report_health("ok", f"{self.parser.frames} frames, {errors} bad")
