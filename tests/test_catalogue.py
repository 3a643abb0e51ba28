"""The session catalogue, the clinical reports and the BIDS export on recordings written
here (the recorder's own writer): rebuilt identically, attempts numbered, bad input refused.
``tests/test_session_outcomes.py`` runs the whole path on real sessions."""

from __future__ import annotations

import gzip
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from dammrl.data.bids import export
from dammrl.data.catalogue import CatalogueError, build, query, trials_of
from dammrl.data.outcomes import participant_report
from dammrl.stack.recording import read_recording
from schemas import (
    ComfortRating,
    EmergencyStop,
    EpisodeResult,
    Header,
    RobotState,
    SensorSample,
    SessionControl,
    SignalChunk,
    TaskGoal,
    encode,
    key,
)
from services.recorder.core import McapRecorder
from tests.test_schemas import EXAMPLES

VALIDATOR = shutil.which("bids-validator-deno") or str(
    Path(sys.executable).parent / "bids-validator-deno"
)
"""The official BIDS validator (from PyPI, runs offline)."""
RESULT = next(m for m in EXAMPLES if isinstance(m, EpisodeResult))
GOAL = next(m for m in EXAMPLES if isinstance(m, TaskGoal))
STATE = next(m for m in EXAMPLES if isinstance(m, RobotState))
MS = 1_000_000


SOURCES = {RobotState: "sim", SessionControl: "tool", ComfortRating: "tool",
           EmergencyStop: "tool", SensorSample: "intent", SignalChunk: "intent"}  # fmt: skip
"""Who publishes what (the rest: the controller)."""


def _put(recorder: McapRecorder, message: Any, log_ns: int, seq: int) -> None:
    header = Header(stamp_ns=log_ns, seq=seq, source=SOURCES.get(type(message), "controller"))
    recorder.record(
        key("dammrl", type(message), "x"),
        encode(message.model_copy(update={"header": header})),
        log_ns,
    )


def write_run(
    path: Path,
    study: dict[str, Any],
    reaches: list[tuple[int, float]],
    t0_ns: int,
    extra: Sequence[Any] = (),
    during: Sequence[Any] = (),
    goal_heard_late_ns: int = 0,
) -> None:
    """A stack run's recording: for each (episode, time) a goal, 20 states on a straight
    line over that time (``during`` messages among them) and its result; then ``extra``
    messages. The goal logged ``goal_heard_late_ns`` after the arm's reset state, if asked."""
    path.parent.mkdir(parents=True, exist_ok=True)
    recorder = McapRecorder(
        path, "dammrl", {"mode": "virtual", "study": json.dumps(study)}, chunk_bytes=4096
    )
    seq, now = 0, t0_ns
    for episode, t_total in reaches:
        goal = GOAL.model_copy(update={"episode": episode})
        _put(recorder, goal, now + goal_heard_late_ns, seq := seq + 1)
        for k in range(20):
            state = STATE.model_copy(
                update={
                    "episode": episode,
                    "t_s": t_total * k / 19,  # the reach's time on the robot's clock
                    "ee_pos_m": (0.3 + 0.001 * k, 0.0, 0.0),
                }
            )
            _put(recorder, state, now + k * 10 * MS, seq := seq + 1)
            if k < len(during):
                _put(recorder, during[k], now + k * 10 * MS + 1, seq := seq + 1)
        result = RESULT.model_copy(update={"episode": episode, "t_total_s": t_total})
        now += 300 * MS
        _put(recorder, result, now, seq := seq + 1)
        now += 100 * MS
    for message in extra:
        _put(recorder, message, now, seq := seq + 1)
    recorder.finish()


def _study(block: str, trials: list[int], session: str = "ses-01") -> dict[str, Any]:
    return {
        "participant": "P007",
        "session": session,
        "protocol": "p",
        "version": "1",
        "sha256": "ab" * 32,
        "block": block,
        "practice": False,
        "condition": {"trigger": "event", "policy": "learned"},
        "trials": trials,
    }


@pytest.fixture
def root(tmp_path: Path) -> Path:
    """P007: ses-01 ran trials 1-3 (trial 2 again, in a second run, after a console
    'again'), a comfort rating, a pause; ses-02 ran trials 1-2; and a stray file."""
    recordings = tmp_path / "P007" / "ses-01" / "recordings"
    pause = SessionControl(header=RESULT.header, episode=2, action="pause", who="T1", why="cough")
    comfort = ComfortRating(
        header=RESULT.header, participant="P007", block="b", trial=3, rating=4, asked_s=2.0
    )
    write_run(
        recordings / "part-01.mcap",
        _study("b", [1, 2, 3]),
        [(1, 5.0), (2, 6.0)],
        10_000 * MS,
        [pause],
    )
    write_run(
        recordings / "part-02.mcap",
        _study("b", [2, 3]),
        [(1, 7.0), (2, 8.0)],
        20_000 * MS,
        [comfort],
    )
    write_run(
        tmp_path / "P007" / "ses-02" / "recordings" / "part-01.mcap",
        _study("b", [1, 2], "ses-02"),
        [(1, 5.5), (2, 6.5)],
        90_000 * MS,
    )
    (recordings / "notes.mcap").write_bytes(b"not a recording")  # passed over
    return tmp_path


def dump_catalogue(root: Path) -> dict[str, list[tuple[Any, ...]]]:
    return {
        table: query(root, f"SELECT * FROM {table} ORDER BY ALL")[1]
        for table in ("participants", "sessions", "trials", "comfort", "actions")
    }


def test_the_catalogue_finds_every_reach_and_numbers_a_trial_run_again(root: Path) -> None:
    build(root)
    _, rows = query(
        root,
        "SELECT session, trial, attempt, final, t_total_s, recording "
        "FROM trials ORDER BY session, start_ns",
    )
    assert rows == [
        ("ses-01", 1, 1, True, 5.0, "P007/ses-01/recordings/part-01.mcap"),
        ("ses-01", 2, 1, False, 6.0, "P007/ses-01/recordings/part-01.mcap"),
        ("ses-01", 2, 2, True, 7.0, "P007/ses-01/recordings/part-02.mcap"),
        ("ses-01", 3, 1, True, 8.0, "P007/ses-01/recordings/part-02.mcap"),
        ("ses-02", 1, 1, True, 5.5, "P007/ses-02/recordings/part-01.mcap"),
        ("ses-02", 2, 1, True, 6.5, "P007/ses-02/recordings/part-01.mcap"),
    ]
    _, sessions = query(root, "SELECT session, trials, recordings FROM sessions ORDER BY 1")
    assert sessions == [("ses-01", 3, 2), ("ses-02", 2, 1)]
    assert query(root, "SELECT trial, rating FROM comfort")[1] == [(3, 4)]
    assert query(root, "SELECT trial, action, who, why FROM actions")[1] == [
        (2, "pause", "T1", "cough")
    ]
    parquet = root / "catalogue" / "trials" / "participant=P007" / "session=ses-01"
    assert len(list(parquet.glob("*.parquet"))) == 1


def test_every_row_points_at_its_reach_in_the_recording(root: Path) -> None:
    build(root)
    _, rows = query(root, "SELECT recording, start_ns, end_ns FROM trials WHERE final")
    for recording, start_ns, end_ns in rows:
        assert (root / recording).is_file() and 0 < end_ns - start_ns < 1e9


def test_a_deleted_catalogue_is_rebuilt_identically(root: Path) -> None:
    build(root)
    first = dump_catalogue(root)
    (root / "catalogue" / "catalogue.duckdb").unlink()
    build(root)
    assert dump_catalogue(root) == first and first["trials"]


def test_the_trials_can_be_filtered_by_participant_day_and_condition(root: Path) -> None:
    build(root)
    assert len(trials_of(root, "p007")[1]) == 5  # final attempts, any case of the id
    assert trials_of(root, "P008")[1] == []
    assert len(trials_of(root, condition="learned")[1]) == 5  # the block's policy
    assert len(trials_of(root, condition="fixed")[1]) == 5  # the trigger the reaches ran
    assert trials_of(root, condition="event")[1] == []
    assert trials_of(root, since="2999-01-01")[1] == []
    with pytest.raises(CatalogueError, match="YYYY-MM-DD"):
        trials_of(root, since="last tuesday")


def test_the_catalogue_is_read_only_and_a_missing_one_says_how_to_build_it(root: Path) -> None:
    with pytest.raises(CatalogueError, match="dammrl session catalogue"):
        query(root, "SELECT 1")
    build(root)
    with pytest.raises(CatalogueError, match="query refused"):
        query(root, "DELETE FROM trials")
    with pytest.raises(CatalogueError, match="query refused"):
        query(root, "SELECT * FROM no_such_table")


def test_a_cut_recording_gives_the_reaches_before_the_cut(root: Path) -> None:
    path = root / "P007" / "ses-02" / "recordings" / "part-01.mcap"
    data = path.read_bytes()
    for size in range(len(data), 0, -64):  # cut where the second reach's result is lost
        path.write_bytes(data[:size])
        if [m.episode for _, m in read_recording(path).decoded(EpisodeResult)] == [1]:
            break
    build(root)
    _, rows = query(root, "SELECT trial FROM trials WHERE session = 'ses-02' ORDER BY 1")
    assert rows == [(1,)]


def test_the_reports_are_written_with_their_figures(root: Path, tmp_path: Path) -> None:
    build(root)
    report = participant_report(root, "P007", tmp_path / "reports")
    text = report.read_text()
    assert "## Test-retest reliability" in text and "ses-01, ses-02" in text
    for name in (
        "P007.html",
        "P007_trends.png",
        "P007_ses-01.md",
        "P007_ses-01.html",
        "P007_ses-01_blocks.png",
        "P007_ses-02.md",
    ):
        assert (tmp_path / "reports" / name).stat().st_size > 0
    session = (tmp_path / "reports" / "P007_ses-01.md").read_text()
    assert "2 (again)" not in session and "1 (again)" in session  # the first try of trial 2
    assert "4" in session.split("comfort (1-5)")[1]  # the rating in the block's row
    with pytest.raises(CatalogueError, match="no trials of P009"):
        participant_report(root, "P009", tmp_path / "reports")


def test_the_bids_export_has_a_run_per_reach_and_never_deletes_a_folder_of_others(
    root: Path, tmp_path: Path
) -> None:
    build(root)
    out = tmp_path / "bids"
    assert export(root, out).counts() == {"participants": 1, "sessions": 2, "runs": 6}
    motion = sorted((out / "sub-P007" / "ses-01" / "motion").glob("*_motion.tsv"))
    assert len(motion) == 4 and len(motion[0].read_text().splitlines()) == 20
    assert (out / "participants.tsv").read_text() == "participant_id\nsub-P007\n"
    export(root, out)  # an earlier export of ours is replaced
    other = tmp_path / "thesis"
    other.mkdir()
    (other / "chapter1.tex").write_text("precious")
    with pytest.raises(CatalogueError, match="not empty"):
        export(root, other)
    assert (other / "chapter1.tex").read_text() == "precious"


def test_an_arms_state_heard_before_its_reachs_goal_is_still_exported(tmp_path: Path) -> None:
    """The recorder hears the goal and the arm's reset state on separate subscribers: on a
    loaded machine the reset state (and the next) can be logged first. No row is lost."""
    write_run(tmp_path / "P007" / "ses-01" / "recordings" / "part-01.mcap", _study("b", [1, 2]),
              [(1, 5.0), (2, 6.0)], 10_000 * MS, goal_heard_late_ns=15 * MS)  # fmt: skip
    build(tmp_path)
    export(tmp_path, tmp_path / "bids")
    motion = sorted((tmp_path / "bids" / "sub-P007" / "ses-01" / "motion").glob("*_motion.tsv"))
    assert [len(m.read_text().splitlines()) for m in motion] == [20, 20]


def test_the_persons_raw_input_is_exported_as_physio_beside_the_motion(tmp_path: Path) -> None:
    """The pad's samples and a wearable's chunks recorded during a reach become
    ``beh/..._recording-pressure_physio.tsv.gz`` and ``..._recording-wearable_...``; a lost
    wearable sample is n/a, never an empty cell; the validator accepts them (when here)."""
    sample = next(m for m in EXAMPLES if isinstance(m, SensorSample))
    chunk = next(m for m in EXAMPLES if isinstance(m, SignalChunk))
    t0 = 10_000 * MS
    chunk = chunk.model_copy(update={"stamps_ns": [t0 + k * MS for k in range(20)]})
    write_run(
        tmp_path / "P007" / "ses-01" / "recordings" / "part-01.mcap",
        _study("b", [1]),
        [(1, 5.0)],
        t0,
        [],
        during=[sample] * 5 + [chunk],
    )
    build(tmp_path)
    export(tmp_path, tmp_path / "bids")
    beh = tmp_path / "bids" / "sub-P007" / "ses-01" / "beh"
    pressure = beh / "sub-P007_ses-01_task-reach_run-01_recording-pressure_physio.tsv.gz"
    wearable = beh / "sub-P007_ses-01_task-reach_run-01_recording-wearable_physio.tsv.gz"
    assert len(gzip.decompress(pressure.read_bytes()).decode().splitlines()) == 5
    lines = gzip.decompress(wearable.read_bytes()).decode().splitlines()
    assert len(lines) == 20 and lines[3].endswith("\tn/a") and "\t\t" not in "".join(lines)
    columns = json.loads(wearable.with_name(wearable.name.replace(".tsv.gz", ".json")).read_text())[
        "Columns"
    ]
    assert columns == ["time", *(f"ch{c}" for c in range(1, 9))]
    if Path(VALIDATOR).exists():
        report = subprocess.run(
            [VALIDATOR, str(tmp_path / "bids"), "--format", "json"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        issues = json.loads(report.stdout)["issues"]["issues"]
        assert [i for i in issues if i["severity"] == "error"] == []


@pytest.mark.parametrize(
    "tag",
    [
        {"participant": "P008"},  # another participant's folder
        {"session": "ses-02"},  # another session's
        {"participant": "../../etc"},  # a path, not a pseudonym
        {"trials": ["one"]},
        {"sha256": "not a hash"},
    ],
)
def test_a_recording_whose_study_tag_is_invalid_or_misplaced_is_passed_over(
    tmp_path: Path, tag: dict[str, Any]
) -> None:
    """A file copied into another participant's folder, or crafted, joins no one's data;
    the build says which and why, and keeps everyone else's."""
    recordings = tmp_path / "P007" / "ses-01" / "recordings"
    write_run(recordings / "part-01.mcap", _study("b", [1]), [(1, 5.0)], 10_000 * MS)
    write_run(recordings / "part-02.mcap", _study("b", [2]) | tag, [(1, 6.0)], 20_000 * MS)
    built = build(tmp_path)
    assert len(built.passed_over) == 1 and "part-02.mcap" in built.passed_over[0]
    assert query(tmp_path, "SELECT trial FROM trials")[1] == [(1,)]


def test_html_in_a_recorded_value_stays_text_in_the_report(root: Path, tmp_path: Path) -> None:
    """A protocol version is free text: a crafted one must not become markup (a script)
    in the HTML report a clinician opens."""
    recordings = root / "P007" / "ses-03" / "recordings"
    crafted = _study("b", [1], "ses-03") | {"version": "<script>alert(1)</script>"}
    write_run(recordings / "part-01.mcap", crafted, [(1, 5.0)], 200_000 * MS)
    build(root)
    participant_report(root, "P007", tmp_path / "reports")
    page = (tmp_path / "reports" / "P007.html").read_text()
    assert "<script>" not in page and "&lt;script&gt;" in page


def test_a_reason_with_tabs_and_newlines_keeps_the_events_file_one_row_per_event(
    root: Path, tmp_path: Path
) -> None:
    recordings = root / "P007" / "ses-04" / "recordings"
    pause = SessionControl(
        header=RESULT.header,
        episode=1,
        action="pause",
        who="T1",
        why="the patient\tcoughs\nand asks\r\nfor water",
    )
    write_run(
        recordings / "part-01.mcap",
        _study("b", [1], "ses-04"),
        [(1, 5.0)],
        300_000 * MS,
        during=[pause],
    )
    build(root)
    export(root, tmp_path / "bids")
    events = next((tmp_path / "bids" / "sub-P007" / "ses-04").rglob("*_events.tsv"))
    rows = [line.split("\t") for line in events.read_text().splitlines()]
    assert all(len(row) == 6 for row in rows)
    assert any(row[-1] == "the patient coughs and asks for water" for row in rows)


def test_a_recording_newer_than_the_catalogue_is_in_the_next_answer(
    root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session run after the last build: `dammrl sessions trials` rebuilds first and
    says so on stderr (its stdout stays the answer)."""
    from dammrl.cli import main
    from dammrl.data.catalogue import stale

    assert stale(root)
    build(root)
    assert not stale(root)
    later = root / "P007" / "ses-02" / "recordings" / "part-02.mcap"
    write_run(later, _study("b", [3], "ses-02"), [(1, 9.0)], 95_000 * MS)
    os.utime(later, (time.time() + 5, time.time() + 5))  # a file system's coarse clock
    assert stale(root)
    assert main(["sessions", "trials", "--root", str(root), "--participant", "P007", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "rebuilding it" in err and len(out.splitlines()) == 6
    assert all(json.loads(line)["participant"] == "P007" for line in out.splitlines())
