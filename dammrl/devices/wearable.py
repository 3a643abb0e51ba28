"""A person on a wearable sensor's LSL stream: calibration, its report, and decoding a
recorded stream (a session's MCAP, or an XDF file other lab software wrote) again offline.

``dammrl intent calibrate`` cues blocks of trials (rest, -1, +1, shuffled in each block)
on the terminal and on an LSL marker stream (``dammrl-cues:<stream>``: lab software and the
emulated armband follow it, and LabRecorder records it beside the signal), records the
stream, trains the person's classifier, cross-validates it leave-one-block-out and
refuses it, saying why, when the classes do not separate.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from dammrl.devices.emulators.emg import cue_stream
from dammrl_core.errors import ConfigurationError, JobFailedError
from dammrl_core.intent.emg.calibration import EmgCalibration
from dammrl_core.intent.emg.classifier import CLASS_NAMES, CLASSES, REJECTED
from dammrl_core.intent.emg.decoder import Contraction, EmgDecoderSettings, WindowDecoder
from dammrl_core.intent.emg.training import Cue, default_conditioning, refusal, train
from dammrl_core.intent.lsl import QUIET_LSL, describe

CUE_WORDS = {0: "rest: relax your forearm", -1: "-1: open your hand (extend) and hold",
             1: "+1: close your hand (flex) and hold"}  # fmt: skip


CUE_WAIT_S = 10.0
"""How long the calibration waits for a follower of its cue stream before it starts [s]:
a follower started beside it on a busy machine resolved the stream after more than 3 s and
missed the first cue (the calibration was then refused)."""


@dataclass(frozen=True)
class Protocol:
    blocks: int = 4
    trial_s: float = 3.0
    relax_s: float = 1.5
    seed: int = 0


def find_stream(name: str, source_id: str | None = None, timeout_s: float = 5.0) -> Any:
    """The one LSL stream called ``name`` (and ``source_id``); a one-line error otherwise."""
    import pylsl

    pylsl.set_config_content(QUIET_LSL)
    found = pylsl.resolve_byprop("name", name, 1, timeout_s)
    if source_id:
        found = [s for s in found if s.source_id() == source_id]
    if not found:
        raise JobFailedError(f"no LSL stream named {name!r} found in {timeout_s:g} s")
    if len(found) > 1:
        where = ", ".join(f"{s.hostname()}/{s.source_id()}" for s in found)
        raise ConfigurationError(f"{len(found)} LSL streams named {name!r} ({where}): "
                                 "give --source-id")  # fmt: skip
    return found[0]


class Recorder:
    """Pulls a stream's chunks on a thread until stopped: (samples, times) on our clock."""

    def __init__(self, info: Any) -> None:
        import pylsl

        if info.nominal_srate() <= 0:
            raise ConfigurationError(f"stream {info.name()!r} has no regular rate")
        self.inlet = pylsl.StreamInlet(info, max_buflen=30, processing_flags=pylsl.proc_clocksync)
        self.stream = describe(self.inlet.info(5.0))  # with its channels' labels and units
        self.inlet.open_stream(5.0)
        self.samples: list[np.ndarray] = []
        self.times: list[np.ndarray] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._pull, daemon=True)
        self.thread.start()

    def _pull(self) -> None:
        while not self.stop.is_set():
            samples, stamps = self.inlet.pull_chunk(timeout=0.05, max_samples=4096)
            if stamps:
                self.samples.append(np.asarray(samples, dtype=float))
                self.times.append(np.asarray(stamps))

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        self.stop.set()
        self.thread.join(2.0)
        self.inlet.close_stream()
        if not self.times:
            raise JobFailedError("the stream sent nothing during the calibration")
        return np.concatenate(self.samples), np.concatenate(self.times)


def feature_set_of(info: Any) -> Literal["emg", "imu"]:
    """The feature set for a stream, from its LSL type (IMU, accelerometer, ...: imu)."""
    kind = str(info.type()).lower()
    return "imu" if any(word in kind for word in ("imu", "acc", "gyro", "mocap")) else "emg"


def calibrate(info: Any, protocol: Protocol, show: Callable[[str], None],
              participant: str | None = None, kind: Literal["emg", "imu"] = "emg",
              mains_hz: Literal[0, 50, 60] = 50) -> tuple[EmgCalibration, str | None]:  # fmt: skip
    """Cue the protocol, record, train: the calibration and why not to use it (or None).
    ``mains_hz``: the notch of an EMG stream's conditioning (0: none)."""
    import pylsl

    name = cue_stream(info.name())
    marker = pylsl.StreamInfo(name, "Markers", 1, 0, pylsl.cf_string, "dammrl-calibrate")
    cues_out = pylsl.StreamOutlet(marker)
    recorder = Recorder(info)
    # software that shows or follows the cues (the emulated armband) connects first; with
    # none (the person reads the terminal) the session starts after CUE_WAIT_S
    show("get ready: the first cue comes in a few seconds")
    cues_out.wait_for_consumers(CUE_WAIT_S)
    time.sleep(1.0)
    cues = _cue_blocks(protocol, cues_out, show)
    cues_out.push_sample(["end"])
    samples, times = recorder.finish()
    conditioning = default_conditioning(kind, mains_hz)
    calibration = train(samples, times, cues, recorder.stream, participant=participant,
                        kind=kind, conditioning=conditioning)  # fmt: skip
    return calibration, refusal(calibration.cross_validation,
                                following=calibration.cue_following)  # fmt: skip


def _cue_blocks(protocol: Protocol, out: Any, show: Callable[[str], None]) -> list[Cue]:
    import pylsl

    rng = np.random.default_rng(protocol.seed)
    cues = []
    for block in range(protocol.blocks):
        for k, label in enumerate(rng.permutation(CLASSES)):
            label = int(label)
            show(f"block {block + 1}/{protocol.blocks}, trial {k + 1}/3 - {CUE_WORDS[label]}")
            out.push_sample([{0: "rest", -1: "-1", 1: "+1"}[label]])
            start = pylsl.local_clock()
            time.sleep(protocol.trial_s)
            cues.append(Cue(label, start, pylsl.local_clock(), block))
            out.push_sample(["rest"])
            show("   relax")
            time.sleep(protocol.relax_s)
    return cues


def write_report(calibration: EmgCalibration, reason: str | None, path: Path) -> Path:
    """A markdown report and its confusion-matrix figure (``<path stem>_confusion.png``)."""
    cv = calibration.cross_validation
    figure = confusion_figure(cv.confusion, path.with_name(path.stem + "_confusion.png"))
    stream = calibration.stream
    lines = [
        f"# Calibration of {calibration.participant or 'a participant'} on {stream.name!r}",
        "",
        f"{calibration.created}; {stream.channel_count} channels at {stream.nominal_srate_hz:g} "
        f"Hz from {stream.hostname or '?'} ({stream.source_id or 'no source id'}); windows "
        f"{calibration.window_s * 1000:.0f} ms, hop {calibration.hop_s * 1000:.0f} ms; LDA "
        + ("on Hudgins' time-domain features (MAV, WL, ZC, SSC per channel)"
           if calibration.features == "emg" else
           "on IMU features (each channel's mean: the posture)")
        + f"; conditioning: {calibration.conditioning.describe()}.",
        "",
        f"**Verdict: {'refused: ' + reason if reason else 'usable'}**",
        "",
        "Leave-one-block-out cross-validation (each block decided by a classifier trained on "
        "the others, with the online rejection and majority vote):",
        "",
        "| metric | value |",
        "|---|---|",
        f"| classification accuracy (accepted windows) | {cv.accuracy:.3f} |",
        f"| active error rate (-1/+1 windows decided wrongly) | {cv.active_error_rate:.3f} |",
        f"| instability (decision changes per window) | {cv.instability:.3f} |",
        f"| rejection rate | {cv.rejection_rate:.3f} |",
        "| accuracy per held-out block | "
        + ", ".join(f"{a:.3f}" for a in cv.per_block_accuracy) + " |",
        "",
        f"![confusion matrix]({figure.name})",
        "",
        _confusion_table(cv.confusion),
    ]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def _confusion_table(confusion: list[list[int]]) -> str:
    names = [CLASS_NAMES[c] for c in (*CLASSES, REJECTED)]
    rows = ["| cued \\ decided | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, counts in zip(CLASSES, confusion, strict=True):
        rows.append(f"| {CLASS_NAMES[label]} | " + " | ".join(str(c) for c in counts) + " |")
    return "\n".join(rows)


def confusion_figure(confusion: list[list[int]], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    counts = np.array(confusion, dtype=float)
    shares = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(4.8, 3.6))
    ax.imshow(shares, cmap="Blues", vmin=0, vmax=1)
    columns = [CLASS_NAMES[c] for c in (*CLASSES, REJECTED)]
    ax.set_xticks(range(len(columns)), columns)
    ax.set_yticks(range(3), [CLASS_NAMES[c] for c in CLASSES])
    for (i, j), share in np.ndenumerate(shares):
        ax.text(j, i, f"{share:.0%}\n({int(counts[i, j])})", ha="center", va="center",
                color="white" if share > 0.6 else "black", fontsize=9)  # fmt: skip
    ax.set(xlabel="decided (after rejection and vote)", ylabel="cued",
           title="windows, leave-one-block-out")  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


@dataclass(frozen=True)
class Signal:
    """A wearable's raw stream: samples (n, channels) at times (n,) [s], its name and rate."""

    name: str
    rate_hz: float
    samples: np.ndarray
    times_s: np.ndarray


def signal_of_recording(path: Path, stream: str | None = None) -> Signal:
    """The raw stream a session recorded (its ``sensor/chunk`` messages), in order."""
    from dammrl.stack.recording import read_recording
    from schemas import SignalChunk

    rows: list[list[float | None]] = []
    stamps: list[int] = []
    names: set[str] = set()
    rate = 0.0
    for _, chunk in read_recording(path).decoded(SignalChunk):
        assert isinstance(chunk, SignalChunk)
        if stream is not None and chunk.stream != stream:
            continue
        names.add(chunk.stream)
        rate = chunk.rate_hz
        rows += chunk.samples
        stamps += chunk.stamps_ns
    if not stamps:
        raise JobFailedError(f"{path}: no raw stream recorded (sensor/chunk)"
                             + (f" named {stream!r}" if stream else ""))  # fmt: skip
    if len(names) > 1:
        raise ConfigurationError(f"{path}: streams {sorted(names)}: choose one with --stream")
    order = np.argsort(stamps, kind="stable")
    samples = np.array([[np.nan if v is None else v for v in row] for row in rows])[order]
    return Signal(names.pop(), rate, samples, np.array(stamps, dtype=float)[order] / 1e9)


def signal_of_xdf(path: Path, stream: str | None = None) -> Signal:
    """A numeric stream of an XDF file (as LabRecorder writes them)."""
    import pyxdf

    try:
        streams, _ = pyxdf.load_xdf(str(path), dejitter_timestamps=False)
    except Exception as exc:  # pyxdf raises whatever its parser meets
        raise ConfigurationError(f"{path}: not a readable XDF file ({exc})") from None
    numeric = [s for s in streams if np.issubdtype(np.asarray(s["time_series"]).dtype, np.number)
               and len(s["time_stamps"]) > 0]  # fmt: skip
    if not numeric:
        raise ConfigurationError(f"{path}: no numeric stream with samples in this XDF file")
    named = [s for s in numeric if stream is None or s["info"]["name"][0] == stream]
    if len(named) != 1:
        found = [s["info"]["name"][0] for s in numeric]
        raise ConfigurationError(f"{path}: numeric streams {found}; choose one with --stream")
    s = named[0]
    rate = float(s["info"]["nominal_srate"][0])
    return Signal(s["info"]["name"][0], rate, np.asarray(s["time_series"], dtype=float),
                  np.asarray(s["time_stamps"], dtype=float))  # fmt: skip


def decode_signal(signal: Signal, calibration: EmgCalibration,
                  settings: EmgDecoderSettings | None = None) -> list[Contraction]:  # fmt: skip
    """Every contraction the calibration's classifier finds in ``signal``, fed in chunks
    of 20 ms as a live stream would be."""
    want = calibration.stream
    if signal.samples.shape[1] != want.channel_count:
        raise ConfigurationError(f"the stream has {signal.samples.shape[1]} channels, the "
                                 f"calibration {want.channel_count}")  # fmt: skip
    decoder = WindowDecoder(calibration, settings or EmgDecoderSettings())
    step = max(1, round(0.02 * signal.rate_hz))
    found: list[Contraction] = []
    for start in range(0, len(signal.times_s), step):
        part = slice(start, start + step)
        found += decoder.push(signal.samples[part], signal.times_s[part])
    return found


def live_onsets(path: Path) -> list[float]:
    """The onsets [s, bus clock] of the decisions a session's source made live."""
    from dammrl.stack.recording import read_recording
    from schemas import IntentEvidence

    return [e.onset_ns / 1e9 for _, e in read_recording(path).decoded(IntentEvidence)
            if isinstance(e, IntentEvidence) and e.acted]  # fmt: skip


def write_csv(rows: list[dict[str, object]], path: Path) -> Path:
    import csv

    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, list(rows[0]) if rows else ["onset_s"])
        writer.writeheader()
        writer.writerows(rows)
    return path


REBASELINE_WAIT_S = 5.0
"""How long `dammrl intent rebaseline` waits for the intent service to confirm [s]."""


def rebaseline(settings: Any, who: str, timeout_s: float = REBASELINE_WAIT_S) -> str | None:
    """Ask the intent service on the bus (``settings``: BusSettings) to measure the
    participant's rest level afresh; its Health line confirming it, or None if none came.
    The request is sent again every second until confirmed (a message may be lost)."""
    from schemas import Health, SessionControl, TaskGoal
    from services.common.bus import Bus
    from services.common.security import OPERATOR

    with Bus(settings, OPERATOR) as bus:  # the therapist's hand, as `dammrl stop`'s
        bus.subscribe(Health, TaskGoal)
        control = bus.publisher(SessionControl)
        episode, start, next_send = 1, time.monotonic(), 0.0
        while (now := time.monotonic()) - start < timeout_s:
            if now >= next_send:
                control.send(SessionControl(header=control.stamp(), episode=episode,
                                            action="rebaseline", who=who))  # fmt: skip
                next_send = now + 1.0
            message = bus.receive(0.05)
            if isinstance(message, TaskGoal):
                episode = max(1, message.episode)  # for the record: the reach it came in
            if (isinstance(message, Health) and message.service == "intent"
                    and "measuring the rest level" in message.detail):  # fmt: skip
                return message.detail
    return None
