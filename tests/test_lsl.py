"""The wearable path on real Lab Streaming Layer (loopback): the LSL intent source against
the emulated armband and its faults, calibration and episodes through `dammrl` itself."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dammrl.devices.emulators.emg import EmgStream
from dammrl.devices.emulators.emg_signal import EmgSynth, model_named
from dammrl.stack.recording import read_recording
from dammrl_core.intent.emg.calibration import save_calibration
from dammrl_core.intent.lsl import LslSettings, LslSource
from dammrl_core.intent.source import Ask, Decided
from schemas import EpisodeRecorded
from tests.busutil import free_port
from tests.test_wearable import STREAM, cued_session

pytest.importorskip("pylsl")
pytestmark = pytest.mark.slow  # real LSL streams, real time

from dammrl_core.intent.emg.training import train  # noqa: E402


@pytest.fixture(scope="module")
def calibration_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    samples, times, cues = cued_session()
    folder = tmp_path_factory.mktemp("wearable")
    return save_calibration(train(samples, times, cues, STREAM), folder / "p.json")


def _name() -> str:
    return f"emg-{uuid.uuid4().hex[:8]}"  # tests never see each other's streams


class Harness:
    """The LSL source as the intent service runs it, beside an emulated armband."""

    def __init__(self, stream: EmgStream, calibration: Path) -> None:
        self.stream = stream
        self.source = LslSource(LslSettings(stream=stream.name, calibration_file=calibration,
                                            resolve_every_s=0.2))  # fmt: skip
        self.source.open()
        self.problems: list[str] = []
        self.request = 0

    def connect(self, timeout_s: float = 15.0) -> None:
        """Until the stream is found, taken and half a second of signal came (a loaded
        machine takes a while to resolve a stream, or to reconnect to one)."""
        deadline = time.monotonic() + timeout_s
        enough = self.source.samples + 500
        while self.source.inlet is None or self.source.samples < enough:
            assert time.monotonic() < deadline, self.problems[-3:]
            self.run(0.1)
        self.problems.clear()

    def ask(self) -> None:
        self.request += 1
        ask = Ask(1, self.request, 0, 0.0, np.zeros(3), np.ones(3), 0, 2)
        self.source.ask(ask, time.monotonic())

    def run(self, seconds: float) -> list[Decided]:
        decided = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if (d := self.source.poll(time.monotonic())) is not None:
                decided.append(d)
            if (problem := self.source.problem()) is not None:
                self.problems.append(problem)
        return decided

    def contract(self, u_h: int = 1, held: bool = True, within_s: float = 15.0) -> list[Decided]:
        """A request, the contraction, and what was decided: in 3 s, or once something is
        (then 0.5 s more: a second decision would show), within ``within_s`` at most (the
        emulator in this process falls behind on a busy machine)."""
        self.ask()
        self.stream.act(u_h, held, 0.2)
        decided, end = self.run(3.0), time.monotonic() + within_s - 3.0
        while not decided and time.monotonic() < end:
            decided += self.run(0.5)
        return decided + self.run(0.5) if decided else decided


@pytest.fixture()
def armband(calibration_file: Path) -> Iterator[Harness]:
    with EmgStream(_name(), EmgSynth(model_named("medium"), seed=3)) as stream:
        harness = Harness(stream, calibration_file)
        harness.connect()
        yield harness
        harness.source.close()


def test_a_contraction_through_lsl_answers_the_open_request(armband: Harness) -> None:
    assert armband.source.problem() is None, armband.problems[-3:]
    decided = armband.contract(-1, held=False)
    assert [(d.u_h, d.human_model) for d in decided] == [(-1, 1)]
    assert 0.0 <= decided[0].decision_s < 1.5  # onset ~0.2 s after the ask (later if busy)
    armband.stream.act(1, True, 0.1)
    unasked, evidence = armband.run(3.0), armband.source.evidence()
    deadline = time.monotonic() + 12.0  # the emulator in this process lags on a busy machine
    while len(evidence) < 2 and time.monotonic() < deadline:
        unasked += armband.run(0.5)
        evidence += armband.source.evidence()
    assert unasked == []  # no request open: evidence only
    assert [e.acted for e in evidence] == [True, False]
    chunks = armband.source.chunks()
    assert sum(len(c.times_s) for c in chunks) > 2500 and chunks[0].samples.shape[1] == 8


def test_a_lost_stream_decides_nothing_until_it_is_back(armband: Harness) -> None:
    armband.stream.lose(1.5)
    during = armband.contract(1, within_s=3.0)
    said = ("silent", "lost", "no LSL stream named")
    assert during == [] and any(w in p for p in armband.problems for w in said), armband.problems
    armband.connect()  # back: LSL reconnects by itself (in seconds, on a loaded machine)
    armband.run(0.5)  # and a rest after the gap
    assert armband.contract(1) != []


@pytest.mark.parametrize(("fault", "words"), [
    ("nan 0.6", "non-finite"), ("flat 2", "flat"), ("clip 5", "clipping"),
    ("jump 30", "jumped"), ("twin", "2 LSL streams"),
])  # fmt: skip
def test_bad_signal_on_the_stream_decides_nothing_and_says_why(
    armband: Harness, fault: str, words: str
) -> None:
    armband.ask()
    armband.stream.act(1, True, 0.3)
    armband.run(0.5)  # the contraction under way
    armband.stream.fault(fault)
    during = armband.run(1.5)
    assert during == [], during
    assert any(words in p for p in armband.problems), sorted(set(armband.problems))


@pytest.mark.parametrize(("changes", "words"), [
    ({"channels": 6}, "6 channels, the calibration 8"), ({"rate_hz": 500.0}, "500 Hz"),
])  # fmt: skip
def test_a_stream_unlike_the_calibration_is_refused(
    calibration_file: Path, changes: dict[str, float], words: str
) -> None:
    with EmgStream(_name(), EmgSynth(model_named("medium", **changes), seed=3)) as stream:
        harness = Harness(stream, calibration_file)
        harness.run(3.0)  # long enough to be found (never taken: it does not fit)
        assert harness.contract(1, within_s=3.0) == []
        assert any(words in p for p in harness.problems), sorted(set(harness.problems))
        harness.source.close()


def _dammrl(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "dammrl", *args], capture_output=True,
                          text=True, timeout=timeout, check=False)  # fmt: skip


def _emulator(*args: str) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "dammrl", "intent", "emulate", *args]
    return subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


def test_calibrate_a_person_then_run_an_episode_through_lsl(tmp_path: Path) -> None:
    """`dammrl intent calibrate` on the emulated armband (cued), then `dammrl up --mode
    semi-virtual --intent lsl` with the simulated patient on the same armband: the episode
    succeeds, the raw stream and every decision's evidence are recorded, and decoding the
    recording again finds the decisions made live."""
    stream, port = _name(), free_port()
    cued = _emulator("--stream", stream, "--pattern", "cued", "--seconds", "60")
    try:
        done = _dammrl("intent", "calibrate", "--stream", stream, "--blocks", "2",
                       "--trial-s", "2", "--relax-s", "0.5", "--participant", "P001",
                       "--out", str(tmp_path / "p.json"),
                       "--report", str(tmp_path / "p.md"))  # fmt: skip
    finally:
        cued.kill()
    assert done.returncode == 0, done.stdout + done.stderr
    assert "accuracy" in done.stdout and (tmp_path / "p_confusion.png").stat().st_size > 5000
    assert "Verdict: usable" in (tmp_path / "p.md").read_text()
    patient = _emulator("--stream", stream, "--pattern", "patient",
                        "--connect", f"tcp/127.0.0.1:{port}")  # fmt: skip
    try:
        up = _dammrl("up", "--mode", "semi-virtual", "--intent", "lsl", "--stream", stream,
                     "--calibration", str(tmp_path / "p.json"), "--episodes", "1", "--json",
                     "--bus-port", str(port), "--record", str(tmp_path / "s.mcap"),
                     timeout=180)  # fmt: skip
    finally:
        patient.kill()
    assert up.returncode == 0, up.stderr[-3000:]
    result = json.loads(up.stdout.strip().splitlines()[-1])
    assert result["success"], (result["outcome"], result["reason"], up.stderr[-2000:])
    info = _dammrl("recording", "info", str(tmp_path / "s.mcap")).stdout
    assert "SignalChunk" in info and "IntentEvidence" in info
    # the launcher stopped the stack only once the recorder confirmed the reach whole
    acks = read_recording(tmp_path / "s.mcap").decoded(EpisodeRecorded)
    assert [(a.episode, a.complete) for _, a in acks if isinstance(a, EpisodeRecorded)] == [
        (1, True)
    ], up.stderr[-2000:]
    decode = _dammrl("recording", "decode", str(tmp_path / "s.mcap"),
                     "--calibration", str(tmp_path / "p.json"))  # fmt: skip
    live, matched = (int(n) for n in decode.stdout.split("live decisions in the recording: ")[1]
                     .replace("; matched here:", "").split())  # fmt: skip
    assert live == result["n_decisions"] and matched == live, decode.stdout
