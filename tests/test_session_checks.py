"""Before anyone is enrolled: a protocol checked completely (one plain line per problem,
naming the field and what it allows; ``dammrl session check``), pseudonyms matched whole,
and counterbalancing rows from an append-only enrolment ledger that a withdrawal never
shifts."""

from __future__ import annotations

import io
import json
import shutil
import threading
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

from dammrl.cli import main
from dammrl.people.enrolment import Ledger
from dammrl.people.participants import JsonLines, Participant, check_participant
from dammrl.people.session import SessionRunner, SetUp
from dammrl_core.errors import UsageError
from dammrl_core.protocol import ProtocolError, load_protocol
from tests.sessionutil import PROTOCOL, ScriptedStack, reset, write_protocol

BROKEN = """\
format: 1
name: broken
version: "1"
blocks:
  - {name: long, trials: 1000, seed: 1}
  - {name: odd, trials: 2, seed: 1, condition: {trigger: sometimes}, speed: 2}
  - {trials: 2, seed: 1, practice: maybe}
"""


def test_every_problem_of_a_protocol_is_one_plain_line_naming_the_field_and_its_values(
    tmp_path: Path,
) -> None:
    with pytest.raises(ProtocolError) as caught:
        load_protocol(write_protocol(tmp_path, BROKEN))
    assert list(caught.value.problems) == [
        "block 1 (long): trials: 1000 is not allowed; it takes a whole number from 1 to 500",
        "block 2 (odd): condition.trigger: 'sometimes' is not allowed; it takes one of event, "
        "fixed",
        "block 2 (odd): speed: unknown key; allowed keys: name, trials, seed, condition, "
        "practice, rest_s, instructions",
        "block 3: name: missing; it takes letters, digits, '_', '.' and '-' of at most 64 "
        "characters",
        "block 3: practice: 'maybe' is not allowed; it takes true or false",
    ]  # no pydantic text, no links, no "blocks: at least 1 item" after the real errors
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("change", "setup", "says"),
    [
        (("condition: {trigger: event}", "condition: {intent: telepathy}"), SetUp(),
         "block 2 (event): condition.intent 'telepathy' is no installed intent source; "
         "allowed: lsl, pad, simulated"),
        (("seed: 200, condition: {trigger: event}", "seed: 2147483646, condition: {}"),
         SetUp(), "seed 2147483646 with 3 trials runs to seed 2147483648"),
        (("condition: {trigger: event}", "condition: {intent: pad}"), SetUp(),
         "block 2 (event): --intent pad needs --port"),
        (("condition: {trigger: event}", "condition: {intent: lsl}"),
         SetUp(mode="semi-virtual", intent="pad", pad_port="/dev/ttyPAD"),
         "needs --stream"),
        (("", ""), SetUp(mode="semi-virtual", intent="lsl", stream="EMG"),
         "blocks 1 (practice), 2 (event), 3 (fixed): --stream needs --calibration"),
        (("", ""), SetUp(lockstep=True, mode="semi-virtual", intent="pad", pad_port="/dev/x"),
         "--lockstep is for simulation only"),
    ],
)  # fmt: skip
def test_a_protocol_that_cannot_run_fails_before_anyone_is_enrolled(
    tmp_path: Path, change: tuple[str, str], setup: SetUp, says: str
) -> None:
    protocol = write_protocol(tmp_path, PROTOCOL.replace(*change))
    root = tmp_path / "sessions"
    with pytest.raises(ProtocolError) as caught:
        SessionRunner(root, "P001", protocol, setup, say=lambda _: None,
                      wait_for_operator=False, console=io.StringIO()).run()  # fmt: skip
    assert any(says in problem for problem in caught.value.problems), caught.value.problems
    assert not root.exists()  # nobody enrolled, no row used, no session to resume


def test_session_check_says_every_problem_on_its_own_line_and_ok_for_the_shipped_protocol(
    tmp_path: Path,
) -> None:
    err, out = io.StringIO(), io.StringIO()
    with redirect_stderr(err), redirect_stdout(out):
        code = main(["session", "check", str(write_protocol(tmp_path, BROKEN))])
        shipped = main(["session", "check", "event-vs-fixed"])
    lines = err.getvalue().splitlines()
    assert code == 3 and lines[0].endswith("5 problems") and len(lines) == 6
    assert lines[2].startswith("  block 2 (odd): condition.trigger")
    assert (
        shipped == 0 and "event-vs-fixed.yaml: ok (event-vs-fixed 1.0: 3 blocks" in out.getvalue()
    )


@pytest.mark.parametrize("bad", ["P7\n", "P7 ", " P7", "P7\r", "P7\x00"])
def test_an_id_with_anything_after_it_is_no_pseudonym(tmp_path: Path, bad: str) -> None:
    with pytest.raises(UsageError, match="pseudonymous"):
        check_participant(bad)
    with pytest.raises(UsageError):
        Participant(tmp_path, bad)
    assert not list(tmp_path.iterdir())


def test_the_ledger_after_a_withdrawal_shifts_nobody(tmp_path: Path) -> None:
    """The issue's sequence: rehearse with T001, enrol P001, delete T001 as the docs once
    said, enrol P002: P002 got P001's row when rows counted folders."""
    root = tmp_path / "sessions"
    assert Participant(root, "T001").enrol()["row"] == 0
    assert Participant(root, "P001").enrol()["row"] == 1
    assert Ledger(root).withdraw("T001", "a rehearsal") == 0
    shutil.rmtree(root / "T001")
    assert Participant(root, "P002").enrol()["row"] == 2  # not 1: rows are used once
    shutil.rmtree(root / "P001")  # a folder lost: their row is still theirs
    assert Participant(root, "P001").enrol()["row"] == 1
    with pytest.raises(UsageError, match="withdrew"):
        Participant(root, "T001").enrol()
    with pytest.raises(UsageError, match="already withdrew"):
        Ledger(root).withdraw("T001", "again")
    lines = [json.loads(line) for line in (root / "enrolment.jsonl").read_text().splitlines()]
    assert [(e["participant"], e.get("row"), e.get("withdrawn")) for e in lines] == [
        ("T001", 0, None), ("P001", 1, None), ("T001", None, "a rehearsal"), ("P002", 2, None)
    ]  # fmt: skip


def test_a_rehearsal_takes_no_row_and_runs_the_order_the_next_participant_will(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("dammrl.people.session.Stack", ScriptedStack)
    scripted = reset(ScriptedStack)
    root, protocol = tmp_path / "sessions", write_protocol(tmp_path)
    Participant(root, "P001").enrol()
    rehearsal = SessionRunner(root, "T001", protocol, SetUp(rehearsal=True),
                              say=lambda _: None, wait_for_operator=False,
                              console=io.StringIO())  # fmt: skip
    assert rehearsal.run() == 0
    rehearsed = [o.trigger for o in scripted.runs]
    scripted.runs.clear()
    assert SessionRunner(root, "P002", protocol, SetUp(), say=lambda _: None,
                         wait_for_operator=False, console=io.StringIO()).run() == 0  # fmt: skip
    assert [o.trigger for o in scripted.runs] == rehearsed == ["event", "fixed", "event"]
    assert Ledger(root).next_row() == 2  # the rehearsal used none
    with pytest.raises(UsageError, match="rehearsal"):
        Participant(root, "T001").enrol()


def test_a_root_made_before_the_ledger_keeps_every_participants_row(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    for participant, row in (("P003", 0), ("P001", 1), ("P002", 2)):
        (root / participant).mkdir(parents=True)
        record = {"id": participant, "row": row, "calibration": None}
        (root / participant / "participant.json").write_text(json.dumps(record))
    assert Participant(root, "P004").enrol()["row"] == 3
    assert Participant(root, "P001").enrol()["row"] == 1
    assert [e.participant for e in Ledger(root).entries()] == ["P003", "P001", "P002", "P004"]


def test_sessions_enrolling_at_once_get_a_row_each(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    rows: list[int] = []
    threads = [threading.Thread(target=lambda n=n: rows.append(Ledger(root).enrol(f"P{n:03d}")))
               for n in range(12)]  # fmt: skip
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert sorted(rows) == list(range(12))


def test_a_torn_line_is_dropped_and_never_swallows_the_next_entry(tmp_path: Path) -> None:
    root = tmp_path / "sessions"
    Ledger(root).enrol("P001")
    with open(root / "enrolment.jsonl", "a") as handle:
        handle.write('{"participant": "P00')  # a kill mid-append: never acknowledged
    assert Ledger(root).enrol("P002") == 1
    assert [e.participant for e in Ledger(root).entries()] == ["P001", "P002"]
    log = JsonLines(tmp_path / "trials.jsonl")
    log.add({"trial": 1})
    with open(log.path, "a") as handle:
        handle.write('{"trial": 2, "res')
    log.add({"trial": 3})
    assert log.read() == ([{"trial": 1}, {"trial": 3}], 1)


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["session", "run", "--participant", "P1", "--protocol", "event-vs-fixed",
          "--outcome-s", "31"],
         "argument --outcome-s: '31': the outcome is held 0 to 30 s"),
        (["up", "--display", "--outcome-s", "nan"],
         "argument --outcome-s: 'nan': the outcome is held 0 to 30 s"),
        (["up", "--large-text"], "--large-text and --outcome-s are the participant display's"),
        (["up", "--outcome-s", "1"], "give --display with them"),
    ],
)  # fmt: skip
def test_the_display_settings_are_refused_in_one_line_out_of_range_or_without_a_display(
    argv: list[str], said: str
) -> None:
    err = io.StringIO()
    with redirect_stderr(err), redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exit_:  # argparse's refusal
            code = exit_.code  # type: ignore[assignment]
    assert code != 0 and said in err.getvalue().splitlines()[-1], err.getvalue()


def test_a_stray_file_among_the_recordings_is_no_part_and_no_crash(tmp_path: Path) -> None:
    """A file manager's copy ("part-01 (copy).mcap") crashed the session's next run."""
    from dammrl.people.participants import SessionFolder

    folder = SessionFolder(tmp_path)
    folder.recordings.mkdir()
    for name in ("part-01.mcap", "part-02-001.mcap", "part-01 (copy).mcap", "part-x.mcap"):
        (folder.recordings / name).write_bytes(b"")
    assert folder.next_part().name == "part-03.mcap"
