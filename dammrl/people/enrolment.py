"""The enrolment ledger: who was enrolled, in which order, and who withdrew; the one source
of a participant's counterbalancing row.

``<root>/enrolment.jsonl`` is append-only, one JSON object a line::

    {"utc": "...", "participant": "P001", "row": 0}
    {"utc": "...", "participant": "P001", "withdrawn": "consent withdrawn"}

A row is used once: a new participant takes the row after the largest ever given, so a
withdrawn participant, or a deleted folder, never shifts anyone else's row (counting
folders did: delete a rehearsal's folder and the next participant got the previous one's
row). A rehearsal (``dammrl session run --rehearsal``) takes no row: it runs the order the
next participant will run. A root made before the ledger existed is entered first, its
participants in the order of their rows. Writers hold an exclusive lock on the ledger
while they read and append, so two sessions enrolling at once get two rows.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

from dammrl_core.errors import ConfigurationError, UsageError

LEDGER = "enrolment.jsonl"


@dataclass(frozen=True)
class Entry:
    """One line of the ledger: an enrolment (``row``) or a withdrawal (``withdrawn``)."""

    participant: str
    row: int | None = None
    withdrawn: str | None = None


def next_row(entries: list[Entry]) -> int:
    """The row a new participant takes: one after the largest ever given."""
    rows = [e.row for e in entries if e.row is not None]
    return max(rows, default=-1) + 1


def row_of(entries: list[Entry], participant: str) -> int | None:
    """``participant``'s row while they are enrolled (None: never, or withdrawn since)."""
    row = None
    for entry in entries:
        if entry.participant != participant:
            continue
        row = entry.row if entry.withdrawn is None else None
    return row


def withdrawn(entries: list[Entry], participant: str) -> str | None:
    """Why ``participant`` withdrew, if their last entry is a withdrawal."""
    mine = [e for e in entries if e.participant == participant]
    return mine[-1].withdrawn if mine else None


class Ledger:
    """``<root>/enrolment.jsonl`` (see the module docstring)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.path = root / LEDGER

    def entries(self) -> list[Entry]:
        """Every entry, in order (read without the lock: a listing)."""
        if not self.path.exists():
            return _legacy(self.root)
        with open(self.path, encoding="utf-8") as handle:
            return _parse(handle, self.path)

    def enrol(self, participant: str) -> int:
        """``participant``'s row: theirs if enrolled, else the next one, written down."""
        with self._locked() as (entries, handle):
            reason = withdrawn(entries, participant)
            if reason is not None:
                raise UsageError(f"participant {participant} withdrew ({reason}): a "
                                 "withdrawn id is never enrolled again; give the person a "
                                 "new id")  # fmt: skip
            row = row_of(entries, participant)
            if row is None:
                row = next_row(entries)
                _append(handle, {"participant": participant, "row": row})
            return row

    def withdraw(self, participant: str, why: str) -> int:
        """Mark ``participant`` withdrawn (their row stays used); their row."""
        with self._locked() as (entries, handle):
            row = row_of(entries, participant)
            if row is None:
                state = (
                    "already withdrew" if withdrawn(entries, participant) else "was never enrolled"
                )
                raise UsageError(f"participant {participant} {state} under {self.root}")
            _append(handle, {"participant": participant, "withdrawn": why or "(no reason given)"})
            return row

    def next_row(self) -> int:
        """The row the next new participant will take."""
        return next_row(self.entries())

    @contextmanager
    def _locked(self) -> Iterator[tuple[list[Entry], IO[str]]]:
        """The entries under an exclusive lock, and the ledger open for appending (a
        missing ledger is started from the root's participants first)."""
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a+", encoding="utf-8") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                handle.seek(0)
                text = handle.read()
                if text and not text.endswith("\n"):  # a torn last line: never acknowledged
                    handle.truncate(text.rfind("\n") + 1)
                handle.seek(0)
                entries = _parse(handle, self.path)
                if not entries and handle.tell() == 0:
                    for entry in _legacy(self.root):
                        _append(handle, {"participant": entry.participant, "row": entry.row,
                                         "from": "participant.json"})  # fmt: skip
                    entries = _legacy(self.root)
                yield entries, handle
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)


def _parse(handle: IO[str], path: Path) -> list[Entry]:
    entries = []
    for number, line in enumerate(handle, start=1):
        if not line.strip():
            continue
        try:
            content = json.loads(line)
            entry = Entry(str(content["participant"]), content.get("row"), content.get("withdrawn"))
        except (ValueError, KeyError, TypeError) as exc:
            if not line.endswith("\n"):
                continue  # a torn last line (a crash mid-append): never acknowledged
            raise ConfigurationError(f"{path}: line {number} is not a ledger entry ({exc}); "
                                     "the ledger is append-only: restore it") from exc  # fmt: skip
        entries.append(entry)
    return entries


def _append(handle: IO[str], entry: dict[str, Any]) -> None:
    utc = datetime.now(UTC).isoformat(timespec="milliseconds")
    handle.write(json.dumps({"utc": utc} | entry) + "\n")
    handle.flush()
    os.fsync(handle.fileno())


def _legacy(root: Path) -> list[Entry]:
    """The participants of a root made before the ledger, in the order of their rows."""
    found = []
    for path in root.glob("*/participant.json"):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        row = record.get("row") if isinstance(record, dict) else None
        if isinstance(row, int) and not record.get("rehearsal"):
            found.append(Entry(path.parent.name, row))
    return sorted(found, key=lambda e: (e.row or 0, e.participant))
