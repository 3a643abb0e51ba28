"""Sequence accounting that a forged, fuzzed or restarted sequence cannot inflate.

``header.seq`` is declared by whoever publishes, so it is trusted only as far as it is
plausible. A *stream* is one run of sequence numbers of one publisher: the key, the
header's source and, when Zenoh carries it, the publishing session's id. A message
continues the stream it plausibly follows: the highest last ``seq`` below its own, with
no more missing messages in between than the stream could have sent in the time since
(at ``RATE_MARGIN`` times the fastest rate it has shown over a second, or
``MAX_RATE_HZ`` before it has shown one). Otherwise it starts a new stream, counted as
a *restart* (the sequence went back: a restarted publisher) or an implausible *jump*
(forward, too far to be loss), never as missing messages.

A gap of more than ``SLACK_MESSAGES`` is only *pending* until the next message of the
publisher continues it; if the old stream continues instead (a forged number between
the real ones), the gap was a jump, not loss. Messages whose source is not the key's
publisher (``services.common.security.PUBLISHES``; ``health/<service>`` for Health) are
counted as *foreign* and kept out of the real publisher's streams.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from services.common.security import roles_publishing

MAX_RATE_HZ = 100_000.0
"""No publisher of the stack sends faster (the recorder benchmark's flood is 10 k/s)."""
RATE_MARGIN = 4.0
"""A publisher may lose up to this many times its fastest rate seen over a second."""
RATE_WINDOW_NS = 1_000_000_000
"""The window over which a stream's rate is measured [ns]."""
SLACK_MESSAGES = 16
"""A jump may exceed the rate bound by this much (receipt-time jitter); a gap larger
than this is pending until the stream continues."""
MAX_STREAMS = 8
"""Streams remembered per publisher (the most recently continued ones)."""


def publishers_of(namespace: str, key_expr: str) -> frozenset[str] | None:
    """The services that may publish on ``key_expr`` (None: not a key of the stack)."""
    topic = key_expr.removeprefix(f"{namespace}/")
    if topic == key_expr:
        return None
    return frozenset(roles_publishing(topic)) or None


@dataclass
class _Stream:
    last_seq: int
    last_ns: int  # receipt time of its last message
    pending: int = 0  # missing messages before its first, until it continues
    window_seq: int = -1  # where the current rate window began
    window_ns: int = -1
    peak_rate_hz: float = 0.0  # the fastest rate seen over a window (0: none yet)

    def __post_init__(self) -> None:
        self.window_seq, self.window_ns = self.last_seq, self.last_ns

    def advance(self, seq: int, log_time_ns: int) -> None:
        self.last_seq, self.last_ns = seq, log_time_ns
        span_ns = log_time_ns - self.window_ns
        if span_ns >= RATE_WINDOW_NS:
            rate = (seq - self.window_seq) / (span_ns * 1e-9)
            self.peak_rate_hz = max(self.peak_rate_hz, rate)
            self.window_seq, self.window_ns = seq, log_time_ns

    def plausible_gap(self, log_time_ns: int) -> float:
        """The most messages this stream can have lost since its last one."""
        elapsed_s = max(log_time_ns - self.last_ns, 0) * 1e-9
        rate = RATE_MARGIN * self.peak_rate_hz if self.peak_rate_hz > 0 else MAX_RATE_HZ
        return SLACK_MESSAGES + elapsed_s * rate


@dataclass
class SequenceAccount:
    """Messages, gaps and anomalies per key, from (key, source, seq, receipt time)."""

    namespace: str
    messages: Counter[str] = field(default_factory=Counter)
    gaps: Counter[str] = field(default_factory=Counter)
    """Messages missing inside a publisher's streams, per key."""
    restarts: Counter[str] = field(default_factory=Counter)
    jumps: Counter[str] = field(default_factory=Counter)
    duplicates: Counter[str] = field(default_factory=Counter)
    foreign: Counter[str] = field(default_factory=Counter)
    headerless: Counter[str] = field(default_factory=Counter)
    """Messages on a typed key without a readable header (only in damaged files)."""
    _streams: dict[tuple[str, str, str], list[_Stream]] = field(default_factory=dict)

    def see(self, key: str, source: str, seq: int, log_time_ns: int, session: str = "") -> int:
        """Account one message; return how many messages are now known to be missing."""
        self.messages[key] += 1
        expected = publishers_of(self.namespace, key)
        if expected is not None and source not in expected:
            self.foreign[key] += 1
            return 0
        streams = self._streams.setdefault((key, source, session), [])
        stream = _followed(streams, seq, log_time_ns)
        if stream is None:
            self._start(key, streams, _Stream(seq, log_time_ns))
            return 0
        confirmed, stream.pending = stream.pending, 0  # it continued: its gap was loss
        missing = max(seq - stream.last_seq - 1, 0)
        if missing > SLACK_MESSAGES:  # loss, or a forged number: the next message tells
            self._keep(key, streams, _Stream(seq, log_time_ns, pending=missing))
            return self._count_gap(key, confirmed)
        if seq == stream.last_seq:
            self.duplicates[key] += 1
        stream.advance(seq, log_time_ns)
        self._keep(key, streams, stream)
        return self._count_gap(key, confirmed + missing)

    def _count_gap(self, key: str, missing: int) -> int:
        if missing:
            self.gaps[key] += missing
        return missing

    def anomalies(self) -> dict[str, dict[str, int]]:
        """The non-empty anomaly counts per kind, then per key (a gap still pending, never
        continued, is a jump)."""
        jumps = self.jumps.copy()
        for (key, _, _), streams in self._streams.items():
            jumps[key] += sum(1 for s in streams if s.pending)
        kinds = {
            "restarts": self.restarts,
            "implausible_jumps": +jumps,
            "duplicates": self.duplicates,
            "foreign_source": self.foreign,
            "no_valid_header": self.headerless,
        }
        return {kind: dict(counts) for kind, counts in kinds.items() if counts}

    def _start(self, key: str, streams: list[_Stream], stream: _Stream) -> None:
        if streams and stream.last_seq < max(s.last_seq for s in streams):
            self.restarts[key] += 1
        elif streams:
            self.jumps[key] += 1
        self._keep(key, streams, stream)

    def _keep(self, key: str, streams: list[_Stream], stream: _Stream) -> None:
        """``stream`` becomes the most recently continued; the oldest beyond
        ``MAX_STREAMS`` is forgotten (a pending one as the jump it was)."""
        if stream in streams:
            streams.remove(stream)
        streams.append(stream)
        for dropped in streams[:-MAX_STREAMS]:
            if dropped.pending:
                self.jumps[key] += 1
        del streams[:-MAX_STREAMS]


def _followed(streams: list[_Stream], seq: int, log_time_ns: int) -> _Stream | None:
    """The stream ``seq`` plausibly continues (or repeats), if any."""
    best = None
    for stream in streams:
        if stream.last_seq <= seq <= stream.last_seq + 1 + stream.plausible_gap(log_time_ns) and (
            best is None or stream.last_seq > best.last_seq
        ):
            best = stream
    return best
