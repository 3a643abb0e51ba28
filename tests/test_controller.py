"""The controller core, driven with hand-made states: steps, triggers, holds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dammrl_core.control.controller import Controller, latency_model
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.control.trajectory import QuinticSegment
from dammrl_core.dynamics import ArmModel, joint_limit_avoidance
from dammrl_core.ik import IKResult
from dammrl_core.robot import RobotDescription
from dammrl_core.state import Intent, JointCommand, RobotState
from tests.conftest import HOME_Q, random_postures


def _state(arm: ArmModel, q: np.ndarray, t: float, ee_vel: np.ndarray | None = None) -> RobotState:
    return RobotState(
        t_s=t,
        q=q,
        dq=np.zeros(6),
        tau=np.zeros(6),
        ee_pos=arm.ee_position(q),
        ee_vel=np.zeros(3) if ee_vel is None else ee_vel,
        button_pressed=False,
        button_travel_m=0.0,
    )


def _controller(robot: RobotDescription, arm: ArmModel, **settings: object) -> Controller:
    config = ControllerSettings(ik_latency="zero", **settings)  # type: ignore[arg-type]
    return Controller(robot, config, np.random.default_rng(0), arm)


def _intent(u_h: int = 1, radius_m: float = 0.004) -> Intent:
    return Intent(t_s=0.0, u_h=u_h, radius_m=radius_m, human_model=2)


def test_event_controller_asks_for_a_decision_then_steps(
    robot: RobotDescription, arm: ArmModel
) -> None:
    controller = _controller(robot, arm)
    start = _state(arm, HOME_Q, 0.0)
    goal = start.ee_pos + np.array([0.2, 0.05, -0.05])
    controller.reset(start, goal)
    assert controller.wants_intent
    controller.on_intent(_intent())
    out = controller.tick(start)
    assert [s.index for s in out.steps] == [1]
    np.testing.assert_allclose(out.steps[0].dx, [0.01, 0.01, -0.01])
    assert not controller.wants_intent  # waiting for the trigger now


def test_step_waits_for_the_trigger_before_the_next_decision(
    robot: RobotDescription, arm: ArmModel
) -> None:
    controller = _controller(robot, arm)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    step = controller.tick(start).steps[0]
    assert controller.subgoal is not None
    controller.tick(_state(arm, HOME_Q, 0.05))  # still 10 mm away: no trigger
    assert not controller.wants_intent
    q_there = controller.segment.target
    moving_away = -(step.dx / np.linalg.norm(step.dx)) * 0.05
    controller.tick(_state(arm, q_there, 0.3, ee_vel=moving_away))  # inside, but dV/dt > 0
    assert not controller.wants_intent
    controller.tick(_state(arm, q_there, 0.31))  # inside and settled
    assert controller.wants_intent


def test_no_trigger_within_the_timeout_ends_in_a_hold(
    robot: RobotDescription, arm: ArmModel
) -> None:
    controller = _controller(robot, arm, trigger_timeout_s=1.0)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    controller.tick(start)
    out = controller.tick(_state(arm, HOME_Q, 1.5))  # the arm never moved
    assert out.hold_reason is not None and "no trigger within 1.0 s" in out.hold_reason
    assert not controller.wants_intent


def test_target_outside_the_workspace_ends_in_a_hold(
    robot: RobotDescription, arm: ArmModel
) -> None:
    start = _state(arm, HOME_Q, 0.0)
    controller = _controller(robot, arm, workspace_max_m=tuple(start.ee_pos + 0.005))
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    out = controller.tick(start)
    assert out.hold_reason is not None and "outside the workspace" in out.hold_reason
    np.testing.assert_allclose(out.command.q_ref, HOME_Q)  # held where it was


def test_limit_violation_ends_in_a_hold_at_the_last_reference(
    robot: RobotDescription, arm: ArmModel
) -> None:
    controller = _controller(robot, arm)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    beyond = HOME_Q.copy()
    beyond[3] = robot.q_max[3] + 0.1
    out = controller.tick(_state(arm, beyond, 0.01))
    assert out.hold_reason is not None and "elbow_flexion" in out.hold_reason
    np.testing.assert_allclose(out.command.q_ref, HOME_Q)


def test_fixed_controller_steps_on_its_timer_with_the_latest_intent(
    robot: RobotDescription, arm: ArmModel
) -> None:
    controller = _controller(robot, arm, trigger="fixed", fixed_period_s=0.1)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    started = [controller.tick(_state(arm, HOME_Q, t)).steps for t in np.arange(0, 0.35, 0.01)]
    times = [steps[0].t_s for steps in started if steps]
    np.testing.assert_allclose(times, [0.0, 0.1, 0.2, 0.3], atol=1e-9)  # the arm never moved


def test_feedforward_torque_is_saturated(robot: RobotDescription, arm: ArmModel) -> None:
    controller = _controller(robot, arm)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos)
    controller.robot = RobotDescription(**{**robot.__dict__, "tau_max": np.full(6, 0.1)})
    controller.segment = controller.segment.plan(
        0.0, 0.1, HOME_Q, np.zeros(6), np.zeros(6), HOME_Q + 0.5
    )
    command = controller.tick(_state(arm, HOME_Q, 0.02)).command
    assert np.all(np.abs(command.tau_ff) <= 0.1)


def test_resolved_acceleration_keeps_the_task_acceleration(
    arm: ArmModel, robot: RobotDescription
) -> None:
    rng = np.random.default_rng(0)
    for q in random_postures(robot, 5, seed=7):
        dq, ddx = rng.normal(0, 0.5, 6), rng.normal(0, 1.0, 3)
        z = joint_limit_avoidance(robot, q, 5.0) + rng.normal(0, 1.0, 6)
        ddq = arm.resolved_acceleration(q, dq, ddx, z)
        achieved = arm.ee_jacobian(q) @ ddq + arm.ee_drift_acceleration(q, dq)
        np.testing.assert_allclose(achieved, ddx, atol=1e-9)


def test_drift_acceleration_matches_finite_differences(arm: ArmModel) -> None:
    q, dq, h = HOME_Q, np.array([0.3, -0.2, 0.1, 0.4, -0.3, 0.2]), 1e-6
    velocity = lambda s: arm.ee_jacobian(q + s * dq) @ dq  # noqa: E731
    numeric = (velocity(h) - velocity(-h)) / (2 * h)
    np.testing.assert_allclose(arm.ee_drift_acceleration(q, dq), numeric, atol=1e-6)


def test_joint_limit_avoidance_points_to_mid_range(robot: RobotDescription) -> None:
    z = joint_limit_avoidance(robot, robot.q_max, 3.0)
    np.testing.assert_allclose(z, -3.0)
    np.testing.assert_allclose(
        joint_limit_avoidance(robot, (robot.q_min + robot.q_max) / 2, 3.0), 0.0
    )


def test_bad_step_vector_is_refused(robot: RobotDescription, arm: ArmModel) -> None:
    with pytest.raises(ValueError, match="3 positive numbers"):
        _controller(robot, arm).set_steps(np.array([0.01, -0.01, np.nan]))


def _arrays(command: JointCommand) -> list[np.ndarray]:
    return [command.q_ref, command.dq_ref, command.tau_ff, command.kp, command.kd]


def _watch_ik(controller: Controller, order: list[str]) -> None:
    solve = controller.ik.solve

    def watched(target: np.ndarray, q_seed: np.ndarray) -> IKResult:
        order.append("ik")
        return solve(target, q_seed)

    controller.ik.solve = watched  # type: ignore[method-assign]


@pytest.mark.parametrize(
    ("latency", "workspace_m"),
    [("zero", None), ("model", None), ("zero", 0.005)],
    ids=["started at once", "started after the IK latency", "refused: a hold"],
)
def test_a_step_from_rest_gives_its_command_before_its_ik(
    robot: RobotDescription, arm: ArmModel, latency: str, workspace_m: float | None
) -> None:
    """The tick that plans a step from a resting reference hands its command out before
    the IK runs (the bus sends it to the arm first), and it is the command the tick would
    have ended with after the plan: a step started at once, one started later, a hold."""
    start = _state(arm, HOME_Q, 0.0)
    bounds = {} if workspace_m is None else {"workspace_max_m": tuple(start.ee_pos + workspace_m)}
    controller = _controller(robot, arm, **bounds)
    controller.settings = controller.settings.model_copy(update={"ik_latency": latency})
    controller.latency = latency_model(controller.settings, np.random.default_rng(0))
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    order: list[str] = []
    _watch_ik(controller, order)
    early: list[JointCommand] = []

    def take(command: JointCommand) -> None:
        order.append("command")
        early.append(command)

    out = controller.tick(start, early=take)
    assert order[0] == "command" and len(early) == 1 and out.command is early[0]
    after_the_plan = controller._command(start)  # what the tick ended with before
    for sent, planned in zip(_arrays(out.command), _arrays(after_the_plan), strict=True):
        np.testing.assert_array_equal(sent, planned)
    assert (out.hold_reason is not None) == (workspace_m is not None)
    assert len(out.steps) == (1 if latency == "zero" and workspace_m is None else 0)


def test_a_step_planned_while_the_reference_moves_has_its_ik_before_its_command(
    robot: RobotDescription, arm: ArmModel
) -> None:
    """A trigger that fires before the reference comes to rest: the next step's tick
    samples a reference the plan may change, so its command waits for the plan."""
    controller = _controller(robot, arm)
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    controller.tick(start)  # the first step starts at once
    segment = controller.segment
    midway = segment.t0_s + segment.duration_s / 2
    controller.tick(_state(arm, segment.target, midway))  # at the subgoal, settled: fired
    assert controller.wants_intent and not segment.finished(midway + 0.01)
    controller.on_intent(_intent())
    order: list[str] = []
    _watch_ik(controller, order)
    out = controller.tick(_state(arm, segment.target, midway + 0.01),
                          early=lambda _: order.append("command"))  # fmt: skip
    assert order == ["ik"] and len(out.steps) == 1


def test_a_step_planned_from_rest_starts_on_the_reference_a_fresh_plan_gives(
    robot: RobotDescription, arm: ArmModel
) -> None:
    """A step planned from a resting reference has its reference made with the plan (off
    the tick that starts it): started later, it is bitwise the one planned at the start."""
    controller = _controller(robot, arm)
    controller.settings = controller.settings.model_copy(update={"ik_latency": "model"})
    controller.latency = latency_model(controller.settings, np.random.default_rng(0))
    start = _state(arm, HOME_Q, 0.0)
    controller.reset(start, start.ee_pos + np.array([0.2, 0.0, 0.0]))
    controller.on_intent(_intent())
    rest = controller.segment
    controller.tick(start)
    (planned,) = controller.planned
    t = math.ceil(planned.ready_s / 0.01) * 0.01
    q0, v0, a0 = rest.sample(t)
    fresh = QuinticSegment.plan(t, controller._duration(planned, q0), q0, v0, a0, planned.q_target)
    (step,) = controller.tick(_state(arm, HOME_Q, t)).steps
    started = controller.segment
    assert started is not rest and started.t0_s == t and step.index == 1
    assert started.duration_s == fresh.duration_s
    np.testing.assert_array_equal(started.coeffs, fresh.coeffs)
    for mine, theirs in zip(started.rest, fresh.rest, strict=True):
        np.testing.assert_array_equal(mine, theirs)
