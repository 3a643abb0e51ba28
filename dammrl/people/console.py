"""The therapist's console: one-letter commands typed in the session's terminal (a reason
may follow), read on a thread so that the session never waits on the keyboard, and
answered at once by whatever the session is doing (a reach, a rest, a question, a wait for
Enter): a line is acted on or refused in one line when it is typed, never kept for later.

Reasons are stored as typed (events, recordings, BIDS): with the lab's participant
registry (``Names``), a reason that names a registered person is stored without the name.
"""

from __future__ import annotations

import queue
import re
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from dammrl_core.errors import ConfigurationError

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


Handler = Callable[[str], None]


class Console:
    """The terminal's lines, each handed at once to the handler in charge (``route``)."""

    def __init__(self, stream: TextIO, handler: Handler, say: Callable[[str], None]) -> None:
        self.lines = Lines(stream)
        self._handler = handler
        self._say = say
        self._lock = threading.Lock()
        threading.Thread(target=self._dispatch, daemon=True).start()

    @property
    def closed(self) -> bool:
        """The terminal has ended (a script's stdin, a closed terminal)."""
        return self.lines.closed

    @property
    def handler(self) -> Handler:
        with self._lock:
            return self._handler

    def route(self, handler: Handler) -> None:
        """Hand the next lines to ``handler``."""
        with self._lock:
            self._handler = handler

    def _dispatch(self) -> None:
        while True:
            line = self.lines.get(0.5)
            if line is None:
                continue
            try:
                self.handler(line)
            except Exception as exc:
                self._say(f"console: {line.strip()!r} failed: {exc}")


REDACTED = "[name removed]"


class Names:
    """The lab's participant registry (a file of names, one a line, never copied): a
    reason typed at the console is stored without any name in it."""

    def __init__(self, names: Iterable[str]) -> None:
        words = sorted({n.strip() for n in names if len(n.strip()) >= 2}, key=len, reverse=True)
        self.count = len(words)
        self._pattern = (
            re.compile(r"\b(" + "|".join(map(re.escape, words)) + r")\b", re.IGNORECASE)
            if words else None
        )  # fmt: skip

    @classmethod
    def read(cls, path: Path) -> Names:
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigurationError(f"--names {path}: cannot read it ({exc})") from exc
        names = cls(text.splitlines())
        if not names.count:
            raise ConfigurationError(f"--names {path}: no names in it (one a line)")
        return names

    def redact(self, why: str) -> tuple[str, bool]:
        """``why`` without the registry's names, and whether one was there."""
        if self._pattern is None:
            return why, False
        cleaned, found = self._pattern.subn(REDACTED, why)
        return cleaned, found > 0
