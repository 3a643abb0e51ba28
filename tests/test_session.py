"""Protocols, participants and sessions: the files, the counterbalancing, resumption (the
stack replaced by a scripted one here; tests/test_session_stack.py runs the real one)."""

from __future__ import annotations

import io
import itertools
import json
import time
from pathlib import Path
from typing import Any

import pytest

from dammrl.people.session import (
    JsonLines,
    SessionRunner,
    SetUp,
    check_participant,
    session_table,
)
from dammrl_core.errors import ConfigurationError, DammrlError, UsageError
from dammrl_core.protocol import balanced_latin_square, block_order, load_protocol, plan_trials
from schemas import SessionControl, decode
from tests.sessionutil import (
    PROTOCOL,
    ScriptedStack,
    ScriptedStopper,
    Typist,
    consoles_controls,
    reset,
)


def _protocol(tmp_path: Path, text: str = PROTOCOL) -> Path:
    path = tmp_path / "protocol.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6])
def test_the_latin_square_balances_positions_and_for_even_n_carry_over(n: int) -> None:
    rows = balanced_latin_square(n)
    assert len(rows) == (n if n % 2 == 0 else 2 * n)
    for position in range(n):  # each condition equally often in each position
        counts = [sum(row[position] == c for row in rows) for c in range(n)]
        assert len(set(counts)) == 1
    pairs = [(a, b) for row in rows for a, b in itertools.pairwise(row)]
    assert len(set(pairs)) == n * (n - 1)  # each ordered pair follows (Williams)
    if n % 2 == 0:
        assert len(pairs) == len(set(pairs))  # exactly once


def test_participants_alternate_the_test_blocks_and_practice_comes_first(tmp_path: Path) -> None:
    protocol = load_protocol(_protocol(tmp_path))
    assert [b.name for b in block_order(protocol, 0)] == ["practice", "event", "fixed"]
    assert [b.name for b in block_order(protocol, 1)] == ["practice", "fixed", "event"]
    trials = plan_trials(protocol, 1)
    assert [t.number for t in trials] == list(range(1, 8))
    assert [t.seed for t in trials] == [100, 200, 201, 202, 200, 201, 202]
    assert trials[1].condition.model == (2, 1) and trials[0].practice


@pytest.mark.parametrize(
    ("text", "says"),
    [
        (PROTOCOL.replace("trials: 3, seed: 200, condition: {trigger: event}",
                          "trials: 3, seed: 200, condition: {trigger: event}, speed: 2"),
         "speed"),
        (PROTOCOL.replace("policy: fixed, model: [2, 1]", "policy: fixed"), "fixed policy"),
        (PROTOCOL.replace("name: fixed", "name: event"), "repeat"),
        (PROTOCOL.replace("trials: 3, seed: 200, condition: {trigger: fixed",
                          "trials: -3, seed: 200, condition: {trigger: fixed"), "trials"),
        ("blocks: [", "cannot read"),
        ("- just a list", "not a mapping"),
        (PROTOCOL.replace("format: 1", "format: 2"), "format"),
    ],
)  # fmt: skip
def test_a_bad_protocol_is_refused_in_one_line_naming_what(
    tmp_path: Path, text: str, says: str
) -> None:
    with pytest.raises(ConfigurationError) as caught:
        load_protocol(_protocol(tmp_path, text))
    assert says in str(caught.value) and "\n" not in str(caught.value)


def test_the_protocol_hash_follows_values_not_layout(tmp_path: Path) -> None:
    original = load_protocol(_protocol(tmp_path)).sha256
    commented = load_protocol(_protocol(tmp_path, "# a comment\n" + PROTOCOL + "\n\n")).sha256
    changed = load_protocol(_protocol(tmp_path, PROTOCOL.replace("seed: 200", "seed: 201")))
    assert original == commented != changed.sha256


@pytest.mark.parametrize("bad", ["John Smith", "", "P", "12", "P012; rm", "anna.meier@x.org"])
def test_a_participant_is_a_pseudonym(bad: str) -> None:
    with pytest.raises(UsageError, match="pseudonymous"):
        check_participant(bad)
    assert check_participant("p012") == "P012"


def test_a_torn_last_log_line_is_skipped_and_counted(tmp_path: Path) -> None:
    log = JsonLines(tmp_path / "trials.jsonl")
    log.add({"trial": 1})
    with open(log.path, "a") as handle:
        handle.write('{"trial": 2, "res')  # kill -9 mid-write
    assert log.read() == ([{"trial": 1}], 1)


@pytest.fixture
def scripted(monkeypatch: pytest.MonkeyPatch) -> type[ScriptedStack]:
    monkeypatch.setattr("dammrl.people.session.Stack", ScriptedStack)
    return reset(ScriptedStack)


def _runner(tmp_path: Path, **kwargs: Any) -> SessionRunner:
    setup = kwargs.pop("setup", SetUp())
    return SessionRunner(tmp_path / "sessions", "P001", _protocol(tmp_path), setup,
                         say=lambda line: None, wait_for_operator=False,
                         console=io.StringIO(), **kwargs)  # fmt: skip


def _trials(tmp_path: Path, session: str = "ses-01") -> list[dict[str, Any]]:
    path = tmp_path / "sessions" / "P001" / session / "trials.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_a_session_runs_each_block_as_one_stack_run_and_logs_every_trial(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    assert _runner(tmp_path).run() == 0
    assert [(o.seed, o.episodes, o.trigger, o.model) for o in scripted.runs] == [
        (100, 1, "event", None), (200, 3, "event", None), (200, 3, "fixed", (2, 1))
    ]  # fmt: skip
    trials = _trials(tmp_path)
    assert [t["trial"] for t in trials] == list(range(1, 8))
    parts = ["recordings/part-01.mcap", "recordings/part-02.mcap"]
    assert [t["recording"] for t in trials][:2] == parts
    study = json.loads(scripted.runs[1].study)
    assert study["participant"] == "P001" and study["trials"] == [2, 3, 4]
    assert session_table(tmp_path / "sessions")[0]["state"] == "ended"


def test_a_crashed_session_resumes_at_its_first_unfinished_trial_each_trial_once(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.crash_after = 3  # the practice trial and two of the first block, then death
    with pytest.raises(DammrlError):
        _runner(tmp_path).run()
    scripted.crash_after = None
    assert _runner(tmp_path).run() == 0
    assert [t["trial"] for t in _trials(tmp_path)] == list(range(1, 8))
    resumed = scripted.runs[2]
    assert (resumed.seed, resumed.episodes) == (202, 1)  # the interrupted trial again
    assert resumed.record is not None and resumed.record.name == "part-03.mcap"  # never reused
    events = (tmp_path / "sessions/P001/ses-01/events.jsonl").read_text()
    assert '"what": "stopped", "trial": 4' in events and '"what": "resume"' in events


def _crash_after_one_trial(tmp_path: Path, scripted: type[ScriptedStack]) -> None:
    """A session whose stack dies after its first trial (left unfinished)."""
    scripted.crash_after = 1
    with pytest.raises(DammrlError):
        _runner(tmp_path).run()
    scripted.crash_after = None


def test_a_changed_set_up_is_refused_unless_the_operator_says_why(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    _crash_after_one_trial(tmp_path, scripted)
    other = SetUp(mode="virtual", lockstep=True)
    with pytest.raises(UsageError, match="lockstep: False then, True now"):
        _runner(tmp_path, setup=other).run()
    assert _runner(tmp_path, setup=other, accept_changes="a faster machine").run() == 0
    events = (tmp_path / "sessions/P001/ses-01/events.jsonl").read_text()
    assert "a faster machine" in events


def test_a_new_session_leaves_the_unfinished_one_marked_and_a_second_participant_alternates(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    _crash_after_one_trial(tmp_path, scripted)
    assert _runner(tmp_path, new=True).run() == 0
    assert len(_trials(tmp_path, "ses-02")) == 7
    assert "left unfinished" in (tmp_path / "sessions/P001/ses-01/events.jsonl").read_text()
    second = SessionRunner(tmp_path / "sessions", "P002", _protocol(tmp_path), SetUp(),
                           say=lambda line: None, wait_for_operator=False,
                           console=io.StringIO())  # fmt: skip
    scripted.runs.clear()
    assert second.run() == 0
    assert [o.trigger for o in scripted.runs] == ["event", "fixed", "event"]  # row 1


def test_a_calibration_given_once_is_kept_for_the_participants_next_sessions(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    calibration = tmp_path / "pad.json"
    calibration.write_text('{"rest_raw": 400, "light_raw": 900, "firm_raw": 2000}')
    pad = SetUp(mode="semi-virtual", intent="pad", pad_port="/dev/ttyPAD",
                calibration=calibration)  # fmt: skip
    assert _runner(tmp_path, setup=pad).run() == 0
    calibration.unlink()
    again = SetUp(mode="semi-virtual", intent="pad", pad_port="/dev/ttyPAD")
    assert _runner(tmp_path, setup=again, new=True).run() == 0
    used = scripted.runs[-1].calibration
    assert used is not None and "light_raw" in used.read_text()
    assert (tmp_path / "sessions/P001/ses-02/calibration.json").exists()


def test_the_consoles_pause_skip_again_and_end_of_block_are_logged_and_counted(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """Reach 2 paused and resumed, reach 3 skipped, reach 4 run again, reach 6 ends its
    block (the rest of it is skipped); tests/test_session_flow.py stops reaches."""
    scripted.console = {2: ["p the patient coughs", "r"], 3: ["s"], 4: ["a the arm slipped"],
                        6: ["e tired"]}  # fmt: skip
    assert _runner(tmp_path).run() == 0
    trials = _trials(tmp_path)
    by_trial: dict[int, list[dict[str, Any]]] = {}
    for t in trials:
        by_trial.setdefault(t["trial"], []).append(t)
    assert by_trial[2][0]["pauses"] == 1
    assert [a["why"] for a in by_trial[2][0]["actions"]] == ["the patient coughs", ""]
    assert by_trial[3][0]["result"]["outcome"] == "skipped"
    again = by_trial[4]
    assert [t.get("repeat", False) for t in again] == [True, False]  # then done
    assert again[0]["recording"] != again[1]["recording"]  # a new stack run for it
    ended = by_trial[5][0]  # trial 5 (block 'fixed' 1) was reach 6
    assert ended["result"]["outcome"] == "skipped"
    assert by_trial[6][0]["skipped"] == "operator: tired" and by_trial[6][0]["result"] is None
    assert sorted(by_trial) == list(range(1, 8))
    controls = [(c.episode, c.action, c.why) for c in consoles_controls()]
    assert controls == [
        (1, "pause", "the patient coughs"),
        (1, "resume", ""),
        (2, "skip", ""),
        (3, "again", "the arm slipped"),
        (1, "end-block", "tired"),
        (2, "pause", "the block ends"),
    ]  # the rest of the block held back


def test_the_persons_posterior_is_carried_to_the_next_run_and_session(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """Each stack run starts its policy from what the earlier runs said of the person."""
    scripted.posterior = (0.2, 0.8)
    assert _runner(tmp_path).run() == 0
    assert [o.prior for o in scripted.runs] == [None, (0.2, 0.8), (0.2, 0.8)]
    scripted.runs.clear()
    scripted.posterior = None
    assert _runner(tmp_path, new=True).run() == 0  # the next session
    assert scripted.runs[0].prior == (0.2, 0.8)
    kept = json.loads((tmp_path / "sessions/P001/posterior.json").read_text())
    assert kept["probabilities"] == [0.2, 0.8] and kept["session"] == "ses-01"


def test_the_console_takes_the_decisions_over_and_gives_them_back(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:

    scripted.console = {2: ["t the patient is tired", "+ small", "-", "g"]}
    assert _runner(tmp_path).run() == 0
    sent = consoles_controls()
    assert [(c.action, c.u_h, c.human_model) for c in sent] == [
        ("take", None, None), ("decide", 1, 2), ("decide", -1, 1), ("give", None, None)
    ]  # fmt: skip
    assert sent[0].why == "the patient is tired" and all(c.who == "operator" for c in sent)


def test_a_takeover_holds_across_stack_runs_until_it_is_given_back(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """Each block is a new stack run, whose intent service and page knew nothing of the
    takeover: the participant's device decided again, and the therapist's + was ignored."""
    scripted.console = {2: ["t"], 5: ["g"]}
    assert _runner(tmp_path).run() == 0
    sent = [(c.episode, c.action, c.why) for c in consoles_controls()]
    again = "taken over in an earlier stack run"
    assert sent == [(1, "take", ""), (1, "take", again), (1, "give", "")], sent


def _said_any(typist: Typist, *words: str) -> bool:
    return any(typist.index(w) >= 0 for w in words)


def _typed_as_the_stop_console_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, line: str, answers: tuple[str, ...]
) -> Typist:
    """A session whose first run's stop console takes its time to open (a busy PC), and
    ``line`` typed meanwhile: it waits (5 s at most) until the session says one of
    ``answers``. The session runs to its end; its typist."""
    typist, opened = Typist([]), ScriptedStack.stop_console

    def slow_stop_console(stack: ScriptedStack) -> ScriptedStopper:
        if not stack.runs[1:]:  # the first run's
            typist.type(line)
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not _said_any(typist, *answers):
                time.sleep(0.01)
        return opened(stack)

    monkeypatch.setattr(ScriptedStack, "stop_console", slow_stop_console)
    runner = SessionRunner(tmp_path / "sessions", "P001", _protocol(tmp_path), SetUp(),
                           say=typist.say, wait_for_operator=False,
                           console=typist.stream)  # fmt: skip
    try:
        runner.run()
    finally:
        typist.close()
    return typist


def test_a_line_typed_while_the_stop_console_opens_acts_on_the_reach(
    tmp_path: Path, scripted: type[ScriptedStack], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stop console's own session takes a second to open on a busy PC, and the first
    reach is under way meanwhile: a takeover typed then acts on it (it was once refused as
    'no reach runs now' until the stop console was open)."""
    # acted on (taken), or refused, while it opens
    typist = _typed_as_the_stop_console_opens(tmp_path, monkeypatch, "t the patient is tired",
                                              ("console: take", "no reach runs"))  # fmt: skip
    sent = consoles_controls()
    assert [c.action for c in sent][:1] == ["take"], typist.said
    assert typist.index("no reach runs now") == -1, typist.said


def test_a_pause_typed_as_the_stack_comes_up_keeps_the_first_reach_held(
    tmp_path: Path, scripted: type[ScriptedStack], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each run's first reach waits for the session's resume as it attaches: a pause typed
    while the stop console opens is the therapist's, and that resume must not undo it."""
    _typed_as_the_stop_console_opens(tmp_path, monkeypatch, "p one moment", ("console: pause",))
    first_run = []
    for key_expr, payload in scripted.sent:
        if key_expr == "dammrl/task/goal":
            break  # the first run's first goal (the scripted stack does not hold it)
        if key_expr == "dammrl/session/control":
            first_run.append(decode(SessionControl, payload))
    assert [(c.episode, c.action, c.why) for c in first_run] == [(1, "pause", "one moment")]


def test_a_closed_console_waits_its_timeout_instead_of_spinning() -> None:
    """With stdin at its end (a session run from a script, CI), the console thread polls
    a closed console: it must wait as an open, silent one does (it once spun a core)."""
    from dammrl.people.console import Lines

    lines = Lines(io.StringIO(""))
    time.sleep(0.1)  # the reader thread meets the end
    assert lines.get(0.0) is None and lines.closed
    started = time.monotonic()
    assert lines.get(0.2) is None
    assert time.monotonic() - started >= 0.19
    assert lines.get(None) is None  # no timeout: at once, never for ever


def _recorded_events(tmp_path: Path) -> list[dict[str, Any]]:
    events = (tmp_path / "sessions/P001/ses-01/events.jsonl").read_text().splitlines()
    return [e for e in map(json.loads, events) if e["what"] == "recorded"]


def test_a_stack_run_stops_only_once_the_recorder_confirms_its_reaches_on_disk(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """The acknowledgements come 0.3 s after each result: each run waits for its last."""
    scripted.ack_after_s = 0.3
    assert _runner(tmp_path).run() == 0
    recorded = _recorded_events(tmp_path)
    assert [e["confirmed"] for e in recorded] == [[1], [2, 3, 4], [5, 6, 7]]
    assert all(e["unconfirmed"] == [] and e["waited_s"] >= 0.2 for e in recorded)


def test_reaches_the_recorder_never_confirms_are_logged_and_said_after_a_bounded_wait(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.ack_after_s = 60.0  # later than the session waits
    said: list[str] = []
    runner = SessionRunner(tmp_path / "sessions", "P001", _protocol(tmp_path), SetUp(),
                           say=said.append, wait_for_operator=False, console=io.StringIO(),
                           recorded_wait_s=0.2)  # fmt: skip
    started = time.monotonic()
    assert runner.run() == 0
    assert time.monotonic() - started < 10  # bounded: three runs, 0.2 s each
    recorded = _recorded_events(tmp_path)
    assert [e["unconfirmed"] for e in recorded] == [[1], [2, 3, 4], [5, 6, 7]]
    assert [e["unconfirmed_episodes"] for e in recorded] == [[1], [1, 2, 3], [1, 2, 3]]
    assert any("did not confirm trial(s) [2, 3, 4] on disk within 0.2 s" in line
               for line in said)  # fmt: skip


def test_a_pause_outlives_its_reach_the_next_one_waits_for_the_resume(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """A reach skipped while paused (or ending just as the pause was typed): the session
    holds the next reach back until the therapist's resume."""
    scripted.console = {2: ["p coughs", "s"], 3: ["r"]}
    assert _runner(tmp_path).run() == 0
    controls = [(c.episode, c.action, c.why) for c in consoles_controls()]
    held = (2, "pause", "paused as the last reach ended")
    assert controls == [(1, "pause", "coughs"), (1, "skip", ""), held, (2, "resume", "")]


def test_the_consoles_again_and_end_of_block_go_on_the_bus_as_themselves(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.console = {2: ["a slipped"], 5: ["e tired"]}
    assert _runner(tmp_path).run() == 0
    actions = [(c.action, c.why) for c in consoles_controls()]
    # each ends the reach under way; the session then holds the run's next reach back (the
    # block ended on its run's last reach: none follows)
    assert actions == [("again", "slipped"), ("pause", "the trial runs again"),
                       ("end-block", "tired")]  # fmt: skip


def test_the_consoles_stop_is_sent_until_every_arm_confirms_it_and_says_so(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """x (one key) goes through the stop console opened with the stack (repeated until each
    arm's Health confirms it, no start-up); what each arm said is told to the operator,
    and an arm that did not confirm sends the operator to the hardware stop."""
    said: list[str] = []
    scripted.console = {2: ["x the patient is tired"]}
    ScriptedStopper.silent = ["robot"]
    runner = _runner(tmp_path)
    runner.say = said.append
    runner.run()
    stopper = scripted.stopper
    assert stopper is not None and stopper.sent[0] == (True, "operator: the patient is tired")
    assert "console: stop confirmed by sim after 12 ms" in said
    assert "console: robot did not confirm the stop within 2 s: use the hardware stop" in said
    assert stopper.closed  # with the stack
