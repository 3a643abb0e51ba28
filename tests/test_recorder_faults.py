"""Recorder faults: crafted files, a killed recorder, a full disk, Ctrl-C of a replay.

Crafted and corrupt MCAP files (``crafted_files``): each builder writes one with the mcap
writer (or, where the writer cannot produce the fault, its records by hand). Every file
with a readable start also holds one valid message of each type a tool looks at, so a
tool that skips the bad records still has something to work on. Every recording tool must
answer each of them with its result or one line, never a traceback.

The recorder's own faults run it as a real process on a loopback bus (marked slow): a
``kill -9`` loses at most about ``chunk_s``; a full disk (a small tmpfs; needs root) makes
it degraded, not dead, and it resumes when space comes back.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgpack
import pytest
import zenoh
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Header, Message
from mcap.writer import CompressionType, Writer

from dammrl.cli import main
from dammrl.stack.recording import info, read_recording
from dammrl.stack.replay import ReplayOptions, selected
from schemas import Header as BusHeader
from schemas import Health, encode, key
from schemas import Message as BusMessage
from schemas.keys import LIMITS
from services.recorder.core import McapRecorder
from tests.busutil import Observer, endpoint, free_port, wait_for
from tests.test_schemas import EXAMPLES

NAMESPACE = "dammrl"
MAGIC = b"\x89MCAP0\r\n"


def _valid(message: BusMessage, seq: int, source: str) -> bytes:
    header = BusHeader(stamp_ns=1_000_000 + seq, seq=seq, source=source)
    return encode(message.model_copy(update={"header": header}))


_SOURCES = {"EmergencyStop": "operator", "RobotState": "sim", "SensorSample": "intent",
            "Intent": "intent", "Health": "sim", "ModelChoice": "policy",
            "SignalChunk": "intent", "IntentEvidence": "intent", "ComfortRating": "display",
            "SessionControl": "operator", "EpisodeRecorded": "recorder",
            "GoalRefused": "sim"}  # fmt: skip


def _session(writer: Writer) -> dict[str, int]:
    """Register every message type's channel and write one valid message on each;
    the channel ids by topic."""
    writer.start(profile="dammrl", library="crafted")
    writer.add_metadata("dammrl.session", {"namespace": NAMESPACE, "mode": "virtual"})
    channels = {}
    for n, message in enumerate(EXAMPLES):
        topic = key(NAMESPACE, type(message), "sim")
        schema = writer.register_schema(type(message).__name__, "jsonschema", b"{}")
        channels[topic] = writer.register_channel(topic, "msgpack", schema)
        source = _SOURCES.get(type(message).__name__, "controller")
        writer.add_message(channels[topic], 1_000 + n, _valid(message, 0, source), 1_000 + n, 0)
    return channels


def _with_writer(extra: Callable[[Writer, dict[str, int]], None]) -> bytes:
    stream = io.BytesIO()
    writer = Writer(stream, chunk_size=1024, compression=CompressionType.ZSTD)
    channels = _session(writer)
    extra(writer, channels)
    writer.finish()  # type: ignore[no-untyped-call]
    return stream.getvalue()


def _on_state(payload: bytes) -> Callable[[Writer, dict[str, int]], None]:
    def add(writer: Writer, channels: dict[str, int]) -> None:
        writer.add_message(channels[f"{NAMESPACE}/robot/state"], 5_000, payload, 5_000, 1)

    return add


def _state(seq: int, source: str = "sim") -> bytes:
    return _valid(EXAMPLES[0], seq, source)


def _unknown_channel(writer: Writer, channels: dict[str, int]) -> None:
    writer.add_message(99, 5_000, _state(1), 5_000, 1)


def _unknown_schema(writer: Writer, channels: dict[str, int]) -> None:
    channel = writer.register_channel(f"{NAMESPACE}/robot/command", "msgpack", 42)
    writer.add_message(channel, 5_000, _valid(EXAMPLES[1], 1, "controller"), 5_000, 1)


def _fuzzed_seq(writer: Writer, channels: dict[str, int]) -> None:
    """A real publisher's 0..9 with one fuzz message claiming seq 2**32 - 1 in between."""
    state = channels[f"{NAMESPACE}/robot/state"]
    for seq in range(1, 10):
        if seq == 5:
            writer.add_message(state, 5_000 + seq, _state(2**32 - 1), 5_000 + seq, 2**32 - 1)
        writer.add_message(state, 5_010 + seq, _state(seq), 5_010 + seq, seq)


def _twenty_times_fuzzed(writer: Writer, channels: dict[str, int]) -> None:
    for _ in range(20):
        _fuzzed_seq(writer, channels)


def _corrupt_first_chunk(data: bytes) -> bytes:
    """Overwrite the middle of the first chunk's compressed data (its framing intact)."""
    index = make_reader(io.BytesIO(data)).get_summary().chunk_indexes[0]  # type: ignore[union-attr]
    middle = index.chunk_start_offset + index.chunk_length // 2
    return data[:middle] + b"\xff" * 16 + data[middle + 16 :]


def _records(*records: Channel | Chunk | Header | Message) -> bytes:
    builder = RecordBuilder()
    for record in records:
        record.write(builder)
    return bytes(builder.end())  # type: ignore[no-untyped-call]


def _unknown_compression() -> bytes:
    chunk = Chunk(compression="brotli", data=b"\x01\x02\x03", message_end_time=0,
                  message_start_time=0, uncompressed_crc=0, uncompressed_size=99)  # fmt: skip
    return MAGIC + _records(Header("dammrl", "crafted"), chunk)


def _non_utf8_topic(complete: bytes) -> bytes:
    """A channel record whose topic is not UTF-8, right after the header of a good file."""
    after_header = len(MAGIC) + 9 + int.from_bytes(complete[9:17], "little")
    topic = b"dammrl/\xff\xfe"
    body = (77).to_bytes(2, "little") + (0).to_bytes(2, "little")
    body += len(topic).to_bytes(4, "little") + topic
    body += (7).to_bytes(4, "little") + b"msgpack" + (0).to_bytes(4, "little")
    channel = bytes([Opcode.CHANNEL]) + len(body).to_bytes(8, "little") + body
    return complete[:after_header] + channel + complete[after_header:]


def _huge_record_length() -> bytes:
    return MAGIC + _records(Header("dammrl", "crafted")) + b"\x07" + (2**62).to_bytes(8, "little")


def crafted_bytes() -> dict[str, bytes]:
    """Every crafted case: name -> file content."""
    complete = _with_writer(lambda w, c: None)
    cut = _with_writer(_twenty_times_fuzzed)
    return {
        "empty file": b"",
        "half the magic": MAGIC[:4],
        "magic only": MAGIC,
        "cut inside the header record": complete[:20],
        "cut in the middle of a chunk": cut[: len(cut) // 2],
        "not an MCAP file": b"not an mcap file at all, just text\n" * 4,
        "non-map payload (an int) on a typed channel": _with_writer(_on_state(msgpack.packb(5))),
        "non-map payload (a list) on a typed channel": _with_writer(_on_state(msgpack.packb([1]))),
        "not msgpack on a typed channel": _with_writer(_on_state(b"\xc1\xc1")),
        "header that is not a map": _with_writer(_on_state(msgpack.packb({"header": 5}))),
        "message on an unknown channel id": _with_writer(_unknown_channel),
        "channel with an unknown schema id": _with_writer(_unknown_schema),
        "fuzzed sequence number": _with_writer(_fuzzed_seq),
        "corrupt chunk data": _corrupt_first_chunk(_with_writer(_fuzzed_seq)),
        "unknown chunk compression": _unknown_compression(),
        "non-UTF-8 topic": _non_utf8_topic(complete),
        "record length of 2**62": _huge_record_length(),
    }


def crafted_files(folder: Path) -> dict[str, Path]:
    """Write every crafted case into ``folder``: name -> path."""
    paths = {}
    for n, (name, data) in enumerate(crafted_bytes().items()):
        paths[name] = folder / f"crafted-{n:02d}.mcap"
        paths[name].write_bytes(data)
    return paths


# ---- every recording tool on every crafted file ------------------------------------
UNREADABLE = {"empty file", "half the magic", "magic only", "cut inside the header record",
              "not an MCAP file"}  # fmt: skip
TOOLS = {
    "info": ["recording", "info", "{file}"],
    "info --json": ["recording", "info", "{file}", "--json"],
    "repair": ["recording", "repair", "{file}", "-o", "{out}/repaired.mcap"],
    "export json": ["recording", "export", "{file}", "--format", "json", "-o", "{out}/x.mcap"],
    "export csv": ["recording", "export", "{file}", "--format", "csv", "-o", "{out}/csv"],
    "human": ["recording", "human", "{file}"],
    "plot": ["recording", "plot", "{file}", "-o", "{out}/plot.png"],
}


@pytest.fixture(scope="module")
def crafted(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return crafted_files(tmp_path_factory.mktemp("crafted"))


@pytest.mark.parametrize("tool", TOOLS)
def test_every_recording_tool_answers_every_crafted_file_in_one_line(
    tool: str, crafted: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for n, (name, path) in enumerate(crafted.items()):
        out = tmp_path / str(n)
        out.mkdir()
        code = main([arg.format(file=path, out=out) for arg in TOOLS[tool]])  # no exception
        err = capsys.readouterr().err
        if name in UNREADABLE:
            assert code == 3, name
            assert err.startswith(f"dammrl: error: {path} is not an MCAP recording: "), name
            assert err.count("\n") == 1 and not err.rstrip().endswith(":"), name
        else:  # read up to the damage, the damage skipped and counted
            assert code == 0 or (tool == "plot" and code == 1), (name, err)


def test_info_counts_what_it_skipped_in_a_crafted_file(crafted: dict[str, Path]) -> None:
    assert info(crafted["message on an unknown channel id"])["skipped"] == {
        "messages on an undeclared channel": 1
    }
    non_map = info(crafted["non-map payload (an int) on a typed channel"])
    assert non_map["sequence_anomalies"] == {"no_valid_header": {"dammrl/robot/state": 1}}
    fuzzed = info(crafted["fuzzed sequence number"])
    assert fuzzed["sequence_gaps"] == {}
    assert fuzzed["sequence_anomalies"] == {"implausible_jumps": {"dammrl/robot/state": 1}}
    assert info(crafted["non-UTF-8 topic"])["skipped"] == {"CHANNEL records": 1}
    assert info(crafted["unknown chunk compression"])["skipped"] == {
        "chunks with unknown compression 'brotli'": 1
    }


def test_replay_selects_only_readable_messages_of_every_crafted_file(
    crafted: dict[str, Path],
) -> None:
    for name, path in crafted.items():
        if name not in UNREADABLE:
            recording = read_recording(path)
            chosen = selected(recording, ReplayOptions())
            assert len(chosen) <= len(recording.messages)
            assert all(topic not in ("safety/stop", "session/control") for topic, _, _ in chosen)


# ---- the recorder as a process ------------------------------------------------------
def _recorder(port: int, out: Path, log: Path, **env: str) -> subprocess.Popen[bytes]:
    environment = os.environ | {"DAMMRL_BUS_CONNECT": json.dumps([endpoint(port)]),
                                "DAMMRL_RECORDER_OUT": str(out)} | env  # fmt: skip
    with open(log, "wb") as stderr:
        return subprocess.Popen([sys.executable, "-m", "services.recorder"], env=environment,
                                stdin=subprocess.DEVNULL, stderr=stderr)  # fmt: skip


def _recorder_health(observer: Observer) -> list[Health]:
    return [h for h in observer.of(Health) if isinstance(h, Health) and h.service == "recorder"]


def _publish(session: zenoh.Session, rate_hz: float, stop: threading.Event,
             payload: Callable[[int], bytes]) -> None:  # fmt: skip
    publisher = session.declare_publisher("dammrl/robot/state")
    seq, start = 0, time.perf_counter()
    while not stop.is_set():
        publisher.put(payload(seq))
        seq += 1
        stop.wait(max(0.0, start + seq / rate_hz - time.perf_counter()))


@pytest.fixture()
def stream(request: pytest.FixtureRequest) -> Iterator[tuple[int, Observer, threading.Event]]:
    """A loopback bus with the test's observer, and a stop for the test's publisher."""
    port = free_port()
    observer = Observer(port)
    stop = threading.Event()
    yield port, observer, stop
    stop.set()
    observer.close()


@pytest.mark.slow
def test_a_killed_recorder_loses_at_most_about_chunk_s(
    stream: tuple[int, Observer, threading.Event], tmp_path: Path
) -> None:
    port, observer, stop = stream
    path = tmp_path / "killed.mcap"
    recorder = _recorder(port, path, tmp_path / "log", DAMMRL_RECORDER_CHUNK_S="0.5")
    try:
        wait_for(lambda: bool(_recorder_health(observer)), 30, "the recorder")
        args = (observer.session, 200.0, stop, _state)
        threading.Thread(target=_publish, args=args, daemon=True).start()
        time.sleep(2.0)  # far from the first 1 MB chunk
        killed_ns = time.time_ns()
        recorder.send_signal(signal.SIGKILL)
    finally:
        recorder.wait(10)
    recording = read_recording(path)
    lost_s = (killed_ns - max(m.log_time for m in recording.messages)) * 1e-9
    assert len(recording.messages) > 100 and lost_s < 1.0


@pytest.fixture()
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 256 KiB tmpfs, unmounted after the test."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs (a disk that fills up) needs root")
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)],
                             capture_output=True, text=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {mounted.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


@pytest.mark.slow
def test_a_full_disk_degrades_the_recorder_which_resumes_when_space_comes_back(
    stream: tuple[int, Observer, threading.Event], small_disk: Path, tmp_path: Path
) -> None:
    port, observer, stop = stream
    log = tmp_path / "recorder.log"
    fast = {"DAMMRL_RECORDER_CHUNK_S": "0.1", "DAMMRL_RECORDER_RETRY_S": "0.5",
            "DAMMRL_BUS_HEALTH_PERIOD_S": "0.2"}  # fmt: skip
    recorder = _recorder(port, small_disk, log, **fast)
    try:
        wait_for(lambda: bool(_recorder_health(observer)), 30, "the recorder")
        # incompressible, within the key's size limit (a larger payload is not recorded)
        size = LIMITS["robot/state"].max_bytes // 2
        noise = (observer.session, 800_000 / size, stop, lambda seq: os.urandom(size))
        threading.Thread(target=_publish, args=noise, daemon=True).start()  # full in ~0.2 s
        wait_for(lambda: _recorder_health(observer)[-1].state == "degraded", 15, "degraded")
        time.sleep(1.5)  # several retries on the full disk
        assert recorder.poll() is None  # alive: the session goes on
        detail = _recorder_health(observer)[-1].detail
        assert "No space left on device" in detail and "messages not recorded" in detail
        stop.set()
        subprocess.run(["mount", "-o", "remount,size=8m", str(small_disk)], check=True)
        wait_for(lambda: _recorder_health(observer)[-1].state == "ok", 15, "recording again")
        recorder.send_signal(signal.SIGINT)
        assert recorder.wait(15) == 0
    finally:
        if recorder.poll() is None:
            recorder.kill()
    text = log.read_text()
    assert "Traceback" not in text
    assert text.count("No space left on device") == 1, text  # one line, not one per retry
    files = sorted(small_disk.glob("*.mcap"))
    assert len(files) == 2  # the cut one, readable up to its last chunk, and the new one
    assert not info(files[0])["complete"] and info(files[1])["complete"]
    assert info(files[0])["messages"] > 0


# ---- Ctrl-C ----------------------------------------------------------------------------
@pytest.mark.slow
def test_replay_loop_ends_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {}, chunk_bytes=4096)
    for seq in range(50):
        recorder.record("dammrl/robot/state", _state(seq), seq * 10_000_000)
    recorder.finish()
    port = free_port()
    observer = Observer(port, namespace="replayed")
    replay = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "replay", str(path), "--loop", "--rate", "4",
         "--namespace", "replayed", "--connect", endpoint(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        wait_for(lambda: len(observer.received) > 60, 30, "a second round of the loop")
        replay.send_signal(signal.SIGINT)
        out, err = replay.communicate(timeout=10)
    finally:
        if replay.poll() is None:
            replay.kill()
        observer.close()
    assert replay.returncode == 0, err
    assert "Traceback" not in err and out.startswith("replayed ")


@pytest.mark.slow
def test_replay_of_a_crafted_file_publishes_what_is_readable(
    crafted: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    observer = Observer(port, namespace="replayed")
    try:
        for name in (
            "message on an unknown channel id",
            "non-map payload (a list) on a typed channel",
        ):
            argv = ["replay", str(crafted[name]), "--rate", "0", "--namespace", "replayed",
                    "--connect", endpoint(port)]  # fmt: skip
            assert main(argv) == 0, capsys.readouterr().err
    finally:
        observer.close()
    replayable = len(EXAMPLES) - 2  # one message per topic; an operator's acts never replay
    assert f"replayed {replayable} messages" in capsys.readouterr().out


def test_dammrl_up_restarts_a_killed_recorder_into_a_new_file_and_completes_the_cut_one(
    tmp_path: Path,
) -> None:
    """With a person attached the session must not depend on its logger: kill -9 of the
    recorder under `dammrl up` leaves the episodes running; the cut file is completed
    where it is (mcap's default reader reads it) and a new recorder writes the next."""
    port, record = free_port(), tmp_path / "session.mcap"
    launcher = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "up", "--episodes", "2", "--model", "2,1",
         "--bus-port", str(port), "--record", str(record), "--insecure"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_for(lambda: record.exists() and record.stat().st_size > 20_000, 90, "a recording")
        recorder = subprocess.run(
            ["pgrep", "-P", str(launcher.pid), "-f", "services.recorder"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.split()
        os.kill(int(recorder[0]), signal.SIGKILL)
        out, err = launcher.communicate(timeout=240)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert launcher.returncode == 0, err
    assert "recorder exited with code -9: restarted into a new file" in err
    assert len([line for line in out.splitlines() if line.startswith("episode ")]) == 2
    second = tmp_path / "session-001.mcap"
    for path in (record, second):
        with open(path, "rb") as stream:  # mcap's own default reader, no repair
            assert sum(1 for _ in make_reader(stream).iter_messages()) > 100
    assert info(record)["complete"] and info(second)["complete"]
