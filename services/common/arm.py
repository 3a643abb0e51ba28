"""What the arm side (sim and robot) shares beyond the pure safety function
(``dammrl.core.safety.guard_command``): which states a command may answer, and the
emergency stop's bookkeeping."""

from __future__ import annotations

from collections import deque

from schemas import EmergencyStop


class CommandFreshness:
    """A command must answer one of the last ``answerable`` states this arm published, and
    no older state than the last applied command answered (no stale, replayed or
    out-of-order command reaches the arm)."""

    def __init__(self, answerable: int) -> None:
        self.recent: deque[int] = deque(maxlen=max(1, answerable))
        self.last_answered_ns = -1

    def published(self, stamp_ns: int) -> None:
        self.recent.append(stamp_ns)

    def why_stale(self, state_stamp_ns: int) -> str | None:
        if state_stamp_ns not in self.recent:
            return "answers no recent state of this arm (stale or replayed)"
        if state_stamp_ns < self.last_answered_ns:
            return "answers an older state than the last applied command (out of order)"
        return None

    def applied(self, state_stamp_ns: int) -> None:
        self.last_answered_ns = state_stamp_ns


class StopLatch:
    """An emergency stop holds until released; the arm's own faults hold until cleared."""

    def __init__(self) -> None:
        self.reason: str | None = None  # why the arm is stopped, None: it is not

    def take(self, message: EmergencyStop) -> bool:
        """Apply a stop or release; True when this changed the state."""
        if message.engaged:
            changed = self.reason is None
            self.reason = f"emergency stop from {message.header.source}" + (
                f": {message.reason}" if message.reason else ""
            )
            return changed
        changed = self.reason is not None
        self.reason = None
        return changed

    @property
    def engaged(self) -> bool:
        return self.reason is not None
