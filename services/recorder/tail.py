"""An MCAP file that any reader opens whenever its writer is killed.

A finished MCAP ends with a footer and the magic bytes, and mcap's default reader
(``make_reader(...)``) starts there: a file cut by a kill is refused
(``RecordLengthLimitExceeded``) until it is repaired. So the file handed to the OS always
ends with a *provisional* footer (no summary: readers then read the data section from the
start, up to the first footer). Each commit of new bytes keeps that true at every
instant, whatever moment a ``kill -9`` picks:

1. the new provisional footer is written beyond the end (the file now ends with it; the
   bytes between are a hole, and the old footer, earlier, still ends every reading);
2. the new bytes fill the hole (any part of them may be cut: nothing reads them yet);
3. the old footer becomes a skipped private record (two bytes in one page: the kernel
   writes them whole or not at all), so readings go on to the new one.

The finish writes the writer's own summary and footer the same way, then cuts the file
after that footer. A footer is placed so that it never straddles a page; the padding is
a private record (opcode 0x80) that every MCAP reader skips, as it skips the old
footers. Nothing is ever fsynced: this survives the process, not a power cut.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"
FOOTER = 0x02
SKIPPED = 0x80
"""The first private opcode: a record every reader skips (MCAP specification)."""
FOOTER_BODY = 20  # summary start, summary offset start (u64 each), summary crc (u32)
TAIL_BYTES = 1 + 8 + FOOTER_BODY + len(MAGIC)  # 37
PROVISIONAL = struct.pack("<BQQQI", FOOTER, FOOTER_BODY, 0, 0, 0) + MAGIC
"""A footer without a summary (summary start 0: read the data section), and the magic."""
SKIP_TAIL = struct.pack("<BB", SKIPPED, FOOTER_BODY + len(MAGIC))
"""Written over a provisional footer's first two bytes: a record of the footer's body and
the magic (28 bytes) that readers skip."""
PAGE = 4096
"""The kernel's unit of a write a fatal signal cannot cut (a page, or a larger folio)."""
MIN_RECORD = 9  # opcode and length


class CommittedFile:
    """A write-only stream for ``mcap.writer.Writer``: what it writes stays in memory until
    :meth:`commit` hands it to the OS as described above. The file appears under its name
    only with its first commit (a kill before leaves no file, never an unreadable one)."""

    def __init__(self, path: Path) -> None:
        """OSError: the file cannot be created."""
        self.path = path
        self._partial = path.with_name(f".{path.name}.partial")
        self._fd = os.open(self._partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._pending = bytearray()
        self.end = 0  # where the next committed bytes go (after the provisional footer)
        self._footer_at: int | None = None  # the provisional footer now in force
        self.closed = False

    # ---- what the writer calls ----------------------------------------------------------
    def write(self, data: bytes) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self.end + len(self._pending)

    def flush(self) -> None:
        """The writer's flush: nothing reaches the OS before :meth:`commit`."""

    @property
    def pending(self) -> int:
        """Bytes written since the last commit."""
        return len(self._pending)

    # ---- commits --------------------------------------------------------------------------
    def sync(self) -> None:
        """Have the OS write what was committed to the disk (fsync)."""
        os.fsync(self._fd)

    def commit(self) -> None:
        """Hand what was written to the OS, the file ending with a provisional footer."""
        if not self._pending and self._footer_at is not None:
            return
        data = bytes(self._pending)
        padding, footer_at = _placed(self.end + len(data))
        os.pwrite(self._fd, PROVISIONAL, footer_at)  # 1: the file ends with the new footer
        os.pwrite(self._fd, data + padding, self.end)  # 2: what it ends
        self._retire_old_footer()  # 3: readings go on to the new footer
        self._footer_at, self.end = footer_at, footer_at + TAIL_BYTES
        self._pending.clear()
        self._appear()

    def finish(self) -> None:
        """Commit the writer's last bytes (its summary and final footer) and end the file
        after them; then close it."""
        data = bytes(self._pending)
        final_end = self.end + len(data)
        _, scratch_at = _placed(final_end + TAIL_BYTES)
        os.pwrite(self._fd, PROVISIONAL, scratch_at)  # the file ends with a footer ...
        os.pwrite(self._fd, data, self.end)  # ... beyond the final one, not yet in force
        self._retire_old_footer()  # the final footer is the first a reading meets
        os.ftruncate(self._fd, final_end)  # and now the last: the summary is in force
        self._pending.clear()
        self.end = final_end
        self._appear()
        self.close()

    def close(self) -> None:
        """Stop writing: the file stays as its last commit left it."""
        if not self.closed:
            self.closed = True
            os.close(self._fd)
            if self._partial.exists():  # never committed: no file
                self._partial.unlink()

    def _retire_old_footer(self) -> None:
        if self._footer_at is not None:
            os.pwrite(self._fd, SKIP_TAIL, self._footer_at)

    def _appear(self) -> None:
        """The first commit gives the file its name (atomically: whole or absent)."""
        if self._partial.exists():
            os.rename(self._partial, self.path)


def _placed(position: int) -> tuple[bytes, int]:
    """Padding (a skipped record, or nothing) and where a footer after ``position`` goes
    so that its first 29 bytes (all a later write changes) lie within one page."""
    room = PAGE - position % PAGE
    if room >= TAIL_BYTES:
        return b"", position
    length = room if room >= MIN_RECORD else room + PAGE
    padding = struct.pack("<BQ", SKIPPED, length - MIN_RECORD) + bytes(length - MIN_RECORD)
    return padding, position + length
