"""Decisions from a wearable sensor's stream: windows, the classifier, contractions.

Samples come in chunks with their timestamps (LSL's, already corrected to this machine's
clock). Every hop, the last window is classified (rest, -1 or +1, or rejected below the
window threshold) and a majority vote smooths the labels. A *contraction* is a run of
voted commands between rests; it becomes one decision when it ends:

* u_h: the command with the larger summed probability over the contraction's windows;
* confidence: sum P(u_h) / sum (P(-1) + P(+1)) over those windows, the classifier's
  probability of the command given that one was made (windows weighted by how surely
  they are a command: the ramps at either end count little);
* the admission radius, the paper's second decision, from the contraction's length as
  the pad's quick and held presses: shorter than ``long_contraction_s`` is E_big (quick,
  coarse), longer is E_small (held, careful). A person controls duration far more
  reliably than strength (strength drifts with fatigue and electrode contact, and a
  linear classifier's classes are strength-invariant by design), and the same rule for
  the pad and the wearable means one instruction for the participant.

Windows count samples, not timestamps, so jittered stamps (a step back of a few ms when
the sender is busy) only blur a contraction's onset by that much. Each chunk is
conditioned first (high-pass, mains notch) and each window's amplitude features taken
relative to the tracked rest level, as the calibration says
(:mod:`dammrl_core.intent.emg.conditioning`): a DC offset or a gain change leaves the
decisions as they were. A channel whose rest level strays outside ``LEVEL_RANGE`` of the
calibration's is a problem (an electrode's contact, not a person's gain);
``rebaseline`` measures the rest level afresh (the participant rests meanwhile).

A decision below ``min_confidence``, or shorter than ``min_contraction_s`` (a twitch),
is not acted on; one held longer than ``max_contraction_s`` is a stuck signal, not a
decision. Bad signal (non-finite samples, a flat or clipping channel, a step of a
channel's baseline, a gap or a jump in the timestamps) drops the contraction in
progress, and nothing counts until the signal is clean and the person has rested: no
decision ever spans it, and ``problem`` says what is wrong until the signal is clean
again.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Self

import numpy as np
from pydantic import BaseModel, Field, model_validator

from dammrl_core.intent.emg.calibration import EmgCalibration
from dammrl_core.intent.emg.classifier import REJECTED, majority
from dammrl_core.intent.emg.conditioning import Filters, Normaliser, baseline_step
from dammrl_core.intent.emg.features import features_of, window_samples
from dammrl_core.settings import FINITE, ordered

FLAT_OF_REST = 0.05
"""A channel whose RMS over a window is below this fraction of its rest RMS is flat."""
CLIPPED_SHARE = 0.05
CLIPPED_MIN = 3
"""A channel with this share of a window's samples (and this many at least) at its
extreme value is clipping: a signal's own peak is one sample."""
SPIKE_OF_REST = 100.0
SPIKE_ALONE = 8.0
"""A sample this many times a channel's rest RMS from its window's median, and this many
times as far as the window's fourth farthest, is a spike (an electrode's pop, a corrupted
packet): muscle signal comes in bursts (the calibration sessions' largest sample is 17 to
98 times the rest RMS, among others nearly as large). One spike once passed every check,
and the filters' ringing after it was decided as a contraction."""
LEVEL_RANGE = (0.1, 10.0)
"""A channel's rest level outside this multiple of the calibration's is a problem: no
gain drift goes so far (a tenth: an electrode nearly off; ten times: noise picked up)."""


class EmgDecoderSettings(BaseModel):
    """How windows become decisions (``DAMMRL_LSL_DECODER__*``)."""

    model_config = FINITE

    reject_below: float = Field(0.6, ge=0.34, le=1.0)
    """A window whose most probable class is less probable than this is rejected."""
    vote_windows: int = Field(3, ge=1, le=15)
    """Majority vote over this many accepted windows."""
    min_confidence: float = Field(0.75, ge=0.5, le=1.0)
    """A decision less confident than this is not acted on (the request stays open)."""
    long_contraction_s: float = Field(0.5, ge=0.1, le=3.0)
    """A contraction this long or longer chooses E_small (held); shorter, E_big (quick) [s]."""
    min_contraction_s: float = Field(0.08, ge=0.0, le=1.0)
    """Shorter contractions are twitches, not decisions [s]."""
    max_contraction_s: float = Field(4.0, ge=0.5, le=30.0)
    """A contraction longer than this is a stuck signal: no decision until rest [s]."""
    max_gap_s: float = Field(0.25, ge=0.01, le=5.0)
    """A gap between timestamps longer than this resets the decoder [s]."""
    onset_tolerance_s: float = Field(0.1, ge=0.0, le=0.5)
    """A contraction whose onset is estimated up to this long before its request opened
    still answers it (the onset's estimate: half a window back from the first voted
    window); one that began earlier answers nothing [s]."""
    max_step_back_s: float = Field(0.05, ge=0.0, le=1.0)
    """Timestamps stepping back by up to this are jitter, not a clock jump: an acquisition
    PC stamps each chunk when it pushes it (LSL back-dates its samples at the nominal
    rate), late when it is busy; a step back further resets the decoder [s]."""

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        """A twitch shorter than a held contraction, which is shorter than a stuck one."""
        ordered(self, "min_contraction_s", "long_contraction_s")
        ordered(self, "long_contraction_s", "max_contraction_s")
        return self


@dataclass(frozen=True)
class Contraction:
    """One decision of the decoder (acted on or not)."""

    u_h: int  # -1 or +1
    human_model: int  # 1 = E_big (quick), 2 = E_small (held)
    confidence: float  # [0, 1]
    onset_s: float  # when it began [s, the samples' clock]
    end_s: float  # when it ended [s]
    decided_s: float  # the time of the sample that completed the decision [s]
    windows: int
    features: tuple[float, ...]  # mean features over its windows
    accepted: bool
    reason: str  # why it was not acted on ("" when accepted)

    @property
    def duration_s(self) -> float:
        return self.end_s - self.onset_s


@dataclass
class _Run:
    """A contraction in progress."""

    first_end_s: float
    last_end_s: float
    p_minus: list[float] = field(default_factory=list)
    p_plus: list[float] = field(default_factory=list)
    features: list[np.ndarray] = field(default_factory=list)


class WindowDecoder:
    def __init__(self, calibration: EmgCalibration, settings: EmgDecoderSettings) -> None:
        self.calibration = calibration
        self.settings = settings
        self.rate_hz = calibration.stream.nominal_srate_hz
        self.channels = calibration.stream.channel_count
        self.size = window_samples(self.rate_hz, calibration.window_s)
        self.hop = window_samples(self.rate_hz, calibration.hop_s)
        self.classes = np.array(calibration.classifier.classes)
        self.rest_rms = np.array(calibration.rest_rms)
        self.rest_level = np.array(calibration.rest_level)
        self.filters = Filters(calibration.conditioning, self.rate_hz)
        self.normaliser = Normaliser(calibration.conditioning, calibration.hop_s,
                                     calibration.features)  # fmt: skip
        self.buffer = np.zeros((0, self.channels))  # raw: clipping is the amplifier's rail
        self.conditioned = np.zeros((0, self.channels))  # what the features see
        self.measuring = 0  # samples left of a rest level measured afresh (rebaseline)
        self.since_window = 0
        self.labels: deque[int] = deque(maxlen=settings.vote_windows)
        self.run: _Run | None = None
        self.stuck = False
        self.need_rest = False
        self.signal_problem: str | None = None
        self.interrupted: str | None = None  # why a rest is awaited (a clock jump)
        self.last_t: float | None = None
        self.windows = 0
        self.voted = 0  # the last voted label (0: rest)

    # ---- input ---------------------------------------------------------------------------
    def push(self, samples: np.ndarray, times: np.ndarray) -> list[Contraction]:
        """Take a chunk (n, channels) with its timestamps (n,) [s]; the contractions that
        ended in it."""
        samples = np.asarray(samples, dtype=float).reshape(len(times), -1)
        if samples.shape[1] != self.channels:
            self._bad(f"{samples.shape[1]} channels, the calibration has {self.channels}")
            return []
        if not np.all(np.isfinite(samples)):
            channel = int(np.argmax(~np.all(np.isfinite(samples), axis=0)))
            self._bad(f"non-finite samples (NaN or inf) on channel {channel}")
            return []
        if (jump := self._time_problem(np.asarray(times, dtype=float))) is not None:
            self._bad(jump)  # the chunk starts a new stretch of signal
        self.last_t = float(times[-1])
        return self._windows(samples, self.filters(samples), np.asarray(times, dtype=float))

    def _time_problem(self, times: np.ndarray) -> str | None:
        steps = np.diff(times, prepend=self.last_t if self.last_t is not None else times[0])
        worst = float(steps[np.argmax(np.abs(steps))]) if len(steps) else 0.0
        if worst < -self.settings.max_step_back_s or worst > self.settings.max_gap_s:
            return f"the samples' clock jumped by {worst:+.3f} s"
        return None

    def _windows(self, samples: np.ndarray, conditioned: np.ndarray,
                 times: np.ndarray) -> list[Contraction]:  # fmt: skip
        decided: list[Contraction] = []
        for k in range(len(samples)):  # a window every hop, wherever the chunks end
            self.since_window += 1
            self.measuring = max(0, self.measuring - 1)
            if self.since_window >= self.hop and len(self.buffer) + k + 1 >= self.size:
                self.since_window = 0
                raw = np.concatenate([self.buffer, samples[: k + 1]])[-self.size :]
                window = np.concatenate([self.conditioned, conditioned[: k + 1]])[-self.size :]
                if (ended := self._window(raw, window, float(times[k]))) is not None:
                    decided.append(ended)
        self.buffer = np.concatenate([self.buffer, samples])[-self.size :]
        self.conditioned = np.concatenate([self.conditioned, conditioned])[-self.size :]
        return decided

    # ---- one window ----------------------------------------------------------------------
    def _window(self, raw: np.ndarray, window: np.ndarray, end_s: float) -> Contraction | None:
        self.windows += 1
        if (spiked := _spike(raw, self.rest_rms)) is not None:  # the signal starts afresh: the
            self._bad(f"channel {spiked} spiked (an electrode's pop?)")  # filters would ring
            return None  # after it for seconds (one of 3e38 left the decoder deaf for 17 s)
        if (problem := self._channel_problem(raw)) is not None:
            self._bad(problem, keep_buffer=True)
            return None
        self.signal_problem = None
        features = self.normaliser(features_of(window, self.rate_hz, self.calibration.features))
        if self.measuring or self.level_problem() is not None:
            self._drop_run()  # the rest level is being measured, or not to be trusted
            return None
        p = self.calibration.classifier.probabilities(features)[0]
        best = int(np.argmax(p))
        self.labels.append(int(self.classes[best]) if p[best] >= self.settings.reject_below
                           else REJECTED)  # fmt: skip
        accepted = [c for c in self.labels if c != REJECTED]
        if accepted:
            self.voted = majority(accepted)
        return self._follow(self.voted, p, features, end_s)

    def _channel_problem(self, raw: np.ndarray) -> str | None:
        """A flat or clipping channel, on the raw samples: the filters' transients (the
        notch rings for a few hundred ms) would hide a channel that just went flat."""
        rms = raw.std(axis=0)
        if np.any(flat := rms < FLAT_OF_REST * self.rest_rms):
            return f"channel {int(np.argmax(flat))} flat (an electrode off?)"
        extreme = np.abs(raw).max(axis=0)
        at_extreme = np.sum(np.abs(raw) >= extreme * (1 - 1e-9), axis=0)
        clipped = at_extreme >= max(CLIPPED_MIN, CLIPPED_SHARE * len(raw))
        if np.any(clipped & (extreme > 0)):
            return f"channel {int(np.argmax(clipped))} clipping (saturated amplifier?)"
        if self.calibration.conditioning.high_pass_hz and (
            step := baseline_step(raw, self.rate_hz)
        ):  # the high-pass rings after it: the burst is no contraction
            return f"channel {step[0]}'s baseline stepped by {step[1]:+.4g} (an electrode moved?)"
        return None

    def _follow(self, label: int, p: np.ndarray, features: np.ndarray,
                end_s: float) -> Contraction | None:  # fmt: skip
        """Grow the contraction in progress, start one, or end it into a decision."""
        if self.need_rest:  # after bad signal: nothing counts until the person rests
            self.need_rest = label != 0
            self.interrupted = self.interrupted if self.need_rest else None
            return None
        if label in (-1, 1):
            if self.run is None:
                self.run = _Run(end_s, end_s)
            self.run.last_end_s = end_s
            self.run.p_minus.append(float(p[self._index(-1)]))
            self.run.p_plus.append(float(p[self._index(1)]))
            self.run.features.append(features)
            if end_s - self.run.first_end_s > self.settings.max_contraction_s:
                self.stuck = True
            return None
        if label != 0 or self.run is None:
            return None
        run, self.run = self.run, None
        if self.stuck:
            self.stuck = False
            return None
        return self._decision(run, end_s)

    def _index(self, label: int) -> int:
        return int(np.flatnonzero(self.classes == label)[0])

    def _decision(self, run: _Run, decided_s: float) -> Contraction:
        minus, plus = np.array(run.p_minus), np.array(run.p_plus)
        u_h = 1 if plus.sum() >= minus.sum() else -1
        chosen = plus if u_h > 0 else minus
        confidence = float(chosen.sum() / max(float((minus + plus).sum()), 1e-12))
        duration = run.last_end_s - run.first_end_s
        onset = run.first_end_s - self.calibration.window_s / 2  # half a window in
        human_model = 2 if duration >= self.settings.long_contraction_s else 1
        reason = ""
        if duration < self.settings.min_contraction_s:
            reason = f"a twitch ({duration:.2f} s)"
        elif confidence < self.settings.min_confidence:
            reason = f"confidence {confidence:.2f} < {self.settings.min_confidence}"
        return Contraction(u_h, human_model, confidence, onset, onset + duration, decided_s,
                           len(minus), tuple(np.mean(run.features, axis=0).tolist()),
                           not reason, reason)  # fmt: skip

    # ---- the rest level ------------------------------------------------------------------
    def level_ratio(self) -> np.ndarray | None:
        """Each channel's rest level now over the calibration's (None: not tracked)."""
        level = self.normaliser.level_log()
        if level is None or not len(self.rest_level):
            return None
        return np.asarray(np.exp(level) / np.maximum(self.rest_level, 1e-12))

    def level_problem(self) -> str | None:
        """A channel's rest level far from the calibration's, once a full history tells
        (at first the level may be a contraction's: one under way when the stream came)."""
        ratio = self.level_ratio()
        low, high = LEVEL_RANGE
        if ratio is None or not self.normaliser.rest.full():
            return None
        if np.all((ratio >= low) & (ratio <= high)):
            return None
        channel = int(np.argmax(np.abs(np.log(ratio))))
        return (f"channel {channel}'s rest level is {ratio[channel]:.2g} x the calibration's "
                f"(not {low:g}-{high:g} x): check its electrode, or calibrate again")  # fmt: skip

    def rebaseline(self, seconds: float) -> None:
        """Measure the rest level afresh over the next ``seconds`` of signal (the person
        rests); nothing is decided meanwhile."""
        self.normaliser.reset()
        self._drop_run()
        self.need_rest = True
        self.measuring = max(1, round(seconds * self.rate_hz))

    # ---- faults --------------------------------------------------------------------------
    def _drop_run(self) -> None:
        self.run = None
        self.stuck = False
        self.labels.clear()
        self.voted = 0

    def _bad(self, problem: str, keep_buffer: bool = False) -> None:
        """Drop the contraction in progress (no decision spans bad signal); unless
        ``keep_buffer``, the signal starts afresh (filters, rest level: a gap)."""
        self.signal_problem = problem
        self._drop_run()
        self.need_rest = True
        if not keep_buffer:
            self.buffer = np.zeros((0, self.channels))
            self.conditioned = np.zeros((0, self.channels))
            self.filters.reset()
            self.normaliser.reset()
            self.since_window = 0
            self.last_t = None

    def interrupt(self, problem: str) -> None:
        """Something happened to the stream (its clock jumped): drop the contraction in
        progress; decide again after a rest, saying why until then."""
        self._drop_run()
        self.need_rest = True
        self.interrupted = problem

    def reset(self) -> None:
        """Forget everything (the stream was lost)."""
        self._bad("", keep_buffer=False)
        self.signal_problem = self.interrupted = None
        self.measuring = 0

    def problem(self) -> str | None:
        if self.signal_problem:
            return self.signal_problem
        if self.interrupted:
            return f"{self.interrupted}: a rest, then decisions again"
        if self.measuring:
            return (f"measuring the rest level: {self.measuring / self.rate_hz:.1f} s left "
                    "(the participant rests)")  # fmt: skip
        if (level := self.level_problem()) is not None:
            return level
        if self.stuck and self.run is not None:
            return (f"a contraction held for {self.run.last_end_s - self.run.first_end_s:.1f} s: "
                    "no decision until rest")  # fmt: skip
        return None


def _spike(raw: np.ndarray, rest_rms: np.ndarray) -> int | None:
    """The first channel of ``raw`` (samples, channels) with a spike (``SPIKE_OF_REST``,
    ``SPIKE_ALONE``), or None."""
    if len(raw) < 4:
        return None
    deviation = np.abs(raw - np.median(raw, axis=0))
    top, fourth = np.max(deviation, axis=0), np.partition(deviation, -4, axis=0)[-4]
    spiked = (top > SPIKE_OF_REST * rest_rms) & (top > SPIKE_ALONE * fourth)
    return int(np.argmax(spiked)) if np.any(spiked) else None
