"""Signal conditioning before the wearable's features: filters against their analytic
responses, one path for calibration, live decoding and recording decode, and the same
decisions under an amplifier's DC offset and gain, on the project's emulator and on a
motor-unit generator written apart from it."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from dammrl.devices.emulators.emg_signal import EmgSynth, model_named
from dammrl.devices.wearable import Signal, decode_signal
from dammrl_core.errors import ConfigurationError
from dammrl_core.intent.emg.calibration import (
    EmgCalibration,
    StreamDescription,
    load_calibration,
    save_calibration,
)
from dammrl_core.intent.emg.conditioning import (
    Conditioning,
    Filters,
    RestLevel,
    baseline_step,
    condition,
)
from dammrl_core.intent.emg.decoder import EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.emg.training import train
from tests import muap_emg
from tests.test_wearable import RATE, STREAM, cued_session, stream_through

MUAP_RATE = 2000.0
MUAP_STREAM = StreamDescription(name="forearm", type="EMG", channel_count=8,
                                nominal_srate_hz=MUAP_RATE)  # fmt: skip
Transform = Callable[[np.ndarray], np.ndarray]
AMPLIFIERS: dict[str, Transform] = {
    "as recorded": lambda x: x,
    "DC +30 uV": lambda x: x + 30.0,
    "DC +300 uV": lambda x: x + 300.0,
    "DC -1 mV to +1 mV across channels": lambda x: x + np.linspace(-1000.0, 1000.0, 8),
    "gain x0.3": lambda x: 0.3 * x,
    "gain x3": lambda x: 3.0 * x,
}
"""What an amplifier does to the same muscles' signal (samples in µV)."""


# ---- the filters ------------------------------------------------------------------------------
def test_the_high_pass_removes_an_offset_and_keeps_emgs_band() -> None:
    t = np.arange(4000) / RATE
    x = (1000.0 + 50.0 * np.sin(2 * np.pi * 100 * t))[:, None]  # 1 mV DC, 100 Hz EMG-like
    y = condition(x, RATE, Conditioning(high_pass_hz=20, notch_hz=0, normalise_level=False))
    assert abs(y[:5, 0]).max() < 60  # started in its steady state: no 1 mV step at first
    np.testing.assert_allclose(y[2000:, 0].mean(), 0.0, atol=0.5)
    np.testing.assert_allclose(y[2000:, 0].std(), 50 / np.sqrt(2), rtol=0.02)  # passband


@pytest.mark.parametrize("mains", [50, 60])
def test_the_notch_takes_out_the_mains_and_little_beside_it(mains: int) -> None:
    t = np.arange(8000) / RATE
    conditioning = Conditioning(high_pass_hz=0, notch_hz=mains, normalise_level=False)
    gain = {}
    for hz in (mains, mains * 1.5, 150.0):
        y = condition(np.sin(2 * np.pi * hz * t)[:, None], RATE, conditioning)
        gain[hz] = y[4000:, 0].std() / np.sin(2 * np.pi * hz * t[4000:]).std()
    assert gain[mains] < 0.03  # at least 30 dB down
    assert gain[mains * 1.5] > 0.97 and gain[150.0] > 0.97


def test_filtering_in_chunks_gives_the_samples_of_filtering_at_once() -> None:
    x = np.random.default_rng(0).normal(size=(3001, 4)) + np.arange(4) * 500.0
    conditioning = Conditioning.emg(50)
    filters = Filters(conditioning, RATE)
    chunked = np.concatenate([filters(x[k : k + 37]) for k in range(0, len(x), 37)])
    np.testing.assert_allclose(chunked, condition(x, RATE, conditioning), atol=1e-9)


def test_a_filter_the_streams_rate_cannot_carry_is_refused_in_one_line() -> None:
    assert "notch_hz 60 Hz" in str(Conditioning.emg(60).problem(100.0))
    with pytest.raises(ConfigurationError, match="high_pass_hz 20 Hz"):
        samples, times, cues = cued_session()
        slow = STREAM.model_copy(update={"nominal_srate_hz": 40.0})
        train(samples[::25], times[::25], cues, slow)


def test_the_rest_level_is_a_low_quantile_once_full_and_the_minimum_at_first() -> None:
    level = RestLevel(Conditioning(high_pass_hz=0, notch_hz=0, normalise_level=True,
                                   level_window_s=1.0, level_quantile=0.2), hop_s=0.05)  # fmt: skip
    assert level.add(np.array([3.0]))[0] == 3.0
    for v in (5.0, 5.0, 5.0):  # a contraction right after a moment of rest
        assert level.add(np.array([v]))[0] == 3.0
    for v in range(20):  # a full history: its 4th lowest of 20
        out = level.add(np.array([float(v)]))
    assert level.full() and out[0] == 3.0


def test_a_baseline_step_is_found_and_emg_or_a_slow_artefact_is_not() -> None:
    rng = np.random.default_rng(1)
    emg = rng.normal(0, 200.0, (200, 2))  # a strong contraction, 200 ms at 1 kHz
    assert baseline_step(emg, RATE) is None
    bump = emg + 300 * np.sin(np.pi * np.arange(200) / 200)[:, None]  # a motion artefact
    assert baseline_step(bump, RATE) is None
    rest = rng.normal(0, 20.0, (200, 2))
    rest[120:, 1] += 1000.0  # an electrode moved: the baseline steps by 1 mV
    channel, size = baseline_step(rest, RATE) or (-1, 0.0)
    assert channel == 1 and size == pytest.approx(1000.0, abs=60)


# ---- calibrations -------------------------------------------------------------------------------
def test_a_version_1_calibration_decodes_as_it_was_trained(tmp_path: Path) -> None:
    """Made before conditioning existed: its classifier saw raw samples, absolute levels."""
    samples, times, cues = cued_session()
    old = train(samples, times, cues, STREAM, conditioning=Conditioning.none())
    data = json.loads(old.model_dump_json())
    data["version"] = 1
    for new in ("conditioning", "rest_level"):
        del data[new]
    for new in ("channel_labels", "units"):
        del data["stream"][new]
    (tmp_path / "v1.json").write_text(json.dumps(data))
    loaded = load_calibration(tmp_path / "v1.json")
    assert loaded.conditioning == Conditioning.none() and loaded.version == 1
    synth = EmgSynth(model_named("medium"), seed=11)
    synth.contract(1, 0.9, 1.0)
    found = stream_through(WindowDecoder(loaded, EmgDecoderSettings()), synth, 2.5)
    assert [(c.u_h, c.human_model) for c in found] == [(1, 2)]
    assert load_calibration(save_calibration(loaded, tmp_path / "again.json")) == loaded


# ---- the same decisions whatever the amplifier ----------------------------------------------
def _scripted_patient(synth: EmgSynth, count: int, seed: int
                      ) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:  # fmt: skip
    """The emulator's forearm making ``count`` contractions 2.5 s apart after 2 s of rest."""
    rng = np.random.default_rng(seed)
    chunks, plan = [synth.generate(2000)], []
    for _ in range(count):
        u_h, held = int(rng.choice([-1, 1])), bool(rng.integers(2))
        synth.contract(u_h, 0.9 if held else 0.3, 0.5)
        chunks.append(synth.generate(2500))
        plan.append((u_h, 2 if held else 1))
    samples = np.concatenate(chunks)
    return samples, np.arange(len(samples)) / RATE, plan


@pytest.fixture(scope="module")
def emulator() -> tuple[EmgCalibration, Signal, list[tuple[int, int]], Signal]:
    samples, times, cues = cued_session()
    calibration = train(samples, times, cues, STREAM)
    x, t, plan = _scripted_patient(EmgSynth(model_named("medium"), seed=5), 12, seed=5)
    rest = EmgSynth(model_named("medium"), seed=6).generate(30_000)
    return (calibration, Signal("emg", RATE, x, t), plan,
            Signal("emg", RATE, rest, np.arange(len(rest)) / RATE))  # fmt: skip


@pytest.fixture(scope="module")
def motor_units() -> tuple[EmgCalibration, Signal, list[tuple[int, int]], Signal]:
    forearm = muap_emg.MuapForearm(seed=1)
    samples, times, cues = muap_emg.cued_session(forearm)
    calibration = train(samples, times, cues, MUAP_STREAM,
                        conditioning=Conditioning.emg(60))  # fmt: skip
    x, t, plan = muap_emg.decisions_session(muap_emg.MuapForearm(seed=1), 12, seed=3)
    rest = muap_emg.MuapForearm(seed=1).samples(30.0, [])
    return (calibration, Signal("forearm", MUAP_RATE, x, t), plan,
            Signal("forearm", MUAP_RATE, rest, np.arange(len(rest)) / MUAP_RATE))  # fmt: skip


def _acted(
    calibration: EmgCalibration, signal: Signal, amplifier: Transform
) -> list[tuple[int, int]]:
    changed = Signal(signal.name, signal.rate_hz, amplifier(signal.samples), signal.times_s)
    return [(c.u_h, c.human_model) for c in decode_signal(changed, calibration) if c.accepted]


@pytest.mark.parametrize("generator", ["emulator", "motor_units"])
@pytest.mark.parametrize("amplifier", list(AMPLIFIERS))
def test_an_offset_or_a_gain_changes_no_decision_and_makes_no_phantom(
    generator: str, amplifier: str, request: pytest.FixtureRequest
) -> None:
    """Independently measured on the previous decoder (features of uncentred samples): a
    30 uV offset silenced it (0 of 6 decisions), x3 as well."""
    calibration, session, plan, rest = request.getfixturevalue(generator)
    assert _acted(calibration, session, AMPLIFIERS[amplifier]) == plan
    assert _acted(calibration, rest, AMPLIFIERS[amplifier]) == []  # 30 s at rest


def test_a_gain_drifting_x1_to_x3_in_a_session_changes_no_decision(
    motor_units: tuple[EmgCalibration, Signal, list[tuple[int, int]], Signal],
) -> None:
    calibration, session, plan, _ = motor_units
    drift = np.exp(np.linspace(0.0, np.log(3.0), len(session.times_s)))[:, None]
    assert _acted(calibration, session, lambda x: x * drift) == plan


def test_a_one_millivolt_step_of_the_baseline_at_rest_is_no_decision(
    motor_units: tuple[EmgCalibration, Signal, list[tuple[int, int]], Signal],
) -> None:
    """The high-pass rings after a step as loud as a contraction: 10 of 11 steps were
    phantom decisions before steps were taken for bad signal."""
    calibration, _, _, rest = motor_units
    every_5_s = ((rest.times_s // 5) % 2)[:, None]
    offsets = np.random.default_rng(0).uniform(-1000.0, 1000.0, 8)
    assert _acted(calibration, rest, lambda x: x + every_5_s * offsets) == []
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    stepped = rest.samples[:4000] + np.where(np.arange(4000) >= 3850, 1000.0, 0.0)[:, None]
    decoder.push(stepped, rest.times_s[:4000])
    assert re.search(r"baseline stepped by \+(9[5-9]\d|10[0-4]\d)\b", str(decoder.problem()))


def test_rebaselining_measures_the_rest_level_afresh_and_decides_nothing_meanwhile(
    emulator: tuple[EmgCalibration, Signal, list[tuple[int, int]], Signal],
) -> None:
    calibration = emulator[0]
    synth = EmgSynth(model_named("medium"), seed=21)
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    stream_through(decoder, synth, 2.0)
    decoder.rebaseline(2.0)
    assert "measuring the rest level: 2.0 s left" in str(decoder.problem())
    synth.contract(1, 0.9, 0.5)  # during the measurement: no decision
    assert stream_through(decoder, synth, 1.8) == []
    synth.contract(-1, 0.3, 0.5)
    found = stream_through(decoder, synth, 2.0)
    assert decoder.problem() is None
    assert [(c.u_h, c.human_model, c.accepted) for c in found] == [(-1, 1, True)]
