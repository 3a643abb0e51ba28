"""Protocols, participants and sessions: the files, the counterbalancing, resumption (the
stack replaced by a scripted one here; tests/test_session_stack.py runs the real one)."""

from __future__ import annotations

import io
import itertools
import json
import threading
import time
from pathlib import Path
from typing import Any, ClassVar

import pytest

from dammrl.console import parse
from dammrl.launch import StackOptions
from dammrl.session import JsonLines, SessionRunner, SetUp, check_participant, session_table
from dammrl_core.errors import ConfigurationError, DammrlError, JobFailedError, UsageError
from dammrl_core.protocol import balanced_latin_square, block_order, load_protocol, plan_trials
from schemas import EpisodeRecorded, EpisodeResult, Header, SessionControl, decode

PROTOCOL = """\
format: 1
name: two-blocks
version: "1"
blocks:
  - {name: practice, practice: true, trials: 1, seed: 100}
  - {name: event, trials: 3, seed: 200, condition: {trigger: event}}
  - {name: fixed, trials: 3, seed: 200, condition: {trigger: fixed, policy: fixed, model: [2, 1]}}
"""


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


def _result(episode: int, seed: int, outcome: str = "success") -> EpisodeResult:
    return EpisodeResult(  # type: ignore[arg-type]  # outcome: one of the Literal's
        header=Header(stamp_ns=1, seq=episode, source="controller"), episode=episode,
        seed=seed, trigger="event", model=(2, 1), success=outcome == "success", reached=True,
        outcome=outcome, reason="button pressed", t_total_s=5.0, t_step_mean_s=0.5,
        final_error_m=0.01, n_osc=1, n_osc_per_step=0.1, jerk_isj=1.0, sparc=-2.0, ldlj=-7.0,
        human_error_rate=0.1, n_steps=10, n_decisions=10, button_pressed=True,
        start_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2),
    )  # fmt: skip


class ScriptedStack:
    """The launcher's part a session uses: episodes of the given seeds, results handed on;
    ``crash_after`` results in all, it dies as a dead service makes it; ``console`` lines
    are typed (to the run's console) before the reach of the given number in all."""

    runs: ClassVar[list[StackOptions]] = []
    crash_after: ClassVar[int | None] = None
    given: ClassVar[int] = 0
    console: ClassVar[dict[int, list[str]]] = {}
    sent: ClassVar[list[Any]] = []
    posterior: ClassVar[tuple[float, float] | None] = None
    ack_after_s: ClassVar[float | None] = None  # the recorder's acknowledgements (None: none)

    def __init__(self, options: StackOptions, out: Any, info: Any, on_result: Any,
                 on_up: Any) -> None:  # fmt: skip
        self.options, self.on_result, self.on_up = options, on_result, on_up
        self.finishing = False

    def put(self, key: str, payload: bytes) -> None:  # the hub session's
        ScriptedStack.sent.append((key, payload))

    def finish(self) -> None:
        self.finishing = True

    def run(self) -> int:
        ScriptedStack.runs.append(self.options)
        assert self.options.episodes is not None and self.options.record is not None
        self.options.record.write_bytes(b"mcap")
        stack_run = self.on_up.__self__
        stack_run.hub = self  # as attach() does, without its console thread
        stack_run.listening = ScriptedStack.ack_after_s is not None
        for episode in range(1, self.options.episodes + 1):
            if ScriptedStack.crash_after is not None and self.given >= self.crash_after:
                raise JobFailedError("service controller exited unexpectedly with code -9")
            ScriptedStack.given += 1
            outcome = "success"
            for line in ScriptedStack.console.get(ScriptedStack.given, []):
                command = parse(line)
                assert not isinstance(command, str)
                stack_run.act(command)
                outcome = "skipped" if command.action in ("skip", "again", "end-block") else outcome
            if ScriptedStack.posterior is not None:  # the policy spoke of the person
                stack_run.posterior = ScriptedStack.posterior
            if ScriptedStack.ack_after_s is not None:
                _acknowledge(stack_run, episode, ScriptedStack.ack_after_s)
            self.on_result(_result(episode, self.options.seed + episode - 1, outcome))
            if self.finishing:
                break
        return 0


def _acknowledge(stack_run: Any, episode: int, after_s: float) -> None:
    """The recorder's acknowledgement of ``episode``, ``after_s`` from now (on its own
    thread, as the bus delivers it)."""
    ack = EpisodeRecorded(header=Header(stamp_ns=1, seq=episode, source="recorder"),
                          episode=episode, file=stack_run.part.name, result_seq=episode,
                          states=100, complete=True)  # fmt: skip
    threading.Timer(after_s, stack_run.recorded.take, args=(ack,)).start()


@pytest.fixture
def scripted(monkeypatch: pytest.MonkeyPatch) -> type[ScriptedStack]:
    monkeypatch.setattr("dammrl.session.Stack", ScriptedStack)
    ScriptedStack.runs, ScriptedStack.crash_after, ScriptedStack.given = [], None, 0
    ScriptedStack.console, ScriptedStack.sent, ScriptedStack.posterior = {}, [], None
    ScriptedStack.ack_after_s = None
    return ScriptedStack


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
    calibration.write_text('{"threshold": 1}')
    pad = SetUp(mode="semi-virtual", intent="pad", pad_port="/dev/ttyPAD",
                calibration=calibration)  # fmt: skip
    assert _runner(tmp_path, setup=pad).run() == 0
    calibration.unlink()
    again = SetUp(mode="semi-virtual", intent="pad", pad_port="/dev/ttyPAD")
    assert _runner(tmp_path, setup=again, new=True).run() == 0
    used = scripted.runs[-1].calibration
    assert used is not None and used.read_text() == '{"threshold": 1}'
    assert (tmp_path / "sessions/P001/ses-02/calibration.json").exists()


def test_the_consoles_pause_skip_again_and_end_of_block_are_logged_and_counted(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """Reach 2 paused and resumed, reach 3 skipped, reach 4 run again, reach 6 ends its
    block (the rest of it is skipped); the stop reaches the bus."""
    scripted.console = {2: ["p the patient coughs", "r"], 3: ["s"], 4: ["a the arm slipped"],
                        6: ["e tired", "x"]}  # fmt: skip
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
    keys = [k for k, _ in scripted.sent]
    assert "dammrl/safety/stop" in keys and keys.count("dammrl/session/control") == 5


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
    from schemas import SessionControl, decode

    scripted.console = {2: ["t the patient is tired", "+ small", "-", "g"]}
    assert _runner(tmp_path).run() == 0
    sent = [decode(SessionControl, p) for k, p in scripted.sent if k == "dammrl/session/control"]
    assert [(c.action, c.u_h, c.human_model) for c in sent] == [
        ("take", None, None), ("decide", 1, 2), ("decide", -1, 1), ("give", None, None)
    ]  # fmt: skip
    assert sent[0].why == "the patient is tired" and all(c.who == "operator" for c in sent)


def test_a_closed_console_waits_its_timeout_instead_of_spinning() -> None:
    """With stdin at its end (a session run from a script, CI), the console thread polls
    a closed console: it must wait as an open, silent one does (it once spun a core)."""
    from dammrl.console import Lines

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


def test_the_consoles_again_and_end_of_block_go_on_the_bus_as_themselves(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.console = {2: ["a slipped"], 5: ["e tired"]}
    assert _runner(tmp_path).run() == 0
    actions = [decode(SessionControl, payload).action for k, payload in scripted.sent
               if k == "dammrl/session/control"]  # fmt: skip
    assert actions == ["again", "end-block"]
