"""Safety checks as pure functions: workspace box, joint limits, effort saturation."""

from __future__ import annotations

import numpy as np

from dammrl.robot import RobotDescription


def outside_workspace(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> str | None:
    """Why ``x`` [m] is outside the box [lower, upper], or None when it is inside."""
    for axis, name in enumerate("xyz"):
        if not lower[axis] <= x[axis] <= upper[axis]:
            return (
                f"target {name}={x[axis]:.3f} m outside the workspace "
                f"[{lower[axis]:.3f}, {upper[axis]:.3f}] m"
            )
    return None


def limit_violation(
    robot: RobotDescription,
    q: np.ndarray,
    dq: np.ndarray,
    position_tolerance_rad: float = 0.02,
    velocity_tolerance: float = 1.0,
) -> str | None:
    """Why the measured state breaks a joint position or velocity limit, or None.

    Positions may exceed the limits by ``position_tolerance_rad`` (the limit constraint is
    soft in simulation); speeds may reach ``velocity_tolerance`` times the URDF limit.
    """
    for i, name in enumerate(robot.joint_names):
        if (
            not robot.q_min[i] - position_tolerance_rad
            <= q[i]
            <= robot.q_max[i] + position_tolerance_rad
        ):
            return (
                f"joint {name} at {q[i]:.3f} rad outside its limits "
                f"[{robot.q_min[i]:.3f}, {robot.q_max[i]:.3f}] rad"
            )
        if abs(dq[i]) > velocity_tolerance * robot.dq_max[i]:
            return f"joint {name} at {dq[i]:.2f} rad/s beyond its limit {robot.dq_max[i]:.2f} rad/s"
    return None


class LimitMonitor:
    """Fast vectorised test of the measured state against the limits, explained on failure."""

    def __init__(
        self,
        robot: RobotDescription,
        position_tolerance_rad: float = 0.02,
        velocity_tolerance: float = 1.0,
    ) -> None:
        self.robot = robot
        self.position_tolerance_rad = position_tolerance_rad
        self.velocity_tolerance = velocity_tolerance
        self.q_mid = (robot.q_min + robot.q_max) / 2
        self.q_half_span = (robot.q_max - robot.q_min) / 2 + position_tolerance_rad
        self.dq_max = velocity_tolerance * robot.dq_max

    def check(self, q: np.ndarray, dq: np.ndarray) -> str | None:
        """Why the state breaks a limit, or None (the common case, in a few microseconds)."""
        # ufunc.reduce directly: ndarray.all() goes through a slow Python-level wrapper
        outside = np.logical_or.reduce(np.abs(q - self.q_mid) > self.q_half_span)
        if not outside and not np.logical_or.reduce(np.abs(dq) > self.dq_max):
            return None
        return limit_violation(
            self.robot, q, dq, self.position_tolerance_rad, self.velocity_tolerance
        )

    def first_violation(self, q: np.ndarray, dq: np.ndarray) -> int | None:
        """Index of the first of many states (rows of ``q``, ``dq`` (n, 6)) breaking a limit."""
        bad = np.any(np.abs(q - self.q_mid) > self.q_half_span, axis=1)
        bad |= np.any(np.abs(dq) > self.dq_max, axis=1)
        return int(np.argmax(bad)) if bad.any() else None


def saturate_torque(tau: np.ndarray, tau_max: np.ndarray) -> np.ndarray:
    """``tau`` [N m] clipped to the effort limits +-tau_max."""
    return np.asarray(np.minimum(np.maximum(tau, -tau_max), tau_max))
