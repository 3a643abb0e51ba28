"""Drives that cut their torque: restarted and put back holding where their joint is, a
bounded number of times.

A servo latches an overload (persistent load beyond its output) by switching its torque
off: its joint is free, and gravity pulls it down with whatever hangs on it. Only a restart
(a Dynamixel's REBOOT) clears the latch, and the drive is powerless while it boots. The
robot service stops the arm (the other joints hold with the stop gains) and restarts the
drive at once; as soon as it answers again, its joint holds where it is then (never pulled
back to where it was: that would move the person's arm). A drive that faults again after
``max_restarts`` restarts, or latches a fault a restart does not clear (overheating,
voltage, encoder, shock), is left off; the arm then needs a brake or a mechanical support
at that joint (docs/tutorials/your-arm.md, "Faults mid-motion").
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from dammrl_core.arm.driver import DriveFault


@dataclass
class DriveRecovery:
    """Which joints' drives restart, are back or are left off; what to say about them."""

    max_restarts: int
    restarts: Counter[int] = field(default_factory=Counter)  # joint -> restarts so far
    restarting: set[int] = field(default_factory=set)
    off: dict[int, str] = field(default_factory=dict)  # joint -> why it stays off
    notes: dict[int, str] = field(default_factory=dict)  # joint -> the latest word on it

    def fault(self, fault: DriveFault) -> bool:
        """A drive reported ``fault``: whether to restart it now."""
        joint = fault.joint
        if joint in self.restarting or joint in self.off:
            return False
        if not fault.restartable:
            return self._leave_off(joint, f"{fault.what}: left off (a restart would not clear it)")
        if self.restarts[joint] >= self.max_restarts:
            return self._leave_off(
                joint, f"{fault.what} again: left off after {self.restarts[joint]} restarts"
            )
        self.restarts[joint] += 1
        self.restarting.add(joint)
        self.notes[joint] = (
            f"{fault.what}: restarting ({self.restarts[joint]} of {self.max_restarts})"
        )
        return True

    def not_sent(self, joint: int) -> None:
        """The restart of ``joint``'s drive never went out: none used, and not restarting."""
        self.restarting.discard(joint)
        self.restarts[joint] -= 1
        self.notes.pop(joint, None)

    def back(self, joint: int, q_rad: float) -> None:
        """The drive of ``joint`` answers again and holds it at ``q_rad``."""
        self.restarting.discard(joint)
        self.notes[joint] = (
            f"joint {joint + 1}'s drive back after a restart, holding at {q_rad:.3f} rad "
            f"({self.restarts[joint]} of {self.max_restarts} restarts used)"
        )

    def not_cleared(self, joint: int) -> None:
        """The drive of ``joint`` answers again with its fault still latched (its restart
        never reached it, or did not clear it): left off."""
        self.restarting.discard(joint)
        self._leave_off(
            joint, f"joint {joint + 1}'s drive still faulted after its restart: left off"
        )

    def _leave_off(self, joint: int, why: str) -> bool:
        self.off[joint] = why
        self.notes[joint] = f"{why}: support the arm at this joint"
        return False

    def detail(self) -> str:
        return "; ".join(self.notes[j] for j in sorted(self.notes))
