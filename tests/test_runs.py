"""Emulators and tools join any run: a local `dammrl up` leaves a card that they find (the
run reading their pad or stream, else the only one, or the one named by --bus-port);
`up` exits non-zero when an episode could not be done because an input never joined;
`--record` is checked before anything starts; the credentials error says where a run's
credentials are."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from dammrl.cli.common import bus_settings
from dammrl.stack.options import StackOptions, check_options
from dammrl_core.errors import UsageError
from services.common.runs import RunCard, local_runs, only_run, remove_card, run_reading, write_card
from services.common.security import CredentialsError, run_credentials
from tests.busutil import free_port, wait_for

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def runtime(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A private runtime folder of this test's own (cards, run credentials)."""
    folder = tmp_path / "runtime"
    folder.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(folder))
    for name in ("DAMMRL_BUS_CONNECT", "DAMMRL_BUS_CREDENTIALS", "DAMMRL_BUS_NAMESPACE"):
        monkeypatch.delenv(name, raising=False)
    yield folder


def _card(port: int, **fields: object) -> RunCard:
    values: dict[str, object] = {"pid": os.getpid(), "port": port,
                                 "endpoint": f"tcp/127.0.0.1:{port}", "namespace": "dammrl",
                                 "credentials": None} | fields  # fmt: skip
    return RunCard(**values)  # type: ignore[arg-type]


def _args(**given: object) -> argparse.Namespace:
    return argparse.Namespace(**({"connect": None, "bus_port": None, "namespace": None,
                                  "credentials": None} | given))  # fmt: skip


def test_a_card_is_found_by_the_pad_or_stream_the_run_reads(runtime: Path, tmp_path: Path) -> None:
    pad = tmp_path / "pad"
    write_card(_card(26452, pad_port=str(pad)))
    write_card(_card(26453, lsl_stream="dammrl-emg"))
    assert [r.port for r in local_runs()] == [26452, 26453]
    found = run_reading(pad_link=pad)
    assert found is not None and found.port == 26452
    found = run_reading(stream="dammrl-emg")
    assert found is not None and found.port == 26453
    assert run_reading(pad_link=tmp_path / "another") is None
    assert only_run() is None  # two runs: a tool is told which
    remove_card(26453, os.getpid())
    only = only_run()
    assert only is not None and only.port == 26452


def test_a_card_whose_launcher_is_gone_is_ignored_and_removed(runtime: Path) -> None:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path = write_card(_card(26454, pid=dead.pid))
    assert local_runs() == [] and not path.exists()


def test_a_tool_joins_the_run_by_its_port_or_the_only_one_with_its_namespace(
    runtime: Path,
) -> None:
    write_card(_card(26455, namespace="lab2", endpoint="tls/127.0.0.1:26455",
                     credentials=str(runtime / "lab-bus")))  # fmt: skip
    by_port = bus_settings(_args(bus_port=26455))
    assert by_port.connect == ["tls/127.0.0.1:26455"] and by_port.namespace == "lab2"
    assert by_port.credentials == runtime / "lab-bus"
    alone = bus_settings(_args())  # nothing said where: the only run there is
    assert alone.connect == by_port.connect and alone.namespace == "lab2"
    with pytest.raises(UsageError, match="one of them"):
        bus_settings(_args(bus_port=26455, connect=["tcp/127.0.0.1:26455"]))


def test_the_credentials_error_says_where_a_runs_credentials_are(runtime: Path) -> None:
    expected = str(run_credentials(26456, create=False))
    with pytest.raises(CredentialsError, match="no credentials were found") as error:
        bus_settings(_args(connect=["tls/127.0.0.1:26456"]))
    assert expected in str(error.value) and "--credentials DIR" in str(error.value)
    from services.common.config import BusSettings

    with pytest.raises(ValueError, match="keeps its own in " + expected):
        BusSettings(connect=["tls/127.0.0.1:26456"])


def test_a_record_path_is_checked_before_anything_starts(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no folder"):
        check_options(StackOptions(record=tmp_path / "missing" / "r.mcap"))
    with pytest.raises(UsageError, match=r"must end in \.mcap"):
        check_options(StackOptions(record=tmp_path / "r.txt"))
    (tmp_path / "r-001.mcap").write_bytes(b"")  # a continuation of an earlier run
    with pytest.raises(UsageError, match=r"r-001\.mcap exists"):
        check_options(StackOptions(record=tmp_path / "r.mcap"))
    check_options(StackOptions(record=tmp_path / "s.mcap"))
    assert not (tmp_path / "missing").exists()  # nothing created


# ---- real processes on loopback --------------------------------------------------------------
def _dammrl(*argv: str, cwd: Path, **environment: str) -> subprocess.Popen[str]:
    env = dict(os.environ) | {"PYTHONPATH": str(ROOT)} | environment
    return subprocess.Popen([sys.executable, "-m", "dammrl", *argv], cwd=cwd, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip


@pytest.mark.slow
def test_an_emulated_patient_joins_the_run_that_reads_its_pad_on_any_port(
    tmp_path: Path,
) -> None:
    """The re-test's command line: the patient, told nothing of the bus, answers a stack
    on a port of its own (its decisions drive the episode: how it ends is the stack's
    business on a loaded machine)."""
    patient = _dammrl("sensor", "emulate", "--link", "./pad", "--pattern", "patient",
                      "--seconds", "240", cwd=tmp_path)  # fmt: skip
    try:
        wait_for((tmp_path / "pad").exists, 60, "the emulated pad")
        up = _dammrl("up", "--mode", "semi-virtual", "--port", "./pad", "--bus-port",
                     str(free_port()), "--episodes", "1", "--json", cwd=tmp_path)  # fmt: skip
        out, err = up.communicate(timeout=240)
    finally:
        patient.terminate()
        _, said = patient.communicate(timeout=30)
    assert up.returncode == 0, err
    episode = json.loads(out.splitlines()[0])
    assert episode["n_decisions"] > 0, (out, err)
    assert "joined the stack at tls/127.0.0.1:" in said


@pytest.mark.slow
def test_dammrl_up_exits_non_zero_when_the_persons_input_never_joined(tmp_path: Path) -> None:
    """The patient sent elsewhere: every episode ends without a decision; `up` says whose
    input never answered and exits 1 (it exited 0 with a misleading reason)."""
    elsewhere = str(free_port())
    patient = _dammrl("sensor", "emulate", "--link", "./pad", "--pattern", "patient",
                      "--bus-port", elsewhere, "--seconds", "240", cwd=tmp_path)  # fmt: skip
    try:
        wait_for((tmp_path / "pad").exists, 60, "the emulated pad")
        up = _dammrl("up", "--mode", "semi-virtual", "--port", "./pad", "--bus-port",
                     str(free_port()), "--episodes", "1", cwd=tmp_path,
                     DAMMRL_TASK_EPISODE_TIMEOUT_S="10")  # fmt: skip
        out, err = up.communicate(timeout=240)
    finally:
        patient.terminate()
        patient.communicate(timeout=30)
    assert up.returncode == 1, (out, err)
    assert "episode 1/1: timeout" in out
    assert "1 of 1 episodes could not be done: no decision ever came from the pad at ./pad" in err
    assert err.count("unanswered for") <= 1  # a warning, not one every 2 s


def test_an_episode_ended_by_a_fault_is_not_blamed_on_the_persons_input() -> None:
    """A hold 0.3 s into a reach (the sim's state stale on a loaded machine) said "in 0 s
    no decision came from the wearable's stream"; only an episode that timed out without
    a decision could not be done for want of the person's input."""
    from dammrl.stack.progress import undecided
    from tests.sessionutil import result as _result

    stalled = _result(1, 0, "hold").model_copy(update={"n_decisions": 0, "t_total_s": 0.3})
    waited = _result(2, 0, "timeout").model_copy(update={"n_decisions": 0})
    assert not undecided(stalled)
    assert undecided(waited)
    assert not undecided(waited.model_copy(update={"n_decisions": 1}))
