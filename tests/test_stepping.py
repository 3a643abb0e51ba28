"""Micro-steps (eq. 2), the event trigger (eq. 1), the fixed timer, the quintic reference."""

from __future__ import annotations

import numpy as np
import pytest

from dammrl_core.control.stepping import (
    event_trigger,
    fixed_timer_due,
    lyapunov,
    lyapunov_rate,
    micro_step,
)
from dammrl_core.control.trajectory import QuinticSegment, segment_duration

W = np.ones(3)
STEPS = np.array([0.01, 0.02, 0.03])


def test_primary_axis_follows_the_human_even_when_wrong() -> None:
    error = np.array([0.1, 0.1, 0.1])
    assert micro_step(error, +1, STEPS, 0, True)[0] == pytest.approx(0.01)
    assert micro_step(error, -1, STEPS, 0, True)[0] == pytest.approx(-0.01)


def test_orthogonal_axes_move_toward_the_goal_by_their_step() -> None:
    dx = micro_step(np.array([0.1, -0.1, 0.1]), 1, STEPS, 0, True)
    np.testing.assert_allclose(dx, [0.01, -0.02, 0.03])


def test_orthogonal_axis_within_half_a_step_stays_put() -> None:
    dx = micro_step(np.array([0.1, 0.009, -0.016]), 1, STEPS, 0, True)
    np.testing.assert_allclose(dx, [0.01, 0.0, -0.03])
    pure_sign = micro_step(np.array([0.1, 0.009, -0.016]), 1, STEPS, 0, False)
    np.testing.assert_allclose(pure_sign, [0.01, 0.02, -0.03])


def test_primary_axis_can_be_z() -> None:
    dx = micro_step(np.array([0.1, 0.1, 0.1]), -1, STEPS, 2, True)
    np.testing.assert_allclose(dx, [0.01, 0.02, -0.03])


def test_binary_command_must_be_plus_or_minus_one() -> None:
    with pytest.raises(ValueError, match="u_h must be -1 or \\+1, got 0"):
        micro_step(np.ones(3), 0, STEPS, 0, True)


def test_lyapunov_rate_matches_finite_difference() -> None:
    subgoal, x, v = (
        np.array([0.1, 0.2, 0.3]),
        np.array([0.12, 0.17, 0.31]),
        np.array([0.3, -0.2, 0.1]),
    )
    weights = np.array([1.0, 2.0, 0.5])
    h = 1e-7
    numeric = (lyapunov(subgoal - (x + h * v), weights) - lyapunov(subgoal - x, weights)) / h
    assert lyapunov_rate(subgoal - x, v, weights) == pytest.approx(numeric, rel=1e-5)


def test_trigger_fires_only_when_inside_and_energy_decreases() -> None:
    subgoal = np.zeros(3)
    inside, outside = np.array([0.003, 0, 0]), np.array([0.02, 0, 0])
    toward, away = np.array([-0.1, 0, 0]), np.array([0.1, 0, 0])
    assert event_trigger(inside, toward, subgoal, 0.005, W)
    assert event_trigger(inside, np.zeros(3), subgoal, 0.005, W)  # settled: dV/dt = 0
    assert not event_trigger(inside, away, subgoal, 0.005, W)
    assert not event_trigger(outside, toward, subgoal, 0.005, W)
    assert not event_trigger(outside, away, subgoal, 0.005, W)


def test_trigger_waits_until_energy_decreases() -> None:
    subgoal = np.zeros(3)
    x = np.array([0.002, 0.0, 0.0])
    overshooting = np.array([0.05, 0.0, 0.0])
    assert not event_trigger(x, overshooting, subgoal, 0.005, W)
    assert event_trigger(x, -overshooting, subgoal, 0.005, W)


def test_fixed_timer_is_due_every_period_whatever_the_arm_does() -> None:
    assert fixed_timer_due(0.0, None, 0.1)
    assert not fixed_timer_due(0.05, 0.0, 0.1)
    assert fixed_timer_due(0.1, 0.0, 0.1)


def test_quintic_meets_its_boundary_conditions() -> None:
    q0, v0, a0, q1 = np.full(6, 0.1), np.full(6, 0.5), np.full(6, -1.0), np.full(6, 0.3)
    segment = QuinticSegment.plan(2.0, 0.4, q0, v0, a0, q1)
    for value, expected in zip(segment.sample(2.0), (q0, v0, a0), strict=True):
        np.testing.assert_allclose(value, expected, atol=1e-12)
    for value, expected in zip(segment.sample(2.4 - 1e-12), (q1, 0 * q1, 0 * q1), strict=True):
        np.testing.assert_allclose(value, expected, atol=1e-8)
    np.testing.assert_allclose(segment.target, q1)


def test_quintic_velocity_is_the_derivative_of_position() -> None:
    segment = QuinticSegment.plan(0.0, 0.3, np.zeros(6), np.ones(6), np.zeros(6), np.ones(6))
    h = 1e-6
    for t in (0.05, 0.15, 0.25):
        (q_a, _, _), (q_b, dq, _) = segment.sample(t - h), segment.sample(t)
        np.testing.assert_allclose((q_b - q_a) / h, dq, rtol=1e-4)


def test_segment_duration_respects_speed_limits() -> None:
    dq_max = np.full(6, 2.0)
    duration = segment_duration(np.array([0.5, 0, 0, 0, 0, 0]), 0.01, dq_max, 0.5, 0.2, 0.08)
    peak = 1.875 * 0.5 / duration
    assert peak == pytest.approx(0.5 * 2.0)
    assert segment_duration(np.zeros(6), 0.001, dq_max, 0.5, 0.2, 0.08) == 0.08
