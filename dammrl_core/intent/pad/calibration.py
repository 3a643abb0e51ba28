"""Calibration of the pressure pad from three recordings: rest, a light and a firm press.

Pure statistics, so they are tested without a terminal; ``dammrl sensor calibrate``
guides the person through the recordings and saves the result as JSON
(:class:`~dammrl_core.intent.pad.decoder.Calibration`, read back through
``DAMMRL_PAD_CALIBRATION_FILE``). The rest recording also measures the pad's noise: a
calibration whose levels, or whose decoder thresholds, that noise could cross is refused
with what to redo (ADC noise would otherwise be taken for presses).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from dammrl_core.errors import ConfigurationError, DammrlError
from dammrl_core.intent.pad.decoder import Calibration, DecoderSettings, level_problem
from dammrl_core.settings import error_line

NOISE_RAW = 12.0  # the emulated pad's ADC noise (standard deviation) [counts]
DEFAULT_CALIBRATION = Calibration(
    rest_raw=400, light_raw=1200, firm_raw=3000, rest_noise_raw=NOISE_RAW
)
"""The emulated pad's levels: what a service uses without a calibration file."""

MIN_PRESS_RISE_RAW = 40.0  # a press must rise at least this far above rest [ADC counts]
NOISE_MARGIN = 8.0  # ... and this many noise standard deviations
MIN_PRESSED_FRACTION = 0.3  # of a step's recording spent pressing
MIN_FIRM_LIGHT_GAP = 0.2  # (firm - light) / (firm - rest): the decoder must tell them apart


class CalibrationError(DammrlError):
    """A recording that cannot calibrate the pad; the message says what to do."""


@dataclass(frozen=True)
class Rest:
    raw: float  # median reading at rest
    noise_raw: float  # robust standard deviation (MAD) of the rest readings


def rest_of(samples: Sequence[int]) -> Rest:
    if len(samples) < 10:
        raise CalibrationError(f"only {len(samples)} samples at rest: is the sensor sending?")
    values = np.asarray(samples, dtype=float)
    median = float(np.median(values))
    noise = 1.4826 * float(np.median(np.abs(values - median)))
    return Rest(median, noise)


def press_threshold(rest: Rest) -> float:
    return rest.raw + max(MIN_PRESS_RISE_RAW, NOISE_MARGIN * rest.noise_raw)


def held_press(samples: Sequence[int], rest: Rest, what: str) -> float:
    """The median reading while pressing (samples clearly above rest)."""
    values = np.asarray(samples, dtype=float)
    pressed = values[values > press_threshold(rest)]
    if len(values) == 0 or len(pressed) < MIN_PRESSED_FRACTION * len(values):
        raise CalibrationError(
            f"no {what} press held: the pad was pressed during {len(pressed)} of "
            f"{len(values)} samples. Press and hold until the recording ends."
        )
    return float(np.median(pressed))


def calibration_from(
    rest: Rest, light_raw: float, firm_raw: float, decoder: DecoderSettings | None = None
) -> Calibration:
    """The calibration of three recordings, checked against the decoder's thresholds."""
    if firm_raw <= light_raw:
        raise CalibrationError(
            f"the firm press ({firm_raw:.0f}) was not harder than the light one "
            f"({light_raw:.0f}): redo both, light first, then as firm as is comfortable"
        )
    gap = (firm_raw - light_raw) / (firm_raw - rest.raw)
    if gap < MIN_FIRM_LIGHT_GAP:
        raise CalibrationError(
            f"light ({light_raw:.0f}) and firm ({firm_raw:.0f}) presses are too close to tell "
            f"apart ({gap:.0%} of the range, need {MIN_FIRM_LIGHT_GAP:.0%}): press lighter "
            "for 'light' or harder for 'firm'"
        )
    try:
        calibration = Calibration(
            rest_raw=rest.raw, light_raw=light_raw, firm_raw=firm_raw, rest_noise_raw=rest.noise_raw
        )
    except ValidationError as exc:
        raise CalibrationError(f"{error_line(exc)}. {_redo(rest)}") from None
    if (problem := level_problem(calibration, decoder or DecoderSettings())) is not None:
        raise CalibrationError(f"{problem}. {_redo(rest)}")
    return calibration


def _redo(rest: Rest) -> str:
    return (
        f"Redo all three steps: keep the pad untouched and still during 'rest' (noise was "
        f"+/-{rest.noise_raw:.0f} counts; if it stays that high, check the sensor's wiring), "
        "press clearly harder than rest for 'light' and as firm as is comfortable for 'firm'"
    )


def load_calibration(path: Path | None) -> Calibration:
    """The calibration saved by ``dammrl sensor calibrate``; None: the emulator's default."""
    if path is None:
        return DEFAULT_CALIBRATION
    try:
        return Calibration.model_validate_json(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigurationError(f"cannot read the calibration file {path}: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigurationError(
            f"{path} is not a calibration file (not UTF-8 text: {exc})"
        ) from None
    except ValidationError as exc:
        raise ConfigurationError(
            f"{path} is not a valid calibration file: {error_line(exc)}; run "
            "dammrl sensor calibrate again"
        ) from None
