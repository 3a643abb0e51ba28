"""What is done to a wearable's samples before the features: the same in calibration,
online decoding and ``dammrl recording decode`` (the calibration file keeps it).

* **High-pass** (Butterworth, per channel): many amplifier programs stream DC-coupled raw
  samples, whose offset (an electrode's half-cell potential: up to hundreds of mV, and
  drifting) would dominate every amplitude feature; surface EMG's power lies above
  ~20 Hz, so a 20 Hz high-pass keeps the signal and removes the offset and the slow
  motion artefacts (LibEMG's common filters do the same).
* **Mains notch** (50 or 60 Hz, settable): the hum electrodes pick up.
* **Level normalisation**: each channel's amplitude features (log MAV, log WL) are taken
  relative to that channel's *rest level*, the ``level_quantile`` of its window MAV over
  the last ``level_window_s`` (while the history fills, a lower one: the minimum at
  first). A person rests most of the time, so that quantile is
  the rest level whatever the classes, as long as a fifth of the last 10 s was rest (a
  decision's contraction lasts 4 s at most); a gain change (electrode impedance, sweat, another
  amplifier setting) scales rest and contraction alike and cancels out. Zero crossings
  and slope sign changes do not depend on the gain. The calibration's classifier is
  trained on the same normalised features, window by window in time order, so calibration
  and decoding see exactly the same numbers.

The filters are causal (``sosfilt`` with its state carried from chunk to chunk), started
in their steady state for the first sample (a DC offset gives no start-up transient), so
filtering a recording at once and filtering it chunk by chunk give the same samples.

A sudden *step* of the offset (an electrode or its cable moved) passes a high-pass as a
burst of ringing as loud as a contraction for ~50 ms; ``baseline_step`` finds one in the
raw samples (the mean of 25 ms beside the mean of the 25 ms before, far beyond the
samples' own spread: EMG has no mean) so the decoder can ignore the burst.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

MAINS_HZ = (50.0, 60.0)
NOTCH_Q = 30.0
"""The notch's quality factor: -3 dB over f0 / Q (1.7 Hz at 50 Hz): mains only."""
HIGH_PASS_ORDER = 4
MAX_OF_NYQUIST = 0.9
"""A filter's frequency must lie below this fraction of half the sample rate."""


class Conditioning(BaseModel):
    """The conditioning of one calibration (kept in its file)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    high_pass_hz: float = Field(ge=0.0, le=200.0)
    """Cut-off of the per-channel high-pass (DC removal) [Hz]; 0: none (an IMU's posture
    is its DC)."""
    notch_hz: Literal[0, 50, 60]
    """The mains frequency to notch out [Hz]; 0: none."""
    normalise_level: bool
    """Amplitude features relative to each channel's tracked rest level (gain-free)."""
    level_window_s: float = Field(10.0, ge=1.0, le=120.0)
    """The rest level is tracked over this much of the latest signal [s]."""
    level_quantile: float = Field(0.2, ge=0.01, le=0.5)
    """The rest level: this quantile of the windows' MAV over ``level_window_s``."""

    @classmethod
    def none(cls) -> Conditioning:
        """Raw samples, absolute amplitudes (a version 1 calibration; an IMU)."""
        return cls(high_pass_hz=0.0, notch_hz=0, normalise_level=False)

    @classmethod
    def emg(cls, mains_hz: Literal[0, 50, 60] = 50, high_pass_hz: float = 20.0) -> Conditioning:
        """What a lab expects before EMG features: 20 Hz high-pass, mains notch, gain-free."""
        return cls(high_pass_hz=high_pass_hz, notch_hz=mains_hz, normalise_level=True)

    def problem(self, rate_hz: float) -> str | None:
        """Why these filters cannot run at ``rate_hz`` (a one-line reason), or None."""
        nyquist = rate_hz / 2
        for name, hz in (("high_pass_hz", self.high_pass_hz), ("notch_hz", self.notch_hz)):
            if hz and hz >= MAX_OF_NYQUIST * nyquist:
                limit = MAX_OF_NYQUIST * nyquist
                return (f"conditioning.{name} {hz:g} Hz: below {limit:g} Hz at "
                        f"{rate_hz:g} Hz (0.9 x half the rate)")  # fmt: skip
        return None

    def describe(self) -> str:
        high = f"high-pass {self.high_pass_hz:g} Hz" if self.high_pass_hz else "no high-pass"
        notch = f"{self.notch_hz} Hz notch" if self.notch_hz else "no notch"
        levels = "levels relative to rest" if self.normalise_level else "absolute levels"
        return f"{high}, {notch}, {levels}"


def filter_sections(conditioning: Conditioning, rate_hz: float) -> np.ndarray | None:
    """The second-order sections of the high-pass and the notch (None: no filter)."""
    from scipy import signal

    sections = []
    if conditioning.high_pass_hz:
        sections.append(signal.butter(HIGH_PASS_ORDER, conditioning.high_pass_hz, "highpass",
                                      fs=rate_hz, output="sos"))  # fmt: skip
    if conditioning.notch_hz:
        b, a = signal.iirnotch(float(conditioning.notch_hz), NOTCH_Q, fs=rate_hz)
        sections.append(signal.tf2sos(b, a))
    return np.concatenate(sections) if sections else None


class Filters:
    """The conditioning's filters on a stream of chunks (n, channels), state carried."""

    def __init__(self, conditioning: Conditioning, rate_hz: float) -> None:
        self.sos = filter_sections(conditioning, rate_hz)
        self.state: np.ndarray | None = None  # (sections, 2, channels)

    def __call__(self, samples: np.ndarray) -> np.ndarray:
        """The filtered chunk (the same shape)."""
        x = np.asarray(samples, dtype=float)
        if self.sos is None or len(x) == 0:
            return x
        from scipy import signal

        if self.state is None:  # steady state for the first sample: no start-up step
            self.state = signal.sosfilt_zi(self.sos)[:, :, None] * x[0][None, None, :]
        y, self.state = signal.sosfilt(self.sos, x, axis=0, zi=self.state)
        return np.asarray(y)

    def reset(self) -> None:
        """Start afresh at the next sample (after a gap: nothing spans it)."""
        self.state = None


def condition(samples: np.ndarray, rate_hz: float, conditioning: Conditioning) -> np.ndarray:
    """A whole recording (n, channels) filtered as a live stream would be."""
    return Filters(conditioning, rate_hz)(samples)


class RestLevel:
    """Each channel's rest level, from the MAV of its latest windows (see the module)."""

    def __init__(self, conditioning: Conditioning, hop_s: float) -> None:
        self.quantile = conditioning.level_quantile
        self.mav_log: deque[np.ndarray] = deque(
            maxlen=max(1, round(conditioning.level_window_s / hop_s))
        )
        self.level = np.zeros(0)

    def add(self, log_mav: np.ndarray) -> np.ndarray:
        """Take one window's log MAV per channel; the rest level's log per channel."""
        self.mav_log.append(np.asarray(log_mav, dtype=float))
        self.level = self._level_log()
        return self.level

    def level_log(self) -> np.ndarray:
        """The rest level's log per channel, as of the last window."""
        return self.level

    def _level_log(self) -> np.ndarray:
        """The k-th lowest window MAV (log) per channel: k = the quantile's share of a
        full history, and while the history fills, of that share as much as the history
        is full (the minimum at first): a calibration's first trial may be a 3 s
        contraction after half a second of rest, and that rest is the level."""
        history = np.sort(np.array(self.mav_log), axis=0)
        full = self.mav_log.maxlen or 1
        k = max(1, math.ceil(self.quantile * len(history) * len(history) / full))
        return np.asarray(history[k - 1])

    def reset(self) -> None:
        self.mav_log.clear()

    def full(self) -> bool:
        return len(self.mav_log) == self.mav_log.maxlen

    @property
    def windows(self) -> int:
        return len(self.mav_log)


AMPLITUDE_FEATURES = 2
"""log MAV and log WL lead the EMG feature vector (``features.FEATURES``): a gain adds
its log to both."""


def normalised(features: np.ndarray, level_log: np.ndarray) -> np.ndarray:
    """EMG features (4 * channels, grouped by feature) with log MAV and log WL taken
    relative to each channel's rest level (``level_log``, (channels,))."""
    out = np.array(features, dtype=float)
    channels = len(level_log)
    out[: AMPLITUDE_FEATURES * channels] -= np.tile(level_log, AMPLITUDE_FEATURES)
    return out


class Normaliser:
    """Window features -> features relative to the tracked rest level (or unchanged)."""

    def __init__(self, conditioning: Conditioning, hop_s: float, kind: str) -> None:
        self.active = conditioning.normalise_level and kind == "emg"
        self.rest = RestLevel(conditioning, hop_s)

    def __call__(self, features: np.ndarray) -> np.ndarray:
        if not self.active:
            return np.asarray(features)
        channels = len(features) // 4
        return normalised(features, self.rest.add(features[:channels]))

    def level_log(self) -> np.ndarray | None:
        """The rest level's log per channel (None before any window, or not normalising)."""
        return self.rest.level_log() if self.active and self.rest.windows else None

    def reset(self) -> None:
        self.rest.reset()


STEP_SEGMENT_S = 0.025
"""A baseline step: the mean of this long beside the mean of as long before [s]."""
STEP_OF_SPREAD = 8.0
"""... differing by more than this many times the samples' spread about those means (EMG,
20-450 Hz, has no mean over 25 ms: its two means differ by a fraction of its spread; a
motion artefact's slow bump by about three times)."""


def baseline_step(raw: np.ndarray, rate_hz: float) -> tuple[int, float] | None:
    """The channel whose raw samples (n, channels) step most beyond their spread, and the
    step's size (the stream's units), or None when none does."""
    x = np.asarray(raw, dtype=float)
    half = max(2, round(STEP_SEGMENT_S * rate_hz))
    if len(x) < 2 * half:
        return None
    x = x - x.mean(axis=0)  # a DC offset of any size keeps its precision
    total = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    squares = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x**2, axis=0)])
    split = np.arange(half, len(x) - half + 1)  # the first sample after each split
    before = (total[split] - total[split - half]) / half
    after = (total[split + half] - total[split]) / half
    spread_before = (squares[split] - squares[split - half]) / half - before**2
    spread_after = (squares[split + half] - squares[split]) / half - after**2
    spread = np.sqrt(np.maximum((spread_before + spread_after) / 2, 1e-24))
    ratio = np.abs(after - before) / spread
    k, channel = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    if ratio[k, channel] <= STEP_OF_SPREAD:
        return None
    return int(channel), float(after[k, channel] - before[k, channel])
