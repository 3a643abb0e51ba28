"""The therapist's pause: the reach's clock stops, the arm holds the last reference at
rest (tests/test_session_stack.py pauses a running reach on the bus)."""

from __future__ import annotations

import numpy as np

from dammrl_core.control.pause import Pause, hold_command
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from dammrl_core.state import JointCommand


def test_the_reach_clock_stops_while_paused_and_goes_on_from_there() -> None:
    pause = Pause()
    assert pause.reach_time(3.0) == 3.0
    assert pause.begin(3.0) and not pause.begin(3.5)  # a second pause changes nothing
    assert pause.reach_time(4.0) == pause.reach_time(9.0) == 3.0
    assert pause.end(9.0) and not pause.end(9.5)
    assert pause.reach_time(10.0) == 4.0 and pause.paused_s(10.0) == 6.0
    pause.begin(11.0)
    assert pause.paused_s(12.0) == 7.0 and pause.count == 2


def test_the_hold_keeps_the_reference_at_rest_against_gravity() -> None:
    robot = RobotSettings().load()
    arm = ArmModel(robot)
    q = np.array([0.1, 0.4, 0.0, 0.9, 0.0, 0.2])
    moving = JointCommand(q, np.full(6, 0.3), np.zeros(6), np.full(6, 50.0), np.full(6, 2.0))
    hold = hold_command(arm, moving, robot.tau_max)
    np.testing.assert_array_equal(hold.q_ref, q)
    np.testing.assert_array_equal(hold.dq_ref, np.zeros(6))
    gravity = arm.inverse_dynamics(q, np.zeros(6), np.zeros(6))
    np.testing.assert_allclose(hold.tau_ff, np.clip(gravity, -robot.tau_max, robot.tau_max))
    assert np.any(np.abs(hold.tau_ff) > 0.1)  # the shoulder and elbow carry the arm
    np.testing.assert_array_equal(hold.kp, moving.kp)
