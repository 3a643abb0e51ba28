"""The wearable intent path, in one run on this machine (figures, not pass/fail):

(a) latency from the deciding sample (its LSL timestamp: the emulated armband stamps each
    sample as acquired at the rate, the newest when its chunk is sent) to the Intent a bus
    subscriber receives, through the real intent service (its own process, the LSL
    source); beside it, pylsl alone: every sample's timestamp to its arrival at an inlet
    polled every millisecond in this process (the same chunks; note that liblsl's
    ``pull_chunk`` with a timeout waits for a full buffer, which alone adds tens of ms);
(b) offline, at the emulator's three noise levels: leave-one-block-out accuracy, active
    error rate, rejection rate of a 4-block calibration, and the same classifier on a
    fresh session it never saw (another seed);
(c) online, in the decoder the service runs (fed 20 ms chunks, as live): phantom
    decisions per minute at rest (10 minutes per level), and the decision error rate per
    radius of a simulated patient intending 80 % (E_big) and 90 % (E_small) correct
    commands (the paper's figures), with the radius decoded from the contraction's length;
(d) episodes: `dammrl up --mode semi-virtual --intent lsl` with the simulated patient on
    the emulated armband (medium noise): success, time, decisions, error rate.

    PYTHONPATH=. python benchmarks/bench_wearable.py [--trials 30] [--episodes 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.emulators.emg import HELD_S, QUICK_S, EmgStream
from dammrl.emulators.emg_signal import NOISE_LEVELS, EmgSynth, model_named
from dammrl.emulators.movements import cued_session
from dammrl_core.human import HumanModel
from dammrl_core.intent.emg.calibration import EmgCalibration, StreamDescription, save_calibration
from dammrl_core.intent.emg.classifier import decide_windows, offline_metrics
from dammrl_core.intent.emg.decoder import EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.emg.training import Cue, labelled_windows, train
from schemas import DecisionRequest, Intent, IntentEvidence, decode, type_of
from services.common.bus import Bus
from services.common.config import BusSettings
from tests.busutil import free_port

NS = "dammrl"
RATE = 1000.0
STREAM = StreamDescription(name="bench", channel_count=8, nominal_srate_hz=RATE)


def percentiles(samples_s: list[float]) -> str:
    ms = np.asarray(samples_s) * 1e3
    p50, p99 = np.percentile(ms, [50, 99])
    return f"p50 {p50:6.2f} ms  p99 {p99:6.2f} ms  (n={len(ms)})"


# ---- offline ------------------------------------------------------------------------------
def cued(level: str, seed: int) -> tuple[np.ndarray, np.ndarray, list[Cue]]:
    return cued_session(EmgSynth(NOISE_LEVELS[level], seed), RATE, blocks=4, seed=seed)


def held_out(calibration: EmgCalibration, level: str, seed: int) -> dict[str, float]:
    samples, times, cues = cued(level, seed)
    window, hop = calibration.window_s, calibration.hop_s
    features, labels, _, trials = labelled_windows(samples, times, cues, RATE, window, hop)
    settings = EmgDecoderSettings()
    p = calibration.classifier.probabilities(features)
    decided = np.concatenate([decide_windows(p[trials == k], calibration.classifier.classes,
                                             settings.reject_below, settings.vote_windows)
                              for k in np.unique(trials)])  # fmt: skip
    m = offline_metrics(labels[np.argsort(trials, kind="stable")], decided)
    return {"accuracy": m.accuracy, "aer": m.active_error_rate, "rejection": m.rejection_rate}


# ---- online, in the decoder ---------------------------------------------------------------
def phantoms_per_minute(calibration: EmgCalibration, level: str, minutes: float) -> float:
    decoder = WindowDecoder(calibration, EmgDecoderSettings())
    synth = EmgSynth(NOISE_LEVELS[level], seed=99)
    found = 0
    for _ in range(round(minutes * 60 * RATE / 20)):
        times = synth.t_s + np.arange(20) / RATE
        found += sum(c.accepted for c in decoder.push(synth.generate(20), times))
    return found / minutes


def error_per_radius(calibration: EmgCalibration, level: str, decisions: int) -> dict[int, Any]:
    """A patient intending the paper's accuracy per radius: the executed error rate (the
    decoded command away from the goal), the patient's own share of it, the decoder's
    flips of the intended command, contractions missed, radii decoded wrongly."""
    human, rng = HumanModel(), np.random.default_rng(7)
    out = {}
    for radius in (1, 2):
        decoder = WindowDecoder(calibration, EmgDecoderSettings())
        synth = EmgSynth(NOISE_LEVELS[level], seed=40 + radius)
        wrong = intended_wrong = flipped = missed = radius_wrong = 0
        for _ in range(decisions):
            intended = 1 if rng.random() < human.accuracy(radius) else -1  # +1: toward the goal
            synth.contract(intended, HELD_S if radius == 2 else QUICK_S, 0.3)
            found = []
            for _ in range(round(1.6 * RATE / 20)):
                times = synth.t_s + np.arange(20) / RATE
                found += [c for c in decoder.push(synth.generate(20), times) if c.accepted]
            if not found:
                missed += 1
                continue
            wrong += found[0].u_h != 1
            intended_wrong += intended != 1
            flipped += found[0].u_h != intended
            radius_wrong += found[0].human_model != radius
        made = max(1, decisions - missed)
        out[radius] = {"error": wrong / made, "intended": intended_wrong / made,
                       "flipped": flipped, "missed": missed,
                       "radius_wrong": radius_wrong}  # fmt: skip
    return out


# ---- latency through the service ------------------------------------------------------------
def pylsl_alone(seconds: float) -> list[float]:
    import pylsl

    name = f"bench-{uuid.uuid4().hex[:6]}"
    latencies: list[float] = []
    with EmgStream(name, EmgSynth(model_named("medium"), 1)):
        inlet = pylsl.StreamInlet(pylsl.resolve_byprop("name", name, 1, 5)[0])
        inlet.open_stream(5)
        inlet.time_correction(5)
        inlet.pull_chunk(timeout=1.0, max_samples=100_000)  # what came before we listened
        end = time.monotonic() + seconds
        while time.monotonic() < end:  # what is there, every millisecond: pylsl at its best
            _, stamps = inlet.pull_chunk(timeout=0.0, max_samples=4096)
            now = pylsl.local_clock()
            latencies += [now - s for s in stamps]
            time.sleep(0.001)
    return latencies


def through_the_service(calibration: Path, trials: int) -> tuple[list[float], int]:
    """(deciding sample -> Intent received, Intents received)."""
    name = f"bench-{uuid.uuid4().hex[:6]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    received: list[tuple[int, str, bytes]] = []
    with EmgStream(name, EmgSynth(model_named("medium"), 5)) as stream, \
            Bus(BusSettings(listen=[endpoint], mode="router"), "controller") as bus:  # fmt: skip
        bus.session.declare_subscriber(  # cheap: decoding waits until the end
            f"{NS}/**",
            lambda s: received.append((time.time_ns(), str(s.key_expr), s.payload.to_bytes())),
        )
        env = os.environ | {"DAMMRL_BUS_CONNECT": json.dumps([endpoint]),
                            "DAMMRL_INTENT_SOURCE": "lsl", "DAMMRL_LSL_STREAM": name,
                            "DAMMRL_LSL_CALIBRATION_FILE": str(calibration),
                            "DAMMRL_LOG_LEVEL": "ERROR"}  # fmt: skip
        service = subprocess.Popen([sys.executable, "-m", "services.intent"], env=env)
        try:
            time.sleep(4.0)  # the service up, the stream found
            request = bus.publisher(DecisionRequest)
            rng = np.random.default_rng(3)
            for k in range(1, trials + 1):
                request.send(DecisionRequest(header=request.stamp(), episode=1, seed=1, request=k,
                                             t_s=0.0, ee_pos_m=(0.0, 0.0, 0.0),
                                             goal_m=(0.3, 0.0, 0.0), primary_axis=0,
                                             human_model=2))  # fmt: skip
                stream.act(int(rng.choice([-1, 1])), bool(k % 2), 0.1)
                time.sleep(1.6)
            time.sleep(0.5)
        finally:
            service.terminate()
            service.wait(10)
    return _latencies(received)


def _latencies(received: list[tuple[int, str, bytes]]) -> tuple[list[float], int]:
    decided: dict[int, int] = {}
    intents: dict[int, int] = {}
    for t_ns, key, payload in received:
        kind = type_of(NS, key)
        if kind is IntentEvidence:
            evidence = decode(IntentEvidence, payload)
            if evidence.acted:
                decided[evidence.request] = evidence.decided_ns
        elif kind is Intent:
            intents.setdefault(decode(Intent, payload).request, t_ns)
    return [(intents[r] - decided[r]) / 1e9 for r in intents if r in decided], len(intents)


def episodes(calibration: Path, count: int) -> list[dict[str, Any]]:
    name, port = f"bench-{uuid.uuid4().hex[:6]}", free_port()
    patient = subprocess.Popen([sys.executable, "-m", "dammrl", "intent", "emulate", "--stream",
                                name, "--pattern", "patient", "--connect",
                                f"tcp/127.0.0.1:{port}"], stdin=subprocess.DEVNULL,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        done = subprocess.run([sys.executable, "-m", "dammrl", "up", "--mode", "semi-virtual",
                               "--intent", "lsl", "--stream", name, "--calibration",
                               str(calibration), "--episodes", str(count), "--json",
                               "--bus-port", str(port)], capture_output=True, text=True,
                              timeout=120 * count, check=False)  # fmt: skip
    finally:
        patient.kill()
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=30)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--minutes", type=float, default=10.0, help="rest per noise level")
    parser.add_argument("--decisions", type=int, default=200, help="per radius and level")
    args = parser.parse_args()

    print("(b) offline: 4-block calibration (leave-one-block-out) | a fresh session (held out)")
    calibrations = {}
    for level in NOISE_LEVELS:
        samples, times, cues = cued(level, seed=1)
        calibration = train(samples, times, cues, STREAM)
        calibrations[level] = calibration
        cv, fresh = calibration.cross_validation, held_out(calibration, level, seed=1001)
        print(f"  {level:6s} CV accuracy {cv.accuracy:.3f}, AER {cv.active_error_rate:.3f}, "
              f"rejection {cv.rejection_rate:.3f} | held out: accuracy {fresh['accuracy']:.3f}, "
              f"AER {fresh['aer']:.3f}, rejection {fresh['rejection']:.3f}")  # fmt: skip

    print(f"(c) online, in the decoder: phantoms at rest ({args.minutes:g} min per level), "
          f"error per radius ({args.decisions} decisions each; intended 20 % / 10 %)")  # fmt: skip
    for level, calibration in calibrations.items():
        rest = phantoms_per_minute(calibration, level, args.minutes)
        radii = error_per_radius(calibration, level, args.decisions)
        cells = "; ".join(
            f"{'E_big' if r == 1 else 'E_small'}: error {v['error']:.3f} (the patient's "
            f"{v['intended']:.3f}, decoder flips {v['flipped']}), missed {v['missed']}, radius "
            f"wrong {v['radius_wrong']}" for r, v in radii.items())  # fmt: skip
        print(f"  {level:6s} phantom decisions/min at rest {rest:.2f}; {cells}")

    with tempfile.TemporaryDirectory() as folder:
        path = save_calibration(calibrations["medium"].model_copy(update={"stream": STREAM}),
                                Path(folder) / "p.json")  # fmt: skip
        print("(a) latency, medium noise, 1 kHz x 8 channels in 20 ms chunks")
        print(f"  pylsl alone, sample -> inlet:           {percentiles(pylsl_alone(10.0))}")
        latency, count = through_the_service(path, args.trials)
        print(f"  deciding sample -> Intent on the bus:   {percentiles(latency)}; "
              f"{count} Intents for {args.trials} requests")  # fmt: skip
        results = episodes(path, args.episodes)
        print(f"(d) {len(results)} semi-virtual episodes through the emulated armband:")
        for r in results:
            print(f"  seed {r['seed']}: {'success' if r['success'] else r['outcome']} in "
                  f"{r['t_total_s']:.1f} s, {r['n_decisions']} decisions, error rate "
                  f"{r['human_error_rate']:.2f}, N_osc {r['n_osc']}")  # fmt: skip


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    main()
