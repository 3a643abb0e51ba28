"""The pressure sensor's wire protocol: one ASCII line per sample, with a checksum.

    $P,<seq>,<raw>*<HH>\\r\\n

``seq`` counts samples (0-65535, wraps), ``raw`` is the ADC reading (0-4095 for a
12-bit converter), ``HH`` the XOR of every byte between ``$`` and ``*`` in two hex digits
(as in NMEA 0183). 115200 baud, 8N1, 100 samples/s. Readable in any serial terminal,
robust to garbage: the parser resynchronises on ``$``, drops lines longer than
``MAX_LINE`` bytes, and counts every kind of error instead of raising.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

BAUD_RATE = 115_200
SAMPLE_RATE_HZ = 100.0
RAW_MAX = 4095
SEQ_MODULO = 65_536
MAX_LINE = 32  # longest valid line is "$P,65535,4095*HH" = 16 bytes


@dataclass(frozen=True)
class Frame:
    seq: int
    raw: int


def frames_lost(previous_seq: int | None, seq: int) -> int | None:
    """Frames missing between two received sequence numbers (wrapping); None: no previous.

    A repeated or restarted count reads as nearly a full wrap of frames lost.
    """
    if previous_seq is None:
        return None
    return (seq - previous_seq - 1) % SEQ_MODULO


def checksum(body: bytes) -> int:
    value = 0
    for byte in body:
        value ^= byte
    return value


def encode_frame(seq: int, raw: int) -> bytes:
    """The line a sensor sends for one sample."""
    body = f"P,{seq % SEQ_MODULO},{raw}".encode()
    return b"$" + body + f"*{checksum(body):02X}\r\n".encode()


@dataclass
class FrameParser:
    """Feed it bytes as they come; it returns the complete valid frames."""

    errors: Counter[str] = field(default_factory=Counter)
    frames: int = 0
    _line: bytearray = field(default_factory=bytearray)
    _skipping: bool = False  # inside an overlong line: drop until its end

    def feed(self, data: bytes) -> list[Frame]:
        out: list[Frame] = []
        for byte in data:
            if byte == ord("$"):
                if self._line:
                    self.errors["partial"] += 1  # a new frame began before the old ended
                self._line = bytearray(b"$")
                self._skipping = False
            elif byte in (ord("\n"), ord("\r")):
                if self._line:
                    frame = self._parse(bytes(self._line))
                    if frame is not None:
                        out.append(frame)
                self._line.clear()
                self._skipping = False
            elif self._skipping:
                continue
            elif not self._line:
                self.errors["garbage"] += 1  # bytes outside any frame
            elif len(self._line) >= MAX_LINE:
                self.errors["overlong"] += 1
                self._line.clear()
                self._skipping = True
            else:
                self._line.append(byte)
        return out

    def _parse(self, line: bytes) -> Frame | None:
        body, star, hex_sum = line[1:].partition(b"*")
        if not star or len(hex_sum) != 2:
            self.errors["malformed"] += 1
            return None
        try:
            expected = int(hex_sum, 16)
        except ValueError:
            self.errors["malformed"] += 1
            return None
        if checksum(body) != expected:
            self.errors["checksum"] += 1
            return None
        parts = body.split(b",")
        if len(parts) != 3 or parts[0] != b"P" or not parts[1].isdigit() or not parts[2].isdigit():
            self.errors["malformed"] += 1
            return None
        seq, raw = int(parts[1]), int(parts[2])
        if seq >= SEQ_MODULO or raw > RAW_MAX:
            self.errors["out of range"] += 1
            return None
        self.frames += 1
        return Frame(seq, raw)
