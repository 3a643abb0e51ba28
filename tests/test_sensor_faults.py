"""Sensor faults never become presses (issue 12): glitches, disconnects, a calibration that
noise could cross, a stuck sensor. Decoder tests first (fast), then the real intent
service reading an emulated pad on a pty (slow)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from dammrl.devices.emulators.pad import DEFAULT_CALIBRATION, Press, SensorEmulator
from dammrl_core.errors import ConfigurationError, Exit
from dammrl_core.intent.pad.calibration import (
    CalibrationError,
    Rest,
    calibration_from,
    load_calibration,
)
from dammrl_core.intent.pad.decoder import Calibration, DecoderSettings, PressDecoder
from dammrl_core.intent.pad.protocol import frames_lost
from schemas import Health
from tests.busutil import Observer, free_port, start_service, wait_for
from tests.sensor_fault_trials import (
    NARROWEST,
    TIGHT,
    PortRig,
    decisions,
    glitch_in_press_trials,
    glitch_trials,
    noisy_rest,
    phantom_trial,
    port_glitch_trials,
    port_press_trials,
    port_rig,
    press_trials,
    unplug_trials,
    with_press,
)

CAL = DEFAULT_CALIBRATION


def feed(decoder: PressDecoder, raws: np.ndarray, t0_s: float = 0.0) -> list[tuple[int, int]]:
    """Samples at 100 Hz from ``t0_s``; the decisions (direction, sub-model)."""
    found = []
    for k, raw in enumerate(raws):
        if (d := decoder.update(t0_s + k / 100, float(raw))) is not None:
            found.append((d.u_h, d.human_model))
    return found


def held(level: float, seconds: float) -> np.ndarray:
    return CAL.rest_raw + level * (CAL.firm_raw - CAL.rest_raw) + np.zeros(int(seconds * 100))


# --- glitches ------------------------------------------------------------------------------


def test_glitches_of_one_to_six_samples_of_any_amplitude_give_no_decision() -> None:
    found, trials = glitch_trials(per_case=2)
    assert (found, trials) == (0, 60)


def test_a_glitch_inside_a_press_never_makes_a_wrong_or_second_decision() -> None:
    wrong, dropped, trials = glitch_in_press_trials(per_case=1)
    assert wrong == 0 and dropped <= trials // 3  # upward glitches may drop it, never flip it


def test_genuine_quick_and_held_presses_are_still_decoded() -> None:
    rates = press_trials(per_case=3)
    assert all(rates[d] == 1.0 for d in (0.15, 0.2, 0.25, 0.8)), rates


def test_a_firm_press_too_short_to_tell_from_a_glitch_is_dropped_not_read_as_light() -> None:
    rng = np.random.default_rng(5)
    for duration in (0.1, 0.12, 0.13):
        raws = with_press(noisy_rest(1.5, rng, CAL), 0.4, Press(0, duration, 0.95), CAL)
        assert decisions(raws) == [], duration


# --- gaps and disconnects -------------------------------------------------------------------


def test_a_press_spanning_a_gap_in_time_stamps_is_no_decision() -> None:
    decoder = PressDecoder(CAL)
    assert feed(decoder, np.concatenate([held(0, 0.5), held(1.0, 0.3)])) == []
    assert decoder.pressing_since is not None
    assert feed(decoder, held(0, 1.0), t0_s=2.0) == []  # 1.2 s later, released


@pytest.mark.parametrize("lost", [None, 30])
def test_a_press_spanning_lost_frames_or_a_reopened_port_is_no_decision(lost: int | None) -> None:
    decoder = PressDecoder(CAL)
    feed(decoder, np.concatenate([held(0, 0.5), held(1.0, 0.3)]))
    assert decoder.update(0.81, CAL.rest_raw, lost) is None  # the next frame, after the gap
    assert feed(decoder, held(0, 1.0), t0_s=0.82) == [] and decoder.pressing_since is None


def test_after_a_gap_a_press_under_way_is_not_counted_and_the_next_one_is() -> None:
    decoder = PressDecoder(CAL)
    feed(decoder, held(0, 0.5))
    decoder.update(0.5, CAL.firm_raw, None)  # reconnected while someone presses
    pressed_then_released = np.concatenate([held(1.0, 0.5), held(0, 0.5)])
    assert feed(decoder, pressed_then_released, t0_s=0.51) == []
    quick_firm = np.concatenate([held(1.0, 0.2), held(0, 0.5)])
    assert feed(decoder, quick_firm, t0_s=1.6) == [(1, 1)]


def test_a_few_lost_frames_inside_a_press_keep_it() -> None:
    decoder = PressDecoder(CAL)
    feed(decoder, np.concatenate([held(0, 0.5), held(1.0, 0.1)]))
    assert decoder.update(0.63, CAL.firm_raw, lost_frames=2) is None
    assert feed(decoder, np.concatenate([held(1.0, 0.1), held(0, 0.5)]), t0_s=0.64) == [(1, 1)]


def test_frames_lost_counts_across_the_wrap_and_flags_a_restart() -> None:
    assert frames_lost(None, 5) is None
    assert frames_lost(65_535, 0) == 0 and frames_lost(65_534, 1) == 2
    assert frames_lost(40_000, 0) == 25_535  # a restarted sensor: far more than any gap


# --- stuck sensor ---------------------------------------------------------------------------


def test_a_stuck_sensor_is_flagged_after_the_set_time_gives_no_decision_and_recovers() -> None:
    decoder = PressDecoder(CAL, DecoderSettings(stuck_after_s=2.0))
    feed(decoder, np.concatenate([held(0, 0.5), held(1.0, 1.8)]))
    assert decoder.stuck_since is None  # held 1.8 s: a long press, not yet stuck
    feed(decoder, held(1.0, 0.5), t0_s=2.3)
    assert decoder.stuck_since == pytest.approx(0.5, abs=0.15)  # since the pad went high
    assert feed(decoder, held(0, 0.5), t0_s=2.8) == []  # back at rest: no decision
    assert decoder.stuck_since is None
    quick_light = np.concatenate([held(0.35, 0.25), held(0, 0.5)])
    assert feed(decoder, quick_light, t0_s=3.3) == [(-1, 1)]


def test_stuck_after_must_exceed_a_held_press() -> None:
    with pytest.raises(ValidationError, match=r"long_press_s=0\.5: outside its range \(0, 0\.4\) "
                       r"\(below stuck_after_s=0\.4\)"):  # fmt: skip
        DecoderSettings(stuck_after_s=0.4)


# --- calibration and rest noise ----------------------------------------------------------------


def test_levels_not_separated_by_a_margin_over_the_rest_noise_are_refused() -> None:
    with pytest.raises(ValidationError, match=r"light_raw is only 100 counts .* need 160"):
        Calibration(rest_raw=400, light_raw=500, firm_raw=2000, rest_noise_raw=20)
    with pytest.raises(ValidationError, match=r"firm_raw is only 30 counts .* need 40 \(no rest"):
        Calibration(rest_raw=400, light_raw=500, firm_raw=530)  # an older file: 40 counts


def test_thresholds_that_rest_noise_could_cross_are_refused_with_the_variable() -> None:
    noisy = Calibration(rest_raw=400, light_raw=1000, firm_raw=1400, rest_noise_raw=30)
    with pytest.raises(ConfigurationError, match=r"DAMMRL_PAD_DECODER__OFF_LEVEL=0\.08 .* 80\.0"):
        PressDecoder(noisy)
    assert PressDecoder(noisy, DecoderSettings(off_level=0.15, on_level=0.25))


def test_levels_the_pad_cannot_read_are_refused_not_taken_as_back() -> None:
    """A hand-edited calibration (or another pad's) beyond the 12-bit range, or a firm level
    no press can reach: every firm press was decoded as back (the arm moved the other way)."""
    with pytest.raises(ValueError, match="less than or equal to 4095"):
        Calibration(rest_raw=400, light_raw=2000, firm_raw=9000)
    wide = Calibration(rest_raw=400, light_raw=1200, firm_raw=3000)
    with pytest.raises(ConfigurationError, match=r"read 4170 counts .* beyond the pad's 4095"):
        PressDecoder(wide, DecoderSettings(firm_level=1.45))
    assert PressDecoder(wide, DecoderSettings(firm_level=1.2))  # 3520 counts: within reach


def test_a_calibration_that_noise_could_cross_is_refused_saying_what_to_redo() -> None:
    with pytest.raises(CalibrationError, match="Redo all three steps: keep the pad untouched"):
        calibration_from(Rest(400, 30), light_raw=1000, firm_raw=1400)


def test_the_issues_calibration_is_refused_and_the_narrowest_accepted_gives_no_command() -> None:
    assert phantom_trial(TIGHT, seconds=5).startswith("refused: light_raw is only 0.0001 counts")
    assert phantom_trial(NARROWEST, seconds=20) == "0 decisions in 20 s"


def test_calibration_files_are_refused_on_one_line_and_older_ones_still_load(
    tmp_path: Path,
) -> None:
    path = tmp_path / "calibration.json"
    path.write_text('{"rest_raw": 400, "light_raw": 400.0001, "firm_raw": 400.0002}')
    with pytest.raises(ConfigurationError) as refused:
        load_calibration(path)
    assert "\n" not in str(refused.value) and "need 40" in str(refused.value)
    path.write_text('{"rest_raw": 400, "light_raw": 1200, "firm_raw": 3000}')  # no rest noise
    assert load_calibration(path).rest_noise_raw is None
    path.write_bytes(b"\xff\xfe{}")
    with pytest.raises(ConfigurationError, match="not UTF-8"):
        load_calibration(path)


def test_the_intent_service_refuses_a_calibration_noise_could_cross(tmp_path: Path) -> None:
    path = tmp_path / "calibration.json"
    path.write_text('{"rest_raw": 400, "light_raw": 400.0001, "firm_raw": 400.0002}')
    port = free_port()
    observer = Observer(port)
    service = start_service("intent", port, DAMMRL_INTENT_SOURCE="pad",
                            DAMMRL_PAD_PORT=str(tmp_path / "tty"),
                            DAMMRL_PAD_CALIBRATION_FILE=str(path))  # fmt: skip
    try:
        assert service.wait(60) == Exit.BAD_INPUT
    finally:
        observer.close()


# --- the real intent service over a pty ---------------------------------------------------------


@pytest.mark.slow
def test_glitches_on_the_port_answer_no_request_and_presses_still_do(tmp_path: Path) -> None:
    with port_rig(tmp_path) as rig, SensorEmulator(rig.link, []) as pad:
        rig.wait_samples()
        assert port_glitch_trials(rig, pad, (4095, 0)) == (0, 12)
        assert port_press_trials(rig, pad, per_case=1) == (6, 6)


@pytest.mark.slow
def test_unplugged_during_a_press_and_replugged_at_rest_answers_nothing(tmp_path: Path) -> None:
    with port_rig(tmp_path) as rig:
        assert unplug_trials(rig, trials=1) == (0, 1)
        with SensorEmulator(rig.link, [], seed=7) as pad:  # and it still listens
            rig.wait_samples()
            assert port_press_trials(rig, pad, per_case=1)[0] >= 5


@pytest.mark.slow
def test_a_stuck_sensor_is_reported_in_health_and_recovers_without_a_decision(
    tmp_path: Path,
) -> None:
    stuck_after = {"DAMMRL_PAD_DECODER__STUCK_AFTER_S": "1.5"}
    with port_rig(tmp_path, **stuck_after) as rig, SensorEmulator(rig.link, []) as pad:
        rig.wait_samples()
        rig.open_request()
        pad.hold(1.0)
        pressed = time.monotonic()
        wait_for(lambda: _latest(rig).state == "degraded", 5, "a stuck report")
        detected_s = time.monotonic() - pressed
        assert "sensor stuck pressed (level 1.00) since" in _latest(rig).detail
        pad.hold(0.0)
        wait_for(lambda: _latest(rig).state == "ok", 5, "recovery")
        time.sleep(0.5)
        assert rig.intents() == 0  # neither the stuck press nor its release decided
        pad.press(0.95, 0.2)
        wait_for(lambda: rig.intents() == 1, 5, "a press after recovery")
    assert 1.5 < detected_s < 3.0


@pytest.mark.slow
def test_a_sensor_that_sends_nothing_is_reported(tmp_path: Path) -> None:
    with port_rig(tmp_path) as rig:
        wait_for(lambda: "not connected" in _latest(rig).detail, 5, "no device")
        with SensorEmulator(rig.link, []) as pad:
            pad.silent.set()  # plugged in, never a frame
            wait_for(lambda: "sensor silent" in _latest(rig).detail, 5, "a silent sensor")
            assert _latest(rig).state == "degraded"


def _latest(rig: PortRig) -> Health:
    reports = [h for h in rig.observer.of(Health) if isinstance(h, Health)]
    mine = [h for h in reports if h.service == "intent"]
    return mine[-1] if mine else Health.model_construct(state="none", detail="")
