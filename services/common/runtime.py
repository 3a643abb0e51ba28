"""Process plumbing shared by the service entry points: signals and a paced loop."""

from __future__ import annotations

import signal
import threading
import time


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so loops end cleanly and ``finally`` runs."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


class Pacer:
    """Keeps a loop at a fixed period in wall time and counts missed deadlines."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.next_s = time.monotonic()
        self.ticks = 0
        self.missed = 0

    def restart(self) -> None:
        """Start counting from now (call when the loop begins)."""
        self.next_s = time.monotonic()
        self.ticks = self.missed = 0

    def wait(self) -> None:
        """Sleep until the next deadline; a loop more than a period late starts afresh."""
        self.ticks += 1
        self.next_s += self.period_s
        delay = self.next_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -self.period_s:
            self.missed += 1
            self.next_s = time.monotonic()
        else:
            self.missed += 1
