"""The therapist's console: one-letter commands typed in the session's terminal (a reason
may follow), read on a thread so that the session never waits on the keyboard."""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import TextIO

COMMANDS = {
    "p": "pause",  # the arm holds; the reach's clock stops
    "r": "resume",
    "s": "skip",  # end this trial; it counts as skipped
    "a": "again",  # end this trial; it runs again
    "e": "end-block",  # end this trial and skip the rest of the block
    "x": "stop",  # the emergency stop (latched until released)
    "release": "release",
    "t": "take",  # the therapist decides for the participant (the device is ignored)
    "+": "forward",  # taken over: the therapist's decision, forward (add 'small': E_small)
    "-": "back",
    "g": "give",  # the participant decides again
    "h": "help",
}
HELP = (
    "console (type, then Enter; a reason may follow, e.g. 'p the patient coughs'): "
    "p pause | r resume | s skip the trial | a run the trial again | e end the block | "
    "x emergency stop | release | t take the decisions over, then + forward or - back "
    "('+ small' for a small step), g give them back | h help"
)


@dataclass(frozen=True)
class Command:
    action: str  # a value of COMMANDS
    why: str


def parse(line: str) -> Command | str:
    """A command, or why the line is none (a one-line answer for the operator)."""
    word, _, why = line.strip().partition(" ")
    action = COMMANDS.get(word.lower())
    if action is None:
        return f"console: {word!r} is no command (h for help)"
    return Command(action, why.strip()[:200])


class Lines:
    """The lines of ``stream`` as they come, from a daemon thread (EOF ends them)."""

    def __init__(self, stream: TextIO) -> None:
        self.queue: queue.Queue[str | None] = queue.Queue()
        self.closed = False
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: TextIO) -> None:
        try:
            for line in stream:
                self.queue.put(line.rstrip("\n"))
        except (OSError, ValueError):  # a closed or unreadable terminal: no console
            pass
        self.queue.put(None)

    def get(self, timeout_s: float | None) -> str | None:
        """The next line; None on a timeout or once the stream has ended (after
        ``timeout_s`` all the same: a loop polling a closed console must not spin)."""
        if self.closed:
            time.sleep(timeout_s or 0.0)
            return None
        try:
            line = self.queue.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if line is None:
            self.closed = True
        return line
