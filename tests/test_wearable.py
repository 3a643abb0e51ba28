"""The wearable's decoder: features against analytic signals, the classifier against
scikit-learn, contractions into decisions, bad signal into no decision, calibration files,
offline decoding of MCAP and XDF."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dammrl.devices.emulators import movements
from dammrl.devices.emulators.emg_signal import EmgSynth, model_named
from dammrl.devices.wearable import Signal, decode_signal, signal_of_xdf
from dammrl_core.errors import ConfigurationError
from dammrl_core.human import HumanModel
from dammrl_core.intent.emg.calibration import (
    EmgCalibration,
    StreamDescription,
    load_calibration,
    save_calibration,
)
from dammrl_core.intent.emg.classifier import (
    REJECTED,
    decide_windows,
    fit,
    majority,
    offline_metrics,
)
from dammrl_core.intent.emg.decoder import EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.emg.features import window_features
from dammrl_core.intent.emg.training import Cue, refusal, train
from dammrl_core.posterior import HumanModelPosterior
from tests.xdf_writer import write_xdf

RATE = 1000.0
STREAM = StreamDescription(name="dammrl-emg", type="EMG", channel_count=8, nominal_srate_hz=RATE)


def cued_session(noise: str = "medium", blocks: int = 3, seed: int = 1
                 ) -> tuple[np.ndarray, np.ndarray, list[Cue]]:  # fmt: skip
    """A cooperative participant's calibration on the emulated armband, 3 s trials."""
    return movements.cued_session(EmgSynth(model_named(noise), seed), RATE, blocks, seed=seed)


@pytest.fixture(scope="module")
def calibration() -> EmgCalibration:
    samples, times, cues = cued_session()
    return train(samples, times, cues, STREAM, participant="P001")


def stream_through(decoder: WindowDecoder, synth: EmgSynth, seconds: float, t0: float = 0.0,
                   chunk: int = 20) -> list:  # type: ignore[type-arg]  # fmt: skip
    found = []
    for _ in range(round(seconds * RATE / chunk)):
        times = t0 + synth.t_s + np.arange(chunk) / RATE
        found += decoder.push(synth.generate(chunk), times)
    return found


# ---- features ---------------------------------------------------------------------------------
def test_features_of_a_sine_match_their_analytic_values() -> None:
    amplitude, frequency = 2.0, 10.0
    t = np.arange(1000) / RATE  # one second: ten periods
    features = window_features((amplitude * np.sin(2 * np.pi * frequency * t))[:, None], RATE)
    log_mav, log_wl, zc_hz, ssc_hz = features
    np.testing.assert_allclose(np.exp(log_mav), 2 * amplitude / np.pi, rtol=1e-3)
    np.testing.assert_allclose(np.exp(log_wl), 4 * amplitude * frequency, rtol=2e-3)  # n-1 steps
    assert zc_hz == pytest.approx(2 * frequency, abs=1.0)  # two crossings a period
    assert ssc_hz == pytest.approx(2 * frequency, abs=1.0)  # a peak and a trough


def test_noise_inside_the_deadband_makes_no_crossings() -> None:
    t = np.arange(200) / RATE
    slow = np.sin(2 * np.pi * 5 * t) + 1e-4 * np.random.default_rng(0).normal(size=200)
    zc_hz = window_features(slow[:, None], RATE)[2]
    assert zc_hz <= 2 / 0.2  # the sine's own crossings, not the noise's


# ---- classifier -------------------------------------------------------------------------------
def test_the_classifier_kept_as_numbers_gives_scikit_learns_probabilities() -> None:
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    rng = np.random.default_rng(3)
    labels = np.repeat([-1, 0, 1], 60)
    features = rng.normal(size=(180, 6)) + labels[:, None] * np.linspace(0.5, 2, 6)
    model = fit(features, labels)
    mean, scale = features.mean(axis=0), features.std(axis=0)
    lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto").fit(
        (features - mean) / scale, labels
    )
    np.testing.assert_allclose(model.probabilities(features),
                               lda.predict_proba((features - mean) / scale), atol=1e-9)  # fmt: skip
    again = type(model).model_validate_json(model.model_dump_json())
    np.testing.assert_array_equal(again.probabilities(features), model.probabilities(features))


def test_rejection_and_the_majority_vote() -> None:
    p = np.array([[0.9, 0.05, 0.05], [0.4, 0.3, 0.3], [0.1, 0.1, 0.8], [0.1, 0.1, 0.8]])
    raw = decide_windows(p, (-1, 0, 1), reject_below=0.6, vote=1)
    assert list(raw) == [-1, REJECTED, 1, 1]
    voted = decide_windows(p, (-1, 0, 1), reject_below=0.6, vote=3)
    assert list(voted) == [-1, -1, 1, 1]  # a tie goes to the newest; rejected windows skip
    assert majority([1, -1, -1, 1]) == 1


def test_offline_metrics_follow_libemgs_definitions() -> None:
    truth = np.array([0, 0, 1, 1, -1, -1, 1, 1])
    decided = np.array([0, 1, 1, REJECTED, -1, 1, 1, 1])
    m = offline_metrics(truth, decided)
    assert m.accuracy == pytest.approx(5 / 7)  # over the 7 accepted windows
    assert m.active_error_rate == pytest.approx(1 / 5)  # -1 taken for +1, of 5 active
    assert m.rejection_rate == pytest.approx(1 / 8)
    assert m.instability == pytest.approx(4 / 7)  # 0>1, 1>rejected, >-1, -1>1
    assert m.confusion == [[1, 0, 1, 0], [0, 1, 1, 0], [0, 0, 3, 1]]


# ---- calibration ------------------------------------------------------------------------------
def test_a_cooperative_participant_calibrates_well(calibration: EmgCalibration) -> None:
    cv = calibration.cross_validation
    assert cv.accuracy > 0.95 and cv.active_error_rate < 0.05, cv
    assert len(cv.per_block_accuracy) == 3
    assert refusal(cv) is None
    following = calibration.cue_following
    assert following is not None and following.rest < 0.05 and following.commands > 0.9


ALIKE = model_named("high", crosstalk=0.9)
"""Electrodes that pick up both muscle groups nearly alike: -1 and +1 hardly separate."""


def _sham_session(moves: bool, seed: int = 1) -> tuple[np.ndarray, np.ndarray, list[Cue]]:
    """A calibration's cues, and a person who ignores them: contracting at random
    (``moves``), or never."""
    wearer, rng = EmgSynth(model_named("medium"), seed), np.random.default_rng(seed)
    chunks, cues, t = [], [], 0.0
    for block in range(3):
        for label in rng.permutation([-1, 0, 1]):
            if moves and (action := int(rng.choice([-1, 0, 1]))):
                wearer.contract(action, 2.7, 0.3)
            chunks += [wearer.generate(3000), wearer.generate(1500)]
            cues.append(Cue(int(label), t, t + 3.0, block))
            t += 4.5
    samples = np.concatenate(chunks)
    return samples, np.arange(len(samples)) / RATE, cues


@pytest.mark.parametrize(("moves", "words"), [
    (True, "the person did not follow the cues"),
    (False, "no contraction seen during the -1/+1 cues"),
])  # fmt: skip
def test_a_person_who_ignores_the_cues_is_refused_saying_so(moves: bool, words: str) -> None:
    """Refused before as "commands are confused with rest (contract more firmly...)",
    beside an accuracy of 0.00 and an active error rate of 0.00 (over no window)."""
    calibration = train(*_sham_session(moves), STREAM)
    reason = str(refusal(calibration.cross_validation, following=calibration.cue_following))
    assert words in reason, reason
    assert "every window rejected" in reason and "0.00" not in reason


def test_classes_that_do_not_separate_are_refused_with_the_reason() -> None:
    samples, times, cues = movements.cued_session(EmgSynth(ALIKE, 1), RATE, 3, seed=1)
    reason = refusal(train(samples, times, cues, STREAM).cross_validation)
    assert reason is not None and "confused" in reason and "accuracy" in reason


def test_a_calibration_file_round_trips_and_bad_files_are_one_line(
    calibration: EmgCalibration, tmp_path: Path
) -> None:
    path = save_calibration(calibration, tmp_path / "p.json")
    assert load_calibration(path) == calibration
    data = json.loads(path.read_text())
    for change, words in (({"version": 7}, "version 7"),
                          ({"rest_rms": [1.0]}, "rest levels"),
                          ({"window_s": 0.01}, "window_s")):  # fmt: skip
        (tmp_path / "bad.json").write_text(json.dumps(data | change))
        with pytest.raises(ConfigurationError, match=words):
            load_calibration(tmp_path / "bad.json")
    (tmp_path / "junk.json").write_text("{not json")
    with pytest.raises(ConfigurationError, match="cannot read"):
        load_calibration(tmp_path / "junk.json")


def test_a_calibration_holds_numbers_only_never_code(calibration: EmgCalibration) -> None:
    def leaves(value: object) -> list[object]:
        if isinstance(value, dict):
            return [x for v in value.values() for x in leaves(v)]
        if isinstance(value, list):
            return [x for v in value for x in leaves(v)]
        return [value]

    kinds = {type(v) for v in leaves(json.loads(calibration.model_dump_json()))}
    assert kinds <= {int, float, str, bool, type(None)}


# ---- decisions --------------------------------------------------------------------------------
@pytest.mark.parametrize(("u_h", "held"), [(1, False), (1, True), (-1, False), (-1, True)])
def test_a_contraction_is_one_decision_its_length_choosing_the_radius(
    calibration: EmgCalibration, u_h: int, held: bool
) -> None:
    synth = EmgSynth(model_named("medium"), seed=11)
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    stream_through(decoder, synth, 1.0)
    synth.contract(u_h, 0.9 if held else 0.25, delay_s=0.2)
    found = stream_through(decoder, synth, 1.5)
    assert len(found) == 1, found
    assert (found[0].u_h, found[0].human_model, found[0].accepted) == (u_h, 2 if held else 1, True)
    assert found[0].onset_s == pytest.approx(1.2, abs=0.1)
    assert found[0].confidence > 0.9 and len(found[0].features) == 32


def test_rest_gives_no_decision_for_a_minute(calibration: EmgCalibration) -> None:
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    assert stream_through(decoder, EmgSynth(model_named("medium"), seed=5), 60.0) == []


def test_a_twitch_and_a_doubtful_contraction_are_not_acted_on(
    calibration: EmgCalibration,
) -> None:
    synth = EmgSynth(model_named("medium"), seed=12)
    decoder = WindowDecoder(calibration, EmgDecoderSettings(min_contraction_s=0.4))
    synth.contract(1, 0.25, delay_s=0.5)
    twitch = stream_through(decoder, synth, 1.5)
    assert len(twitch) == 1 and not twitch[0].accepted and "twitch" in twitch[0].reason
    # on a noisy arm the classifier's honest probabilities are lower (its temperature)
    samples, times, cues = movements.cued_session(EmgSynth(ALIKE, 1), RATE, 3, seed=1)
    noisy = train(samples, times, cues, STREAM)
    decoder = WindowDecoder(noisy, EmgDecoderSettings(min_confidence=0.95))
    synth = EmgSynth(ALIKE, seed=4)
    stream_through(decoder, synth, 1.0)  # at rest: the rest level
    synth.contract(1, 0.8, delay_s=0.2)
    doubtful = stream_through(decoder, synth, 1.5)
    assert len(doubtful) == 1, doubtful
    assert doubtful[0].confidence < 0.95 and not doubtful[0].accepted
    assert "confidence" in doubtful[0].reason


@pytest.mark.parametrize("fault", ["nan", "flat", "clip", "spike", "clock jump",
                                   "wrong channels"])  # fmt: skip
def test_bad_signal_drops_the_contraction_and_says_why(
    calibration: EmgCalibration, fault: str
) -> None:
    synth = EmgSynth(model_named("medium"), seed=13)
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    stream_through(decoder, synth, 0.5)
    synth.contract(1, 0.9, delay_s=0.1)
    found = stream_through(decoder, synth, 0.4)  # the contraction under way
    words = {"nan": "non-finite", "flat": "flat", "clip": "clipping", "spike": "spiked",
             "clock jump": "jumped", "wrong channels": "channels"}[fault]  # fmt: skip
    if fault in ("nan", "spike"):
        bad = synth.generate(20)
        bad[3, 2] = np.nan if fault == "nan" else 1e5
        found += decoder.push(bad, synth.t_s + np.arange(20) / RATE)
        for _ in range(10):  # a spike is seen by the first window that holds it
            if decoder.problem() is not None:
                break
            found += stream_through(decoder, synth, 0.02)
    elif fault in ("flat", "clip"):
        synth.lift(4, "flat" if fault == "flat" else "clip")
        found += stream_through(decoder, synth, 0.3)
        synth.put_back(4)
    elif fault == "clock jump":
        found += stream_through(decoder, synth, 0.1, t0=5.0)
    else:
        found += decoder.push(np.zeros((20, 6)), synth.t_s + np.arange(20) / RATE)
    problem = decoder.problem()
    assert problem is not None and words in problem, problem
    found += stream_through(decoder, synth, 1.5, t0=5.0 if fault == "clock jump" else 0.0)
    assert [c for c in found if c.accepted] == [], found
    assert decoder.problem() is None  # clean signal again


@pytest.mark.parametrize("seed", range(8))
def test_one_spike_at_rest_is_no_decision(calibration: EmgCalibration, seed: int) -> None:
    """One sample of 2e4 uV on one channel (rest is ~33 uV RMS): the filters' ringing after
    it was decided as a contraction, accepted (a phantom movement; 1 in 8 at this size, 6
    in 8 at 1e6)."""
    synth = EmgSynth(model_named("medium"), seed=seed)
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    found = stream_through(decoder, synth, 2.0)
    for size in (2e4, 1e6, 3e38):
        bad = synth.generate(20)
        bad[5, seed % bad.shape[1]] = size
        found += decoder.push(bad, synth.t_s + np.arange(20) / RATE)
        found += stream_through(decoder, synth, 2.0)
    assert [c for c in found if c.accepted] == []
    synth.contract(1, 0.25, delay_s=0.2)  # and it decides again, at once
    assert [c.u_h for c in stream_through(decoder, synth, 1.0) if c.accepted] == [1]


def test_a_busy_senders_jittered_stamps_still_decide_and_a_step_back_is_a_jump(
    calibration: EmgCalibration,
) -> None:
    """A sender stamps each chunk when it pushes it, back-dating its samples at the nominal
    rate (LSL's push_chunk): pushed late, a chunk's first stamps fall before the last
    chunk's end. That jitter (here up to 30 ms) is no clock jump; a step back of 1 s is."""
    synth = EmgSynth(model_named("medium"), seed=15)
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    rng = np.random.default_rng(0)
    found = []
    synth.contract(1, 0.9, delay_s=0.5)
    for _ in range(100):  # 2 s in chunks of 20 samples
        pushed_late_s = rng.uniform(0.0, 0.03)
        times = synth.t_s + pushed_late_s + np.arange(-19, 1) / RATE + 19 / RATE
        found += decoder.push(synth.generate(20), times)
    assert decoder.problem() is None
    assert [(c.u_h, c.accepted) for c in found] == [(1, True)], found
    decoder.push(synth.generate(20), synth.t_s - 1.0 + np.arange(20) / RATE)
    assert "jumped by -1.0" in str(decoder.problem())


def test_a_contraction_held_too_long_is_a_stuck_signal(calibration: EmgCalibration) -> None:
    synth = EmgSynth(model_named("medium"), seed=14)
    decoder = WindowDecoder(calibration, EmgDecoderSettings(max_contraction_s=1.0))
    stream_through(decoder, synth, 1.0)  # at rest: the rest level
    synth.contract(-1, 2.0, delay_s=0.1)
    found = stream_through(decoder, synth, 1.8)
    assert decoder.problem() is not None and "held" in str(decoder.problem())
    found += stream_through(decoder, synth, 1.0)
    assert found == []


# ---- the posterior ------------------------------------------------------------------------------
def test_a_command_of_no_confidence_tells_the_posterior_nothing() -> None:
    posterior = HumanModelPosterior(HumanModel(), use_decision_time=False)
    before = posterior.probabilities.copy()
    np.testing.assert_allclose(posterior.update(False, None, confidence=0.0), before)
    doubtful = HumanModelPosterior(HumanModel(), use_decision_time=False)
    sure = HumanModelPosterior(HumanModel(), use_decision_time=False)
    # a wrong command favours E_big (80 % accurate) over E_small (90 %): less so if doubtful
    assert sure.update(False)[0] > doubtful.update(False, confidence=0.5)[0] > 0.5
    human = HumanModel()  # the mixture, by hand: 0.5 * 0.2 + 0.5 * 0.5 vs 0.5 * 0.1 + 0.25
    np.testing.assert_allclose(doubtful.probabilities[0], 0.35 / (0.35 + 0.30))
    assert human.accuracy(1) == 0.8 and human.accuracy(2) == 0.9


# ---- offline decoding ---------------------------------------------------------------------------
def test_an_xdf_file_from_other_lab_software_decodes_as_the_live_stream(
    calibration: EmgCalibration, tmp_path: Path
) -> None:
    synth = EmgSynth(model_named("medium"), seed=21)
    synth.contract(1, 0.3, 0.5)
    synth.contract(-1, 0.9, 2.0)
    samples = synth.generate(4000)
    times = 5000.0 + np.arange(4000) / RATE
    markers = np.zeros((3, 1))
    path = write_xdf(tmp_path / "session.xdf", [("dammrl-emg", "EMG", RATE, samples, times),
                                                ("other", "Misc", 10.0, markers,
                                                 times[:3])])  # fmt: skip
    signal = signal_of_xdf(path, "dammrl-emg")
    assert signal.samples.shape == (4000, 8)
    decided = [(c.u_h, c.human_model) for c in decode_signal(signal, calibration)]
    live = decode_signal(Signal("dammrl-emg", RATE, samples, times), calibration)
    assert decided == [(c.u_h, c.human_model) for c in live] == [(1, 1), (-1, 2)]
    with pytest.raises(ConfigurationError, match="choose one with --stream"):
        signal_of_xdf(path)
    (tmp_path / "junk.xdf").write_bytes(b"XDF:garbage")
    with pytest.raises(ConfigurationError, match=r"junk\.xdf: no numeric stream"):
        signal_of_xdf(tmp_path / "junk.xdf")


def test_a_wrist_imu_decides_by_posture(tmp_path: Path) -> None:
    """The IMU feature set: a wrist flexed (+1) or extended (-1) and held, on the emulated
    6-axis IMU at 100 Hz; the sign of the posture decides, its length the radius."""
    from dammrl.devices.emulators.imu_signal import IMU_NOISE_LEVELS, ImuSynth

    model = IMU_NOISE_LEVELS["medium"]
    samples, times, cues = movements.cued_session(ImuSynth(model, seed=1), 100.0, seed=1)
    stream = StreamDescription(name="wrist", type="IMU", channel_count=6, nominal_srate_hz=100)
    imu = train(samples, times, cues, stream, kind="imu")
    assert imu.features == "imu" and refusal(imu.cross_validation) is None
    assert load_calibration(save_calibration(imu, tmp_path / "imu.json")) == imu
    decoder, wrist = WindowDecoder(imu, EmgDecoderSettings()), ImuSynth(model, seed=9)
    for u_h, held in ((1, True), (-1, False), (-1, True), (1, False)):
        wrist.contract(u_h, 0.9 if held else 0.25, delay_s=0.5)
        found = []
        for _ in range(100):  # 2 s in 20 ms chunks
            found += decoder.push(wrist.generate(2), wrist.t_s + np.arange(2) / 100)
        assert [(c.u_h, c.human_model, c.accepted) for c in found] == [
            (u_h, 2 if held else 1, True)
        ]


def test_raw_samples_go_out_paced_and_whole() -> None:
    """One message every 20 ms at most (the key's rate limit drops one that follows
    another too soon), as many samples as fit in the key's size, none lost, none
    reordered."""
    from dammrl_core.intent.source import Chunk
    from schemas.messages import samples_per_chunk
    from services.intent.node import CHUNK_PERIOD_S, RawBacklog

    backlog, rng = RawBacklog(), np.random.default_rng(0)
    times = np.arange(1000) / RATE
    for start in range(0, 1000, 37):  # an amplifier's chunks of any size
        part = slice(start, start + 37)
        backlog.add(Chunk("emg", RATE, rng.normal(size=(len(times[part]), 8)), times[part]))
    sent, tick = [], 0
    while backlog.waiting:
        now = tick * CHUNK_PERIOD_S * 1.001
        if (chunk := backlog.take(now)) is not None:
            sent.append(chunk)
        assert backlog.take(now + CHUNK_PERIOD_S / 2) is None  # not twice in a period
        tick += 1
    assert max(len(c.times_s) for c in sent) == samples_per_chunk(8) == 256 and len(sent) == 4
    np.testing.assert_array_equal(np.concatenate([c.times_s for c in sent]), times)
