"""Service nodes without a network: their message handling, driven by hand."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from dammrl_core.human import HumanModel
from dammrl_core.intent.simulated import SimulatedSource
from dammrl_core.intent.source import Ask, Decided, Reading, SourceContext
from dammrl_core.models import ModelSet
from schemas import DecisionRequest, Header, Message, ModelChoice, TaskGoal
from services.common.config import BusSettings
from services.intent.config import IntentSettings
from services.intent.node import IntentNode

HEADER = Header(stamp_ns=1, seq=0, source="test")


class FakePublisher:
    def __init__(self, bus: FakeBus) -> None:
        self.bus = bus

    def stamp(self) -> Header:
        return HEADER

    def send(self, message: Message) -> Message:
        self.bus.published.append(message)
        return message


class FakeBus:
    """Records what a node publishes; subscriptions and source checks are no-ops."""

    def __init__(self) -> None:
        self.settings = BusSettings()
        self.published: list[Any] = []

    def publisher(self, message_type: type) -> FakePublisher:
        return FakePublisher(self)

    def subscribe(self, *message_types: type) -> None: ...

    def expect(self, message_type: type, *sources: str) -> None: ...

    def key(self, message_type: type) -> str:
        return message_type.__name__

    def rehearse(self, due_s: float, work: Callable[[], object]) -> None:
        self.rehearsal = work  # run by a test when it wants


class ScriptedPerson:
    """A person at a sensor whose decisions the test makes (``decide``)."""

    person = True
    waits_for_model_choice = False

    def __init__(self) -> None:
        self.asked: list[Ask] = []
        self.coming: list[Decided] = []

    def open(self) -> None: ...
    def close(self) -> None: ...
    def new_episode(self, episode: int, seed: int) -> None: ...

    def ask(self, ask: Ask, now_s: float) -> None:
        self.asked.append(ask)

    def cancel(self) -> None: ...

    def poll(self, now_s: float) -> Decided | None:
        return self.coming.pop(0) if self.coming else None

    def readings(self) -> list[Reading]:
        return []

    def problem(self) -> str | None:
        return None

    def detail(self) -> str:
        return ""


def _step(node: IntentNode, *messages: Message) -> None:
    """Messages in, then one poll of the source (what the node's loop does)."""
    for message in messages:
        node._dispatch(message)
    node._ask_unanswered_by_the_policy()
    if (decided := node.source.poll(time.monotonic())) is not None:
        node._answer(decided)


def _goal(episode: int, seed: int) -> TaskGoal:
    return TaskGoal(header=HEADER, episode=episode, seed=seed, start_m=(0.3, 0, 0),
                    goal_m=(0.5, 0, -0.2), q_start_rad=(0, 1, 0, 1.6, 0, 0.3))  # fmt: skip


def _request(request: int, episode: int = 1, seed: int = 5, t_s: float = 1.0) -> DecisionRequest:
    return DecisionRequest(header=HEADER, episode=episode, seed=seed, request=request, t_s=t_s,
                           ee_pos_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2), primary_axis=0,
                           human_model=1)  # fmt: skip


def _choice(request: int, i: int, episode: int = 1) -> ModelChoice:
    return ModelChoice(header=HEADER, episode=episode, request=request, human_model=i,
                       robot_model=1, radius_m=0.004, steps_m=(0.01, 0.01, 0.01))  # fmt: skip


def _intent_node() -> tuple[IntentNode, FakeBus]:
    bus = FakeBus()
    source = SimulatedSource(SourceContext(ModelSet(), HumanModel()))
    node = IntentNode(IntentSettings(), source, "simulated", ModelSet(), bus)  # type: ignore[arg-type]
    return node, bus


def _fields(bus: FakeBus) -> list[dict[str, Any]]:
    return [m.model_dump(exclude={"header"}) for m in bus.published]


def test_a_policy_choice_that_overtakes_its_request_is_used_when_the_request_arrives() -> None:
    node, bus = _intent_node()
    _step(node, _goal(1, 5), _choice(1, 2))
    assert bus.published == []
    _step(node, _request(1))
    assert [(p["request"], p["human_model"]) for p in _fields(bus)] == [(1, 2)]


def test_a_repeated_task_goal_does_not_reseed_the_human_mid_episode() -> None:
    reference, reference_bus = _intent_node()
    node, bus = _intent_node()
    for target in (reference, node):
        _step(target, _goal(1, 5))
        for request in (1, 2, 3):
            if target is node and request == 3:
                _step(target, _goal(1, 5))  # the announcement, repeated
            _step(target, _choice(request, 1), _request(request))
    assert [p["decision_s"] for p in _fields(bus)] == [
        p["decision_s"] for p in _fields(reference_bus)
    ]


def test_an_intent_service_that_missed_the_announcement_seeds_from_the_first_request() -> None:
    """A late-joining intent service (it came up after the controller's last TaskGoal)
    draws the seed's decisions all the same: parity must not depend on start-up order."""
    reference, reference_bus = _intent_node()
    late, late_bus = _intent_node()
    _step(reference, _goal(1, 5))
    for target in (reference, late):
        for request in (1, 2, 3):
            _step(target, _choice(request, 1), _request(request))
    assert _fields(late_bus) == _fields(reference_bus)


def test_a_stray_request_of_an_older_episode_does_not_reseed_the_human() -> None:
    reference, reference_bus = _intent_node()
    node, bus = _intent_node()
    for target in (reference, node):
        _step(target, _goal(2, 6))
        if target is node:
            _step(node, _request(9, episode=1, seed=5))  # a late repeat from episode 1
        for request in (1, 2):
            _step(target, _choice(request, 1, episode=2), _request(request, episode=2, seed=6))
    assert len(reference_bus.published) == 2
    assert [p for p in _fields(bus) if p["episode"] == 2] == _fields(reference_bus)


def test_the_launcher_counts_only_the_controllers_new_results() -> None:
    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions
    from schemas import EpisodeResult, encode
    from tests.busutil import free_port

    stack = Stack(StackOptions(port=free_port(), insecure=True), info=lambda line: None)
    fields = dict(episode=1, seed=0, trigger="event", model=(2, 1), success=True, reached=True,
                  outcome="success", reason="button pressed", t_total_s=5.0, t_step_mean_s=0.5,
                  final_error_m=0.01, n_osc=1, n_osc_per_step=0.1, jerk_isj=1.0, sparc=-2.0,
                  ldlj=-7.0, human_error_rate=0.1, n_steps=10, n_decisions=10, button_pressed=True,
                  start_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2))  # fmt: skip
    genuine = EpisodeResult(header=Header(stamp_ns=1, seq=0, source="controller"), **fields)
    forged = EpisodeResult(header=Header(stamp_ns=1, seq=0, source="intruder"), **fields)
    assert stack.tally.accept(bytes(12)) is None  # garbage: ignored, never fatal
    assert stack.tally.accept(encode(forged)) is None
    accepted = stack.tally.accept(encode(genuine))
    assert accepted is not None
    stack.tally.results.append(accepted)
    assert stack.tally.accept(encode(genuine)) is None  # the same episode again: a replay


def test_the_controller_ignores_states_whose_time_runs_backwards_or_jumps() -> None:
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings
    from services.controller.node import ControllerNode

    bus = FakeBus()
    node = ControllerNode(ControllerSettings(), TaskSettings(), RobotSettings(), ModelSet(),
                          bus)  # type: ignore[arg-type]  # fmt: skip
    assert node._implausible_time(8.0) is None  # a restarted controller takes over
    node.started, node.last_t = True, 2.0
    assert node._implausible_time(2.01) is None
    assert node._implausible_time(1.99) is not None
    assert node._implausible_time(1e6) is not None


def test_the_controller_takes_steps_and_radius_from_the_model_set_not_from_a_message() -> None:
    import numpy as np

    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings
    from schemas import Intent
    from services.controller.node import ControllerNode

    node = ControllerNode(ControllerSettings(), TaskSettings(), RobotSettings(), ModelSet(),
                          FakeBus())  # type: ignore[arg-type]  # fmt: skip
    node._next_episode()
    assert node.reach is not None
    node.reach.asked, node.requests.number = True, 1
    huge = ModelChoice(header=HEADER, episode=1, request=1, human_model=2, robot_model=1,
                       radius_m=0.1, steps_m=(0.1, 0.1, 0.1))  # fmt: skip
    node._take_answer(huge)
    answer_of_human = Intent(header=HEADER, episode=1, request=1, u_h=1, human_model=2,
                             radius_m=0.1, confidence=1.0, source="pad", person=True,
                             decision_s=0.3)  # fmt: skip
    node._take_answer(answer_of_human)
    answer = node.reach.pending
    assert answer is not None and answer.steps_m is not None
    np.testing.assert_array_equal(answer.steps_m, ModelSet().steps_m(1))
    assert answer.intent.radius_m == ModelSet().radius_m(2)


def test_a_re_sent_request_gets_the_same_answer_from_the_simulated_human() -> None:
    node, bus = _intent_node()
    _step(node, _goal(1, 5), _choice(1, 2), _request(1))
    _step(node, _request(1))  # the controller heard nothing and sent it again
    assert len(bus.published) == 2 and _fields(bus)[0] == _fields(bus)[1]


def _person_node() -> tuple[IntentNode, ScriptedPerson, FakeBus]:
    bus, person = FakeBus(), ScriptedPerson()
    node = IntentNode(IntentSettings(), person, "pad", ModelSet(), bus)  # type: ignore[arg-type]
    return node, person, bus


def test_a_re_sent_request_gets_the_same_answer_from_a_person_not_a_new_decision() -> None:
    """The person's intent was lost on the way (the controller heard nothing and asks
    again): the same answer goes out again; a later decision answers nothing."""
    node, person, bus = _person_node()
    _step(node, _request(1))
    person.coming.append(Decided(u_h=1, human_model=2, confidence=0.9, decision_s=0.8))
    _step(node)
    _step(node, _request(1))  # re-sent
    person.coming.append(Decided(u_h=-1, human_model=1, confidence=0.9, decision_s=0.1))
    _step(node)
    assert len(bus.published) == 2 and _fields(bus)[0] == _fields(bus)[1]
    assert len(person.asked) == 1 and _fields(bus)[0]["person"]


def test_a_restarted_controllers_request_of_the_same_number_asks_the_person_afresh() -> None:
    """A controller restarted during episode 1 counts from 1 again: its request 1 (asked at
    another robot time) was answered from memory with the old press, and the arm moved
    on a decision the person never made for it."""
    node, person, bus = _person_node()
    _step(node, _request(1, t_s=1.0))
    person.coming.append(Decided(u_h=1, human_model=2, confidence=0.9, decision_s=0.8))
    _step(node)
    _step(node, _request(1, t_s=9.0))  # the restarted controller's
    assert len(bus.published) == 1 and len(person.asked) == 2  # asked, not answered
    person.coming.append(Decided(u_h=-1, human_model=1, confidence=0.9, decision_s=0.3))
    _step(node)
    assert [p["u_h"] for p in _fields(bus)] == [1, -1]
    _step(node, _request(1, t_s=9.0))  # a re-send of the new one: its own answer again
    assert [p["u_h"] for p in _fields(bus)] == [1, -1, -1]


def test_a_request_whose_episode_announcement_arrives_after_it_stays_open() -> None:
    """TaskGoal and DecisionRequest come on two subscriptions: the first request of an
    episode may overtake the episode's announcement. It stays open; a new episode closes
    an older episode's open request."""
    node, person, bus = _person_node()
    _step(node, _request(1), _goal(1, 5))  # the announcement late: the same episode
    person.coming.append(Decided(u_h=1, human_model=2, confidence=0.9, decision_s=0.8))
    _step(node)
    assert [p["request"] for p in _fields(bus)] == [1]
    _step(node, _request(2), _goal(2, 6))  # a new episode closes episode 1's open request
    assert node.open is None


def test_a_press_with_no_request_open_is_no_decision() -> None:
    from dammrl_core.intent.pad.source import PadSettings, PadSource

    pad = PadSource(PadSettings(port="/dev/null"))
    assert pad.open_since_s is None and pad.ignored_presses == 0


def test_the_controller_sends_an_unanswered_request_again() -> None:
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings
    from services.controller.node import ControllerNode

    bus = FakeBus()
    settings = ControllerSettings(request_resend_s=0.05)
    node = ControllerNode(settings, TaskSettings(), RobotSettings(), ModelSet(),
                          bus)  # type: ignore[arg-type]  # fmt: skip
    node._next_episode()
    assert node.reach is not None and node.plan is not None
    node.reach.asked = True
    bus.published.append(node.requests.make(node.asks.stamp, 0.0, np.zeros(3),
                                             node.plan.task.goal, 0, 1))  # fmt: skip
    sent = len(bus.published)
    node._resend_if_unanswered()
    assert len(bus.published) == sent  # not yet
    time.sleep(0.06)
    node._resend_if_unanswered()
    assert len(bus.published) == sent + 1 and bus.published[-1].request == 1
    assert "waiting for the answer to request 1" in node._waiting_for()


def test_planning_an_episode_is_not_a_stall_of_the_controller() -> None:
    """Planning the next reach may take longer than the state's staleness (a loaded
    machine: 0.3 s seen); the first state after it starts the reach, it does not end it as
    the controller's own stall. A real gap in the loop after that still does."""
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings
    from services.controller import node as controller

    node = controller.ControllerNode(ControllerSettings(), TaskSettings(), RobotSettings(),
                                     ModelSet(), FakeBus())  # type: ignore[arg-type]  # fmt: skip
    plan = controller.plan_reach

    def slow_plan(*args: object) -> controller.Plan:
        time.sleep(2 * node.stale_s)
        return plan(*args)  # type: ignore[arg-type]

    controller.plan_reach = slow_plan  # type: ignore[assignment]
    try:
        node._next_episode()
    finally:
        controller.plan_reach = plan
    node.started = True  # its first state came with the first look
    assert not node._stalled_itself(time.monotonic())
    assert node._stalled_itself(time.monotonic() + 2 * node.stale_s)


def _control(action: str, **decision: int) -> Message:
    from schemas import SessionControl

    return SessionControl(header=HEADER, episode=1, action=action, who="T1",
                          **decision)  # type: ignore[arg-type]  # fmt: skip


def test_a_takeover_answers_with_the_therapists_decisions_and_hands_back() -> None:
    """Taken over, the participant's device is not asked and its decisions are dropped;
    the therapist's answer goes out as the operator's, not a person's; handed back, the
    open request is asked of the participant afresh."""
    node, person, bus = _person_node()
    _step(node, _goal(1, 5), _request(1))
    assert len(person.asked) == 1
    _step(node, _control("take"))
    person.coming.append(Decided(u_h=-1, human_model=1, confidence=0.9, decision_s=0.5))
    _step(node)  # the participant pressed anyway: dropped
    assert bus.published == []
    _step(node, _control("decide", u_h=1, human_model=2))
    (answer,) = _fields(bus)
    assert (answer["source"], answer["person"], answer["u_h"]) == ("operator", False, 1)
    assert answer["human_model"] == 2 and answer["confidence"] == 1.0
    _step(node, _request(2))
    assert len(person.asked) == 1  # taken over: the device is not asked
    _step(node, _control("give"))
    assert len(person.asked) == 2 and person.asked[-1].request == 2  # asked afresh
    person.coming.append(Decided(u_h=-1, human_model=1, confidence=0.9, decision_s=0.5))
    _step(node)
    assert _fields(bus)[-1]["source"] == "pad" and _fields(bus)[-1]["person"]
    _step(node, _control("decide", u_h=1, human_model=1))  # not taken over: ignored
    assert len(bus.published) == 2
    _step(node, _control("take"), _control("decide", u_h=-1, human_model=1))  # too early
    _step(node, _request(3))  # its request comes after it: answered at once
    assert _fields(bus)[-1]["request"] == 3 and _fields(bus)[-1]["source"] == "operator"


def test_the_posterior_learns_nothing_from_the_therapists_decisions() -> None:
    from dammrl_core.human import HumanModel
    from dammrl_core.policy.settings import PolicySettings
    from schemas import Intent
    from services.policy.node import PolicyNode

    settings = PolicySettings(kind="fixed", estimate_human="always")
    node = PolicyNode(settings, HumanModel(), ModelSet(), FakeBus())  # type: ignore[arg-type]
    for request, source in ((1, "operator"), (2, "pad")):
        node._answer(_request(request))
        node._observe_human(Intent(header=HEADER, episode=1, request=request, u_h=1,
                                   human_model=2, radius_m=0.01, confidence=1.0,
                                   source=source, person=source == "pad",
                                   decision_s=0.6))  # fmt: skip
    assert node.posterior.decisions == 1  # the participant's only


def test_the_controller_gives_a_policy_that_came_alive_late_its_whole_wait() -> None:
    """Beside two CPU hogs the stack's start-up took longer than the policy's wait: the
    controller started the first reach into that start-up (and it held at 0.7 s). The wait
    counts from the policy's liveliness; a policy never alive still gets it from the start."""
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings
    from services.controller.node import ControllerNode

    class StartingBus(FakeBus):
        """The policy comes alive after 0.3 s and speaks 0.4 s after that."""

        def __init__(self) -> None:
            super().__init__()
            self.start = time.monotonic()

        def receive(self, timeout_s: float) -> Message | None:
            time.sleep(0.01)
            return _choice(-1, 2) if time.monotonic() - self.start > 0.7 else None

        def alive_peers(self) -> set[str]:
            late = time.monotonic() - self.start > 0.3
            return {"intent", "policy"} if late else {"intent"}

        def report_health(self, state: str, detail: str) -> None: ...

    bus = StartingBus()
    node = ControllerNode(ControllerSettings(policy_wait_s=0.5), TaskSettings(), RobotSettings(),
                          ModelSet(), bus)  # type: ignore[arg-type]  # fmt: skip
    node._wait_for_peers(threading.Event())
    assert node.choice[0] == 2  # it waited past 0.5 s from its start, for the policy's choice
    never = StartingBus()
    never.alive_peers = lambda: {"intent"}  # type: ignore[method-assign]
    node = ControllerNode(ControllerSettings(policy_wait_s=0.5), TaskSettings(), RobotSettings(),
                          ModelSet(), never)  # type: ignore[arg-type]  # fmt: skip
    node._wait_for_peers(threading.Event())
    assert node.choice[0] != 2  # its 0.5 s from the start ran out before the choice came


def _controller_in_a_reach() -> tuple[Any, FakeBus, np.ndarray]:
    """A controller node in its first reach, its last command a hold of the start posture
    ``q`` (returned with its bus)."""
    from dammrl_core.control.settings import ControllerSettings
    from dammrl_core.models import ModelSet
    from dammrl_core.robot import RobotSettings
    from dammrl_core.state import JointCommand as CoreCommand
    from dammrl_core.task import TaskSettings
    from services.controller.node import ControllerNode

    bus = FakeBus()
    node = ControllerNode(ControllerSettings(), TaskSettings(), RobotSettings(), ModelSet(),
                          bus)  # type: ignore[arg-type]  # fmt: skip
    q = np.array(TaskSettings().home_q_rad)
    node._next_episode()
    node.last_command = CoreCommand(q, np.zeros(6), np.zeros(6), np.full(6, 40.0), np.full(6, 4.0))
    return node, bus, q


def test_between_two_reaches_the_controller_holds_the_arm_until_its_reset() -> None:
    """The next reach announced, the arm not yet reset: each state of the last reach is
    answered with a hold of its final reference for that reach (else the arm holds for
    want of commands, and says so, between every two reaches on a loaded machine)."""
    from dammrl_core.state import RobotState as CoreState
    from schemas import JointCommand
    from services.common import convert

    node, bus, q = _controller_in_a_reach()
    node._next_episode()  # reach 2 announced; the arm is still in reach 1
    zeros = np.zeros(3)
    state = CoreState(1.0, q, np.zeros(6), np.zeros(6), zeros, zeros, False, 0.0)
    header = Header(stamp_ns=77, seq=5, source="sim")
    node._on_state(convert.state_message(header, state, 1, holding=False))
    holds = [m for m in bus.published if isinstance(m, JointCommand)]
    assert len(holds) == 1 and holds[0].episode == 1 and holds[0].state_stamp_ns == 77
    np.testing.assert_allclose(holds[0].q_ref_rad, q)
    np.testing.assert_allclose(holds[0].dq_ref_rad_s, 0.0)
    node._on_state(convert.state_message(header, state, 0, holding=False))  # older: nothing
    assert len([m for m in bus.published if isinstance(m, JointCommand)]) == 1


def test_after_a_stop_the_controller_never_pulls_the_arm_back_to_an_old_reference() -> None:
    """A release returns the arm to its ordinary hold, not to motion: the arm may have been
    moved by hand, so neither between reaches nor until the next reset does the controller
    command the reference it had before the stop."""
    from dammrl_core.state import RobotState as CoreState
    from schemas import EmergencyStop, JointCommand
    from services.common import convert

    node, bus, q = _controller_in_a_reach()
    operator = Header(stamp_ns=2, seq=0, source="operator")
    for engaged in (True, False):
        node._take_stop(EmergencyStop(header=operator, engaged=engaged))
    zeros = np.zeros(3)
    state = CoreState(1.0, q + 0.3, np.zeros(6), np.zeros(6), zeros, zeros, False, 0.0)
    node._on_state(convert.state_message(Header(stamp_ns=77, seq=5, source="sim"), state, 1,
                                         holding=True))  # fmt: skip
    node._next_episode()  # the next reach announced, the arm not yet reset
    node._on_state(convert.state_message(Header(stamp_ns=78, seq=6, source="sim"), state, 1,
                                         holding=True))  # fmt: skip
    assert not [m for m in bus.published if isinstance(m, JointCommand)]


def test_the_controller_sends_the_arms_command_before_the_request_and_the_ik() -> None:
    """Off lockstep nothing in a tick's command waits for the decision request it sends,
    nor for the IK of a step planned from a resting reference: the command goes out first,
    and exactly one answers each state."""
    from dammrl_core.state import RobotState as CoreState
    from schemas import DecisionRequest, Intent, JointCommand
    from services.common import convert

    node, bus, _ = _controller_in_a_reach()
    assert node.plan is not None and node.reach is not None
    q = node.plan.q_start
    zeros = np.zeros(3)
    ik_after: list[int] = []  # how many commands were out when each solve began
    solve = node.reach.controller.ik.solve

    def watched(target: np.ndarray, q_seed: np.ndarray) -> Any:
        ik_after.append(sum(isinstance(m, JointCommand) for m in bus.published))
        return solve(target, q_seed)

    node.reach.controller.ik.solve = watched  # type: ignore[method-assign]

    def state(k: int) -> None:
        core = CoreState(k * 0.01, q, np.zeros(6), np.zeros(6), node.arm.ee_position(q), zeros,
                         False, 0.0)  # fmt: skip
        header = Header(stamp_ns=100 + k, seq=k, source="sim")
        node._on_state(convert.state_message(header, core, 1, holding=False))

    bus.published.clear()  # the episode's announcement
    state(0)  # the reach's first tick asks for a decision
    assert [type(m) for m in bus.published] == [JointCommand, DecisionRequest]
    node._take_answer(_choice(1, 2))
    node._take_answer(Intent(header=HEADER, episode=1, request=1, u_h=1, human_model=2,
                             radius_m=0.01, confidence=1.0, source="pad", person=True,
                             decision_s=0.02))  # fmt: skip
    for k in range(1, 6):  # the answer is due at 0.02 s: the step is planned there
        state(k)
    commands = [m for m in bus.published if isinstance(m, JointCommand)]
    assert [m.state_stamp_ns for m in commands] == [100 + k for k in range(6)]
    assert ik_after == [3]  # the plan's tick (0.02 s) had its command out before its IK
