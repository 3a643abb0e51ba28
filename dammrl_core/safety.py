"""Safety checks as pure functions: workspace box, joint limits, effort saturation, and
the arm side's checks of what arrives (commands, episode resets)."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dammrl_core.robot import RobotDescription
from dammrl_core.robot.scene import SceneLayout
from dammrl_core.state import JointCommand


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


def command_violation(
    command: JointCommand,
    robot: RobotDescription,
    limit_tolerance_rad: float,
    max_kp_nm_per_rad: float,
    max_kd_nms_per_rad: float,
) -> str | None:
    """Why a joint command must not reach the arm, or None (the arm side's check)."""
    q_ref = command.q_ref
    outside = (q_ref < robot.q_min - limit_tolerance_rad) | (
        q_ref > robot.q_max + limit_tolerance_rad
    )
    if outside.any():
        i = int(np.argmax(outside))
        return (
            f"q_ref of {robot.joint_names[i]} = {q_ref[i]:.3f} rad outside "
            f"[{robot.q_min[i]:.3f}, {robot.q_max[i]:.3f}] rad"
        )
    tau = np.abs(command.tau_ff)
    if (tau > robot.tau_max).any():
        i = int(np.argmax(tau - robot.tau_max))
        name, limit = robot.joint_names[i], robot.tau_max[i]
        return f"tau_ff of {name} = {tau[i]:.1f} N m beyond its effort limit {limit:.1f} N m"
    kp, kd = float(np.max(command.kp)), float(np.max(command.kd))
    if kp > max_kp_nm_per_rad:
        return f"kp {kp:.0f} N m/rad above the allowed {max_kp_nm_per_rad:.0f}"
    if kd > max_kd_nms_per_rad:
        return f"kd {kd:.0f} N m s/rad above the allowed {max_kd_nms_per_rad:.0f}"
    return None


def goal_violation(
    q_start: np.ndarray,
    goal_m: Sequence[float],
    robot: RobotDescription,
    layout: SceneLayout,
    limit_tolerance_rad: float,
) -> str | None:
    """Why a new episode's start posture and goal must not reset the arm, or None."""
    if not robot.within_limits(q_start, limit_tolerance_rad):
        return f"start posture {np.round(q_start, 3).tolist()} rad outside the joint limits"
    (cx, cy), (hx, hy) = layout.table_center_xy_m, layout.table_half_size_xy_m
    x, y = goal_m[0], goal_m[1]
    if abs(x - cx) > hx or abs(y - cy) > hy:
        return f"button position ({x:.3f}, {y:.3f}) m is not on the table"
    return None


@dataclass(frozen=True)
class ArmCaps:
    """What the arm side lets through, whatever the bus says (sim now, robot later)."""

    limit_tolerance_rad: float  # q_ref may exceed the joint limits by this before rejection
    max_kp_nm_per_rad: float  # stiffer commands are rejected
    max_kd_nms_per_rad: float  # more damped commands are rejected
    max_relative_target_rad: float  # |q_ref - q| is clamped to this per joint
    speed_fraction: float  # |dq_ref| and the rate of change of q_ref: <= this x URDF limit


NOTABLE_CLAMP_RAD = 0.01
"""A cap that changes a reference by less (0.57 deg, at most ~5 mm at the fingertip) is
counted but not worth a person's attention: e.g. the first command after a hold moving the
reference by the IK's tolerance in no robot time."""


@dataclass(frozen=True)
class Guarded:
    """The command the arm applies, or why none is applied."""

    command: JointCommand | None  # None: rejected
    reason: str | None  # why it was rejected, or which cap changed it
    clamped: bool = False  # a cap changed the command (it is still applied)
    change_rad: float = 0.0  # the largest change a cap made to the reference [rad or rad/s]

    @property
    def log_level(self) -> int:
        """A clamp's log level: a warning when it changed the reference notably."""
        return logging.WARNING if self.change_rad >= NOTABLE_CLAMP_RAD else logging.INFO


def guard_command(
    command: JointCommand,
    q: np.ndarray,
    last_q_ref: np.ndarray | None,
    dt_s: float,
    robot: RobotDescription,
    caps: ArmCaps,
) -> Guarded:
    """Reject a command that breaks a limit; clamp the reference so that it stays within
    ``max_relative_target_rad`` of the measured posture ``q`` (6,) [rad], moves from the
    last applied reference at most at the capped joint speed over ``dt_s`` [s], and asks
    for no joint speed above it (LeRobot's ``max_relative_target``, ros2_control's joint
    limiters). The genuine controller never meets a cap (measured: |q_ref - q| <= 0.054
    rad, |dq_ref| <= 0.68 of the limit, q_ref moving <= 1.27 rad/s)."""
    reason = command_violation(
        command, robot, caps.limit_tolerance_rad, caps.max_kp_nm_per_rad, caps.max_kd_nms_per_rad
    )
    if reason is not None:
        return Guarded(None, reason)
    speed = caps.speed_fraction * robot.dq_max
    near = np.clip(
        command.q_ref, q - caps.max_relative_target_rad, q + caps.max_relative_target_rad
    )
    q_ref = near
    if last_q_ref is not None:
        q_ref = np.clip(q_ref, last_q_ref - speed * dt_s, last_q_ref + speed * dt_s)
    dq_ref = np.clip(command.dq_ref, -speed, speed)
    if np.array_equal(q_ref, command.q_ref) and np.array_equal(dq_ref, command.dq_ref):
        return Guarded(command, None)
    change = np.abs(q_ref - command.q_ref) + np.abs(dq_ref - command.dq_ref)
    i = int(np.argmax(change))
    if dq_ref[i] != command.dq_ref[i]:
        cap = f"speed {command.dq_ref[i]:+.2f} rad/s beyond {speed[i]:.2f}"
    elif last_q_ref is not None and q_ref[i] != near[i]:  # the tighter cap, when both bind
        cap = (f"{abs(command.q_ref[i] - last_q_ref[i]):.3f} rad from the last reference in "
               f"{dt_s * 1e3:.0f} ms, beyond {speed[i] * dt_s:.3f}")  # fmt: skip
    else:
        cap = (f"{abs(command.q_ref[i] - q[i]):.3f} rad from the measured posture, beyond "
               f"{caps.max_relative_target_rad:.3f}")  # fmt: skip
    why = f"reference of {robot.joint_names[i]} clamped by the arm's caps ({cap})"
    applied = JointCommand(q_ref, dq_ref, command.tau_ff, command.kp, command.kd)
    return Guarded(applied, why, clamped=True, change_rad=float(change[i]))


# ---- the arm side's bookkeeping (sim and robot) -------------------------------------------
class CommandFreshness:
    """A command must answer one of the last ``answerable`` states this arm published, and
    no older state than the last applied command answered (no stale, replayed or
    out-of-order command reaches the arm).

    It also keeps the robot time the applied reference belongs to: the answered state's
    time for a command, the start for a hold. The reference may move by the capped joint
    speed times the robot time between the state it answers and that one: commands that
    reach the arm bunched together (a loaded machine) are not clamped for it, and no
    sequence of commands moves the reference faster than the cap."""

    def __init__(self, answerable: int) -> None:
        self.recent: deque[tuple[int, float]] = deque(maxlen=max(1, answerable))
        self.last_answered_ns = -1
        self.reference_t_s = 0.0  # robot time of the reference in force
        self.clamped = 0  # commands the arm's caps changed

    def published(self, stamp_ns: int, t_s: float) -> None:
        self.recent.append((stamp_ns, t_s))

    def why_stale(self, state_stamp_ns: int) -> str | None:
        if self.time_of(state_stamp_ns) is None:
            return "answers no recent state of this arm (stale or replayed)"
        if state_stamp_ns < self.last_answered_ns:
            return "answers an older state than the last applied command (out of order)"
        return None

    def time_of(self, state_stamp_ns: int) -> float | None:
        """Robot time of a recent state [s] (None: not recent)."""
        return next((t for stamp, t in self.recent if stamp == state_stamp_ns), None)

    def since_reference_s(self, state_stamp_ns: int) -> float:
        """Robot time from the reference in force to this state (0: not recent) [s]."""
        t = self.time_of(state_stamp_ns)
        return 0.0 if t is None else max(t - self.reference_t_s, 0.0)

    def allowance_s(self, state_stamp_ns: int, cap_s: float) -> float:
        """Robot time over which the reference may move for a command answering this
        state: since the reference in force, at most ``cap_s`` [s]."""
        return min(self.since_reference_s(state_stamp_ns), cap_s)

    def clamp(self, reason: str | None, state_stamp_ns: int) -> str | None:
        """Count a clamped command; its log line for the first five and every hundredth
        (None: not logged). A rate cap after a stall of the loop shows as a state long
        after the reference in force."""
        self.clamped += 1
        if self.clamped > 5 and self.clamped % 100 != 0:
            return None
        since_ms = self.since_reference_s(state_stamp_ns) * 1e3
        return (f"command #{self.clamped} clamped: {reason}; it answers a state "
                f"{since_ms:.0f} ms after the reference in force")  # fmt: skip

    def applied(self, state_stamp_ns: int) -> None:
        self.last_answered_ns = state_stamp_ns
        self.reference_t_s = self.time_of(state_stamp_ns) or self.reference_t_s

    def held(self, t_s: float) -> None:
        """A hold began at robot time ``t_s`` (its reference is the posture there)."""
        self.reference_t_s = t_s


class StopLatch:
    """An emergency stop holds until released; the arm's own faults hold until cleared."""

    def __init__(self) -> None:
        self.reason: str | None = None  # why the arm is stopped, None: it is not

    def take(self, engaged: bool, source: str, reason: str = "") -> bool:
        """Apply a stop (``engaged``) or a release from ``source``; True when this changed
        the state."""
        if engaged:
            changed = self.reason is None
            self.reason = f"emergency stop from {source}" + (f": {reason}" if reason else "")
            return changed
        changed = self.reason is not None
        self.reason = None
        return changed

    @property
    def engaged(self) -> bool:
        return self.reason is not None
