"""Servos that cut their torque: put back holding where their joint is, a bounded number
of times.

A servo latches an overload (persistent load beyond its output) by switching its torque
off: its joint is free, and gravity pulls it down with whatever hangs on it. Only a
REBOOT clears the latch, and the servo is powerless while it boots. The robot service
stops the arm (the other joints hold with the stop gains) and reboots the servo at once;
as soon as the servo answers again, its joint holds where it is then (never pulled back
to where it was: that would move the person's arm). A servo that overloads again after
``max_reboots`` reboots, or latches any other error (overheating, voltage, encoder,
shock: a reboot would not help or is unsafe), is left off; the arm then needs a brake or
a mechanical support at that joint (README, "Faults mid-motion").
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from services.robot.driver import describe_errors

OVERLOAD = 0x20


@dataclass
class ServoRecovery:
    """Which joints' servos are rebooting, back or left off; what to say about them."""

    max_reboots: int
    reboots: Counter[int] = field(default_factory=Counter)  # joint -> reboots so far
    rebooting: set[int] = field(default_factory=set)
    off: dict[int, str] = field(default_factory=dict)  # joint -> why it stays off
    notes: dict[int, str] = field(default_factory=dict)  # joint -> the latest word on it

    def fault(self, joint: int, servo_id: int, bits: int) -> bool:
        """A servo reported error ``bits``: whether to reboot it now."""
        if joint in self.rebooting or joint in self.off:
            return False
        what = f"servo {servo_id}: {describe_errors(bits)}"
        if bits != OVERLOAD:
            return self._leave_off(joint, f"{what}: left off (a reboot would not clear it)")
        if self.reboots[joint] >= self.max_reboots:
            return self._leave_off(joint, f"{what} again: left off after "
                                          f"{self.reboots[joint]} reboots")  # fmt: skip
        self.reboots[joint] += 1
        self.rebooting.add(joint)
        self.notes[joint] = f"{what}: rebooting ({self.reboots[joint]} of {self.max_reboots})"
        return True

    def back(self, joint: int, servo_id: int, q_rad: float) -> None:
        """The servo answers again and holds joint ``joint`` at ``q_rad``."""
        self.rebooting.discard(joint)
        self.notes[joint] = (
            f"servo {servo_id} back after a reboot, holding at {q_rad:.3f} rad "
            f"({self.reboots[joint]} of {self.max_reboots} reboots used)"
        )

    def _leave_off(self, joint: int, why: str) -> bool:
        self.off[joint] = why
        self.notes[joint] = f"{why}: support the arm at this joint"
        return False

    def detail(self) -> str:
        return "; ".join(self.notes[j] for j in sorted(self.notes))
