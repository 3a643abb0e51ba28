"""Micro-steps (paper eq. 2) and the two progression rules (event trigger, fixed timer)."""

from __future__ import annotations

import numpy as np


def micro_step(
    error: np.ndarray,
    u_h: int,
    steps_m: np.ndarray,
    primary_axis: int,
    orthogonal_deadband: bool,
) -> np.ndarray:
    """Cartesian micro-step dx [m] (3,) of paper eq. 2.

    The primary axis moves ``u_h * delta`` (the human's binary command, right or wrong);
    each orthogonal axis moves ``sgn(e) * delta``. With ``orthogonal_deadband`` an
    orthogonal axis already within half a step of the goal stays put: the step would
    leave it farther away than it is (sgn(e) taken as 0 inside the deadband).
    """
    if u_h not in (-1, 1):
        raise ValueError(f"u_h must be -1 or +1, got {u_h}")
    direction = np.sign(error)
    if orthogonal_deadband:
        direction[np.abs(error) <= steps_m / 2] = 0.0
    direction[primary_axis] = u_h
    return np.asarray(direction * steps_m)


def lyapunov(error: np.ndarray, weights: np.ndarray) -> float:
    """V = 1/2 e^T W e for a diagonal W given by ``weights`` (3,)."""
    return 0.5 * float(error @ (weights * error))


def lyapunov_rate(error: np.ndarray, ee_vel: np.ndarray, weights: np.ndarray) -> float:
    """dV/dt for e = x_m - x with the subgoal x_m fixed: -e^T W xdot."""
    return -float(error @ (weights * ee_vel))


def event_trigger(
    x: np.ndarray,
    ee_vel: np.ndarray,
    subgoal: np.ndarray,
    radius_m: float,
    weights: np.ndarray,
) -> bool:
    """Paper eq. 1: ||x - x_m|| <= eps and dV/dt <= 0 (V measured against the subgoal)."""
    error = subgoal - x
    inside = float(error @ error) <= radius_m * radius_m
    return inside and lyapunov_rate(error, ee_vel, weights) <= 0.0


def fixed_timer_due(t_s: float, last_step_s: float | None, period_s: float) -> bool:
    """The fixed-frequency baseline steps every ``period_s`` whatever the arm is doing."""
    return last_step_s is None or t_s >= last_step_s + period_s - 1e-9
