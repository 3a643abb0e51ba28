"""A press is timed on the pad's own clock: frames a busy host delivers late and in a burst
decode as the person pressed, and only a lost frame breaks a press."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from dammrl.devices.emulators.pad import SensorEmulator
from dammrl_core.intent.pad.protocol import SEQ_MODULO
from dammrl_core.intent.pad.serial import MAX_CLOCK_DRIFT, PadClock
from dammrl_core.intent.pad.source import PadSettings, PadSource
from dammrl_core.intent.source import Ask

PERIOD = 0.01


def test_prompt_frames_are_sampled_when_they_arrive() -> None:
    clock = PadClock(PERIOD)
    times = [clock.sampled_at(seq, 50.0 + seq * PERIOD) for seq in range(100)]
    np.testing.assert_allclose(times, 50.0 + np.arange(100) * PERIOD, atol=1e-9)


def test_a_burst_of_late_frames_keeps_the_spacing_of_their_samples() -> None:
    """One second of frames read in one go after a stall: each is timed when the pad took
    it, not when the host read it."""
    clock = PadClock(PERIOD)
    for seq in range(10):
        clock.sampled_at(seq, 50.0 + seq * PERIOD)
    burst = [clock.sampled_at(seq, 51.2) for seq in range(10, 110)]
    drift = MAX_CLOCK_DRIFT * 1.2  # the most the offset may have grown over the stall
    np.testing.assert_allclose(burst, 50.0 + np.arange(10, 110) * PERIOD, atol=drift)
    np.testing.assert_allclose(np.diff(burst), PERIOD, atol=1e-9)


def test_a_late_first_frame_is_corrected_by_the_first_prompt_one_and_time_never_runs_back() -> None:
    clock = PadClock(PERIOD)
    first = clock.sampled_at(0, 10.5)  # read 0.5 s after it was taken
    later = [clock.sampled_at(seq, 10.0 + seq * PERIOD) for seq in range(60, 80)]
    assert first == 10.5 and later[0] >= first
    np.testing.assert_allclose(later[-1], 10.0 + 79 * PERIOD, atol=1e-9)
    assert np.all(np.diff(later) >= 0)


def test_a_pad_whose_clock_runs_slow_is_followed() -> None:
    """The pad's period 0.05 % longer than it says: an hour later its samples are still
    timed within a millisecond of when they arrive promptly."""
    clock, slow = PadClock(PERIOD), PERIOD * (1 + 5e-4)
    assert MAX_CLOCK_DRIFT > 5e-4
    seqs = np.arange(360_000)
    times = [clock.sampled_at(int(s % SEQ_MODULO), 100.0 + s * slow) for s in seqs]
    assert abs(times[-1] - (100.0 + seqs[-1] * slow)) < 1e-3


def test_lost_frames_advance_the_pads_time_by_their_samples() -> None:
    clock = PadClock(PERIOD)
    clock.sampled_at(SEQ_MODULO - 2, 20.0)
    assert clock.sampled_at(3, 20.05) == pytest.approx(20.05)  # wrapped, 4 lost between


def test_a_held_press_read_late_in_one_burst_is_still_a_held_press(tmp_path: Path) -> None:
    """The port is not read while the person holds a firm press for 1.0 s (a host too busy
    to hand the reader its bytes): the frames come in one burst, and the press decodes
    as held (E_small) and firm (+1), timed from when it began."""
    link = tmp_path / "ttySENSOR"
    with SensorEmulator(link, []) as pad:
        source = PadSource(PadSettings(port=str(link)))
        source.open()
        try:
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:  # rest: the decoder's baseline
                source.poll(time.monotonic())
            asked = time.monotonic()
            source.ask(_ask(), asked)
            pad.press(1.0, 1.0, delay_s=0.2)
            time.sleep(2.0)  # nothing read meanwhile: 2 s of frames wait in the port
            decided = None
            deadline = time.monotonic() + 2.0
            while decided is None and time.monotonic() < deadline:
                decided = source.poll(time.monotonic())
        finally:
            source.close()
    assert decided is not None, "the press read late was decided"
    assert (decided.u_h, decided.human_model) == (1, 2)
    assert 0.1 < decided.decision_s < 0.4  # from the request to the press's onset


def _ask() -> Ask:
    zeros = np.zeros(3)
    return Ask(episode=1, request=1, seed=0, t_s=0.0, ee_pos_m=zeros, goal_m=zeros,
               primary_axis=0, human_model=1)  # fmt: skip
