"""The recorder says when an episode is on disk, and a session waits for it.

The ledger (``services.recorder.episodes``) is pure and tested on written messages; the
recorder as a process is tested on a loopback bus (slow): its acknowledgement comes only
once the result and the arm's state it was decided from are in the file, and a finished
file marks the episodes it saw begin without their result (a tail it never received).
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from dammrl.stack.recorded import RecordedEpisodes
from dammrl.stack.recording import read_recording
from schemas import (
    EpisodeRecorded,
    EpisodeResult,
    Header,
    Intent,
    RobotState,
    TaskGoal,
    encode,
    key,
)
from services.recorder.episodes import METADATA, EpisodeLedger
from tests.busutil import Observer, free_port, wait_for
from tests.test_recorder_faults import _recorder
from tests.test_schemas import EXAMPLES

RESULT = next(m for m in EXAMPLES if isinstance(m, EpisodeResult))
GOAL = next(m for m in EXAMPLES if isinstance(m, TaskGoal))
STATE = next(m for m in EXAMPLES if isinstance(m, RobotState))
INTENT = next(m for m in EXAMPLES if isinstance(m, Intent))
SOURCE = {RobotState: "sim", TaskGoal: "controller", EpisodeResult: "controller",
          Intent: "intent"}  # fmt: skip


def _payload(message: Any, stamp_ns: int, seq: int, source: str | None = None) -> bytes:
    header = Header(stamp_ns=stamp_ns, seq=seq, source=source or SOURCE[type(message)])
    return encode(message.model_copy(update={"header": header}))


def _state(episode: int, stamp_ns: int, t_s: float = 1.0) -> tuple[str, bytes]:
    state = STATE.model_copy(update={"episode": episode, "t_s": t_s})
    return key("dammrl", RobotState), _payload(state, stamp_ns, stamp_ns)


def _result(episode: int, last_state_ns: int | None, source: str = "controller",
            decisions: int = 0) -> tuple[str, bytes]:  # fmt: skip
    result = RESULT.model_copy(update={"episode": episode, "last_state_stamp_ns": last_state_ns,
                                       "n_decisions": decisions})  # fmt: skip
    return key("dammrl", EpisodeResult), _payload(result, 10**9, 40 + episode, source)


def _intent(episode: int, request: int, source: str = "intent") -> tuple[str, bytes]:
    intent = INTENT.model_copy(update={"episode": episode, "request": request})
    return key("dammrl", Intent), _payload(intent, 10**9, 100 + request, source)


def _goal(episode: int) -> tuple[str, bytes]:
    return key("dammrl", TaskGoal), _payload(GOAL.model_copy(update={"episode": episode}), 1, 1)


def test_a_result_heard_before_its_last_state_is_acknowledged_only_with_that_state() -> None:
    ledger = EpisodeLedger("dammrl", wait_s=5.0)
    ledger.written(*_goal(1), now_s=0.0)
    ledger.written(*_state(1, 100), now_s=0.0)
    ledger.written(*_result(1, last_state_ns=300), now_s=0.0)
    assert ledger.due(now_s=1.0) == []  # the arm's states up to 300 are still on the way
    ledger.written(*_state(1, 200), now_s=1.0)
    assert ledger.due(now_s=1.5) == []
    ledger.written(*_state(1, 300, t_s=2.0), now_s=2.0)
    (ack,) = ledger.due(now_s=2.0)
    assert (ack.episode, ack.result_seq, ack.states, ack.complete) == (1, 41, 3, True)
    assert ledger.due(now_s=3.0) == []  # said once


def test_a_last_state_that_never_comes_is_acknowledged_as_missing_then_as_complete() -> None:
    ledger = EpisodeLedger("dammrl", wait_s=5.0)
    ledger.written(*_state(1, 100, t_s=4.23), now_s=0.0)
    ledger.written(*_result(1, last_state_ns=300), now_s=0.0)
    assert ledger.due(now_s=4.9) == []
    (ack,) = ledger.due(now_s=5.0)
    assert not ack.complete and "robot time 4.230 s" in ack.missing
    assert ledger.due(now_s=6.0) == []
    ledger.written(*_state(2, 400), now_s=7.0)  # the arm went on: the state was written
    (later,) = ledger.due(now_s=7.0)
    assert later.complete and later.episode == 1


def test_a_result_heard_before_its_last_decision_is_acknowledged_only_with_that_decision() -> None:
    """The intent service's link was slower than the controller's: the reach's last
    decision (an Intent answering its request) comes after the result that counts it."""
    ledger = EpisodeLedger("dammrl", wait_s=5.0)
    ledger.written(*_state(1, 100), now_s=0.0)
    ledger.written(*_intent(1, request=0), now_s=0.0)
    ledger.written(*_intent(1, request=0), now_s=0.0)  # a request answered again counts once
    ledger.written(*_intent(1, request=-1), now_s=0.0)  # unsolicited: no decision of a request
    ledger.written(*_intent(1, request=1, source="controller"), now_s=0.0)  # not its key's
    ledger.written(*_result(1, last_state_ns=100, decisions=2), now_s=0.0)
    assert ledger.due(now_s=1.0) == []
    (ack,) = ledger.due(now_s=5.0)
    assert not ack.complete and ack.missing == "1 of the 2 decisions its result counts"
    ledger.written(*_intent(1, request=1), now_s=6.0)
    (later,) = ledger.due(now_s=6.0)
    assert later.complete and later.episode == 1


def test_a_result_naming_no_state_is_acknowledged_at_once_and_a_forged_one_never() -> None:
    ledger = EpisodeLedger("dammrl")
    ledger.written(*_result(1, last_state_ns=None, source="intent"), now_s=0.0)  # not its key's
    assert ledger.due(now_s=100.0) == []
    ledger.written(*_result(1, last_state_ns=None), now_s=0.0)  # a controller before the field
    assert [a.complete for a in ledger.due(now_s=0.0)] == [True]
    ledger.written(key("dammrl", EpisodeResult), b"\xc1 not msgpack", now_s=0.0)
    assert ledger.due(now_s=100.0) == []


def test_a_finished_file_marks_the_episodes_it_saw_begin_without_their_result() -> None:
    ledger = EpisodeLedger("dammrl", wait_s=0.0)
    ledger.written(*_goal(1), now_s=0.0)
    ledger.written(*_state(1, 100), now_s=0.0)
    ledger.written(*_result(1, last_state_ns=100), now_s=0.0)
    ledger.written(*_goal(2), now_s=0.0)
    ledger.written(*_state(2, 200, t_s=4.23), now_s=0.0)
    ledger.written(*_result(3, last_state_ns=900), now_s=0.0)  # its states never came
    missing = "the robot state its result was decided from (the arm's states written reach none)"
    assert ledger.metadata() == {
        "results": "[1, 3]",
        "open_at_close": "[2]",
        "incomplete": json.dumps({"3": missing}),
    }
    assert ledger.metadata()["results"] == "[]"  # the next file starts afresh


@pytest.mark.slow
def test_the_recorder_acknowledges_an_episode_once_its_result_and_last_state_are_in_the_file(
    tmp_path: Path,
) -> None:
    """The result comes first (the controller's link was faster); the acknowledgement
    waits for the arm's state the result names and the decision it counts, and the file
    then holds them all."""
    port = free_port()
    observer = Observer(port)
    path = tmp_path / "part-01.mcap"
    recorder = _recorder(port, path, tmp_path / "log")
    try:
        wait_for(lambda: path.exists(), 30, "the recorder's file")
        session = observer.session
        time.sleep(1.0)  # the recorder's subscription reaches the hub
        now = time.time_ns()
        session.put(key("dammrl", TaskGoal),
                    _payload(GOAL.model_copy(update={"episode": 1}), now, 0))  # fmt: skip
        for k in range(5):
            session.put(*_state(1, now + k))
        result = RESULT.model_copy(update={"episode": 1, "last_state_stamp_ns": now + 9,
                                           "n_decisions": 1})  # fmt: skip
        session.put(key("dammrl", EpisodeResult), _payload(result, now + 10, 1))
        time.sleep(1.0)
        assert observer.of(EpisodeRecorded) == []  # the state it names is not there yet
        session.put(*_state(1, now + 9))
        time.sleep(1.0)
        assert observer.of(EpisodeRecorded) == []  # nor the decision it counts
        session.put(*_intent(1, request=0))
        wait_for(lambda: bool(observer.of(EpisodeRecorded)), 20, "the acknowledgement")
        (ack,) = observer.of(EpisodeRecorded)
        assert isinstance(ack, EpisodeRecorded)
        assert (ack.episode, ack.file, ack.states, ack.complete) == (1, path.name, 6, True)
        on_disk = read_recording(path)  # the recorder still runs: synced, readable
        assert [m.episode for _, m in on_disk.decoded(EpisodeResult)] == [1]
        assert max(s.header.stamp_ns for _, s in on_disk.decoded(RobotState)) == now + 9
        session.put(key("dammrl", TaskGoal),
                    _payload(GOAL.model_copy(update={"episode": 2}), now + 20, 2))  # fmt: skip
        session.put(*_state(2, now + 21))
        time.sleep(1.0)
    finally:
        recorder.send_signal(signal.SIGTERM)
        recorder.wait(20)
        observer.close()
    metadata = read_recording(path).metadata[METADATA]
    assert json.loads(metadata["results"]) == [1] and json.loads(metadata["open_at_close"]) == [2]


def _ack(episode: int, complete: bool, file: str = "run.mcap") -> EpisodeRecorded:
    header = Header(stamp_ns=1, seq=episode, source="recorder")
    return EpisodeRecorded(header=header, file=file, episode=episode, result_seq=1, states=1,
                           complete=complete, missing="" if complete else "a state")  # fmt: skip


def test_a_runs_wait_ends_with_its_episodes_confirmed_or_at_once_on_a_stop() -> None:
    recorded = RecordedEpisodes(Path("run.mcap"))
    recorded.take(_ack(1, complete=True, file="other.mcap"))  # another run's file
    recorded.take(_ack(2, complete=False))
    threading.Timer(0.2, recorded.take, [_ack(1, complete=True, file="run-001.mcap")]).start()
    started = time.monotonic()
    acks = recorded.wait([1, 2], timeout_s=1.0)  # 2 stays incomplete: the whole second
    assert 0.9 < time.monotonic() - started < 5.0
    assert {e: a.complete for e, a in acks.items()} == {1: True, 2: False}
    recorded.take(_ack(2, complete=True))  # a complete one supersedes it
    assert recorded.wait([1, 2], timeout_s=0.0)[2].complete
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    started = time.monotonic()
    assert recorded.wait([3], timeout_s=30.0, stop=stop) == {}  # Ctrl-C: no 30 s wait
    assert time.monotonic() - started < 5.0
