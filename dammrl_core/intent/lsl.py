"""A wearable sensor on Lab Streaming Layer: the intent source ``lsl``.

It looks for the LSL stream named ``DAMMRL_LSL_STREAM`` (and of the calibration's type),
takes it when exactly one matches (several: pin one with ``DAMMRL_LSL_SOURCE_ID``) and
it passes the calibration's checks, maps its timestamps to this machine's clock (LSL's
clock correction, then :mod:`dammrl_core.intent.stamps` for a sender's own clock
jumping), and decodes windows into decisions with the person's classifier
(:mod:`dammrl_core.intent.emg.decoder`). One decision answers one open request, and only
a contraction that began while that request was open (see ``belongs_to_request``; one
decided just before its request arrived, late on a busy bus, still answers it); any
other is not acted on but kept as evidence. The raw samples go on as chunks.

**Any sender.** Every LSL error (a stream lost, a timeout, a library error) is caught
and becomes the problem Health states: nothing is decided meanwhile (the arm holds at
its request) and the service lives. The inlet never recovers by itself (liblsl would
re-attach a stream of the same source id *without* the checks, and never one without a
source id, nor a restarted sender with another): a lost stream, or one silent while
another of its name appears, is looked for again by name and type, with or without a
source id, and every (re-)attachment re-runs the checks (channel count, rate within
``rate_tolerance``, channel labels and units as the calibration recorded them) before a
sample is decoded. A stream that fails them is refused with one line, which stays until
a fitting stream is there. A sender restarted (any source id) is taken within about
``resolve_every_s`` plus LSL's discovery (a second or two on a LAN).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import Field, ValidationError
from pydantic_settings import SettingsConfigDict

from dammrl_core.errors import ConfigurationError, DammrlError
from dammrl_core.intent.emg.calibration import (
    EmgCalibration,
    StreamDescription,
    load_calibration,
)
from dammrl_core.intent.emg.decoder import Contraction, EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.source import (
    Ask,
    Chunk,
    Decided,
    Evidence,
    Reading,
    SourceContext,
    belongs_to_request,
)
from dammrl_core.intent.stamps import StreamClock
from dammrl_core.settings import Settings

QUIET_LSL = "[log]\nlevel = -3\n"
"""liblsl's own log: fatal errors only (its INFO lines would fill the service's stderr)."""
OPEN_TIMEOUT_S = 1.0
"""How long an attachment waits for the sender (opening, its metadata, a clock offset):
the service's loop waits meanwhile [s]."""
MEASURED_RATE_TOLERANCE = 0.05
"""A stream delivering (by its timestamps) this much more or less than its nominal rate
is refused: a sender that announces one rate and sends another."""
CLAIM_WITHIN_S = 1.0
"""A decision made with no request open answers one that arrives this soon after, if the
contraction began after that request was stamped: the bus delivered it late [s]."""
MAX_REFUSED = 64
"""Streams remembered as refused (by their LSL uid: a stream's properties never change)."""
log = logging.getLogger("dammrl.intent")
T = TypeVar("T")


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
    """No sample for this long: the stream is reported silent [s]."""
    resolve_every_s: float = Field(1.0, ge=0.2, le=60.0)
    """How often the stream is looked for again (missing, lost, refused, silent, or
    another of its name) [s]."""
    rate_tolerance: float = Field(0.005, ge=0.0, le=0.05)
    """The stream's nominal rate may differ from the calibration's by this fraction."""
    rebaseline_s: float = Field(3.0, ge=1.0, le=30.0)
    """How long the rest level is measured when the therapist asks for it again
    (`dammrl intent rebaseline`) [s]."""


class LslError(DammrlError):
    """What an LSL call raised, in one line."""


def lsl_call(what: str, call: Callable[[], T]) -> T:
    """``call()``; any error of LSL's (pylsl raises RuntimeError's kinds; ctypes others)
    as an LslError saying what was being done."""
    try:
        return call()
    except Exception as exc:  # a library's boundary: every error is stated
        raise LslError(f"{what}: {type(exc).__name__}: {exc}") from None


def channel_metadata(info: Any) -> tuple[list[str], list[str]]:
    """(labels, units) of a full StreamInfo's channels (``desc/channels/channel``, LSL's
    metadata convention); empty lists when it has none."""
    labels: list[str] = []
    units: list[str] = []
    channel = info.desc().child("channels").child("channel")
    while not channel.empty() and len(labels) < info.channel_count():
        labels.append(channel.child_value("label"))
        units.append(channel.child_value("unit"))
        channel = channel.next_sibling("channel")
    if len(labels) != info.channel_count():
        return [], []
    return labels, units


def describe(info: Any) -> StreamDescription:
    """A StreamInfo (with its metadata, from an inlet's ``info()``) as a calibration keeps it."""
    plain = StreamDescription(name=info.name(), type=info.type(),
                              channel_count=info.channel_count(),
                              nominal_srate_hz=info.nominal_srate(),
                              source_id=info.source_id(), hostname=info.hostname())  # fmt: skip
    labels, units = channel_metadata(info)  # read once the stream is one a calibration takes
    return StreamDescription(**plain.model_dump() | {"channel_labels": labels, "units": units})


def mismatch(
    found: StreamDescription, want: StreamDescription, rate_tolerance: float
) -> str | None:
    """Why the stream ``found`` is not the one calibrated (``want``), in one line, or None.
    Labels and units count only where the calibration recorded them."""
    name = f"stream {found.name!r}"
    if found.channel_count != want.channel_count:
        return (f"{name} has {found.channel_count} channels, the calibration "
                f"{want.channel_count}: calibrate on this stream")  # fmt: skip
    if abs(found.nominal_srate_hz - want.nominal_srate_hz) > rate_tolerance * want.nominal_srate_hz:
        return (f"{name} runs at {found.nominal_srate_hz:g} Hz, the calibration at "
                f"{want.nominal_srate_hz:g} Hz")  # fmt: skip
    if want.type and found.type != want.type:
        return f"{name} is of type {found.type!r}, the calibration's {want.type!r}"
    for what, now, then in (("labels", found.channel_labels, want.channel_labels),
                            ("units", found.units, want.units)):  # fmt: skip
        if then and now != then:
            k = next((k for k in range(len(then)) if k >= len(now) or now[k] != then[k]), 0)
            given = now[k] if k < len(now) else "none"
            return (f"{name}'s channel {k} {what[:-1]} is {given!r}, the calibration's "
                    f"{then[k]!r}: another montage or amplifier setting")  # fmt: skip
    return None


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
        rate = self.calibration.stream.nominal_srate_hz
        self.clock = StreamClock(rate, settings.decoder.max_gap_s, settings.decoder.max_step_back_s)
        self.inlet: Any = None
        self.attached: str | None = None  # the uid of the stream taken
        self.refused: dict[str, str] = {}  # uid -> why (a stream's properties never change)
        self.resolver: Any = None
        self.stream_problem: str | None = "not opened yet"  # no stream taken, and why
        self.twins: str | None = None  # another stream of the name appeared meanwhile
        self.last_resolve = -np.inf
        self.last_sample = time.monotonic()
        self.open_since: float | None = None
        self.request = -1
        self._chunks: list[Chunk] = []
        self._evidence: list[Evidence] = []
        self.samples = 0
        self.decisions = 0
        self.not_acted = 0
        self.attachments = 0
        self.unclaimed: tuple[Contraction, float] | None = None  # decided, no request yet

    # ---- finding the stream ------------------------------------------------------------------
    def open(self) -> None:
        try:
            import pylsl

            pylsl.set_config_content(QUIET_LSL)  # harmless once liblsl already started
            # looks for streams of the name in the background for as long as the source
            # runs: a second one appearing later (another device, a restarted sender) is seen
            forget_s = self.settings.stale_s * 4
            self.resolver = lsl_call("starting LSL's resolver", lambda: pylsl.ContinuousResolver(
                "name", self.settings.stream, None, forget_s))  # fmt: skip
        except (ImportError, OSError, LslError) as exc:  # no liblsl here: said, retried
            problem = f"LSL unavailable: {exc}"
            if problem != self.stream_problem:
                log.error("%s", problem)
            self.stream_problem = problem
            return
        self._attach()

    def _candidates(self) -> list[Any]:
        """The streams of the name (and type, and source id when set) LSL sees now."""
        found = list(lsl_call("listing LSL streams", self.resolver.results))
        want = self.calibration.stream.type
        if want:
            found = [s for s in found if s.type() == want]
        if self.settings.source_id:
            found = [s for s in found if s.source_id() == self.settings.source_id]
        return found

    def _attach(self) -> None:
        """Take the stream if exactly one matches and it passes the calibration's checks."""
        self.last_resolve = time.monotonic()
        if self.resolver is None:
            self.open()
            return
        try:
            found = self._candidates()
            if len(found) != 1:
                self.stream_problem = self._not_one(found)
                return
            uid = found[0].uid()
            if uid in self.refused:
                self.stream_problem = self.refused[uid]
                return
            self._take(found[0], uid)
        except LslError as exc:
            self._drop(f"stream {self.settings.stream!r}: {exc}")

    def _take(self, info: Any, uid: str) -> None:
        import pylsl

        inlet = lsl_call("opening an inlet", lambda: pylsl.StreamInlet(
            info, max_buflen=2, recover=False, processing_flags=pylsl.proc_clocksync))  # fmt: skip
        try:
            full = lsl_call("reading the stream's metadata", lambda: inlet.info(OPEN_TIMEOUT_S))
            if (refused := self._unfit(full)) is not None:
                if len(self.refused) >= MAX_REFUSED:  # a sender restarted again and again
                    self.refused.pop(next(iter(self.refused)))
                self.refused[uid] = self.stream_problem = refused
                log.warning("%s", refused)
                _close(inlet)
                return
            lsl_call("opening the stream", lambda: inlet.open_stream(OPEN_TIMEOUT_S))
        except LslError:
            _close(inlet)
            raise
        self.inlet, self.attached, self.stream_problem = inlet, uid, None
        self.attachments += 1
        self.last_sample = time.monotonic()
        self.clock.reset()
        self.decoder.reset()
        log.info("taken LSL stream %r from %s (%s)", full.name(), full.hostname(),
                 full.source_id() or "no source id")  # fmt: skip

    def _unfit(self, info: Any) -> str | None:
        """Why the stream ``info`` (with its metadata) cannot be decoded, or None."""
        try:
            found = describe(info)
        except ValidationError as exc:  # no regular rate, 300 channels, a name of 1 kB
            first = exc.errors()[0]
            where = ".".join(str(p) for p in first["loc"])
            return f"stream {self.settings.stream!r} cannot be used: {where}: {first['msg']}"
        return mismatch(found, self.calibration.stream, self.settings.rate_tolerance)

    def _not_one(self, found: list[Any]) -> str:
        name = self.settings.stream
        if not found:
            kind = (
                f" of type {self.calibration.stream.type!r}" if self.calibration.stream.type else ""
            )
            return (f"no LSL stream named {name!r}{kind} found (is the amplifier's software "
                    "streaming?)")  # fmt: skip
        where = ", ".join(f"{s.hostname()}/{s.source_id() or '-'}" for s in found)
        return (f"{len(found)} LSL streams named {name!r} ({where}): set "
                "DAMMRL_LSL_SOURCE_ID to the one to use")  # fmt: skip

    def _drop(self, problem: str) -> None:
        """Let the stream go (lost, or replaced): nothing is decided until one is taken."""
        inlet, self.inlet = self.inlet, None
        if inlet is not None:
            _close(inlet)
        if problem != self.stream_problem:
            log.warning("%s", problem)
        self.attached, self.stream_problem, self.twins = None, problem, None
        self.decoder.reset()
        self.last_resolve = -np.inf  # look for it again at once

    def _watch(self, now_s: float) -> None:
        """Every ``resolve_every_s`` while attached: another stream of the name (twins:
        which one is the person's is unknown), or ours gone quiet and no longer listed
        (its sender stopped: another, restarted with any source id, is looked for)."""
        if now_s - self.last_resolve <= self.settings.resolve_every_s:
            return
        self.last_resolve = now_s
        found = self._candidates()
        silent = time.monotonic() - self.last_sample > self.settings.stale_s
        if silent and self.attached not in {s.uid() for s in found}:
            self._drop(f"stream {self.settings.stream!r} silent and no longer listed (its "
                       "sender stopped?): looking for it again")  # fmt: skip
            return
        self.twins = self._not_one(found) if len(found) > 1 else None

    def close(self) -> None:
        inlet, self.inlet = self.inlet, None
        if inlet is not None:
            _close(inlet)

    # ---- requests --------------------------------------------------------------------------
    def new_episode(self, episode: int, seed: int) -> None: ...

    def ask(self, ask: Ask, now_s: float) -> None:
        self.open_since, self.request = now_s, ask.request

    def cancel(self) -> None:
        self.open_since, self.request = None, -1

    def rebaseline(self) -> str:
        """Measure the participant's rest level afresh (they rest for ``rebaseline_s``)."""
        if not self.decoder.normaliser.active:
            return ("no rest level to measure: this calibration takes absolute levels (an "
                    "IMU, or version 1: calibrate again)")  # fmt: skip
        self.decoder.rebaseline(self.settings.rebaseline_s)
        return f"measuring the rest level for {self.settings.rebaseline_s:g} s"

    # ---- the samples -------------------------------------------------------------------------
    def poll(self, now_s: float) -> Decided | None:
        if (claimed := self._claim()) is not None:
            return claimed
        if self.inlet is None:
            if now_s - self.last_resolve > self.settings.resolve_every_s:
                self._attach()
            time.sleep(0.005)
            return None
        try:
            self._watch(now_s)
            if self.inlet is None:
                return None
            samples, stamps = lsl_call("reading the stream", lambda: self.inlet.pull_chunk(
                timeout=0.005, max_samples=4096, as_numpy=True))  # fmt: skip
        except LslError as exc:
            self._drop(f"stream {self.settings.stream!r} lost ({exc}): looking for it again")
            return None
        if not len(stamps):
            if time.monotonic() - self.last_sample > self.settings.stale_s:
                self.decoder.reset()  # nothing spans a silent stream
            return None
        return self._samples(np.asarray(samples, dtype=float), np.asarray(stamps))

    def _samples(self, samples: np.ndarray, stamps: np.ndarray) -> Decided | None:
        self.last_sample = arrived = time.monotonic()
        timed = self.clock.take(stamps, arrived)  # corrected to this machine's clock
        self.samples += len(stamps)
        rate = self.calibration.stream.nominal_srate_hz
        self._chunks.append(Chunk(str(self.settings.stream), rate, samples, timed.times_s,
                                  timed.missing, self.clock.offset_s))  # fmt: skip
        if timed.jump_s:  # no decision spans it (the sender may have restarted its device)
            self.decoder.interrupt(f"the stream's timestamps jumped by {-timed.jump_s:+.3f} s "
                                   "(corrected to this machine's clock)")  # fmt: skip
        if self.twins is not None or self._rate_problem() is not None:
            self.decoder.reset()  # which stream, or what rate, is unknown: nothing decides
            return None
        decided = None
        for contraction in self.decoder.push(samples, timed.times_s):
            decided = self._take_decision(contraction) or decided
        return decided

    def _rate_problem(self) -> str | None:
        delivered = self.clock.delivered_hz()
        nominal = self.calibration.stream.nominal_srate_hz
        if delivered is None or abs(delivered / nominal - 1) <= MEASURED_RATE_TOLERANCE:
            return None
        return (f"stream {self.settings.stream!r} delivers {delivered:.0f} samples/s by its "
                f"timestamps but announces {nominal:g} Hz (the calibration's)")  # fmt: skip

    def _take_decision(self, contraction: Contraction) -> Decided | None:
        c = contraction
        if c.accepted and self.open_since is None:  # its request may be on its way still
            self._expire_unclaimed(now_s=np.inf)
            self.unclaimed = (c, time.monotonic())
            return None
        return self._verdict(c)

    def _claim(self) -> Decided | None:
        """A decision made before its request arrived answers it, if it began after the
        request was stamped (the bus was slower than the person)."""
        self._expire_unclaimed(time.monotonic())
        if self.unclaimed is None or self.open_since is None:
            return None
        contraction, self.unclaimed = self.unclaimed[0], None
        return self._verdict(contraction)

    def _expire_unclaimed(self, now_s: float) -> None:
        if self.unclaimed is not None and now_s - self.unclaimed[1] > CLAIM_WITHIN_S:
            contraction, self.unclaimed = self.unclaimed[0], None
            self._verdict(contraction)  # no request came for it: evidence only

    def _verdict(self, contraction: Contraction) -> Decided | None:
        """The decision acted on, or not (its evidence either way)."""
        self.decisions += 1
        c = contraction
        # LSL's local clock is this machine's monotonic clock (as time.monotonic)
        tolerance = self.settings.decoder.onset_tolerance_s
        reason = c.reason or belongs_to_request(c.onset_s, self.open_since, tolerance)
        acted = not reason
        self._evidence.append(Evidence(self.request, c.u_h, c.human_model, c.confidence,
                                       c.onset_s, c.decided_s, c.duration_s, c.windows,
                                       c.features, acted, reason))  # fmt: skip
        if not acted or self.open_since is None:
            self.not_acted += 1
            return None
        since, self.open_since, self.request = self.open_since, None, -1
        return Decided(c.u_h, c.human_model, c.confidence, max(0.0, c.onset_s - since))

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
        if (problem := self.stream_problem or self.twins) is not None:
            return problem
        silent = time.monotonic() - self.last_sample
        if silent > self.settings.stale_s:
            return f"stream {self.settings.stream!r} silent for {silent:.1f} s (lost?)"
        return self._rate_problem() or self.decoder.problem()

    def detail(self) -> str:
        clock, ratio = self.clock, self.decoder.level_ratio()
        parts = [f"{self.samples} samples", f"{self.decisions} decisions "
                 f"({self.not_acted} not acted on)"]  # fmt: skip
        if clock.gaps:
            parts.insert(1, f"{clock.missing} samples missing in {clock.gaps} gaps")
        if ratio is not None:
            parts.append(f"rest level x{np.min(ratio):.2g}-{np.max(ratio):.2g} of calibration")
        return ", ".join(parts)


def _close(inlet: Any) -> None:
    """Close an inlet that may be lost already (closing it may fail too: said, not raised)."""
    try:
        inlet.close_stream()
    except Exception as exc:  # a library's boundary
        log.debug("closing an inlet: %s", exc)


class LslPlugin:
    name = "lsl"
    settings = LslSettings

    def create(self, settings: Settings, context: SourceContext) -> LslSource:
        assert isinstance(settings, LslSettings)
        return LslSource(settings)


PLUGIN = LslPlugin()
