"""A person pressing the pressure pad: the semi-virtual mode's intent source.

It reads the pad's frames from the serial port (reopening it with back-off when it
disappears), passes every sample on as a reading, decodes presses into decisions (firm =
+1, light = -1; quick = E_big, held = E_small) and answers the open request with each. A
press with no open request, or one that began before the open request did (meant for
another moment), is not a decision (the arm only moves when asked). While the
pad is silent, unplugged or stuck pressed it says so; a press the decoder did not see
whole (the pad was lost, frames went missing) never becomes a decision.
"""

from __future__ import annotations

import time
from pathlib import Path

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.pad.calibration import load_calibration
from dammrl_core.intent.pad.decoder import DecoderSettings, PressDecoder
from dammrl_core.intent.pad.serial import SerialSensor
from dammrl_core.intent.source import Ask, Decided, Reading, SourceContext, belongs_to_request
from dammrl_core.settings import Settings


class PadSettings(Settings):
    """The pressure pad (environment prefix ``DAMMRL_PAD_``)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_PAD_")

    port: str | None = None
    """Serial device of the pad, e.g. /dev/ttyUSB0."""
    baud_rate: int = Field(115_200, ge=300, le=4_000_000)
    """The pad's serial speed [bit/s]."""
    decoder: DecoderSettings = DecoderSettings()
    """Press thresholds, filter and timing, e.g. DAMMRL_PAD_DECODER__LONG_PRESS_S=0.7."""
    calibration_file: Path | None = None
    """JSON from `dammrl sensor calibrate`; None: the emulator's default calibration."""
    sensor_stale_s: float = Field(0.5, ge=0.05, le=5.0)
    """No valid frame for this long: the pad is reported silent [s]."""
    reconnect_max_s: float = Field(5.0, ge=0.1, le=60)
    """Longest wait between attempts to reopen a lost serial device [s]."""


class PadSource:
    person = True
    waits_for_model_choice = False  # the person picks the radius: a quick or a held press

    def __init__(self, settings: PadSettings) -> None:
        if settings.port is None:
            raise ConfigurationError("DAMMRL_PAD_PORT (the pad's serial device) is not set")
        self.settings = settings
        self.decoder = PressDecoder(load_calibration(settings.calibration_file), settings.decoder)
        self.sensor = SerialSensor(settings.port, settings.baud_rate, settings.reconnect_max_s)
        self.open_since_s: float | None = None  # when the open request came (wall clock)
        self.ignored_presses = 0
        self._readings: list[Reading] = []

    def open(self) -> None:
        self.sensor.__enter__()

    def close(self) -> None:
        self.sensor.__exit__(None, None, None)

    def new_episode(self, episode: int, seed: int) -> None: ...

    def ask(self, ask: Ask, now_s: float) -> None:
        self.open_since_s = now_s

    def cancel(self) -> None:
        self.open_since_s = None

    def poll(self, now_s: float) -> Decided | None:
        decided = None
        for arrival in self.sensor.read():  # waits a few ms for bytes
            decision = self.decoder.update(arrival.sampled_s, arrival.frame.raw,
                                           arrival.lost_frames)  # fmt: skip
            self._readings.append(Reading(arrival.frame.seq, arrival.frame.raw,
                                          self.decoder.level,
                                          self.decoder.pressing_since is not None))  # fmt: skip
            if decision is None:
                continue
            onset_s = decision.t_s - decision.duration_s  # decided when pressing starts
            tolerance = self.settings.decoder.onset_tolerance_s
            if belongs_to_request(onset_s, self.open_since_s, tolerance) or (
                self.open_since_s is None
            ):  # a press meant for another moment (none open, or one that closed)
                self.ignored_presses += 1
                continue
            decided = Decided(decision.u_h, decision.human_model, decision.confidence,
                              max(0.0, onset_s - self.open_since_s))  # fmt: skip
            self.open_since_s = None
        if not self.sensor.connected:
            self.decoder.reset()  # a press spanning a disconnect is never a decision
        return decided

    def readings(self) -> list[Reading]:
        taken, self._readings = self._readings, []
        return taken

    def problem(self) -> str | None:
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

    def detail(self) -> str:
        parser = self.sensor.parser
        return f"{parser.frames} frames, {sum(parser.errors.values())} bad"


class PadPlugin:
    name = "pad"
    settings = PadSettings

    def create(self, settings: Settings, context: SourceContext) -> PadSource:
        assert isinstance(settings, PadSettings)
        return PadSource(settings)


PLUGIN = PadPlugin()
