"""Sequence accounting: the messages a recording lacks, as its own sequence numbers show,
whatever order they arrived in, and never inflated by a forged, fuzzed or restarted
sequence.

A *stream* is one run of sequence numbers of one publisher (the key, the header's source
and, when Zenoh carries it, the publishing session's id). It keeps the numbers it
received as ranges; the numbers between two ranges are its *holes*. Each message is
placed by its sequence number *and* its publisher's stamp (``header.stamp_ns``, clamped
to at most ``CLOCK_SLACK_NS`` after its receipt: the stack's clocks agree, one machine's
or NTP's, and a forged stamp from the future buys nothing):

- a number inside a hole whose neighbours' stamps bracket its own fills the hole: it
  arrived late (another route, a backlog after a stall), it was not lost;
- a number the stream has, with a stamp no newer than the stream's newest, is a
  duplicate; a newer stamp means the publisher restarted: a new stream;
- a number above (or below, if older) the stream extends it when the stream could have
  sent that many in the time its stamps show (``RATE_MARGIN`` times its fastest rate over
  a second, ``MAX_RATE_HZ`` before it has shown one): the publisher's clock, so that
  messages received in a burst after a stall are judged by when they were sent;
- anything else starts a new stream, counted as a *restart* (the number went back) or an
  implausible *jump* (forward, too far to be loss), never as missing messages.

Missing messages are the holes. A hole wider than ``SLACK_MESSAGES`` is loss only once
the stream went on above it (the range above holds more than one number, or another
range lies above), or the publisher sent nothing after it (a recording that ends one
message after a wide gap); a single number ahead of a stream the publisher then went on
with (a forged one) leaves a wide hole that counts as a jump, not as loss. The same
account run over a file's messages in its order (``dammrl recording info``) gives the
same figures as the recorder's ``dammrl.loss`` metadata. Messages whose source is not
the key's publisher (``services.common.security.PUBLISHES``; ``health/<service>`` for
Health) are counted as *foreign* and kept out of the real publisher's streams.
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

from services.common.security import roles_publishing

MAX_RATE_HZ = 100_000.0
"""No publisher of the stack sends faster (the recorder benchmark's flood is 10 k/s)."""
RATE_MARGIN = 4.0
"""A publisher may lose up to this many times its fastest rate seen over a second."""
RATE_WINDOW_NS = 1_000_000_000
"""The window over which a stream's rate is measured, on its publisher's clock [ns]."""
SLACK_MESSAGES = 16
"""A gap may exceed the rate bound by this much (clock jitter); a wider hole is loss only
once the stream went on above it."""
CLOCK_SLACK_NS = 1_000_000_000
"""How much later than its receipt a message's stamp may be before it is clamped (clocks
further apart make the stamps of that publisher count as their receipt times)."""
MAX_STREAMS = 8
"""Streams remembered per publisher (the most recently continued ones)."""
MAX_RANGES = 1024
"""Ranges kept per stream: beyond, its oldest hole is final (no late number can fill it)."""
MAX_KEYS = 256
"""Keys counted apart; beyond, they share one count (random keys cannot grow memory)."""
SHARED_KEY = "<other keys>"


def sent_at(stamp_ns: int, log_time_ns: int) -> int:
    """When a message was sent: its publisher's stamp, at most ``CLOCK_SLACK_NS`` after it
    was received."""
    return min(stamp_ns, log_time_ns + CLOCK_SLACK_NS)


def publishers_of(namespace: str, key_expr: str) -> frozenset[str] | None:
    """The services that may publish on ``key_expr`` (None: not a key of the stack)."""
    topic = key_expr.removeprefix(f"{namespace}/")
    if topic == key_expr:
        return None
    return frozenset(roles_publishing(topic)) or None


@dataclass
class _Range:
    """Sequence numbers ``lo``..``hi`` all received; their publisher's stamps [ns]."""

    lo: int
    hi: int
    lo_ns: int
    hi_ns: int

    @property
    def grew(self) -> bool:
        return self.hi > self.lo


@dataclass
class _Stream:
    ranges: list[_Range]  # sorted, disjoint, never adjacent
    newest_ns: int  # the newest stamp it holds
    last_used: int = 0  # when it was last continued (the account's message count)
    window: tuple[int, int] = (0, 0)  # (seq, stamp) where the current rate window began
    peak_rate_hz: float = 0.0  # the fastest rate seen over a window (0: none yet)

    @classmethod
    def first(cls, seq: int, sent_ns: int) -> _Stream:
        return cls([_Range(seq, seq, sent_ns, sent_ns)], sent_ns, window=(seq, sent_ns))

    @property
    def lo(self) -> int:
        return self.ranges[0].lo

    @property
    def hi(self) -> int:
        return self.ranges[-1].hi

    def plausible(self, gap: int, span_ns: int) -> bool:
        """Whether ``gap`` messages can have been sent (and lost) in ``span_ns``."""
        rate = RATE_MARGIN * self.peak_rate_hz if self.peak_rate_hz > 0 else MAX_RATE_HZ
        return gap <= SLACK_MESSAGES + max(span_ns, 0) * 1e-9 * rate

    def holes(self, latest: bool = False) -> list[tuple[int, bool]]:
        """(missing numbers, confirmed) of each hole, bottom up: a wide one is confirmed
        once the stream went on above it (the range above grew, or is not the top), or,
        for the publisher's ``latest`` stream, nothing came after its last message."""
        pairs = list(zip(self.ranges, self.ranges[1:], strict=False))
        top = len(pairs) - 1
        return [(b.lo - a.hi - 1,
                 b.lo - a.hi - 1 <= SLACK_MESSAGES or b.grew or i < top or latest)
                for i, (a, b) in enumerate(pairs)]  # fmt: skip

    def measure_rate(self, seq: int, sent_ns: int) -> None:
        start_seq, start_ns = self.window
        if sent_ns - start_ns >= RATE_WINDOW_NS and seq > start_seq:
            rate = (seq - start_seq) / ((sent_ns - start_ns) * 1e-9)
            self.peak_rate_hz = max(self.peak_rate_hz, rate)
            self.window = (seq, sent_ns)


@dataclass
class SequenceAccount:
    """Messages, missing messages and anomalies per key, from (key, source, seq, stamp,
    receipt time) in the order of receipt."""

    namespace: str
    messages: Counter[str] = field(default_factory=Counter)
    restarts: Counter[str] = field(default_factory=Counter)
    jumps: Counter[str] = field(default_factory=Counter)
    """New streams started ahead of the others (before the pending ones are added)."""
    duplicates: Counter[str] = field(default_factory=Counter)
    late: Counter[str] = field(default_factory=Counter)
    """Numbers that filled a hole: they came after a later number (another route)."""
    foreign: Counter[str] = field(default_factory=Counter)
    headerless: Counter[str] = field(default_factory=Counter)
    """Messages on a typed key without a readable header (only in damaged files)."""
    closed_gaps: Counter[str] = field(default_factory=Counter)
    """Missing messages of holes no longer open (a stream or range beyond the bounds)."""
    _streams: dict[tuple[str, str, str], list[_Stream]] = field(default_factory=dict)
    _seen: int = 0  # messages accounted (the order in which streams were last continued)

    @property
    def gaps(self) -> Counter[str]:
        """Messages missing inside the publishers' streams, per key (the holes; a late
        message that fills one takes it back)."""
        missing = self.closed_gaps.copy()
        for key, stream, latest in self._every_stream():
            missing[key] += sum(n for n, confirmed in stream.holes(latest) if confirmed)
        return +missing

    def _every_stream(self) -> Iterator[tuple[str, _Stream, bool]]:
        """(key, stream, whether it is its publisher's most recently continued)."""
        for (key, _, _), streams in self._streams.items():
            latest = max(streams, key=lambda s: s.last_used)
            for stream in streams:
                yield key, stream, stream is latest

    def see(self, key: str, source: str, seq: int, log_time_ns: int, session: str = "",
            stamp_ns: int | None = None) -> int:  # fmt: skip
        """Account one message (``stamp_ns``: its header's, default its receipt); how
        many messages are now known to be missing (a new narrow hole below it, or a wide
        one the stream just went on from; 0: none, or not yet known)."""
        key = key if key in self.messages or len(self.messages) < MAX_KEYS else SHARED_KEY
        self.messages[key] += 1
        expected = publishers_of(self.namespace, key)
        if expected is not None and source not in expected:
            self.foreign[key] += 1
            return 0
        self._seen += 1
        sent = sent_at(log_time_ns if stamp_ns is None else stamp_ns, log_time_ns)
        streams = self._streams.setdefault((key, source, session), [])
        ordered = sorted(streams, key=lambda s: -s.hi)
        for below in (False, True):  # a stream it continues or fills first, then one it precedes
            for stream in ordered:
                placed = self._place(key, stream, seq, sent, below)
                if placed is not None:
                    stream.last_used = self._seen
                    self._bound(key, stream)
                    return placed
        self._start(key, streams, seq, sent)
        return 0

    def _place(self, key: str, stream: _Stream, seq: int, sent_ns: int,
               below: bool) -> int | None:  # fmt: skip
        """Put ``seq`` into ``stream`` if it belongs there (``below``: under its lowest
        number too); what ``see`` returns; None: it does not belong there."""
        ranges = stream.ranges
        top = ranges[-1]
        if seq == top.hi + 1 and sent_ns >= top.hi_ns:  # the next one, as it mostly is
            confirmed = 0 if top.grew or len(ranges) < 2 else top.lo - ranges[-2].hi - 1
            top.hi, top.hi_ns = seq, sent_ns
            stream.newest_ns = max(stream.newest_ns, sent_ns)
            stream.measure_rate(seq, sent_ns)
            return confirmed if confirmed > SLACK_MESSAGES else 0
        index = bisect.bisect_right([r.lo for r in ranges], seq) - 1  # the range at or below
        if index >= 0 and seq <= ranges[index].hi:  # a number the stream has
            if sent_ns > stream.newest_ns:
                return None  # sent after everything of the stream: a restarted publisher
            self.duplicates[key] += 1
            return 0
        if 0 <= index < len(ranges) - 1:  # inside a hole
            under, over = ranges[index], ranges[index + 1]
            if not under.hi_ns <= sent_ns <= over.lo_ns:
                return None
            self.late[key] += 1
            self._insert(stream, index + 1, seq, sent_ns)
            return 0
        if index == len(ranges) - 1:  # above the stream
            if sent_ns < top.hi_ns or not stream.plausible(seq - top.hi - 1, sent_ns - top.hi_ns):
                return None
            self._insert(stream, len(ranges), seq, sent_ns)
            stream.newest_ns = max(stream.newest_ns, sent_ns)
            stream.measure_rate(seq, sent_ns)
            gap = seq - top.hi - 1
            return gap if gap <= SLACK_MESSAGES else 0  # a wide one: once the stream goes on
        bottom = ranges[0]  # below the stream: an older message that came late
        if not below or sent_ns > bottom.lo_ns or not stream.plausible(bottom.lo - seq - 1,
                                                          bottom.lo_ns - sent_ns):  # fmt: skip
            return None
        self.late[key] += 1
        self._insert(stream, 0, seq, sent_ns)
        return 0

    @staticmethod
    def _insert(stream: _Stream, at: int, seq: int, sent_ns: int) -> None:
        """``seq`` as a new range at position ``at``, merged with neighbours it touches."""
        ranges = stream.ranges
        ranges.insert(at, _Range(seq, seq, sent_ns, sent_ns))
        if at + 1 < len(ranges) and ranges[at + 1].lo == seq + 1:
            above = ranges.pop(at + 1)
            ranges[at].hi, ranges[at].hi_ns = above.hi, above.hi_ns
        if at > 0 and ranges[at - 1].hi == seq - 1:
            below = ranges.pop(at - 1)
            ranges[at - 1].lo, ranges[at - 1].lo_ns = below.lo, below.lo_ns

    def _start(self, key: str, streams: list[_Stream], seq: int, sent_ns: int) -> None:
        if streams and seq < max(s.hi for s in streams):
            self.restarts[key] += 1
        elif streams:
            self.jumps[key] += 1
        stream = _Stream.first(seq, sent_ns)
        stream.last_used = self._seen
        streams.append(stream)
        if len(streams) > MAX_STREAMS:  # forget the least recently continued
            oldest = min(streams, key=lambda s: s.last_used)
            streams.remove(oldest)
            self._close(key, oldest.holes())

    def _bound(self, key: str, stream: _Stream) -> None:
        """Keep at most ``MAX_RANGES`` ranges: the oldest hole becomes final."""
        while len(stream.ranges) > MAX_RANGES:
            self._close(key, stream.holes()[:1])
            low = stream.ranges.pop(0)
            stream.ranges[0].lo, stream.ranges[0].lo_ns = low.lo, low.lo_ns

    def _close(self, key: str, holes: list[tuple[int, bool]]) -> None:
        for missing, confirmed in holes:
            if confirmed:
                self.closed_gaps[key] += missing
            else:
                self.jumps[key] += 1

    def anomalies(self) -> dict[str, dict[str, int]]:
        """The non-empty anomaly counts per kind, then per key (a wide hole never confirmed
        is a jump)."""
        jumps = self.jumps.copy()
        for key, stream, latest in self._every_stream():
            jumps[key] += sum(1 for _, confirmed in stream.holes(latest) if not confirmed)
        kinds = {
            "restarts": self.restarts,
            "implausible_jumps": +jumps,
            "duplicates": self.duplicates,
            "late": self.late,
            "foreign_source": self.foreign,
            "no_valid_header": self.headerless,
        }
        return {kind: dict(counts) for kind, counts in kinds.items() if counts}
