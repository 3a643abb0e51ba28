"""Nothing a participant did is lost without a word: each session's trial log reconciled
with its recordings (crafted with the recorder's own writer), every file checked before
use. ``tests/test_session_outcomes.py`` does the same on real lockstep sessions."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from dammrl.cli import main
from dammrl.data.catalogue import build, query
from dammrl.data.outcomes import session_report
from dammrl.stack.recording import read_recording
from schemas import EpisodeResult, Header, RobotState, encode, key
from services.recorder.core import McapRecorder
from services.recorder.episodes import METADATA, EpisodeLedger
from tests.test_catalogue import GOAL, MS, RESULT, STATE, _study, write_run

SESSION = Path("P007") / "ses-01"


def _log(root: Path, lines: list[dict[str, Any]]) -> None:
    """The session's trials.jsonl as the session runner writes it."""
    folder = root / SESSION
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "trials.jsonl", "a") as handle:
        for line in lines:
            handle.write(json.dumps(line) + "\n")


def _line(trial: int, episode: int, part: str = "part-01", t_total_s: float = 5.0
          ) -> dict[str, Any]:  # fmt: skip
    return {"trial": trial, "block": "b", "recording": f"recordings/{part}.mcap",
            "episode": episode, "result": {"t_total_s": t_total_s, "success": True}}  # fmt: skip


def _completeness(root: Path) -> list[tuple[Any, ...]]:
    return query(root, "SELECT trial, status, reason FROM completeness ORDER BY line, trial")[1]


@pytest.fixture
def three(tmp_path: Path) -> Path:
    """P007/ses-01: a run of trials 1-3, each logged."""
    write_run(tmp_path / SESSION / "recordings" / "part-01.mcap", _study("b", [1, 2, 3]),
              [(1, 5.0), (2, 6.0), (3, 6.88)], 10_000 * MS)  # fmt: skip
    _log(tmp_path, [_line(1, 1), _line(2, 2), _line(3, 3, t_total_s=6.88)])
    return tmp_path


def _cut_before_result(path: Path, episodes: list[int]) -> None:
    """Cut ``path`` where the results after ``episodes`` are lost."""
    data = path.read_bytes()
    for size in range(len(data), 0, -64):
        path.write_bytes(data[:size])
        if [m.episode for _, m in read_recording(path).decoded(EpisodeResult)] == episodes:
            return
    raise AssertionError("no cut keeps exactly those results")


def test_every_logged_trial_recorded_whole_is_said_so(three: Path) -> None:
    built = build(three)
    assert built.incomplete == [] and built.damaged == []
    assert [row[:2] for row in _completeness(three)] == [(1, "recorded"), (2, "recorded"),
                                                          (3, "recorded")]  # fmt: skip
    _, sessions = query(three, "SELECT reaches_logged, recorded_whole, missing FROM sessions")
    assert sessions == [(3, 3, 0)]


def test_a_recording_whose_tail_is_cut_has_its_trial_reported_missing(
    three: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    part = three / SESSION / "recordings" / "part-01.mcap"
    _cut_before_result(part, [1, 2])
    assert main(["sessions", "catalogue", "--root", str(three)]) == 0
    out, err = capsys.readouterr()
    assert "2 recorded whole, 0 in part, 1 missing from the recordings" in out
    assert "used in part P007/ses-01/recordings/part-01.mcap: cut at byte" in err
    assert "kept 2 reaches (trials 1, 2)" in err  # what was kept, by name
    (said,) = [line for line in err.splitlines() if "trial 3" in line]
    assert said.startswith("P007/ses-01 trial 3: missing from the recordings: part-01.mcap")
    assert "of 6.88 s and no result: the file is cut at byte" in said
    report = session_report(three, "P007", "ses-01", tmp_path / "reports").read_text()
    assert "**Data completeness:** 3 reaches in the trial log: 2 recorded whole, **1 missing" in (
        report
    )
    assert "| 3 | b | n/a | missing from the recordings |" in report  # no silent jump 2 -> 4


def _recorded_without_its_tail(path: Path, t0: int) -> None:
    """The issue's case: the recorder got the goal and the arm's states up to 4.23 s of a
    6.88 s reach, then nothing (the bus dropped the rest); its file ends cleanly."""
    path.parent.mkdir(parents=True)
    recorder = McapRecorder(path, "dammrl", {"study": json.dumps(_study("b", [1, 2]))}, 4096)
    ledger, seq = EpisodeLedger("dammrl"), 0

    def put(message: Any, log_ns: int, source: str) -> None:
        nonlocal seq
        seq += 1
        header = Header(stamp_ns=log_ns, seq=seq, source=source)
        topic, payload = key("dammrl", type(message)), encode(message.model_copy(
            update={"header": header}))  # fmt: skip
        recorder.record(topic, payload, log_ns)
        ledger.written(topic, payload, now_s=0.0)

    for episode, span_s in ((1, 5.0), (2, 4.23)):
        put(GOAL.model_copy(update={"episode": episode}), t0, "controller")
        for k in range(int(span_s / 0.01) + 1):
            put(STATE.model_copy(update={"episode": episode, "t_s": 0.01 * k}), t0 + k * 10 * MS,
                "sim")  # fmt: skip
        if episode == 1:
            last = t0 + int(span_s / 0.01) * 10 * MS
            put(RESULT.model_copy(update={"episode": 1, "last_state_stamp_ns": last}), last + 1,
                "controller")  # fmt: skip
        t0 += 10_000 * MS
    recorder.writer.add_metadata(METADATA, ledger.metadata())  # as the recorder node does
    recorder.finish()


def test_a_reach_the_recorder_never_heard_end_is_missing_with_what_it_holds(
    tmp_path: Path,
) -> None:
    _recorded_without_its_tail(tmp_path / SESSION / "recordings" / "part-01.mcap", 10_000 * MS)
    _log(tmp_path, [_line(1, 1), _line(2, 2, t_total_s=6.88)])
    built = build(tmp_path)
    assert _completeness(tmp_path)[1] == (
        2,
        "missing",
        "part-01.mcap holds its states up to 4.23 s of 6.88 s and no result: the recorder "
        "never received the reach's tail (the recorder closed the file with the reach open)",
    )
    assert built.incomplete == [f"P007/ses-01 trial 2: missing from the recordings: "
                                f"{_completeness(tmp_path)[1][2]}"]  # fmt: skip


def test_a_result_whose_last_states_never_came_is_recorded_in_part(tmp_path: Path) -> None:
    path = tmp_path / SESSION / "recordings" / "part-01.mcap"
    path.parent.mkdir(parents=True)
    recorder = McapRecorder(path, "dammrl", {"study": json.dumps(_study("b", [1]))}, 4096)
    t0 = 10_000 * MS
    for k in (0, 1, 2, 5, 6):  # states 3 and 4 lost inside, 7-9 never came
        state = STATE.model_copy(update={"episode": 1, "t_s": 0.01 * k,
                                         "header": Header(stamp_ns=t0 + k * 10 * MS, seq=k,
                                                          source="sim")})  # fmt: skip
        recorder.record(key("dammrl", RobotState), encode(state), t0 + k * 10 * MS)
    result = RESULT.model_copy(update={
        "episode": 1, "last_state_stamp_ns": t0 + 90 * MS,
        "header": Header(stamp_ns=t0 + 95 * MS, seq=0, source="controller")})  # fmt: skip
    recorder.record(key("dammrl", EpisodeResult), encode(result), t0 + 95 * MS)
    recorder.finish()
    _log(tmp_path, [_line(1, 1)])
    build(tmp_path)
    ((trial, status, reason),) = _completeness(tmp_path)
    assert (trial, status) == (1, "partial")
    assert reason == ("the arm's states stop 0.03 s before the one its result was decided from; "
                      "2 of its 7 arm states missing inside it")  # fmt: skip
    assert query(tmp_path, "SELECT count(*) FROM trials")[1] == [(1,)]  # its result counts


def test_logged_trials_without_their_recording_and_recorded_reaches_without_a_line(
    tmp_path: Path,
) -> None:
    """A line naming a recording that is gone; a line of a skipped trial; a reach the
    session recorded but never logged (it stopped before, and the trial ran again)."""
    write_run(tmp_path / SESSION / "recordings" / "part-01.mcap", _study("b", [1, 2]),
              [(1, 5.0), (2, 6.0)], 10_000 * MS)  # fmt: skip
    skipped = {"trial": 3, "block": "b", "result": None, "skipped": "T1: tired"}
    _log(tmp_path, [_line(1, 1), _line(2, 1, part="part-02"), skipped])
    build(tmp_path)
    assert _completeness(tmp_path) == [
        (1, "recorded", ""),
        (2, "missing", "its recording part-02.mcap does not exist"),
        (3, "skipped", "skipped by T1: tired"),
        (2, "unlogged", "the session stopped before logging it (the trial ran again)"),
    ]


def test_a_truncated_or_unreadable_recording_is_reported_by_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recordings = tmp_path / SESSION / "recordings"
    write_run(recordings / "part-01.mcap", _study("b", [1, 2]), [(1, 5.0), (2, 6.0)],
              10_000 * MS)  # fmt: skip
    (recordings / "part-02.mcap").write_bytes(b"\x89MCAP0\r\n")  # its start, then nothing
    (recordings / "part-03.mcap").write_bytes(b"")
    (recordings / "notes.mcap").write_bytes(b"a note")
    assert main(["sessions", "catalogue", "--root", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "passed over P007/ses-01/recordings/part-03.mcap: " in err and "0 bytes" in err
    assert "passed over P007/ses-01/recordings/notes.mcap: not read" in err
    assert "part-02.mcap" in err  # a start and no footer: no study tag
    _, files = query(tmp_path, "SELECT recording, used FROM recordings ORDER BY 1")
    assert files == [(f"P007/ses-01/recordings/part-0{n}.mcap", n == 1) for n in (1, 2, 3)]


@pytest.mark.parametrize(
    ("tag", "why"),
    [
        ({"participant": "P008"}, "its tag says P008/ses-01, its folder P007/ses-01"),
        ({"trials": [4, 5]}, "its tag names another run (block b, trials [4, 5])"),
    ],
)
def test_a_continuation_must_carry_its_runs_tag(tmp_path: Path, tag: dict[str, Any],
                                                why: str) -> None:  # fmt: skip
    """Another participant's part-01.mcap copied as P007's part-01-001.mcap (or another
    run's) joins nothing; the run's own continuation does."""
    recordings = tmp_path / SESSION / "recordings"
    write_run(recordings / "part-01.mcap", _study("b", [1, 2]), [(1, 5.0)], 10_000 * MS)
    write_run(recordings / "part-01-001.mcap", _study("b", [1, 2]), [(2, 6.0)], 20_000 * MS)
    write_run(recordings / "part-01-002.mcap", _study("b", [1, 2]) | tag, [(1, 9.0)],
              30_000 * MS)  # fmt: skip
    built = build(tmp_path)
    assert built.passed_over == [f"P007/ses-01/recordings/part-01-002.mcap: {why}"] or (
        built.passed_over[0].startswith(f"P007/ses-01/recordings/part-01-002.mcap: {why}")
    )
    _, rows = query(tmp_path, "SELECT trial, t_total_s, recording FROM trials ORDER BY 1")
    assert rows == [(1, 5.0, "P007/ses-01/recordings/part-01.mcap"),
                    (2, 6.0, "P007/ses-01/recordings/part-01-001.mcap")]  # fmt: skip


def test_the_catalogue_reads_each_recording_once(
    three: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import dammrl.data.catalogue.recordings as recordings

    write_run(three / SESSION / "recordings" / "part-01-001.mcap", _study("b", [1, 2, 3]),
              [(3, 7.0)], 60_000 * MS)  # fmt: skip
    read: list[Path] = []
    original = recordings.read_recording
    monkeypatch.setattr(recordings, "read_recording", lambda p: read.append(p) or original(p))
    build(three)
    assert sorted(p.name for p in read) == ["part-01-001.mcap", "part-01.mcap"]


def test_the_therapists_acts_are_each_their_own_action(tmp_path: Path) -> None:
    from schemas import EmergencyStop, SessionControl

    header = RESULT.header
    acts = [
        SessionControl(header=header, episode=1, action=action, who="T1", why="because")
        for action in ("pause", "resume", "skip", "again", "end-block", "take", "give")
    ]
    acts.append(SessionControl(header=header, episode=1, action="decide", who="T1", u_h=-1,
                               human_model=2))  # fmt: skip
    stop = header.model_copy(update={"source": "operator"})
    acts += [EmergencyStop(header=stop, engaged=True, reason="T1: the arm slipped"),
             EmergencyStop(header=stop, engaged=False, reason="T1: all clear")]  # fmt: skip
    write_run(tmp_path / SESSION / "recordings" / "part-01.mcap", _study("b", [1]), [(1, 5.0)],
              10_000 * MS, during=acts)  # fmt: skip
    build(tmp_path)
    _, rows = query(tmp_path, "SELECT trial, action, who, why, detail FROM actions ORDER BY log_ns")
    assert [r[1] for r in rows] == ["pause", "resume", "skip", "again", "end-block", "take",
                                    "give", "decide", "stop", "release"]  # fmt: skip
    assert rows[7] == (1, "decide", "T1", "", "back, radius small")
    assert rows[8] == (1, "stop", "T1", "the arm slipped", "")
