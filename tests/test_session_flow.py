"""A session flow without surprises (the stack scripted; tests/test_session_display.py runs
the real one with the participant's page): an emergency stop pauses the session and its
trial is run again or marked stopped, by the therapist's choice; console lines are acted
on or refused when typed, never kept for a later step; nothing moves before Enter; a
resumed session completes the comfort question and the rest a kill interrupted; the
controller publishes no goal while a stop is latched and holds each outcome."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dammrl.people.session import SessionRunner, SetUp
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.models import ModelSet
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import (
    ComfortRating,
    EmergencyStop,
    EpisodeResult,
    Header,
    RobotState,
    SessionControl,
    TaskGoal,
    decode,
)
from services.controller.node import ControllerNode
from tests.sessionutil import (
    Killed,
    ScriptedStack,
    StubDisplay,
    Typist,
    consoles_controls,
    reset,
    result,
    write_protocol,
)
from tests.test_nodes import FakeBus

TWO_BLOCKS = """\
format: 1
name: flow
version: "1"
blocks:
  - {name: one, trials: 2, seed: 200, rest_s: REST}
  - {name: two, trials: 2, seed: 300}
"""


@pytest.fixture
def scripted(monkeypatch: pytest.MonkeyPatch) -> type[ScriptedStack]:
    monkeypatch.setattr("dammrl.people.session.Stack", ScriptedStack)
    return reset(ScriptedStack)


def _runner(tmp_path: Path, typist: Typist, rest_s: float = 0.0, **kwargs: Any) -> SessionRunner:
    protocol = write_protocol(tmp_path, TWO_BLOCKS.replace("REST", str(rest_s)))
    return SessionRunner(tmp_path / "sessions", "P001", protocol, SetUp(outcome_s=0.0),
                         say=typist.say,
                         wait_for_operator=True, console=typist.stream, **kwargs)  # fmt: skip


def _lines(tmp_path: Path, name: str) -> list[dict[str, Any]]:
    path = tmp_path / "sessions" / "P001" / "ses-01" / name
    return [json.loads(line) for line in path.read_text().splitlines()]


def _run(runner: SessionRunner, typist: Typist, timeout_s: float = 60) -> int:
    """Run the session on a thread (bounded); its exit code."""
    codes: list[int] = []
    thread = threading.Thread(target=lambda: codes.append(runner.run()), daemon=True)
    thread.start()
    thread.join(timeout_s)
    typist.close()
    thread.join(5)
    assert codes, f"the session did not end in {timeout_s} s; it said: {typist.said[-8:]}"
    return codes[0]


ENTER = {"press Enter": ""}


def test_a_stop_mid_reach_is_not_counted_and_the_trial_runs_again_after_release(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.console = {2: ["x the arm slipped"]}
    typist = Typist([("is not counted", "a"), ("type release first", "release"),
                     ("released", "a")], every=ENTER)  # fmt: skip
    assert _run(_runner(tmp_path, typist), typist) == 0
    trials = _lines(tmp_path, "trials.jsonl")
    second = [t for t in trials if t["trial"] == 2]
    assert second[0]["repeat"] and "the arm slipped" in second[0]["stopped"]
    assert second[0]["result"]["outcome"] == "stopped" and "repeat" not in second[1]
    assert sorted(t["trial"] for t in trials if not t.get("repeat")) == [1, 2, 3, 4]
    # released, chosen, then Enter: only then the next stack (the trial again)
    assert typist.index("released") < typist.index("runs again") < len(typist.said)
    assert [o.seed for o in scripted.runs] == [200, 201, 300]
    events = [e["what"] for e in _lines(tmp_path, "events.jsonl")]
    assert "emergency-stop" in events
    comfort = [e for e in _lines(tmp_path, "events.jsonl") if e["what"] == "comfort"]
    assert not comfort  # no display: no question, and none for the stopped attempt


def test_a_stopped_trial_can_be_marked_stopped_instead_and_counts_as_done(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.console = {1: ["x"]}
    typist = Typist([("is not counted", "release"), ("released", "s the patient is tired")],
                    every=ENTER)  # fmt: skip
    assert _run(_runner(tmp_path, typist), typist) == 0
    first = [t for t in _lines(tmp_path, "trials.jsonl") if t["trial"] == 1]
    assert len(first) == 2 and first[0]["repeat"]
    assert first[1]["result"] is None and "emergency stop" in first[1]["stopped"]
    assert first[1]["why"] == "the patient is tired"
    assert [o.seed for o in scripted.runs] == [200, 201, 300]  # trial 1 is not run again


def test_without_a_console_a_stopped_session_ends_and_resumes_later(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.console = {1: ["x"]}
    typist = Typist([("is not counted", None)], every=ENTER)  # then the console ends
    assert _run(_runner(tmp_path, typist), typist) == 1
    events = _lines(tmp_path, "events.jsonl")
    assert events[-1]["what"] == "stopped" and events[-1]["trial"] == 1


def test_console_input_during_a_rest_acts_or_is_refused_and_never_reaches_the_next_block(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    typist = Typist([("rest for", "t the patient is tired"), ("refused", "s")], every=ENTER)
    started = time.monotonic()
    assert _run(_runner(tmp_path, typist, rest_s=60), typist) == 0
    assert time.monotonic() - started < 30  # the 60 s rest ended early
    refused = typist.said[typist.index("refused")]
    assert refused.startswith("console: take refused: the rest")
    rest_end = next(e for e in _lines(tmp_path, "events.jsonl") if e["what"] == "rest-end")
    assert rest_end["early"] and rest_end["rested_s"] < 30
    # the next block waited for its own Enter, after the rest; nothing typed acted on it
    assert typist.index("rest ended early") < typist.said.index("block 2 (two)")
    assert typist.index("press Enter") < typist.said.index("block 2 (two)") < len(typist.said)
    assert all(not t["actions"] for t in _lines(tmp_path, "trials.jsonl"))
    assert not consoles_controls()


def test_a_command_typed_before_the_stack_is_up_is_refused_not_applied_later(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    typist = Typist([("press Enter", "a"), ("refused", ""), ("press Enter", "")])
    assert _run(_runner(tmp_path, typist), typist) == 0
    assert "again refused: waiting for Enter" in typist.said[typist.index("refused")]
    trials = _lines(tmp_path, "trials.jsonl")
    assert [t["trial"] for t in trials] == [1, 2, 3, 4] and not any(t["actions"] for t in trials)
    runner = _runner(tmp_path, typist)
    runner._idle("s")  # a stack starting or ending
    assert "skip refused: no reach runs now" in typist.said[-1]


def test_a_resumed_session_waits_for_enter_before_anything_moves(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    scripted.crash_after = 1
    typist = Typist([], every=ENTER)
    with pytest.raises(Exception, match="exited unexpectedly"):
        _runner(tmp_path, typist).run()
    scripted.crash_after, runs = None, len(scripted.runs)
    typist = Typist([])  # a therapist who has not pressed Enter yet
    runner = _runner(tmp_path, typist)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while typist.index("press Enter") < 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)
    assert len(scripted.runs) == runs  # resumed mid-block: no stack before Enter
    assert typist.index("block 1 (one) goes on at trial 2") >= 0
    typist.every = ENTER
    typist.type("")
    thread.join(30)
    typist.close()
    assert not thread.is_alive() and len(scripted.runs) > runs


def test_a_kill_during_the_comfort_question_is_completed_when_the_session_resumes(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    typist = Typist([], every=ENTER)
    with pytest.raises(Killed):
        _runner(tmp_path, typist, rest_s=2, display=StubDisplay(kill_at="comfort")).run()
    events = _lines(tmp_path, "events.jsonl")
    assert not [e for e in events if e["what"] in ("comfort", "block-end", "rest")]
    typist = Typist([], every=ENTER)
    display = StubDisplay(rating=4)
    assert _run(_runner(tmp_path, typist, rest_s=2, display=display), typist) == 0
    events = _lines(tmp_path, "events.jsonl")
    order = [(e["what"], e.get("block")) for e in events
             if e["what"] in ("comfort", "block-end", "rest", "rest-end", "run")]  # fmt: skip
    assert order[:6] == [("run", "one"), ("comfort", "one"), ("block-end", "one"),
                         ("rest", "one"), ("rest-end", "one"), ("run", "two")]  # fmt: skip
    assert events[[e["what"] for e in events].index("comfort")]["rating"] == 4
    ratings = [decode(ComfortRating, p) for k, p in scripted.sent if k == "dammrl/session/comfort"]
    assert [(r.block, r.rating) for r in ratings] == [("one", 4), ("two", 4)]  # both recorded


def test_ctrl_c_ends_the_comfort_question_asked_inside_the_stacks_loop(
    tmp_path: Path, scripted: type[ScriptedStack], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A block's last result asks the question inside the stack's loop, which looks at
    Ctrl-C only between results: it went on waiting for the answer (up to the comfort
    timeout) and the recorder (15 s) before the stack stopped."""

    class Unanswered(StubDisplay):
        def ask_comfort(self, timeout_s: float, cancel: threading.Event | None = None
                        ) -> tuple[int, float] | None:  # fmt: skip
            assert cancel is not None and cancel.wait(timeout_s), "not ended by Ctrl-C"
            return None

    interrupted = threading.Event()
    interrupted.set()  # Ctrl-C came as the reach ended
    monkeypatch.setattr(ScriptedStack, "signalled", interrupted, raising=False)
    typist = Typist([], every=ENTER)
    runner = _runner(tmp_path, typist, display=Unanswered(), comfort_timeout_s=60,
                     recorded_wait_s=60)  # fmt: skip
    started = time.monotonic()
    assert _run(runner, typist, timeout_s=60) == 0
    assert time.monotonic() - started < 30


def test_a_stop_while_a_block_ended_between_reaches_asks_its_comfort_question_once(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    """`e` between two reaches closes the block on a thread (the question, then the run's
    end); an `x` while the question is open ended the run at once, and the session asked
    the question a second time beside the first (one answer logged null)."""

    class Slow(StubDisplay):
        def ask_comfort(self, timeout_s: float, cancel: threading.Event | None = None
                        ) -> tuple[int, float] | None:  # fmt: skip
            self.shown.append(("comfort", None))
            time.sleep(0.5)  # the participant reads it
            return (4, 0.5)

    scripted.between = {1: ["e tired", "x the arm slipped", "release"]}
    typist = Typist([], every=ENTER)
    display = Slow()
    assert _run(_runner(tmp_path, typist, display=display), typist) == 0
    comfort = [e for e in _lines(tmp_path, "events.jsonl") if e["what"] == "comfort"]
    assert [(e["block"], e["rating"]) for e in comfort][:1] == [("one", 4)]
    assert [e["block"] for e in comfort].count("one") == 1
    assert display.shown.count(("comfort", None)) == len(comfort)


def test_a_kill_during_the_rest_resumes_what_was_left_of_it(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    typist = Typist([], every=ENTER)
    with pytest.raises(Killed):
        _runner(tmp_path, typist, rest_s=3, display=StubDisplay(kill_at="rest")).run()
    time.sleep(1.0)  # the session is down a second
    typist = Typist([], every=ENTER)
    display = StubDisplay()
    assert _run(_runner(tmp_path, typist, rest_s=3, display=display), typist) == 0
    events = _lines(tmp_path, "events.jsonl")
    rests = [e for e in events if e["what"] == "rest"]
    assert len(rests) == 2 and rests[1]["resumed"] and 0.5 < rests[1]["seconds"] < 2.5
    assert next(e for e in events if e["what"] == "rest-end")["early"] is False
    comfort = [e["block"] for e in events if e["what"] == "comfort"]
    assert comfort == ["one", "two"]  # block one's was answered before the kill: not again
    shown = [seconds for what, seconds in display.shown if what == "rest"]
    assert shown == [pytest.approx(rests[1]["seconds"], abs=0.06)]  # the page counts it down


def test_reasons_are_stored_without_the_names_of_the_registry(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    from dammrl.people.console import Names

    scripted.console = {2: ["p Anna coughs", "r"]}
    typist = Typist([], every=ENTER)
    protocol = write_protocol(tmp_path, TWO_BLOCKS.replace("REST", "0"))
    setup = SetUp(names=Names(["Anna Meier", "Anna", "Meier"]))
    runner = SessionRunner(tmp_path / "sessions", "P001", protocol, setup, say=typist.say,
                           wait_for_operator=True, console=typist.stream)  # fmt: skip
    assert _run(runner, typist) == 0
    stored = (tmp_path / "sessions/P001/ses-01/events.jsonl").read_text()
    stored += (tmp_path / "sessions/P001/ses-01/trials.jsonl").read_text()
    assert "Anna" not in stored and "[name removed] coughs" in stored
    assert any("stored without the name" in line for line in typist.said)
    sent = consoles_controls()
    assert sent[0].why == "[name removed] coughs"


def test_without_a_registry_the_console_says_reasons_are_stored_as_typed(
    tmp_path: Path, scripted: type[ScriptedStack]
) -> None:
    typist = Typist([], every=ENTER)
    assert _run(_runner(tmp_path, typist), typist) == 0
    assert any("stored as typed" in line for line in typist.said)


# ---- the controller: stops, outcomes held, pauses between reaches --------------------------
HEADER = Header(stamp_ns=1, seq=0, source="tool")


def _controller(hold_s: float) -> tuple[ControllerNode, FakeBus]:
    bus = FakeBus()
    node = ControllerNode(ControllerSettings(outcome_hold_s=hold_s), TaskSettings(),
                          RobotSettings(), ModelSet(), bus)  # type: ignore[arg-type]  # fmt: skip
    return node, bus


def _state(node: ControllerNode, t_s: float) -> RobotState:
    assert node.plan is not None
    q = tuple(float(v) for v in node.plan.q_start)
    zero = (0.0,) * 6
    return RobotState(header=Header(stamp_ns=int(t_s * 1e9), seq=0, source="sim"),
                      episode=node.number, t_s=t_s, q_rad=q, dq_rad_s=zero, tau_nm=zero,
                      ee_pos_m=tuple(float(v) for v in node.plan.task.start),
                      ee_vel_m_s=(0.0, 0.0, 0.0), button_pressed=False,
                      button_travel_m=0.0, holding=False)  # type: ignore[arg-type]  # fmt: skip


def _published(bus: FakeBus, kind: type) -> list[Any]:
    return [m for m in bus.published if isinstance(m, kind)]


def _watch_for(node: ControllerNode, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        node._watch()
        time.sleep(0.01)


def test_a_stop_ends_the_reach_as_stopped_and_no_goal_goes_out_until_its_release() -> None:
    node, bus = _controller(hold_s=0.1)
    node.next_due_s = time.monotonic()
    node._watch()  # the first reach begins
    assert [g.episode for g in _published(bus, TaskGoal)] == [1]
    node._dispatch_all([_state(node, 1.0)])  # it runs
    stop = EmergencyStop(header=HEADER, engaged=True, reason="T1: the arm slipped")
    node._dispatch_all([stop])
    results = _published(bus, EpisodeResult)
    assert [(r.episode, r.outcome) for r in results] == [(1, "stopped")]
    assert "emergency stop from tool: T1: the arm slipped" in results[0].reason
    _watch_for(node, 0.5)  # well past the outcome's hold: still stopped
    assert [g.episode for g in _published(bus, TaskGoal)] == [1]
    assert "waits for its release" in node._waiting_for()
    node._dispatch_all([EmergencyStop(header=HEADER, engaged=False)])
    _watch_for(node, 0.05)
    assert [g.episode for g in _published(bus, TaskGoal)] == [1, 2]


def test_the_next_reach_waits_for_its_predecessors_outcome_and_for_a_resume() -> None:
    node, bus = _controller(hold_s=0.4)
    node.next_due_s = time.monotonic()
    node._watch()
    node._dispatch_all([_state(node, 1.0)])
    skip = SessionControl(header=HEADER, episode=1, action="skip", who="T1")
    node._dispatch_all([skip])
    ended = time.monotonic()
    pause = SessionControl(header=HEADER, episode=2, action="pause", who="T1", why="a sip")
    node._dispatch_all([pause])  # between the reaches: the next one is held
    _watch_for(node, 0.6)
    assert [g.episode for g in _published(bus, TaskGoal)] == [1]
    assert "paused by T1: a sip before reach 2" in node._waiting_for()
    node._dispatch_all([SessionControl(header=HEADER, episode=2, action="resume", who="T1")])
    _watch_for(node, 0.05)
    goals = _published(bus, TaskGoal)
    assert [g.episode for g in goals] == [1, 2] and time.monotonic() - ended >= 0.4


def test_a_sessions_stack_holds_its_first_reach_until_the_session_resumes_it() -> None:
    """Nothing moves before the session is attached (its console routed, its stop one key
    away): the resume may come while the controller still waits for its peers."""

    class StartingBus(FakeBus):
        """Peers alive; the session's resume is the first message to come."""

        def __init__(self) -> None:
            super().__init__()
            self.inbox = [SessionControl(header=HEADER, episode=1, action="resume", who="T1")]

        def receive(self, timeout_s: float) -> object:
            time.sleep(0.01)
            return self.inbox.pop() if self.inbox else None

        def alive_peers(self) -> set[str]:
            return {"intent", "policy"}

        def report_health(self, state: str, detail: str) -> None: ...

    bus = StartingBus()
    settings = ControllerSettings(first_reach_held_by="the session", policy_wait_s=0.2)
    node = ControllerNode(settings, TaskSettings(), RobotSettings(), ModelSet(),
                          bus)  # type: ignore[arg-type]  # fmt: skip
    node.next_due_s = time.monotonic()
    _watch_for(node, 0.2)
    assert not _published(bus, TaskGoal)
    assert "paused by the session before reach 1" in node._waiting_for()
    node._wait_for_peers(threading.Event())  # the policy is silent: 0.2 s, then on
    assert not bus.inbox
    node.next_due_s = time.monotonic()
    node._watch()
    assert [g.episode for g in _published(bus, TaskGoal)] == [1]


def test_the_arm_is_held_where_the_reach_left_it_while_the_outcome_shows() -> None:
    from schemas import JointCommand

    node, bus = _controller(hold_s=1.0)
    node.next_due_s = time.monotonic()
    node._watch()
    for k in range(3):
        node._dispatch_all([_state(node, 1.0 + 0.01 * k)])
    node._dispatch_all([SessionControl(header=HEADER, episode=1, action="skip", who="T1")])
    before = len(_published(bus, JointCommand))
    node._dispatch_all([_state_of_episode(node, 1, 1.05)])
    held = _published(bus, JointCommand)[before:]
    assert len(held) == 1 and held[0].episode == 1
    np.testing.assert_array_equal(held[0].dq_ref_rad_s, np.zeros(6))


def test_an_episode_the_arm_cannot_begin_ends_as_a_hold_and_the_next_follows() -> None:
    """Before, a start posture the arm could not reach (an arm truly blocked) left the
    controller announcing that episode every 0.5 s for good, with no result: the session
    stuck. The arm's refusal now ends it as a hold that says why; stale refusals (of an
    episode not announced, or begun) change nothing."""
    from dammrl.stack.progress import undecided
    from schemas import GoalRefused

    node, bus = _controller(hold_s=0.1)
    node.next_due_s = time.monotonic()
    node._watch()
    robot = Header(stamp_ns=1, seq=0, source="robot")
    why = "episode 1: the start posture not reached (0.542 rad away 5.0 s after the move)"
    node._dispatch_all([GoalRefused(header=robot, episode=2, reason="not announced yet")])
    assert _published(bus, EpisodeResult) == []
    node._dispatch_all([GoalRefused(header=robot, episode=1, reason=why)])
    node._dispatch_all([GoalRefused(header=robot, episode=1, reason=why)])  # again: ignored
    results = _published(bus, EpisodeResult)
    assert [(r.episode, r.outcome) for r in results] == [(1, "hold")]
    assert results[0].reason == f"the robot cannot begin it: {why}"
    assert results[0].n_decisions == 0 and not undecided(results[0])  # not the person's
    _watch_for(node, 0.3)
    assert [g.episode for g in _published(bus, TaskGoal)][-1] == 2
    node._dispatch_all([_state(node, 1.0)])  # episode 2 begins: a late refusal is stale
    node._dispatch_all([GoalRefused(header=robot, episode=2, reason="late")])
    assert len(_published(bus, EpisodeResult)) == 1 and node.started


def _state_of_episode(node: ControllerNode, episode: int, t_s: float) -> RobotState:
    zero = (0.0,) * 6
    return RobotState(header=Header(stamp_ns=int(t_s * 1e9), seq=0, source="sim"),
                      episode=episode, t_s=t_s, q_rad=(0.0, 1.0, 0.0, 1.6, 0.0, 0.3),
                      dq_rad_s=zero, tau_nm=zero, ee_pos_m=(0.4, 0.0, 0.0),
                      ee_vel_m_s=(0.0, 0.0, 0.0), button_pressed=False,
                      button_travel_m=0.0, holding=False)  # type: ignore[arg-type]  # fmt: skip


@pytest.mark.parametrize(
    ("outcome", "reason", "could_not_be_done"),
    [
        ("timeout", "no button press within 10 s", True),  # waited for decisions in vain
        ("hold", "robot state stale: sim alive but silent for 0.10 s", False),  # the stack's
        ("hold", "the controller itself stalled for 0.31 s (the arm held)", False),
    ],
)
def test_a_hold_for_a_fault_of_the_stack_is_not_blamed_on_the_persons_input(
    outcome: str, reason: str, could_not_be_done: bool
) -> None:
    """A loaded PC once ended a session's one-reach block (a stale arm state 0.5 s in, no
    decision yet) with "no decision ever came from the pad": the session stopped, blaming
    the person's input for the stack's fault."""
    from dammrl.stack.progress import undecided

    ended = result(1, 7100100, outcome, reason).model_copy(update={"n_decisions": 0})
    assert undecided(ended) is could_not_be_done
