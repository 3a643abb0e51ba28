"""How the real arm starts to move without a fall or a jump, however late the host is.

The host's loop may stall (a busy PC: cycles 0.9 s late were measured beside two CPU
hogs). Three rules keep the start and every planned move safe through it:

* the drives never have the torque on without damping: they hold from the torque-on with
  the full damping (a joint that sags or is pushed moves at most as fast as gravity's
  torque over that damping) and a stiffness that ramps up (the soft start); a drive
  that stops itself when the host is silent keeps these gains;
* a planned motion (the soft start's ramp, the homing move) runs on its own clock, which
  advances with wall time but by at most ``LATE_CYCLE_S`` per cycle: a late cycle slows
  the motion down and never jumps its reference further than that much of its motion;
* after the drives stopped themselves (a stall longer than their watchdog), the arm's
  law starts again from the measured posture (services.robot.law).

Pure: time is passed in.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from dammrl_core.arm.driver import DriveCommand

LATE_CYCLE_S = 0.1
"""A planned motion's clock advances by at most this per cycle [s]: as long as a servo's
bus watchdog (after which it stops by itself and the motion is planned again from the
measured posture), and short enough that a jump of the reference is small (homing at
0.3 rad/s: 0.03 rad, as far as the joint limits' tolerance); a loop merely a little late
under load is not slowed down."""


@dataclass
class MotionClock:
    """A planned motion's own time [s]: wall time, at most ``max_step_s`` per advance."""

    max_step_s: float
    t_s: float = 0.0
    last_s: float | None = None  # the wall time of the last advance [s]

    def advance(self, now_s: float) -> float:
        """Move on to wall time ``now_s``; the motion's time."""
        if self.last_s is not None:
            self.t_s += min(max(now_s - self.last_s, 0.0), self.max_step_s)
        self.last_s = now_s
        return self.t_s


@dataclass
class SoftStart:
    """The stiffness's share after a torque-on: from ``fraction`` to 1 over ``duration_s``
    of its own clock (the damping is full from the start)."""

    duration_s: float
    fraction: float
    clock: MotionClock

    @classmethod
    def begin(cls, duration_s: float, fraction: float, max_step_s: float,
              now_s: float, done: bool = False) -> SoftStart:  # fmt: skip
        """A soft start from ``now_s`` (``done``: already over, drives that held)."""
        clock = MotionClock(max_step_s, duration_s if done else 0.0)
        clock.advance(now_s)
        return cls(duration_s, fraction, clock)

    def share(self, now_s: float) -> float:
        t = self.clock.advance(now_s)
        ramp = 1.0 if self.duration_s <= 0 else min(t / self.duration_s, 1.0)
        return self.fraction + (1.0 - self.fraction) * ramp


def softened(law: DriveCommand, share: float) -> DriveCommand:
    """``law`` with its stiffness at ``share`` (a soft start), its damping whole."""
    return replace(law, kp=law.kp * share)
