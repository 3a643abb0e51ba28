"""From pressure samples to decisions a patient can produce with one pressure pad.

One press is one decision, emitted when the press ends:

* **direction** from how hard: a *firm* press (peak above ``firm_level``) means +1
  (toward the goal side of the primary axis), a *light* press means -1;
* **admission radius** from how long: a quick press (< ``long_press_s``) chooses E_big
  (fast, less precise), a held press chooses E_small (careful);
* **confidence** from how far the peak is from the firm/light boundary.

Pressure is normalised with the calibration (0 at rest, 1 at a firm press), passed through
a running median (a glitch of up to ``glitch_frames`` samples, of any amplitude, never
reaches the level), low-pass filtered, and thresholded with hysteresis (on above
``on_level``, off below ``off_level``); presses shorter than ``min_press_s`` are bounces.

Nothing the decoder did not see from start to end becomes a decision: after a gap in the
samples (lost frames, a reconnected port, stale time stamps) it starts afresh and waits
for the pad to be at rest before it counts a press; a press held longer than
``stuck_after_s`` is a stuck sensor (:attr:`PressDecoder.stuck_since`), dropped, and the
decoder again waits for rest.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass

from pydantic import BaseModel, Field, model_validator

from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.pad.protocol import RAW_MAX, SAMPLE_RATE_HZ
from dammrl_core.settings import FINITE, ordered

NOISE_MARGIN = 8.0  # calibrated levels are at least this many rest-noise deviations apart
MIN_LEVEL_GAP_RAW = 40.0  # ... and at least this far apart (1 % of a 12-bit ADC) [counts]
OFF_LEVEL_NOISE_MARGIN = 4.0  # the off level sits this many rest-noise deviations over rest


class Calibration(BaseModel):
    """Raw readings of the pad at rest, under a light press and under a firm press."""

    model_config = FINITE

    rest_raw: float = Field(ge=0, le=RAW_MAX)  # readings the pad can make (12 bits)
    light_raw: float = Field(ge=0, le=RAW_MAX)
    firm_raw: float = Field(ge=0, le=RAW_MAX)
    rest_noise_raw: float | None = Field(None, ge=0)
    """Robust standard deviation of the readings at rest [ADC counts]; None in files written
    before it was measured: then the levels need only be MIN_LEVEL_GAP_RAW apart."""

    @model_validator(mode="after")
    def _ordered(self) -> Calibration:
        if not self.rest_raw < self.light_raw < self.firm_raw:
            raise ValueError(
                f"calibration needs rest < light < firm, got {self.rest_raw}, "
                f"{self.light_raw}, {self.firm_raw} (was the pad pressed during 'rest'?)"
            )
        for low, high in (("rest", "light"), ("light", "firm")):
            gap = getattr(self, f"{high}_raw") - getattr(self, f"{low}_raw")
            if gap < self.level_gap_raw:
                raise ValueError(
                    f"{high}_raw is only {gap:.4g} counts above {low}_raw, need "
                    f"{self.level_gap_raw:.0f} ({self._gap_rule()}): ADC noise would be "
                    "taken for presses"
                )
        return self

    @property
    def level_gap_raw(self) -> float:
        """Least distance between rest, light and firm [ADC counts]."""
        return max(MIN_LEVEL_GAP_RAW, NOISE_MARGIN * (self.rest_noise_raw or 0.0))

    def _gap_rule(self) -> str:
        if self.rest_noise_raw is None:
            return f"no rest noise in the file: {MIN_LEVEL_GAP_RAW:.0f} counts"
        return (
            f"the larger of {MIN_LEVEL_GAP_RAW:.0f} counts and {NOISE_MARGIN:.0f} x the rest "
            f"noise {self.rest_noise_raw:.1f}"
        )

    def normalise(self, raw: float) -> float:
        return (raw - self.rest_raw) / (self.firm_raw - self.rest_raw)

    @property
    def light_level(self) -> float:
        return self.normalise(self.light_raw)


class DecoderSettings(BaseModel):
    model_config = FINITE

    filter_time_constant_s: float = Field(0.03, ge=0, le=1)
    """Low-pass filter of the normalised level (0: none) [s]."""
    on_level: float = Field(0.15, gt=0, lt=1)
    """A press begins above this normalised level (0 rest, 1 firm)..."""
    off_level: float = Field(0.08, gt=0, lt=1)
    """... and ends below this one (hysteresis: below ``on_level``)."""
    min_press_s: float = Field(0.06, ge=0, le=2)
    """Shorter presses are bumps, not decisions [s]."""
    long_press_s: float = Field(0.5, gt=0, le=10)
    """A press held this long chooses E_small (careful), a shorter one E_big [s]."""
    firm_level: float | None = Field(None, gt=0, lt=1.5)
    """Peak above which a press is firm; None: halfway between light and firm calibration."""
    glitch_frames: int = Field(6, ge=0, le=50)
    """Bursts of up to this many samples, of any amplitude, are ignored (a running median
    of 2n+1 samples; it delays the level by n samples)."""
    max_gap_s: float = Field(0.25, gt=0, le=5)
    """Samples missing for longer (lost frames at the protocol's rate, or between arrivals):
    the press in progress is dropped and the pad must be at rest again [s]."""
    stuck_after_s: float = Field(10.0, gt=0, le=600)
    """Pressed for longer than this: a stuck sensor, reported; the press is dropped [s]."""
    onset_tolerance_s: float = Field(0.05, ge=0.0, le=0.5)
    """A press that began up to this long before its request opened still answers it (the
    request reaches the display and the intent service at slightly different times);
    one that began earlier answers nothing [s]."""

    @model_validator(mode="after")
    def _hysteresis(self) -> DecoderSettings:
        ordered(self, "off_level", "on_level")  # hysteresis
        ordered(self, "min_press_s", "long_press_s")
        ordered(self, "long_press_s", "stuck_after_s")  # else a held press would be "stuck"
        return self


def level_problem(calibration: Calibration, settings: DecoderSettings) -> str | None:
    """Why rest noise could cross the thresholds, or a light press not reach them; None: ok."""
    span = calibration.firm_raw - calibration.rest_raw
    noise = calibration.rest_noise_raw or MIN_LEVEL_GAP_RAW / NOISE_MARGIN
    if settings.off_level * span < OFF_LEVEL_NOISE_MARGIN * noise:
        return (
            f"the off level (DAMMRL_PAD_DECODER__OFF_LEVEL={settings.off_level} of the "
            f"{span:.0f} counts from rest to firm) is {settings.off_level * span:.1f} counts "
            f"over rest, need {OFF_LEVEL_NOISE_MARGIN:.0f} x the rest noise ({noise:.1f} "
            "counts): ADC noise would be taken for presses"
        )
    if calibration.light_level <= settings.on_level:
        return (
            f"a light press ({calibration.light_level:.2f} of the range from rest to firm) does "
            f"not reach the on level (DAMMRL_PAD_DECODER__ON_LEVEL={settings.on_level})"
        )
    firm = firm_level(calibration, settings)
    if (firm_raw := calibration.rest_raw + firm * span) > RAW_MAX:
        return (
            f"a firm press must read {firm_raw:.0f} counts (DAMMRL_PAD_DECODER__FIRM_LEVEL="
            f"{firm:.2f} of the range from rest to firm), beyond the pad's {RAW_MAX}: no press "
            "could be firm, and every one would be taken as back"
        )
    return None


def firm_level(calibration: Calibration, settings: DecoderSettings) -> float:
    """The normalised peak from which a press is firm: the setting, else halfway from a
    light press to the calibrated firm one."""
    if settings.firm_level is not None:
        return settings.firm_level
    return (calibration.light_level + 1) / 2


@dataclass(frozen=True)
class PressDecision:
    t_s: float  # when the press ended [s]
    u_h: int  # +1 firm, -1 light
    human_model: int  # 1 = E_big (quick press), 2 = E_small (held press)
    confidence: float  # 0..1
    duration_s: float
    peak: float  # normalised


class PressDecoder:
    def __init__(self, calibration: Calibration, settings: DecoderSettings | None = None) -> None:
        self.calibration = calibration
        self.settings = settings or DecoderSettings()
        s = self.settings
        if (problem := level_problem(calibration, s)) is not None:
            raise ConfigurationError(
                f"{problem}: recalibrate (dammrl sensor calibrate) or change the levels"
            )
        self.firm_level = firm_level(calibration, s)
        self._window: deque[float] = deque(maxlen=2 * s.glitch_frames + 1)
        self._recent: deque[float] = deque(maxlen=3)
        self._tops: deque[float] = deque(maxlen=2 * s.glitch_frames + 1)  # 3-sample medians
        self.ambiguous = 0  # presses dropped: too short to tell firm from a glitch
        self._max_lost = s.max_gap_s * SAMPLE_RATE_HZ
        self.reset()

    def reset(self) -> None:
        """Start afresh (a disconnect, a gap): the press in progress never becomes a decision,
        and no press counts until the pad has been at rest."""
        self._window.clear()
        self._recent.clear()
        self._tops.clear()
        self.level = 0.0  # filtered, normalised pressure
        self.pressing_since: float | None = None  # a press that will be a decision
        self.peak = 0.0  # since the pad left rest, of the median: a glitch cannot raise it
        self._quick_peak = 0.0  # ... of 3-sample medians: a quick press's top raises it too
        self.high_since: float | None = None  # over the on level (hysteresis), press or not
        self.armed = False  # the pad was at rest since the last reset or stuck press
        self._last_t: float | None = None

    @property
    def stuck_since(self) -> float | None:
        """When the pad went over the on level, if it stayed there longer than allowed."""
        held = self.high_since
        if held is None or self._last_t is None:
            return None
        return held if self._last_t - held > self.settings.stuck_after_s else None

    def update(self, t_s: float, raw: float, lost_frames: int | None = 0) -> PressDecision | None:
        """One sample; the decision of the press that just ended, if any.

        lost_frames: frames missing just before this one (from the sequence numbers); None
        when unknown (the first frame after the port was opened).
        """
        if self._gap(t_s, lost_frames):
            self.reset()
        value = self.calibration.normalise(raw)
        self._window.append(value)
        self._recent.append(value)
        self._tops.append(statistics.median(self._recent))
        median = statistics.median(self._window)
        self._filter(t_s, median)
        if len(self._window) < (self._window.maxlen or 1):
            return None  # too few samples yet to tell a glitch from a press
        self._track_peaks(median)
        if self.high_since is None:
            self._rest_or_onset(t_s)
            return None
        if self.level >= self.settings.off_level:
            if self.stuck_since is not None:
                self.pressing_since = None  # a stuck sensor's "press" is no decision
            return None
        return self._release(t_s)

    def _gap(self, t_s: float, lost_frames: int | None) -> bool:
        if lost_frames is None or lost_frames > self._max_lost:
            return True
        last = self._last_t
        return last is not None and not 0 <= t_s - last <= self.settings.max_gap_s

    def _track_peaks(self, median: float) -> None:
        """The peaks since the pad left rest: the filtered level lags the samples, so a
        quick press's top is over before the level crosses the on level."""
        if self.high_since is None and self.level < self.settings.off_level:
            self.peak = self._quick_peak = 0.0
            return
        self.peak = max(self.peak, median)
        self._quick_peak = max(self._quick_peak, *self._tops)

    def _rest_or_onset(self, t_s: float) -> None:
        if self.level < self.settings.off_level:
            self.armed = True
        elif self.level > self.settings.on_level:
            self.high_since = t_s
            if self.armed:
                self.pressing_since = t_s

    def _release(self, t_s: float) -> PressDecision | None:
        since, self.pressing_since, self.high_since = self.pressing_since, None, None
        self.armed = True
        if since is None:
            return None  # the pad was pressed before we could see it start, or stuck
        duration = t_s - since
        if duration < self.settings.min_press_s:
            return None  # a bounce
        return self._decision(t_s, duration)

    def _filter(self, t_s: float, value: float) -> None:
        tau = self.settings.filter_time_constant_s
        if self._last_t is None or tau == 0:
            self.level = value
        else:
            alpha = 1.0 - math.exp(-max(t_s - self._last_t, 0.0) / tau)
            self.level += alpha * (value - self.level)
        self._last_t = t_s

    def _decision(self, t_s: float, duration: float) -> PressDecision | None:
        firm = self.peak >= self.firm_level
        if firm != (self._quick_peak >= self.firm_level):
            # firm for fewer samples than a glitch lasts: a quick firm press, or a light
            # one with a glitch on top; either way no decision rather than a wrong one
            self.ambiguous += 1
            return None
        spread = max(self.firm_level - self.settings.on_level, 1e-6)
        confidence = min(1.0, abs(self.peak - self.firm_level) / spread)
        return PressDecision(
            t_s=t_s,
            u_h=1 if firm else -1,
            human_model=2 if duration >= self.settings.long_press_s else 1,
            confidence=confidence,
            duration_s=duration,
            peak=self.peak,
        )
