"""A wearable sensor on Lab Streaming Layer: the intent source ``lsl``.

It subscribes to the LSL stream named ``DAMMRL_LSL_STREAM`` (EMG, IMU or any numeric
stream: channel count and rate come from the stream and must match the person's
calibration), maps its timestamps to this machine's clock with LSL's clock correction,
and decodes windows into decisions with the person's classifier
(:mod:`dammrl_core.intent.emg.decoder`). One decision answers one open request; a
decision with no request open, or below the confidence threshold, is not acted on (the
request stays open) but is kept as evidence. The raw samples go on as chunks.

It refuses to decide, and says why in Health, while: no stream of that name is found,
or several are (the same name from another machine or device: pin one with
``DAMMRL_LSL_SOURCE_ID``); the stream differs from the calibration's (channels, rate);
the stream is silent (lost: LSL reconnects by itself when it returns); or the signal is
bad (non-finite samples, a flat or clipping channel, a clock jump).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.emg.calibration import EmgCalibration, load_calibration
from dammrl_core.intent.emg.decoder import Contraction, EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.source import Ask, Chunk, Decided, Evidence, Reading, SourceContext
from dammrl_core.settings import Settings

QUIET_LSL = "[log]\nlevel = -3\n"
"""liblsl's own log: fatal errors only (its INFO lines would fill the service's stderr)."""


class LslSettings(Settings):
    """A wearable sensor on Lab Streaming Layer (environment prefix ``DAMMRL_LSL_``)."""

    model_config = SettingsConfigDict(env_prefix="DAMMRL_LSL_")

    stream: str | None = Field(None, max_length=200)
    """Name of the LSL stream (as the amplifier's software or `dammrl intent emulate` names it)."""
    source_id: str | None = Field(None, max_length=200)
    """Only the stream with this source id (when several have the stream's name)."""
    calibration_file: Path | None = None
    """The person's calibration, from `dammrl intent calibrate`."""
    decoder: EmgDecoderSettings = EmgDecoderSettings()
    """Thresholds, e.g. DAMMRL_LSL_DECODER__MIN_CONFIDENCE=0.8."""
    stale_s: float = Field(0.5, ge=0.05, le=5.0)
    """No sample for this long: the stream is reported lost [s]."""
    resolve_every_s: float = Field(1.0, ge=0.2, le=60.0)
    """How often the stream is looked for again (missing, or another of its name) [s]."""


class LslSource:
    person = True
    waits_for_model_choice = False  # the person picks the radius: a quick or held contraction

    def __init__(self, settings: LslSettings) -> None:
        if not settings.stream:
            raise ConfigurationError("DAMMRL_LSL_STREAM (the LSL stream's name) is not set")
        if settings.calibration_file is None:
            raise ConfigurationError(
                "DAMMRL_LSL_CALIBRATION_FILE is not set: calibrate the person first "
                "(dammrl intent calibrate --stream NAME --out FILE)"
            )
        self.settings = settings
        self.calibration: EmgCalibration = load_calibration(settings.calibration_file)
        self.decoder = WindowDecoder(self.calibration, settings.decoder)
        self.inlet: Any = None
        self.resolver: Any = None
        self.stream_problem: str | None = "not opened yet"
        self.last_resolve = -np.inf
        self.last_sample = time.monotonic()
        self.open_since: float | None = None
        self.request = -1
        self._chunks: list[Chunk] = []
        self._evidence: list[Evidence] = []
        self.samples = 0
        self.decisions = 0
        self.not_acted = 0

    # ---- the stream ------------------------------------------------------------------------
    def open(self) -> None:
        import pylsl

        pylsl.set_config_content(QUIET_LSL)  # harmless once liblsl already started
        # looks for streams of the name in the background, for as long as the source runs:
        # a second one appearing later (another device, another machine) is seen too
        forget_s = self.settings.stale_s * 4
        self.resolver = pylsl.ContinuousResolver("name", self.settings.stream, None, forget_s)
        self._connect()

    def _candidates(self) -> list[Any]:
        found = list(self.resolver.results())
        if self.settings.source_id:
            found = [s for s in found if s.source_id() == self.settings.source_id]
        return found

    def _connect(self) -> None:
        """Take the stream if exactly one matches and it fits the calibration."""
        import pylsl

        self.last_resolve = time.monotonic()
        found = self._candidates()
        if len(found) != 1:
            self.stream_problem = self._not_one(found)
            return
        info = found[0]
        if (mismatch := self._mismatch(info)) is not None:
            self.stream_problem = mismatch
            return
        self.inlet = pylsl.StreamInlet(info, max_buflen=2, recover=True,
                                       processing_flags=pylsl.proc_clocksync)  # fmt: skip
        self.inlet.open_stream(2.0)
        self.stream_problem = None
        self.last_sample = time.monotonic()

    def _twins(self) -> str | None:
        """Another stream of the name appeared: which one is the person's is unknown."""
        found = self._candidates()
        return self._not_one(found) if len(found) > 1 else None

    def _not_one(self, found: list[Any]) -> str:
        name = self.settings.stream
        if not found:
            return f"no LSL stream named {name!r} found (is the amplifier's software streaming?)"
        where = ", ".join(f"{s.hostname()}/{s.source_id() or '-'}" for s in found)
        return (f"{len(found)} LSL streams named {name!r} ({where}): set "
                "DAMMRL_LSL_SOURCE_ID to the one to use")  # fmt: skip

    def _mismatch(self, info: Any) -> str | None:
        want = self.calibration.stream
        if info.channel_count() != want.channel_count:
            return (f"stream {info.name()!r} has {info.channel_count()} channels, the "
                    f"calibration {want.channel_count}: calibrate on this stream")  # fmt: skip
        if abs(info.nominal_srate() - want.nominal_srate_hz) > 1e-6 * want.nominal_srate_hz:
            return (f"stream {info.name()!r} runs at {info.nominal_srate():g} Hz, the "
                    f"calibration at {want.nominal_srate_hz:g} Hz")  # fmt: skip
        return None

    def close(self) -> None:
        if self.inlet is not None:
            self.inlet.close_stream()
            self.inlet = None

    # ---- requests --------------------------------------------------------------------------
    def new_episode(self, episode: int, seed: int) -> None: ...

    def ask(self, ask: Ask, now_s: float) -> None:
        self.open_since, self.request = now_s, ask.request

    def cancel(self) -> None:
        self.open_since, self.request = None, -1

    def poll(self, now_s: float) -> Decided | None:
        if self.inlet is None:
            if now_s - self.last_resolve > self.settings.resolve_every_s:
                self._connect()
            time.sleep(0.005)
            return None
        if now_s - self.last_resolve > self.settings.resolve_every_s:
            self.last_resolve = now_s
            self.stream_problem = self._twins()
        samples, stamps = self.inlet.pull_chunk(timeout=0.005, max_samples=4096)
        if not stamps:
            if time.monotonic() - self.last_sample > self.settings.stale_s:
                self.decoder.reset()  # nothing spans a lost stream
            return None
        self.last_sample = time.monotonic()
        times = np.asarray(stamps)  # corrected to this machine's clock (proc_clocksync)
        chunk = np.asarray(samples, dtype=float)
        self.samples += len(times)
        rate = self.calibration.stream.nominal_srate_hz
        self._chunks.append(Chunk(str(self.settings.stream), rate, chunk, times))
        if self.stream_problem is not None:  # twins: nothing decides until one is left
            self.decoder.reset()
            return None
        decided = None
        for contraction in self.decoder.push(chunk, times):
            decided = self._take(contraction) or decided
        return decided

    def _take(self, contraction: Contraction) -> Decided | None:
        self.decisions += 1
        since = self.open_since
        acted = contraction.accepted and since is not None
        c = contraction
        reason = c.reason or ("" if acted else "no request open")
        self._evidence.append(Evidence(self.request, c.u_h, c.human_model, c.confidence,
                                       c.onset_s, c.decided_s, c.duration_s, c.windows,
                                       c.features, acted, reason))  # fmt: skip
        if not acted or since is None:
            self.not_acted += 1
            return None
        # LSL's local clock is this machine's monotonic clock (as time.monotonic)
        self.open_since, self.request = None, -1
        return Decided(contraction.u_h, contraction.human_model, contraction.confidence,
                       max(0.0, contraction.onset_s - since))  # fmt: skip

    # ---- what goes on the bus --------------------------------------------------------------
    def readings(self) -> list[Reading]:
        return []  # the raw signal goes out as chunks

    def chunks(self) -> list[Chunk]:
        taken, self._chunks = self._chunks, []
        return taken

    def evidence(self) -> list[Evidence]:
        taken, self._evidence = self._evidence, []
        return taken

    def problem(self) -> str | None:
        if self.stream_problem is not None:
            return self.stream_problem
        silent = time.monotonic() - self.last_sample
        if silent > self.settings.stale_s:
            return f"stream {self.settings.stream!r} silent for {silent:.1f} s (lost?)"
        return self.decoder.problem()

    def detail(self) -> str:
        return (f"{self.samples} samples, {self.decisions} decisions "
                f"({self.not_acted} not acted on)")  # fmt: skip


class LslPlugin:
    name = "lsl"
    settings = LslSettings

    def create(self, settings: Settings, context: SourceContext) -> LslSource:
        assert isinstance(settings, LslSettings)
        return LslSource(settings)


PLUGIN = LslPlugin()
