"""Service nodes without a network: their message handling, driven by hand."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dammrl.core.human import HumanModel
from dammrl.core.models import ModelSet
from schemas import DecisionRequest, Header, ModelChoice, TaskGoal
from services.common.config import BusSettings
from services.intent.config import IntentSettings
from services.intent.node import IntentNode

HEADER = Header(stamp_ns=1, seq=0, source="test")


class FakeBus:
    """Records what a node publishes; subscriptions and source checks are no-ops."""

    def __init__(self) -> None:
        self.settings = BusSettings()
        self.published: list[dict[str, Any]] = []

    def publisher(self, message_type: type) -> FakeBus:
        return self

    def publish(self, **fields: Any) -> None:
        self.published.append(fields)

    def subscribe(self, *message_types: type) -> None: ...

    def expect(self, message_type: type, *sources: str) -> None: ...

    def key(self, message_type: type) -> str:
        return message_type.__name__


def _goal(episode: int, seed: int) -> TaskGoal:
    return TaskGoal(header=HEADER, episode=episode, seed=seed, start_m=(0.3, 0, 0),
                    goal_m=(0.5, 0, -0.2), q_start_rad=(0, 1, 0, 1.6, 0, 0.3))  # fmt: skip


def _request(request: int, episode: int = 1, seed: int = 5) -> DecisionRequest:
    return DecisionRequest(header=HEADER, episode=episode, seed=seed, request=request, t_s=1.0,
                           ee_pos_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2), primary_axis=0,
                           human_model=1)  # fmt: skip


def _choice(request: int, i: int, episode: int = 1) -> ModelChoice:
    return ModelChoice(header=HEADER, episode=episode, request=request, human_model=i,
                       robot_model=1, radius_m=0.004, steps_m=(0.01, 0.01, 0.01))  # fmt: skip


def _intent_node() -> tuple[IntentNode, FakeBus]:
    bus = FakeBus()
    node = IntentNode(IntentSettings(), HumanModel(), ModelSet(), bus)  # type: ignore[arg-type]
    return node, bus


def test_a_policy_choice_that_overtakes_its_request_is_used_when_the_request_arrives() -> None:
    node, bus = _intent_node()
    node._dispatch(_goal(1, 5))
    node._dispatch(_choice(1, 2))
    assert bus.published == []
    node._dispatch(_request(1))
    assert [(p["request"], p["human_model"]) for p in bus.published] == [(1, 2)]


def test_a_repeated_task_goal_does_not_reseed_the_human_mid_episode() -> None:
    reference, reference_bus = _intent_node()
    node, bus = _intent_node()
    for target in (reference, node):
        target._dispatch(_goal(1, 5))
        for request in (1, 2, 3):
            if target is node and request == 3:
                target._dispatch(_goal(1, 5))  # the announcement, repeated
            target._dispatch(_choice(request, 1))
            target._dispatch(_request(request))
    assert [p["decision_s"] for p in bus.published] == [
        p["decision_s"] for p in reference_bus.published
    ]


def test_an_intent_service_that_missed_the_announcement_seeds_from_the_first_request() -> None:
    """A late-joining intent service (it came up after the controller's last TaskGoal)
    draws the seed's decisions all the same: parity must not depend on start-up order."""
    reference, reference_bus = _intent_node()
    late, late_bus = _intent_node()
    reference._dispatch(_goal(1, 5))
    for target in (reference, late):
        for request in (1, 2, 3):
            target._dispatch(_choice(request, 1))
            target._dispatch(_request(request))
    assert late_bus.published == reference_bus.published


def test_a_stray_request_of_an_older_episode_does_not_reseed_the_human() -> None:
    reference, reference_bus = _intent_node()
    node, bus = _intent_node()
    for target in (reference, node):
        target._dispatch(_goal(2, 6))
        if target is node:
            node._dispatch(_request(9, episode=1, seed=5))  # a late repeat from episode 1
        for request in (1, 2):
            target._dispatch(_choice(request, 1, episode=2))
            target._dispatch(_request(request, episode=2, seed=6))
    assert len(reference_bus.published) == 2
    assert [p for p in bus.published if p["episode"] == 2] == reference_bus.published


def test_the_launcher_counts_only_the_controllers_new_results() -> None:
    from dammrl.launch import Stack, StackOptions
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
    assert stack._accept(bytes(12)) is None  # garbage: ignored, never fatal
    assert stack._accept(encode(forged)) is None
    accepted = stack._accept(encode(genuine))
    assert accepted is not None
    stack.results.append(accepted)
    assert stack._accept(encode(genuine)) is None  # the same episode again: a replay


def test_the_controller_ignores_states_whose_time_runs_backwards_or_jumps() -> None:
    from dammrl.core.models import ModelSet
    from dammrl.core.robot import RobotSettings
    from dammrl.core.task import TaskSettings
    from services.controller.config import ControllerSettings
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

    from dammrl.core.models import ModelSet
    from dammrl.core.robot import RobotSettings
    from dammrl.core.task import TaskSettings
    from schemas import Intent
    from services.controller.config import ControllerSettings
    from services.controller.node import ControllerNode

    node = ControllerNode(ControllerSettings(), TaskSettings(), RobotSettings(), ModelSet(),
                          FakeBus())  # type: ignore[arg-type]  # fmt: skip
    node._next_episode()
    assert node.reach is not None
    node.reach.asked, node.request = True, 1
    huge = ModelChoice(header=HEADER, episode=1, request=1, human_model=2, robot_model=1,
                       radius_m=0.1, steps_m=(0.1, 0.1, 0.1))  # fmt: skip
    node._on_choice(huge)
    answer_of_human = Intent(header=HEADER, episode=1, request=1, u_h=1, human_model=2,
                             radius_m=0.1, confidence=1.0, source="sensor",
                             decision_s=0.3)  # fmt: skip
    node._on_intent(answer_of_human)
    answer = node.reach.pending
    assert answer is not None and answer.steps_m is not None
    np.testing.assert_array_equal(answer.steps_m, ModelSet().steps_m(1))
    assert answer.intent.radius_m == ModelSet().radius_m(2)


def test_a_re_sent_request_gets_the_same_answer_from_the_simulated_human() -> None:
    node, bus = _intent_node()
    node._dispatch(_goal(1, 5))
    node._dispatch(_choice(1, 2))
    node._dispatch(_request(1))
    node._dispatch(_request(1))  # the controller heard nothing and sent it again
    assert len(bus.published) == 2 and bus.published[0] == bus.published[1]


def test_a_re_sent_request_gets_the_same_answer_from_the_sensor_not_a_new_press() -> None:
    """The sensor's intent was lost on the way (the controller heard nothing and asks
    again): the same answer goes out again; a later press answers nothing."""
    from services.intent.config import IntentSettings
    from services.intent.decoder import PressDecision
    from services.intent.sensor_node import SensorIntentNode

    bus = FakeBus()
    node = SensorIntentNode(IntentSettings(port="/dev/null"), ModelSet(), bus)  # type: ignore[arg-type]
    node._dispatch(_request(1))
    node._answer(PressDecision(t_s=1.0, u_h=1, human_model=2, confidence=0.9, duration_s=0.8,
                               peak=0.9))  # fmt: skip
    node._dispatch(_request(1))  # re-sent
    node._answer(PressDecision(t_s=3.0, u_h=-1, human_model=1, confidence=0.9, duration_s=0.1,
                               peak=0.9))  # fmt: skip
    assert len(bus.published) == 2 and bus.published[0] == bus.published[1]
    assert node.ignored_presses == 1


def test_the_sensor_keeps_a_request_whose_episode_announcement_arrives_after_it() -> None:
    """TaskGoal and DecisionRequest come on two subscriptions: the first request of an
    episode may overtake the episode's announcement. It stays open (it was dropped, and
    every re-send ignored as a repeat: no press was ever answered)."""
    from services.intent.config import IntentSettings
    from services.intent.decoder import PressDecision
    from services.intent.sensor_node import SensorIntentNode

    bus = FakeBus()
    node = SensorIntentNode(IntentSettings(port="/dev/null"), ModelSet(), bus)  # type: ignore[arg-type]
    node._dispatch(_request(1))
    node._dispatch(_goal(1, 5))  # late: the same episode
    node._answer(PressDecision(t_s=1.0, u_h=1, human_model=2, confidence=0.9, duration_s=0.8,
                               peak=0.9))  # fmt: skip
    assert [p["request"] for p in bus.published] == [1]
    node._dispatch(_request(2))
    node._dispatch(_goal(2, 6))  # a new episode closes episode 1's open request
    assert node.request is None


def test_the_controller_sends_an_unanswered_request_again() -> None:
    from dammrl.core.models import ModelSet
    from dammrl.core.robot import RobotSettings
    from dammrl.core.task import TaskSettings
    from services.controller.config import ControllerSettings
    from services.controller.node import ControllerNode

    bus = FakeBus()
    settings = ControllerSettings(request_resend_s=0.05)
    node = ControllerNode(settings, TaskSettings(), RobotSettings(), ModelSet(),
                          bus)  # type: ignore[arg-type]  # fmt: skip
    node._next_episode()
    assert node.reach is not None and node.episode is not None
    node.reach.asked = True
    node._request_decision(np.zeros(3), node.episode)
    sent = len(bus.published)
    node._resend_if_unanswered()
    assert len(bus.published) == sent  # not yet
    time.sleep(0.06)
    node._resend_if_unanswered()
    assert len(bus.published) == sent + 1 and bus.published[-1]["request"] == 1
    assert "waiting for the answer to request 1" in node._waiting_for()
