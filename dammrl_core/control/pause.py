"""A therapist's pause of a reach: the arm holds where its reference is, and the reach's
own clock stops, so that every timer of the reach (its trajectory, the trigger's and the
episode's timeouts, decisions due) goes on after the pause exactly where it stopped.

The reach sees ``reach_time(t)``: the robot clock minus the time spent paused. While
paused, the arm gets ``hold_command``: the last reference, at rest, with its gravity
torque. On resume the reference goes on from the same posture, so the position never
jumps; only the reference velocity returns from zero to the trajectory's (bounded by the
trajectory's own velocity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dammrl_core import safety
from dammrl_core.dynamics import ArmModel
from dammrl_core.state import JointCommand


@dataclass
class Pause:
    """The pauses of one reach, on the robot clock [s]."""

    since_s: float | None = None  # when the current pause began (None: running)
    total_s: float = 0.0  # time paused before the current pause
    count: int = 0

    @property
    def paused(self) -> bool:
        return self.since_s is not None

    def begin(self, t_s: float) -> bool:
        """Pause at ``t_s``; False if already paused."""
        if self.since_s is not None:
            return False
        self.since_s, self.count = t_s, self.count + 1
        return True

    def end(self, t_s: float) -> bool:
        """Resume at ``t_s``; False if not paused."""
        if self.since_s is None:
            return False
        self.total_s += max(0.0, t_s - self.since_s)
        self.since_s = None
        return True

    def reach_time(self, t_s: float) -> float:
        """The reach's clock at robot time ``t_s`` (frozen while paused)."""
        if self.since_s is not None:
            return self.since_s - self.total_s
        return t_s - self.total_s

    def paused_s(self, t_s: float) -> float:
        """All the time paused until ``t_s``."""
        current = 0.0 if self.since_s is None else max(0.0, t_s - self.since_s)
        return self.total_s + current


def hold_command(arm: ArmModel, last: JointCommand, tau_max: np.ndarray) -> JointCommand:
    """Hold ``last``'s reference posture at rest: zero reference velocity, the gravity
    torque there as feedforward, the same gains."""
    q = np.asarray(last.q_ref, dtype=float)
    zero = np.zeros_like(q)
    tau = safety.saturate_torque(arm.inverse_dynamics(q, zero, zero), tau_max)
    return JointCommand(q.copy(), zero, tau, last.kp, last.kd)
