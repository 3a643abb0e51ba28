"""Known presses on a recorded-style trace give known decisions."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from dammrl_core.intent.pad.decoder import Calibration, PressDecoder

CAL = Calibration(rest_raw=400, light_raw=1200, firm_raw=3000)
RATE_HZ = 100.0


def trace(presses: list[tuple[float, float, float]], total_s: float, seed: int = 0) -> np.ndarray:
    """Raw samples at 100 Hz: presses (start s, duration s, level 0..1) on a noisy rest."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, total_s, 1 / RATE_HZ)
    level = np.zeros_like(t)
    for start, duration, height in presses:
        ramp = np.clip(np.minimum(t - start, start + duration - t) / 0.05, 0, 1)
        level = np.maximum(level, height * ramp)
    raw = CAL.rest_raw + level * (CAL.firm_raw - CAL.rest_raw) + rng.normal(0, 15, t.size)
    return np.stack([t, np.clip(raw, 0, 4095)], axis=1)


def decode(samples: np.ndarray) -> list[tuple[int, int]]:
    decoder = PressDecoder(CAL)
    out = []
    for t, raw in samples:
        decision = decoder.update(float(t), float(raw))
        if decision is not None:
            out.append((decision.u_h, decision.human_model))
    return out


def test_known_presses_give_known_commands() -> None:
    presses = [
        (0.5, 0.25, 1.0),  # quick firm: +1, E_big
        (1.5, 0.25, 0.35),  # quick light: -1, E_big
        (2.5, 0.9, 1.0),  # held firm: +1, E_small
        (4.0, 0.9, 0.35),  # held light: -1, E_small
    ]
    assert decode(trace(presses, 6.0)) == [(1, 1), (-1, 1), (1, 2), (-1, 2)]


def test_rest_noise_and_bounces_give_no_decision() -> None:
    assert decode(trace([], 5.0)) == []
    assert decode(trace([(1.0, 0.03, 1.0)], 3.0)) == []  # a 30 ms tap is a bounce


def test_hysteresis_keeps_one_press_one_decision_when_the_level_wobbles() -> None:
    samples = trace([(1.0, 1.0, 0.4)], 3.0)
    wobble = (np.abs(samples[:, 0] - 1.5) < 0.3) * 120 * np.sin(samples[:, 0] * 80)
    samples[:, 1] += wobble  # dips toward the on level but not below the off level
    assert decode(samples) == [(-1, 2)]


def test_confidence_grows_with_the_margin_from_the_boundary() -> None:
    decoder = PressDecoder(CAL)
    decisions = []
    for height in (1.0, 0.62):
        for t, raw in trace([(0.5, 0.3, height)], 1.5):
            if (d := decoder.update(float(t) + len(decisions) * 2.0, float(raw))) is not None:
                decisions.append(d)
    assert decisions[0].confidence > decisions[1].confidence


def test_a_calibration_that_is_not_ordered_is_refused() -> None:
    with pytest.raises(ValidationError, match="rest < light < firm"):
        Calibration(rest_raw=1000, light_raw=900, firm_raw=3000)
