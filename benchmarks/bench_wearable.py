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
    the emulated armband (medium noise): success, time, decisions, error rate;
(e) latency from a 0.3 s contraction's onset (its first sample's LSL timestamp) to the
    Intent a bus subscriber receives, before and after the signal conditioning, paired:
    two intent services at once (two namespaces), one decoding with a calibration
    without conditioning (raw samples, absolute levels: the decoder as it was), one with
    it (20 Hz high-pass, 50 Hz notch, levels relative to rest), the same requests and
    the same contractions on the same stream;
(f) offline, the same muscles through other amplifiers: decisions correct (of 12, and
    in order), and phantom decisions in 30 s at rest, under DC offsets up to 1 mV and
    gains x0.3-x3, before and after the conditioning, on the emulator and on a signal
    of another generator (motor units firing: ``tests/muap_emg.py``).

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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dammrl.devices.emulators.emg import HELD_S, QUICK_S, EmgStream
from dammrl.devices.emulators.emg_signal import NOISE_LEVELS, EmgSynth, model_named
from dammrl.devices.emulators.movements import cued_session
from dammrl_core.human import HumanModel
from dammrl_core.intent.emg.calibration import EmgCalibration, StreamDescription, save_calibration
from dammrl_core.intent.emg.classifier import decide_windows, offline_metrics
from dammrl_core.intent.emg.conditioning import Conditioning
from dammrl_core.intent.emg.decoder import EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.emg.training import Cue, labelled_windows, train
from schemas import (
    DecisionRequest,
    Header,
    Health,
    Intent,
    IntentEvidence,
    decode,
    encode,
    key,
    type_of,
)
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
    c = calibration
    features, labels, _, trials = labelled_windows(samples, times, cues, RATE, c.window_s,
                                                   c.hop_s, c.features, c.conditioning)  # fmt: skip
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
        try:  # the service up and decoding (a fixed 4 s lost a third of the trials to a
            _wait_decoding(received, [NS], 90.0)  # loaded machine's slow start)
            time.sleep(2.0)  # the rest level
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
    for t_ns, topic, payload in received:
        kind = type_of(NS, topic)
        if kind is IntentEvidence:
            evidence = decode(IntentEvidence, payload)
            if evidence.acted:
                decided[evidence.request] = evidence.decided_ns
            else:  # why a contraction answered nothing, for the record
                print(f"  (a decision not acted on: {evidence.reason})")
        elif kind is Intent:
            intents.setdefault(decode(Intent, payload).request, t_ns)
    return [(intents[r] - decided[r]) / 1e9 for r in intents if r in decided], len(intents)


def onset_to_intent(calibrations: dict[str, Path], trials: int) -> dict[str, dict[int, float]]:
    """(e): per namespace (one intent service each, its calibration), seconds from each
    0.3 s contraction's onset to the Intent received, per request; a missed one is absent."""
    name = f"bench-{uuid.uuid4().hex[:6]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    received: list[tuple[int, str, bytes]] = []
    onsets: dict[int, int] = {}  # request -> onset on the bus clock [ns]
    with EmgStream(name, EmgSynth(model_named("medium"), 5)) as stream, \
            Bus(BusSettings(listen=[endpoint], mode="router"), "controller") as bus:  # fmt: skip
        bus.session.declare_subscriber(
            "**", lambda s: received.append((time.time_ns(), str(s.key_expr), s.payload.to_bytes()))
        )
        services = [_intent_service(name, path, endpoint, namespace)
                    for namespace, path in calibrations.items()]  # fmt: skip
        try:
            _wait_decoding(received, list(calibrations), 90.0)
            time.sleep(2.0)  # the rest level
            rng = np.random.default_rng(3)
            for k in range(1, trials + 1):
                for namespace in calibrations:
                    header = Header(stamp_ns=time.time_ns(), seq=k, source="controller")
                    ask = DecisionRequest(header=header, episode=1, seed=1, request=k, t_s=0.0,
                                          ee_pos_m=(0.0, 0.0, 0.0), goal_m=(0.3, 0.0, 0.0),
                                          primary_axis=0, human_model=1)  # fmt: skip
                    bus.session.put(key(namespace, DecisionRequest), encode(ask))
                onset = stream.contract(int(rng.choice([-1, 1])), 0.3, 0.2)
                onsets[k] = time.time_ns() - round((time.monotonic() - onset) * 1e9)
                time.sleep(1.6)
            time.sleep(0.5)
        finally:
            for service in services:
                service.terminate()
                service.wait(10)
    out: dict[str, dict[int, float]] = {namespace: {} for namespace in calibrations}
    for t_ns, topic, payload in received:
        namespace = topic.split("/", 1)[0]
        if namespace in out and type_of(namespace, topic) is Intent:
            request = decode(Intent, payload).request
            out[namespace].setdefault(request, (t_ns - onsets[request]) / 1e9)
        elif namespace in out and type_of(namespace, topic) is IntentEvidence:
            evidence = decode(IntentEvidence, payload)
            if not evidence.acted:  # why a contraction answered nothing, for the record
                print(f"  ({namespace}: a decision not acted on: {evidence.reason})")
    return out


def _wait_decoding(received: list[tuple[int, str, bytes]], namespaces: list[str],
                   timeout_s: float) -> None:  # fmt: skip
    """Until every namespace's intent service reports Health "ok" (its stream taken)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        health = [(t.split("/", 1)[0], p) for _, t, p in list(received)
                  if t.endswith("/health/intent")]  # fmt: skip
        ok = {namespace for namespace, payload in health if decode(Health, payload).state == "ok"}
        if ok >= set(namespaces):
            return
        time.sleep(0.2)
    raise SystemExit(f"the intent services did not decode the stream in {timeout_s:g} s")


def _intent_service(stream: str, calibration: Path, endpoint: str,
                    namespace: str) -> subprocess.Popen[bytes]:  # fmt: skip
    env = os.environ | {"DAMMRL_BUS_CONNECT": json.dumps([endpoint]),
                        "DAMMRL_BUS_NAMESPACE": namespace, "DAMMRL_INTENT_SOURCE": "lsl",
                        "DAMMRL_LSL_STREAM": stream,
                        "DAMMRL_LSL_CALIBRATION_FILE": str(calibration),
                        "DAMMRL_LOG_LEVEL": "ERROR"}  # fmt: skip
    return subprocess.Popen([sys.executable, "-m", "services.intent"], env=env)


def paired_difference_ms(before: dict[int, float], after: dict[int, float]) -> str:
    """The median of after - before over the contractions both decoded, with a bootstrap
    95 % interval over contractions (the two services heard the same ones)."""
    both = sorted(set(before) & set(after))
    n = len(both)
    if n < 3:
        return "too few pairs"
    diff = np.array([after[k] - before[k] for k in both]) * 1e3
    rng = np.random.default_rng(0)
    boot = [np.median(rng.choice(diff, n)) for _ in range(2000)]
    low, high = np.percentile(boot, [2.5, 97.5])
    return f"median {np.median(diff):+.1f} ms (95 % CI {low:+.1f} to {high:+.1f}, {n} pairs)"


# ---- offline, through other amplifiers ------------------------------------------------------
AMPLIFIERS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "as recorded": lambda x: x,
    "DC +30 uV": lambda x: x + 30.0,
    "DC +300 uV": lambda x: x + 300.0,
    "DC +1 mV": lambda x: x + 1000.0,
    "DC -1..+1 mV": lambda x: x + np.linspace(-1000.0, 1000.0, x.shape[1]),
    "gain x0.3": lambda x: 0.3 * x,
    "gain x2": lambda x: 2.0 * x,
    "gain x3": lambda x: 3.0 * x,
}


def amplifier_figures() -> None:
    """(f): per generator and conditioning, each amplifier's decisions and phantoms."""
    from dammrl.devices.wearable import Signal, decode_signal
    from dammrl_core.intent.emg.conditioning import Conditioning
    from tests import muap_emg
    from tests.test_conditioning import MUAP_STREAM, _scripted_patient

    samples, times, cues = cued("medium", seed=1)
    x, t, plan = _scripted_patient(EmgSynth(NOISE_LEVELS["medium"], seed=5), 12, seed=5)
    rest = EmgSynth(NOISE_LEVELS["medium"], seed=6).generate(30_000)
    forearm = muap_emg.MuapForearm(seed=1)
    m_samples, m_times, m_cues = muap_emg.cued_session(forearm)
    mx, mt, m_plan = muap_emg.decisions_session(muap_emg.MuapForearm(seed=1), 12, seed=3)
    m_rest = muap_emg.MuapForearm(seed=1).samples(30.0, [])
    generators = {
        "emulator": (samples, times, cues, STREAM, (x, t, plan), rest, 50),
        "motor units": (m_samples, m_times, m_cues, MUAP_STREAM, (mx, mt, m_plan), m_rest, 60),
    }
    for generator, (s, st, c, stream, (sx, stt, splan), srest, mains) in generators.items():
        for label, conditioning in (("before", Conditioning.none()),
                                    ("after", Conditioning.emg(mains))):  # fmt: skip
            calibration = train(s, st, c, stream, conditioning=conditioning)
            rate = stream.nominal_srate_hz
            cells = []
            for name, amplifier in AMPLIFIERS.items():
                found = decode_signal(Signal("s", rate, amplifier(sx), stt), calibration)
                acted = [(d.u_h, d.human_model) for d in found if d.accepted]
                right = sum(a == b for a, b in zip(acted, splan, strict=False))
                at_rest = Signal("s", rate, amplifier(srest), np.arange(len(srest)) / rate)
                resting = decode_signal(at_rest, calibration)
                phantoms = sum(d.accepted for d in resting)
                order = "" if acted == splan else "*"
                cells.append(f"{name}: {right}/{len(splan)}{order} {phantoms}ph")
            print(f"  {generator:11s} {label:6s} " + "; ".join(cells))


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

    print("(f) offline, other amplifiers: decisions right of 12 (* not all in order), "
          "phantoms in 30 s at rest (ph)")  # fmt: skip
    amplifier_figures()

    with tempfile.TemporaryDirectory() as folder:
        path = save_calibration(calibrations["medium"].model_copy(update={"stream": STREAM}),
                                Path(folder) / "p.json")  # fmt: skip
        samples, times, cues = cued("medium", seed=1)
        unconditioned = train(samples, times, cues, STREAM, conditioning=Conditioning.none())
        raw = save_calibration(unconditioned, Path(folder) / "raw.json")
        print(f"(e) a 0.3 s contraction's onset -> Intent on the bus, {args.trials} trials, "
              "paired (two services at once)")  # fmt: skip
        latency = onset_to_intent({"before": raw, "after": path}, args.trials)
        for label, values in latency.items():
            print(f"  {label:6s} conditioning: {percentiles(list(values.values()))}; "
                  f"{len(values)} Intents for {args.trials} contractions")  # fmt: skip
        print(f"  after - before: {paired_difference_ms(latency['before'], latency['after'])}")
        print("(a) latency, medium noise, 1 kHz x 8 channels in 20 ms chunks")
        print(f"  pylsl alone, sample -> inlet:           {percentiles(pylsl_alone(10.0))}")
        latency, count = through_the_service(path, args.trials)
        print(f"  deciding sample -> Intent on the bus:   {percentiles(latency)}; "
              f"{count} Intents for {args.trials} requests")  # fmt: skip
        results = episodes(path, args.episodes)
        print(f"(d) {len(results)} semi-virtual episodes through the emulated armband:")
        for r in results:
            why = "" if r["success"] else f" ({r['reason']})"  # a hold names its fault
            print(f"  seed {r['seed']}: {'success' if r['success'] else r['outcome']} in "
                  f"{r['t_total_s']:.1f} s, {r['n_decisions']} decisions, error rate "
                  f"{r['human_error_rate']:.2f}, N_osc {r['n_osc']}{why}")  # fmt: skip


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    main()
