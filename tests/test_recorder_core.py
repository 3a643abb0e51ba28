"""The MCAP writer core, without a bus: channels, invalid payloads, gaps, flushes, cut files."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest
from mcap.reader import make_reader

from dammrl.stack.recording import RecordingError, info, read_recording, repair
from schemas import Header, encode
from services.recorder.config import RecorderSettings
from services.recorder.core import McapRecorder
from services.recorder.gaps import SequenceAccount, publishers_of
from tests.test_schemas import EXAMPLES

STATE = EXAMPLES[0]
KEY = "dammrl/robot/state"
MS = 1_000_000  # [ns]


def _state(seq: int, source: str = "sim") -> bytes:
    header = Header(stamp_ns=1_000 + seq * MS, seq=seq, source=source)  # 1 kHz
    return encode(STATE.model_copy(update={"header": header}))


def test_every_payload_is_kept_and_gaps_are_counted(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=4096)
    for seq in (0, 1, 2, 5, 6):  # 3 and 4 were lost
        recorder.record(KEY, _state(seq), 2_000 + seq)
    recorder.record(KEY, _state(0, source="sim2"), 2_010)  # not the key's publisher
    recorder.record(KEY, b"\x00garbage", 2_020)
    recorder.record("dammrl/robot/command", bytes(msgpack.packb({"no": "header"})), 2_030)
    recorder.finish()
    summary = info(path)
    assert summary["complete"]
    assert summary["topics"][KEY] == {
        "type": "RobotState", "count": 6, "rate_hz": pytest.approx(5 / 10e-9)
    }  # fmt: skip
    assert summary["topics"][f"_invalid/{KEY}"]["count"] == 1
    assert summary["topics"]["_invalid/dammrl/robot/command"]["count"] == 1
    assert summary["sequence_gaps"] == {KEY: 2}
    assert summary["sequence_anomalies"] == {"foreign_source": {KEY: 1}}
    assert recorder.loss.gaps[KEY] == 2
    assert summary["metadata"]["dammrl.loss"]["gaps"] == '{"dammrl/robot/state": 2}'
    recording = read_recording(path)
    assert [m.data for m in recording.messages][:1] == [_state(0)]  # the bytes as they came
    assert recording.messages[0].publish_time == 1_000  # the header stamp


# ---- sequence accounting ------------------------------------------------------------
def test_the_publishers_of_a_key_is_the_role_allowed_to_publish_it() -> None:
    assert publishers_of("dammrl", KEY) == {"sim", "robot"}
    assert publishers_of("dammrl", "dammrl/task/goal") == {"controller"}
    assert publishers_of("dammrl", "dammrl/health/intent") == {"intent"}
    assert publishers_of("dammrl", "dammrl/elsewhere") is None
    assert publishers_of("lab2", KEY) is None


def test_a_fuzzed_sequence_number_is_an_anomaly_not_four_billion_lost_messages() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(10):
        account.see(KEY, "sim", seq, seq * MS)
        if seq == 4:
            assert account.see(KEY, "sim", 2**32 - 1, seq * MS + 1) == 0  # the fuzz
    assert account.gaps == {}
    assert account.anomalies() == {"implausible_jumps": {KEY: 1}}
    assert account.messages[KEY] == 11


def test_a_restarted_publisher_starts_a_new_stream() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(500, 510):
        account.see(KEY, "sim", seq, seq * MS)
    for seq in (0, 1, 3):  # the restarted sim: 2 was lost
        account.see(KEY, "sim", seq, 600 * MS + seq * MS)
    assert account.gaps == {KEY: 1}
    assert account.anomalies() == {"restarts": {KEY: 1}}


def test_a_forged_source_cannot_touch_the_real_publishers_counts() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(20):
        account.see(KEY, "sim", seq, seq * MS)
        account.see(KEY, "intruder", 10**9 - seq, seq * MS)  # wrong source, wild seqs
    assert account.gaps == {}
    assert account.anomalies() == {"foreign_source": {KEY: 20}}


def test_a_real_outage_is_counted_as_missing_once_the_stream_goes_on() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(600):  # 1.2 s at 500 Hz
        account.see(KEY, "sim", seq, seq * 2 * MS)
    assert account.see(KEY, "sim", 1600, 3_200 * MS) == 0  # 2 s without state: pending
    assert account.see(KEY, "sim", 1601, 3_202 * MS) == 1000  # it goes on: loss
    assert account.gaps == {KEY: 1000} and account.anomalies() == {}


def test_a_forged_number_between_real_ones_is_a_jump_not_loss() -> None:
    """One task/goal with seq 1000 from the controller's own role after 60 s of silence,
    then the real controller goes on (the adversary's measurement: 976 'lost')."""
    account = SequenceAccount("dammrl")
    goal = "dammrl/task/goal"
    for seq in range(24):  # announced every 0.5 s
        account.see(goal, "controller", seq, seq * 500 * MS)
    account.see(goal, "controller", 1000, 70_000 * MS)
    account.see(goal, "controller", 24, 75_000 * MS)
    account.see(goal, "controller", 25, 75_500 * MS)
    assert account.gaps == {}
    assert account.anomalies() == {"implausible_jumps": {goal: 1}}


def test_a_slow_publisher_cannot_be_made_to_lose_more_than_its_rate_allows() -> None:
    """Two consecutive forged numbers far ahead of a 2 Hz stream: a new stream (jump)."""
    account = SequenceAccount("dammrl")
    goal = "dammrl/task/goal"
    for seq in range(10):
        account.see(goal, "controller", seq, seq * 500 * MS)
    account.see(goal, "controller", 1000, 65_000 * MS)
    account.see(goal, "controller", 1001, 65_100 * MS)
    assert account.gaps == {}
    assert account.anomalies() == {"implausible_jumps": {goal: 1}}


def test_streams_of_two_zenoh_sessions_are_kept_apart() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(5):
        account.see(KEY, "sim", seq, seq * MS, session="a")
        account.see(KEY, "sim", 100 + seq, seq * MS, session="b")
    assert account.gaps == {} and account.anomalies() == {}


def test_a_loss_received_in_a_burst_after_a_stall_is_loss_not_a_jump() -> None:
    """The re-test's 19 states: the recorder stalled, the backlog came in a burst and the
    publisher had dropped 19 states meanwhile (their stamps tell; receipt times do not)."""
    account = SequenceAccount("dammrl")
    for seq in range(300):  # 100 Hz, received on time
        account.see(KEY, "sim", seq, seq * 10 * MS, stamp_ns=seq * 10 * MS)
    burst_ns = 3_400 * MS  # a stall of 0.4 s: 300-329 queued, 330-348 dropped, then on
    for i, seq in enumerate([*range(300, 330), *range(349, 400)]):
        account.see(KEY, "sim", seq, burst_ns + i * 10_000, stamp_ns=seq * 10 * MS)
    assert account.gaps == {KEY: 19} and account.anomalies() == {}


def test_messages_coming_late_by_another_route_fill_their_hole() -> None:
    """A restarted recorder hears a state through the launcher's router first, then the
    sim's own link is up and its newest states overtake the router's backlog: what the
    backlog brings is not missing (the re-test: 1,463 counted, 148 missing)."""
    account = SequenceAccount("dammrl")
    sent = {seq: seq * 10 * MS for seq in range(5000, 7000)}
    arrivals = [5000, *range(6463, 6600)]  # the router's first, then the direct link
    arrivals += list(range(5001, 6316))  # the router's backlog, late (6316-6462 lost)
    arrivals += list(range(6600, 7000))
    for i, seq in enumerate(arrivals):
        account.see(KEY, "sim", seq, 70_000 * MS + i * MS, stamp_ns=sent[seq])
    assert account.gaps == {KEY: 6462 - 6316 + 1}
    assert set(account.anomalies()) == {"late"}


def test_the_same_message_by_two_routes_is_a_duplicate_not_a_restart() -> None:
    account = SequenceAccount("dammrl")
    for seq in range(200):
        account.see(KEY, "sim", seq, seq * 10 * MS, stamp_ns=seq * 10 * MS)
        account.see(KEY, "sim", seq, seq * 10 * MS + 3 * MS, stamp_ns=seq * 10 * MS)
    assert account.gaps == {} and account.anomalies() == {"duplicates": {KEY: 200}}


def test_a_restarted_publishers_numbers_never_fill_the_old_streams_holes() -> None:
    account = SequenceAccount("dammrl")
    for seq in (*range(0, 50), *range(60, 100)):  # 50-59 lost
        account.see(KEY, "sim", seq, seq * 10 * MS, stamp_ns=seq * 10 * MS)
    for seq in range(80):  # restarted 5 s later: 0, 1, ... sent anew
        at = 6_000 * MS + seq * 10 * MS
        account.see(KEY, "sim", seq, at, stamp_ns=at)
    assert account.gaps == {KEY: 10}
    assert account.anomalies() == {"restarts": {KEY: 1}}


def test_forged_numbers_with_stamps_from_the_future_are_a_jump_not_loss() -> None:
    account = SequenceAccount("dammrl")
    goal = "dammrl/task/goal"
    for seq in range(10):  # 2 Hz
        account.see(goal, "controller", seq, seq * 500 * MS, stamp_ns=seq * 500 * MS)
    for seq in (1000, 1001):  # stamped an hour ahead: clamped to their receipt
        account.see(goal, "controller", seq, 6_000 * MS, stamp_ns=3_600_000 * MS)
    account.see(goal, "controller", 10, 6_500 * MS, stamp_ns=6_500 * MS)
    assert account.gaps == {}
    assert account.anomalies() == {"implausible_jumps": {goal: 1}}


def test_a_recording_that_ends_right_after_a_loss_counts_it() -> None:
    account = SequenceAccount("dammrl")
    for seq in (*range(100), 130):  # 100-129 lost, then the recorder was stopped
        account.see(KEY, "sim", seq, seq * 10 * MS, stamp_ns=seq * 10 * MS)
    assert account.gaps == {KEY: 30} and account.anomalies() == {}


def test_a_plausible_forged_number_the_publisher_then_contradicts_is_no_loss() -> None:
    """On a slow key, after a silence long enough to make it plausible, one number far
    ahead: the real publisher then goes on from its own last number."""
    account = SequenceAccount("dammrl")
    goal = "dammrl/task/goal"
    for seq in range(24):  # 2 Hz
        account.see(goal, "controller", seq, seq * 500 * MS, stamp_ns=seq * 500 * MS)
    account.see(goal, "controller", 74, 21_000 * MS, stamp_ns=21_000 * MS)  # 50 ahead
    for seq in range(24, 40):
        at = 21_500 * MS + seq * 500 * MS
        account.see(goal, "controller", seq, at, stamp_ns=at)
    assert account.gaps == {}
    assert account.anomalies()["implausible_jumps"] == {goal: 1}


@pytest.mark.parametrize("seed", range(20))
def test_any_arrival_order_counts_what_the_sequence_numbers_lack(seed: int) -> None:
    """A 100 Hz stream with random losses, each message delayed at random by up to
    0.5 s (two routes, stalls): the account is exactly the numbers never received."""
    import numpy as np

    rng = np.random.default_rng(seed)
    sent = np.arange(2000) * 10 * MS
    kept = np.flatnonzero(rng.random(2000) > rng.uniform(0, 0.2))
    for burst in rng.integers(0, 1900, 3):  # a few runs of consecutive losses
        kept = kept[(kept < burst) | (kept > burst + rng.integers(1, 40))]
    kept = np.union1d(kept, np.arange(1995, 2000))  # it goes on after its last loss
    received = sent[kept] + rng.uniform(0, 500 * MS, len(kept)).astype(int)
    account = SequenceAccount("dammrl")
    for index in np.argsort(received, kind="stable"):
        seq = int(kept[index])
        account.see(KEY, "sim", seq, int(received[index]), stamp_ns=int(sent[seq]))
    expected = int(kept[-1] - kept[0] + 1 - len(kept))
    assert account.gaps.get(KEY, 0) == expected
    assert "restarts" not in account.anomalies() and "implausible_jumps" not in account.anomalies()


# ---- what reaches the disk -----------------------------------------------------------
def test_the_chunk_age_bound_is_a_finite_setting_of_at_most_a_second_by_default() -> None:
    assert RecorderSettings().chunk_s <= 1.0
    with pytest.raises(ValueError, match="DAMMRL_RECORDER_CHUNK_S"):
        RecorderSettings(chunk_s=float("inf"))


def test_a_new_file_is_a_readable_recording_at_once(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=1_000_000)  # never finished
    recording = read_recording(path)
    assert recording.metadata["dammrl.session"]["mode"] == "virtual"
    assert not recording.complete and recording.messages == []


def test_a_chunk_is_closed_by_age_and_reaches_the_os(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {}, chunk_bytes=1_000_000)
    for seq in range(50):
        recorder.record(KEY, _state(seq), seq * 10 * MS)
    assert not recorder.flush_due(690 * MS, chunk_s=0.7)
    assert recorder.flush_due(700 * MS, chunk_s=0.7)
    recorder.flush()
    assert not recorder.flush_due(10**12, chunk_s=0.7)  # nothing unflushed
    copy = tmp_path / "as-the-os-has-it.mcap"
    shutil.copy(path, copy)  # what a kill -9 now would leave
    assert len(read_recording(copy).messages) == 50


# ---- damaged files -------------------------------------------------------------------
def _chunked(path: Path, chunks: int, per_chunk: int) -> None:
    recorder = McapRecorder(path, "dammrl", {}, chunk_bytes=1_000_000)
    for seq in range(chunks * per_chunk):
        recorder.record(KEY, _state(seq), seq * MS)
        if seq % per_chunk == per_chunk - 1:
            recorder.flush()
    recorder.finish()


def test_a_file_cut_mid_chunk_is_read_and_repaired_up_to_its_last_complete_chunk(
    tmp_path: Path,
) -> None:
    path = tmp_path / "r.mcap"
    _chunked(path, chunks=5, per_chunk=40)
    with open(path, "rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes  # type: ignore[union-attr]
    last = chunks[-1]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: last.chunk_start_offset + last.chunk_length // 2])
    summary = info(cut)
    assert not summary["complete"] and summary["messages"] == 4 * 40
    assert f"inside the CHUNK record at byte {last.chunk_start_offset}" in summary["truncated"]
    done = repair(cut, tmp_path / "fixed.mcap")
    assert done["messages"] == 160 and info(tmp_path / "fixed.mcap")["complete"]


def test_a_corrupt_chunk_is_skipped_and_the_chunks_after_it_are_read(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    _chunked(path, chunks=5, per_chunk=40)
    with open(path, "rb") as stream:
        second = make_reader(stream).get_summary().chunk_indexes[1]  # type: ignore[union-attr]
    data = bytearray(path.read_bytes())
    middle = second.chunk_start_offset + second.chunk_length // 2
    data[middle : middle + 8] = b"\xff" * 8  # its framing intact, its content not
    path.write_bytes(bytes(data))
    summary = info(path)
    assert summary["messages"] == 4 * 40 and summary["complete"]
    assert summary["skipped"] == {"chunks that do not decompress or fail their CRC": 1}
    assert summary["sequence_gaps"] == {KEY: 40}  # the lost chunk, as missing messages


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"", "the file is empty (0 bytes): nothing reached the disk"),
        (b"\x89MCA", "cut at byte 4, inside the 8-byte MCAP magic"),
        (b"\x89MCAP0\r\n", "cut at byte 8, right after the MCAP magic"),
        (b"not an mcap file at all", "it does not start with the MCAP magic (found b'not an m')"),
    ],
    ids=["empty", "half magic", "magic only", "text"],
)
def test_a_file_that_is_no_recording_is_a_one_line_reason(
    tmp_path: Path, content: bytes, reason: str
) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="not an MCAP recording: ") as error:
        info(path)
    assert reason in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(RecordingError, match="does not exist"):
        info(tmp_path / "missing.mcap")


# ---- a file any reader opens, whenever the recorder is killed ------------------------------
class _Syscalls:
    """The recorder's file writes, logged (and done) so that every moment a kill could pick
    is replayed: before each call, and inside a write that spans pages (the kernel stops
    a killed write only between pages)."""

    def __init__(self) -> None:
        import os

        self.os = os
        self.calls: list[tuple[str, object, int]] = []
        self.committed: list[int] = []  # messages in the file after each commit

    def pwrite(self, fd: int, data: bytes, offset: int) -> int:
        self.calls.append(("pwrite", bytes(data), offset))
        return self.os.pwrite(fd, data, offset)

    def ftruncate(self, fd: int, length: int) -> None:
        self.calls.append(("truncate", b"", length))
        self.os.ftruncate(fd, length)

    def rename(self, source: object, target: object) -> None:
        self.calls.append(("rename", b"", 0))
        self.os.rename(source, target)  # type: ignore[arg-type]

    def __getattr__(self, name: str) -> object:
        return getattr(self.os, name)

    def moments(self) -> Iterator[tuple[bool, bytes, int]]:
        """(the file exists, its bytes, calls completed) at every moment a kill could pick."""
        from services.recorder.tail import PAGE

        content, exists = bytearray(), False
        for done, (kind, data, offset) in enumerate(self.calls):
            yield exists, bytes(content), done
            if kind == "pwrite":
                assert isinstance(data, bytes)
                cuts = range(PAGE - offset % PAGE, len(data), PAGE)
                for cut in cuts:  # killed inside the write, between two pages
                    yield exists, bytes(_written(content, data[:cut], offset)), done
                content = _written(content, data, offset)
            elif kind == "truncate":
                del content[offset:]
            else:
                exists = True
        yield exists, bytes(content), len(self.calls)


def _written(content: bytearray, data: bytes, offset: int) -> bytearray:
    out = bytearray(content)
    if len(out) < offset + len(data):
        out.extend(bytes(offset + len(data) - len(out)))
    out[offset : offset + len(data)] = data
    return out


def test_a_recorder_killed_at_any_moment_leaves_a_file_mcaps_default_reader_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every moment of a recording (its start, chunks closed by size and by age, the rare
    messages flushed at once, its finish), replayed: mcap's own reader opens the file, reads
    every message of the last commit that began before, and nothing else."""
    import io

    from services.recorder.tail import CommittedFile

    syscalls = _Syscalls()
    monkeypatch.setattr("services.recorder.tail.os", syscalls)
    recorded = [0]
    commits: list[tuple[int, int]] = []  # (calls done when a commit ended, messages in it)
    commit = CommittedFile.commit

    def logged(self: CommittedFile) -> None:
        commit(self)
        commits.append((len(syscalls.calls), recorded[0]))

    monkeypatch.setattr(CommittedFile, "commit", logged)
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=4096)
    for seq in range(400):
        recorded[0] = seq + 1
        recorder.record(KEY, _state(seq), seq * MS)
        if seq % 97 == 96:
            recorder.flush()  # by age
    recorder.finish()
    commits.append((len(syscalls.calls), 400))
    assert len(commits) > 20  # many commits: by size, by age, the finish
    checked = 0
    for exists, content, calls in syscalls.moments():
        if not exists:
            continue  # killed before the first commit: no file at all, never a broken one
        floor = max(n for done, n in commits if done <= calls)
        messages = list(make_reader(io.BytesIO(content)).iter_messages())
        assert len(messages) >= floor, (calls, len(messages), floor)
        assert [m.sequence for _, _, m in messages] == list(range(len(messages)))
        checked += 1
    assert checked > 100
    assert info(path)["complete"] and info(path)["messages"] == 400


def test_a_header_whose_source_is_no_string_is_kept_as_invalid_not_a_crash(tmp_path: Path) -> None:
    """A list as the header's source made the episode ledger's membership test raise
    (unhashable): the recorder died and lost what it had not yet written."""
    from services.recorder.episodes import EpisodeLedger

    odd = msgpack.unpackb(_state(0))
    odd["header"]["source"] = ["sim"]
    payload = bytes(msgpack.packb(odd))
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=4096)
    recorder.record(KEY, payload, 2_000)
    recorder.record(KEY, _state(1), 2_001)
    recorder.finish()
    EpisodeLedger("dammrl").written(KEY, payload, 0.0)  # ignored, no TypeError
    summary = info(path)
    assert summary["topics"][f"_invalid/{KEY}"]["count"] == 1
    assert summary["topics"][KEY]["count"] == 1


class _AckBus:
    """The recorder node's bus in-process: what it publishes is kept (its acknowledgements)."""

    namespace = "dammrl"

    class _Session:
        def declare_subscriber(self, *args: object) -> None: ...

    session = _Session()

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def publisher(self, kind: type) -> _AckBus:
        return self

    def stamp(self) -> Header:
        return Header(stamp_ns=1, seq=len(self.sent), source="recorder")

    def send(self, message: Any) -> None:
        self.sent.append(message)

    def report_health(self, *args: object, **kwargs: object) -> None: ...


def test_what_a_write_error_lost_is_never_acknowledged_complete(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk filled before the chunk holding an episode's decision was on it: the chunk
    was lost, the recorder wrote on in a new file once space came back, and the episode's
    acknowledgement said complete (the session took it as on disk)."""
    import errno
    import time

    from schemas import EpisodeResult, Intent, RobotState, TaskGoal, key
    from services.recorder import tail
    from services.recorder.node import RecorderNode

    def sent(kind: type, source: str, seq: int, **fields: Any) -> tuple[int, tuple[Any, ...]]:
        stamp = time.time_ns()
        header = {"stamp_ns": stamp, "seq": seq, "source": source}
        payload = bytes(msgpack.packb({"header": header, **fields}))
        return stamp, (key("dammrl", kind), payload, time.time_ns(), "")

    def full(*args: object) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    bus = _AckBus()
    node = RecorderNode(RecorderSettings(out=tmp_path / "out.mcap", retry_s=0.1), bus)  # type: ignore[arg-type]
    for message in (sent(TaskGoal, "controller", 0, episode=1),
                    sent(RobotState, "sim", 0, episode=1, t_s=1.0),
                    sent(Intent, "intent", 0, episode=1, request=1)):  # fmt: skip
        node._write(message[1])  # type: ignore[arg-type]
    with monkeypatch.context() as disk:
        disk.setattr(tail.os, "pwrite", full)
        assert node.recorder is not None
        node.recorder.unflushed_ns = 0  # its chunk is due: its write fails
        node._keep_up()
        assert node.recorder is None
    time.sleep(0.15)
    node._keep_up()  # space again: a new file
    assert node.recorder is not None
    state_ns, last = sent(RobotState, "sim", 1, episode=1, t_s=9.0)
    node._write(last)  # type: ignore[arg-type]
    node._write(sent(EpisodeResult, "controller", 0, episode=1, n_decisions=1,  # type: ignore[arg-type]
                     last_state_stamp_ns=state_ns)[1])  # fmt: skip
    node.episodes.wait_s = 0.0  # an incomplete one is said at once
    node._acknowledge()
    node._close()
    [ack] = bus.sent
    assert not ack.complete and "what a write error lost (out.mcap: " in ack.missing


def test_acknowledgements_a_failed_sync_held_back_go_out_later(tmp_path: Path) -> None:
    """They were marked said before the sync that failed, and never sent."""
    from services.recorder.episodes import EpisodeLedger

    ledger = EpisodeLedger("dammrl", wait_s=0.0)
    result = msgpack.packb({"header": {"stamp_ns": 1, "seq": 0, "source": "controller"},
                            "episode": 1, "n_decisions": 0})  # fmt: skip
    ledger.written("dammrl/task/result", bytes(result), 0.0)
    [ack] = ledger.due(1.0)
    assert ack.complete and ledger.due(2.0) == []
    ledger.not_acknowledged([1])
    assert [a.episode for a in ledger.due(3.0)] == [1]
