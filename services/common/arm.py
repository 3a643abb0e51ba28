"""What the arm side (sim and robot) shares beyond the pure safety function
(``dammrl.core.safety.guard_command``): which states a command may answer, and the
emergency stop's bookkeeping."""

from __future__ import annotations

from collections import deque

from schemas import EmergencyStop


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

    def allowance_s(self, state_stamp_ns: int, cap_s: float) -> float:
        """Robot time over which the reference may move for a command answering this
        state: since the reference in force, at most ``cap_s`` [s]."""
        t = self.time_of(state_stamp_ns)
        return 0.0 if t is None else min(max(t - self.reference_t_s, 0.0), cap_s)

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
