"""The numbers the cores exchange in-process: robot state and joint command.

These are plain dataclasses of numpy arrays (fast, no validation on the hot path). The
bus carries their pydantic twins from :mod:`schemas`; nodes convert at the boundary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RobotState:
    """What the arm reports at one instant (SI units, arrays of shape (6,) or (3,))."""

    t_s: float  # simulation / robot clock [s]
    q: np.ndarray  # joint positions [rad] (6,)
    dq: np.ndarray  # joint velocities [rad/s] (6,)
    tau: np.ndarray  # actuator torques actually applied, after saturation [N m] (6,)
    ee_pos: np.ndarray  # end-effector position in the task frame [m] (3,)
    ee_vel: np.ndarray  # end-effector linear velocity [m/s] (3,)
    button_pressed: bool  # goal button pushed past its detection travel
    button_travel_m: float  # how far the button cap is pushed down [m]
    # simulation only: the noise-free end-effector position [m] (3,), ground truth for
    # analysis (dammrl study); never read by the controller, absent on the bus and the arm
    ee_pos_true: np.ndarray | None = None


@dataclass(frozen=True)
class JointCommand:
    """Joint impedance command: tau = tau_ff + kp (q_ref - q) + kd (dq_ref - dq)."""

    q_ref: np.ndarray  # [rad] (6,)
    dq_ref: np.ndarray  # [rad/s] (6,)
    tau_ff: np.ndarray  # feedforward torque [N m] (6,)
    kp: np.ndarray  # [N m/rad] (6,)
    kd: np.ndarray  # [N m s/rad] (6,)


@dataclass(frozen=True)
class Intent:
    """One decision of the human agent: direction on the primary axis and sphere radius."""

    t_s: float  # when the decision became available [s]
    u_h: int  # -1 or +1 on the primary axis
    radius_m: float  # admission-sphere radius epsilon the human chose [m]
    human_model: int  # 1 = E_big, 2 = E_small
    confidence: float = 1.0  # in [0, 1]


@dataclass(frozen=True)
class StepEvent:
    """One micro-step: why and when it started, where it goes, what IK cost."""

    index: int  # 1-based step number in the episode
    t_s: float  # when the step was decided [s]
    start_s: float  # when its joint reference began (after the IK latency) [s]
    trigger: str  # 'event' or 'fixed'
    u_h: int
    radius_m: float
    steps_m: np.ndarray  # delta (3,) [m]
    dx: np.ndarray  # micro-step (3,) [m]
    x_start: np.ndarray  # measured end-effector position when decided (3,) [m]
    subgoal: np.ndarray  # x_m = x_start + dx (3,) [m]
    goal_error_m: float  # ||x_g - x_start|| [m]
    ik_compute_s: float  # wall time of the solve [s]
    ik_latency_s: float  # simulated time the solve took [s]
