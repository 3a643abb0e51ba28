"""What the recorder confirms of a run's episodes on disk (``EpisodeRecorded``), and a
bounded wait for it: a run stops its stack only once its last reach is in the file (the
recorder hears the arm, the controller and the intent service on separate links, and
what is still on the way when it stops is lost)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from schemas import EpisodeRecorded

RECORDED_WAIT_S = 15.0
"""How long a run waits at its end for the recorder to confirm that each of its reaches
is on disk before the stack stops [s] (the recorder says an episode is incomplete, and
what it lacks, 5 s after its result)."""
STOP_POLL_S = 0.05
"""How often a wait looks whether it was asked to stop [s]."""


class RecordedEpisodes:
    """The recorder's acknowledgements of one stack run's episodes, as they come (a
    complete one supersedes an incomplete one), and a bounded wait for them."""

    def __init__(self, part: Path) -> None:
        self.stem = part.stem  # part-NN: its continuations are part-NN-001.mcap, ...
        self.acks: dict[int, EpisodeRecorded] = {}
        self.changed = threading.Condition()

    def take(self, ack: EpisodeRecorded) -> None:
        """One acknowledgement heard (the recorder of another run's file is not ours)."""
        if ack.header.source != "recorder" or not ack.file.startswith(self.stem):
            return
        with self.changed:
            known = self.acks.get(ack.episode)
            if known is None or not known.complete:
                self.acks[ack.episode] = ack
            self.changed.notify_all()

    def wait(
        self, episodes: list[int], timeout_s: float, stop: threading.Event | None = None
    ) -> dict[int, EpisodeRecorded]:
        """The acknowledgements of ``episodes`` once each is complete, or what came within
        ``timeout_s`` or before ``stop`` was set (Ctrl-C ends the wait at once)."""
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while not all(e in self.acks and self.acks[e].complete for e in episodes):
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (stop is not None and stop.is_set()):
                    break
                self.changed.wait(min(remaining, STOP_POLL_S))
            return {e: self.acks[e] for e in episodes if e in self.acks}
