"""The MCAP writer core, without a bus: channels, invalid payloads, gaps, cut files."""

from __future__ import annotations

from pathlib import Path

import msgpack
import pytest

from dammrl.recording import RecordingError, info, read_recording
from schemas import Header, encode
from services.recorder.core import McapRecorder
from tests.test_schemas import EXAMPLES

STATE = EXAMPLES[0]


def _state(seq: int, source: str = "sim") -> bytes:
    header = Header(stamp_ns=1_000 + seq, seq=seq, source=source)
    return encode(STATE.model_copy(update={"header": header}))


def test_every_payload_is_kept_and_gaps_are_counted(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {"mode": "virtual"}, chunk_bytes=4096)
    for seq in (0, 1, 2, 5, 6):  # 3 and 4 were lost
        recorder.record("dammrl/robot/state", _state(seq), 2_000 + seq)
    recorder.record("dammrl/robot/state", _state(0, source="sim2"), 2_010)  # another publisher
    recorder.record("dammrl/robot/state", b"\x00garbage", 2_020)
    recorder.record("dammrl/robot/command", bytes(msgpack.packb({"no": "header"})), 2_030)
    recorder.finish()
    summary = info(path)
    assert summary["complete"]
    assert summary["topics"]["dammrl/robot/state"] == {
        "type": "RobotState", "count": 6, "rate_hz": pytest.approx(5 / 10e-9)
    }  # fmt: skip
    assert summary["topics"]["_invalid/dammrl/robot/state"]["count"] == 1
    assert summary["topics"]["_invalid/dammrl/robot/command"]["count"] == 1
    assert summary["sequence_gaps"] == {"dammrl/robot/state": 2}
    assert recorder.loss.gaps["dammrl/robot/state"] == 2
    recording = read_recording(path)
    assert [m.data for m in recording.messages][:1] == [_state(0)]  # the bytes as they came
    assert recording.messages[0].publish_time == 1_000  # the header stamp


def test_a_file_cut_mid_chunk_is_read_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    recorder = McapRecorder(path, "dammrl", {}, chunk_bytes=4096)
    for seq in range(400):
        recorder.record("dammrl/robot/state", _state(seq), 2_000 + seq)
    recorder._stream.flush()
    size = path.stat().st_size
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: size // 2])  # through the middle of a chunk
    summary = info(cut)
    assert not summary["complete"]
    assert 0 < summary["messages"] < 400


def test_a_file_that_is_not_mcap_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="not an MCAP recording"):
        info(path)
    with pytest.raises(RecordingError, match="does not exist"):
        info(tmp_path / "missing.mcap")
