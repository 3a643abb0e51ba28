"""Loss figures a reader can trust, with real processes on loopback: the recorder's
``dammrl.loss`` equals what each file's own sequence numbers lack, after restarts, stalls
and kills, under load; and a recorder killed anywhere leaves a file that mcap's default
reader opens as it is (no ``dammrl recording repair``)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import msgpack
import pytest
import zenoh
from mcap.reader import make_reader

from dammrl.stack.options import recording_files
from dammrl.stack.recording import info, repair
from services.recorder.core import complete_mcap
from services.recorder.gaps import publishers_of
from tests.busutil import endpoint, free_port, listener_settings, wait_for

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parent.parent
NAMESPACE = "losstest"

PUBLISHER = """
import sys, time, zenoh, json
from schemas import Header, encode
from tests.test_schemas import EXAMPLES
config = zenoh.Config()
config.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
config.insert_json5("scouting/multicast/enabled", "false")
state = EXAMPLES[0]
with zenoh.open(config) as session:
    publisher = session.declare_publisher(sys.argv[2] + "/robot/state",
                                          congestion_control=zenoh.CongestionControl.DROP)
    seq, start = 0, time.monotonic()
    while time.monotonic() - start < float(sys.argv[3]):
        header = Header(stamp_ns=time.time_ns(), seq=seq, source="sim")
        if not 250 <= seq % 500 < 269:  # 19 states lost on their way, every half second
            publisher.put(encode(state.model_copy(update={"header": header})))
        seq += 1
        time.sleep(0.001)
"""


def file_loss(path: Path, namespace: str = NAMESPACE) -> dict[str, int]:
    """What a file's own sequence numbers lack, per topic (the numbers of each publisher
    between its first and its last recorded, that the file does not hold): read with
    mcap's default reader, as anyone would."""
    numbers: dict[tuple[str, str], set[int]] = defaultdict(set)
    with open(path, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            if channel.metadata.get("dammrl.invalid"):
                continue
            header = msgpack.unpackb(message.data)["header"]
            publishers = publishers_of(namespace, channel.topic) or frozenset()
            if header["source"] in publishers:
                numbers[(channel.topic, header["source"])].add(header["seq"])
    missing: dict[str, int] = defaultdict(int)
    for (topic, _), seqs in numbers.items():
        if max(seqs) - min(seqs) + 1 - len(seqs):
            missing[topic] += max(seqs) - min(seqs) + 1 - len(seqs)
    return dict(missing)


def metadata_loss(path: Path) -> tuple[dict[str, int], dict[str, dict[str, int]]]:
    """The recorder's (or repair's) ``dammrl.loss``: missing per topic, anomalies."""
    with open(path, "rb") as stream:
        records = {m.name: m.metadata for m in make_reader(stream).iter_metadata()}
    loss = records["dammrl.loss"]
    return json.loads(loss["gaps"]), json.loads(loss["anomalies"])


@contextmanager
def two_cpu_hogs() -> Iterator[None]:
    hogs = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(2)]
    try:
        yield
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


def _recorder(port: int, out: Path) -> subprocess.Popen[bytes]:
    env = dict(os.environ) | {"PYTHONPATH": str(ROOT), "DAMMRL_LOG_LEVEL": "ERROR",
                              "DAMMRL_BUS_CONNECT": json.dumps([endpoint(port)]),
                              "DAMMRL_BUS_NAMESPACE": NAMESPACE,
                              "DAMMRL_RECORDER_OUT": str(out)}  # fmt: skip
    return subprocess.Popen([sys.executable, "-m", "services.recorder"], env=env,
                            stdin=subprocess.DEVNULL)  # fmt: skip


def _stall(pid: int, seconds: float) -> None:
    """The recorder stopped as a loaded machine stops it: a backlog, then a burst."""
    os.kill(pid, signal.SIGSTOP)
    time.sleep(seconds)
    os.kill(pid, signal.SIGCONT)


def _grows(path: Path, after: int = 0) -> bool:
    return path.exists() and path.stat().st_size > after


def test_a_stalled_killed_and_restarted_recorder_reports_exactly_what_its_files_lack(
    tmp_path: Path,
) -> None:
    """A 1 kHz publisher that drops 19 states of its own every half second, reaching the
    recorder through a router and then directly (two routes), beside two CPU hogs; the
    recorder stalled twice, killed with -9 twice and restarted: every file opens in
    mcap's default reader as it is, and each figure of loss equals the file's own."""
    port, out = free_port(), tmp_path / "rec.mcap"
    with two_cpu_hogs(), zenoh.open(_router(port)):
        env = dict(os.environ) | {"PYTHONPATH": str(ROOT)}
        publisher = subprocess.Popen(
            [sys.executable, "-c", PUBLISHER, endpoint(port), NAMESPACE, "90"], env=env,
            stdin=subprocess.DEVNULL, cwd=ROOT,
        )  # fmt: skip
        try:
            first = _recorder(port, out)  # cut by kill -9 after a stall
            wait_for(lambda: _grows(out, 20_000), 60, "the first file")
            _stall(first.pid, 1.5)
            time.sleep(1.0)
            first.kill()
            first.wait(10)
            second = _recorder(port, out)  # finished after a stall
            wait_for(lambda: _grows(tmp_path / "rec-001.mcap", 20_000), 60, "the second file")
            _stall(second.pid, 1.0)
            time.sleep(2.0)
            second.send_signal(signal.SIGTERM)
            assert second.wait(30) == 0
            third = _recorder(port, out)  # killed right after its start
            wait_for(lambda: _grows(tmp_path / "rec-002.mcap", 2_000), 60, "the third file")
            time.sleep(0.3)
            third.kill()
            third.wait(10)
        finally:
            publisher.kill()
            publisher.wait(10)
    files = recording_files(out)
    assert [f.name for f in files] == ["rec.mcap", "rec-001.mcap", "rec-002.mcap"]
    finished = tmp_path / "rec-001.mcap"
    assert complete_mcap(finished) and not complete_mcap(out)
    gaps, anomalies = metadata_loss(finished)
    topic = f"{NAMESPACE}/robot/state"
    assert gaps == file_loss(finished), anomalies
    assert gaps[topic] >= 19 and "implausible_jumps" not in anomalies, (gaps, anomalies)
    for cut in (out, tmp_path / "rec-002.mcap"):
        with open(cut, "rb") as stream:  # mcap's default reader, as it is
            assert sum(1 for _ in make_reader(stream).iter_messages()) > 0, cut
        repaired = tmp_path / f"repaired-{cut.name}"
        repair(cut, repaired)
        gaps, anomalies = metadata_loss(repaired)
        assert gaps == file_loss(repaired) and "implausible_jumps" not in anomalies
        assert info(repaired)["complete"]


def _router(port: int) -> zenoh.Config:
    from services.common.bus import zenoh_config

    return zenoh_config(listener_settings(port, NAMESPACE, mode="router"))


def test_dammrl_up_beside_two_hogs_reports_the_loss_its_files_show(tmp_path: Path) -> None:
    """The stack itself, loaded, its recorder stalled and killed once (restarted by
    `dammrl up` into a new file, the cut one completed with recounted figures): every
    file's dammrl.loss is what its sequence numbers lack, with no implausible jump."""
    port, record = free_port(), tmp_path / "session.mcap"
    with two_cpu_hogs():
        launcher = subprocess.Popen(
            [sys.executable, "-m", "dammrl", "up", "--episodes", "2", "--model", "2,1",
             "--bus-port", str(port), "--record", str(record)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
            env=dict(os.environ) | {"PYTHONPATH": str(ROOT)},
        )  # fmt: skip
        try:
            wait_for(lambda: _grows(record, 30_000), 120, "a recording")
            recorder = _child(launcher.pid, "services.recorder")
            _stall(recorder, 1.5)
            time.sleep(2.0)
            os.kill(recorder, signal.SIGKILL)
            wait_for(lambda: _grows(tmp_path / "session-001.mcap", 30_000), 120, "a restart")
            _stall(_child(launcher.pid, "services.recorder"), 1.0)
            _, err = launcher.communicate(timeout=300)
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.communicate()
    assert launcher.returncode == 0, err
    for path in recording_files(record):
        gaps, anomalies = metadata_loss(path)
        assert gaps == file_loss(path, "dammrl"), (path.name, gaps, anomalies)
        assert "implausible_jumps" not in anomalies, (path.name, anomalies)
        print(f"\n{path.name}: {gaps or 'nothing'} missing, {anomalies}")


def _child(parent: int, module: str) -> int:
    found = subprocess.run(["pgrep", "-P", str(parent), "-f", module], capture_output=True,
                           text=True, check=False).stdout.split()  # fmt: skip
    assert found, f"no {module} under {parent}"
    return int(found[0])
