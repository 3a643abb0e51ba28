"""Sessions with a person's device: a counterbalanced protocol through the emulated pad
pressed by the simulated patient, and through the emulated EMG armband after a live
calibration; the patient follows the stack from block to block (one stack per block)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dammrl.stack.recording import read_recording
from schemas import Intent
from tests.busutil import free_port, start_patient

pytestmark = pytest.mark.slow

PROTOCOL = """\
format: 1
name: people
version: "1"
blocks:
  - {name: event, trials: 2, seed: 7100100, condition: {policy: fixed, model: [2, 1]}}
  - {name: fixed, trials: 2, seed: 7100100,
     condition: {trigger: fixed, policy: fixed, model: [2, 1]}}
"""


def _session(tmp_path: Path, participant: str, *device: str) -> subprocess.CompletedProcess[str]:
    (tmp_path / "protocol.yaml").write_text(PROTOCOL)
    return subprocess.run(
        [sys.executable, "-m", "dammrl", "session", "run", "--participant", participant,
         "--protocol", str(tmp_path / "protocol.yaml"), "--root", str(tmp_path / "sessions"),
         "--mode", "semi-virtual", *device, "--no-display", "--operator", "T1"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=600,
    )  # fmt: skip


def _check(tmp_path: Path, participant: str, source: str) -> None:
    """Every trial done once; the decisions in the recordings are the person's."""
    folder = tmp_path / "sessions" / participant / "ses-01"
    trials = [json.loads(line) for line in (folder / "trials.jsonl").read_text().splitlines()]
    assert sorted(t["trial"] for t in trials) == [1, 2, 3, 4]
    assert sum(t["result"]["success"] for t in trials) >= 3, trials
    intents = [m for part in sorted((folder / "recordings").glob("*.mcap"))
               for _, m in read_recording(part).decoded(Intent)]  # fmt: skip
    assert intents and all(i.person and i.source == source for i in intents)


def test_a_protocol_through_the_emulated_pad(tmp_path: Path) -> None:
    link, port = tmp_path / "ttyPAD", free_port()
    patient = start_patient(link, port, human_model=1)
    try:
        done = _session(tmp_path, "P001", "--port", str(link), "--bus-port", str(port))
    finally:
        patient.terminate()
        patient.wait(10)
    assert done.returncode == 0, done.stderr[-3000:]
    _check(tmp_path, "P001", "pad")


def test_a_protocol_through_the_emulated_emg_armband(tmp_path: Path) -> None:
    stream, port = f"dammrl-emg-{free_port()}", free_port()
    emulate = [sys.executable, "-m", "dammrl", "intent", "emulate", "--stream", stream]
    cued = subprocess.Popen([*emulate, "--pattern", "cued", "--seconds", "60"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        calibrated = subprocess.run(
            [sys.executable, "-m", "dammrl", "intent", "calibrate", "--stream", stream,
             "--blocks", "2", "--trial-s", "2", "--relax-s", "0.5", "--participant", "P002",
             "--out", str(tmp_path / "p.json")],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        cued.kill()
        cued.wait()
    assert calibrated.returncode == 0, calibrated.stdout + calibrated.stderr
    patient = subprocess.Popen(
        [*emulate, "--pattern", "patient", "--connect", f"tcp/127.0.0.1:{port}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        done = _session(tmp_path, "P002", "--stream", stream, "--calibration",
                        str(tmp_path / "p.json"), "--bus-port", str(port))  # fmt: skip
    finally:
        patient.kill()
        patient.wait()
    assert done.returncode == 0, done.stderr[-3000:]
    _check(tmp_path, "P002", "lsl")
    kept = tmp_path / "sessions" / "P002" / "calibration.json"
    assert kept.read_bytes() == (tmp_path / "p.json").read_bytes()  # for their next session
