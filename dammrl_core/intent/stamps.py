"""A streamed sensor's timestamps kept true on this machine's clock: a jump of the
sender's clock corrected, a gap counted, the delivered rate measured.

LSL's clock synchronisation (``proc_clocksync``) maps a sender's clock to ours, but a
sender may stamp its samples with a clock of its own that jumps (an amplifier reset, a
PC's clock set), or with no relation to LSL's clock at all. Samples cannot be acquired
after they arrive, nor before the previous ones: so a chunk whose first stamp steps back
from the last chunk's end by more than a busy sender's jitter, or ahead of it by more
than the time that passed between the two arrivals (plus ``max_gap_s``), or whose stamps
lie in the future, is a jump, not time; it is corrected by an offset that keeps the
stream's latency what it was (its smallest over the last chunks). A real gap (no sample
for a while, then stamps that moved on as time did) is counted as missing samples.

Pure: stamps and arrival times in, times out (arrival times are this machine's
monotonic clock, LSL's local clock).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

MAX_FUTURE_S = 0.5
"""A stamp this far after its arrival is a clock of the sender's own, not LSL's [s]."""
MAX_LAG_S = 30.0
"""A first stamp this far before its arrival too (an inlet buffers 2 s of samples) [s]."""
LAG_MEMORY = 50
"""The stream's latency is the smallest over this many chunks (a late pull adds to one)."""
RATE_WINDOW_S = 4.0
"""The delivered rate is measured over this much of gap-free signal [s]."""


@dataclass(frozen=True)
class Timed:
    """A chunk's times on this machine's clock, and what happened before it."""

    times_s: np.ndarray  # (n,) [s]
    missing: int  # samples missing between the last chunk and this one (a gap)
    jump_s: float  # the correction added here because the stamps jumped (0: none)


class StreamClock:
    def __init__(self, rate_hz: float, max_gap_s: float, jitter_s: float) -> None:
        """``max_gap_s``: a step ahead beyond the time passed by more than this is a jump;
        ``jitter_s``: a step back by less than this, or a gap shorter, is a busy sender's
        jitter (both the decoder's settings) [s]."""
        self.rate_hz = rate_hz
        self.max_gap_s = max_gap_s
        self.jitter_s = jitter_s
        self.reset()

    def reset(self) -> None:
        """A new stream (another sender, or the same one attached again)."""
        self.offset_s = 0.0  # added to the stamps since the last jump
        self.last_s: float | None = None  # the last chunk's last time (corrected)
        self.last_arrival_s = 0.0
        self.lags: deque[float] = deque(maxlen=LAG_MEMORY)
        self.stretch: tuple[float, int] | None = None  # (first time, samples) gap-free
        self.rate_measured: float | None = None
        self.missing = 0
        self.gaps = 0
        self.jumps = 0

    def take(self, stamps: np.ndarray, arrived_s: float) -> Timed:
        """The times of a chunk's ``stamps`` (n,) that arrived at ``arrived_s``."""
        stamps = np.asarray(stamps, dtype=float)
        jump = self._jump(stamps, arrived_s)
        if jump:
            self.offset_s += jump
            self.jumps += 1
        times = stamps + self.offset_s
        missing = self._gap(float(times[0]), jump)
        self.lags.append(arrived_s - float(times[-1]))
        self.last_s, self.last_arrival_s = float(times[-1]), arrived_s
        self._measure(times, restart=bool(missing or jump))
        return Timed(times, missing, jump)

    def _jump(self, stamps: np.ndarray, arrived_s: float) -> float:
        """The correction the chunk's stamps need (0: none)."""
        first, last = float(stamps[0]) + self.offset_s, float(stamps[-1]) + self.offset_s
        lag = min(self.lags) if self.lags else 0.0
        if self.last_s is None:  # a first chunk: its stamps must be plausible at least
            if -MAX_FUTURE_S <= arrived_s - last <= MAX_LAG_S:
                return 0.0
            return arrived_s - last
        step = first - self.last_s
        passed = arrived_s - self.last_arrival_s
        back, ahead = step < -self.jitter_s, step - passed > self.max_gap_s
        if back or ahead or last - arrived_s > MAX_FUTURE_S:
            return (arrived_s - lag) - last
        return 0.0

    def _gap(self, first_s: float, jump: float) -> int:
        if self.last_s is None or jump:
            return 0
        step = first_s - self.last_s
        if step <= 1.0 / self.rate_hz + self.jitter_s:
            return 0
        missing = max(0, round(step * self.rate_hz) - 1)
        self.missing += missing
        self.gaps += 1
        return missing

    def _measure(self, times: np.ndarray, restart: bool) -> None:
        """Count the chunk into the gap-free stretch; its rate once it is long enough,
        then a new stretch from its last sample (the rate's memory stays short)."""
        if self.stretch is None or restart:
            self.stretch = (float(times[0]), 0)
        first, count = self.stretch
        count += len(times)
        span = float(times[-1]) - first
        self.stretch = (first, count)
        if span >= RATE_WINDOW_S:
            self.rate_measured = (count - 1) / span
            self.stretch = (float(times[-1]), 1)

    def delivered_hz(self) -> float | None:
        """Samples per second over the last ``RATE_WINDOW_S`` of gap-free signal, by its
        timestamps (None until that much came)."""
        return self.rate_measured
