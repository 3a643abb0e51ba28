"""From pressure samples to decisions a patient can produce with one pressure pad.

One press is one decision, emitted when the press ends:

* **direction** from how hard: a *firm* press (peak above ``firm_level``) means +1
  (toward the goal side of the primary axis), a *light* press means -1;
* **admission radius** from how long: a quick press (< ``long_press_s``) chooses E_big
  (fast, less precise), a held press chooses E_small (careful);
* **confidence** from how far the peak is from the firm/light boundary.

Pressure is normalised with the calibration (0 at rest, 1 at a firm press), low-pass
filtered, and thresholded with hysteresis (on above ``on_level``, off below
``off_level``); presses shorter than ``min_press_s`` are bounces and ignored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pydantic import BaseModel, Field, model_validator

from dammrl.core.settings import FINITE


class Calibration(BaseModel):
    """Raw readings of the pad at rest, under a light press and under a firm press."""

    model_config = FINITE

    rest_raw: float = Field(ge=0)
    light_raw: float = Field(ge=0)
    firm_raw: float = Field(ge=0)

    @model_validator(mode="after")
    def _ordered(self) -> Calibration:
        if not self.rest_raw < self.light_raw < self.firm_raw:
            raise ValueError(
                f"calibration needs rest < light < firm, got {self.rest_raw}, "
                f"{self.light_raw}, {self.firm_raw} (was the pad pressed during 'rest'?)"
            )
        return self

    def normalise(self, raw: float) -> float:
        return (raw - self.rest_raw) / (self.firm_raw - self.rest_raw)

    @property
    def light_level(self) -> float:
        return self.normalise(self.light_raw)


class DecoderSettings(BaseModel):
    model_config = FINITE

    filter_time_constant_s: float = Field(0.03, ge=0)
    on_level: float = Field(0.15, gt=0, lt=1)
    off_level: float = Field(0.08, gt=0, lt=1)
    min_press_s: float = Field(0.06, ge=0)
    long_press_s: float = Field(0.5, gt=0)
    firm_level: float | None = Field(None, gt=0, lt=1.5)
    """Peak above which a press is firm; None: halfway between light and firm calibration."""

    @model_validator(mode="after")
    def _hysteresis(self) -> DecoderSettings:
        if not self.off_level < self.on_level:
            raise ValueError(f"off_level {self.off_level} must be below on_level {self.on_level}")
        return self


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
        self.firm_level = (
            s.firm_level if s.firm_level is not None else (calibration.light_level + 1) / 2
        )
        self.level = 0.0  # filtered, normalised pressure
        self.pressing_since: float | None = None
        self.peak = 0.0
        self._last_t: float | None = None

    def update(self, t_s: float, raw: float) -> PressDecision | None:
        """One sample; the decision of the press that just ended, if any."""
        self._filter(t_s, self.calibration.normalise(raw))
        s = self.settings
        if self.pressing_since is None:
            if self.level > s.on_level:
                self.pressing_since, self.peak = t_s, self.level
            return None
        self.peak = max(self.peak, self.level)
        if self.level >= s.off_level:
            return None
        duration = t_s - self.pressing_since
        self.pressing_since = None
        if duration < s.min_press_s:
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

    def _decision(self, t_s: float, duration: float) -> PressDecision:
        firm = self.peak >= self.firm_level
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
