"""Sequence accounting that a forged, fuzzed or restarted sequence cannot inflate.

``header.seq`` is declared by whoever publishes, so it is trusted only as far as it is
plausible. A *stream* is one run of sequence numbers of one publisher: the key, the
header's source and, when Zenoh carries it, the publishing session's id. A message
continues the stream it plausibly follows (the highest last ``seq`` below its own, with
no more missing messages in between than could have been sent in the time since, at
``MAX_RATE_HZ``); otherwise it starts a new stream, counted as a *restart* (the sequence
went back: a restarted publisher) or an implausible *jump* (forward, too far to be
loss), never as missing messages. Messages whose source is not the key's publisher
(``services.common.security.PUBLISHES``; ``health/<service>`` for Health) are counted
as *foreign* and kept out of the real publisher's streams.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from services.common.security import PUBLISHES

MAX_RATE_HZ = 100_000.0
"""No publisher of the stack sends faster (the recorder benchmark's flood is 10 k/s)."""
SLACK_MESSAGES = 16
"""A jump may exceed the rate bound by this much (receipt-time jitter)."""
MAX_STREAMS = 8
"""Streams remembered per publisher (the most recently continued ones)."""


def publishers_of(namespace: str, key_expr: str) -> frozenset[str] | None:
    """The services that may publish on ``key_expr`` (None: not a key of the stack)."""
    topic = key_expr.removeprefix(f"{namespace}/")
    if topic == key_expr:
        return None
    if topic.startswith("health/"):
        return frozenset({topic.removeprefix("health/")})
    roles = frozenset(role for role, topics in PUBLISHES.items() if topic in topics)
    return roles or None


@dataclass
class _Stream:
    last_seq: int
    last_ns: int  # receipt time of its last message


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
        """Account one message; return how many messages before it are missing."""
        self.messages[key] += 1
        expected = publishers_of(self.namespace, key)
        if expected is not None and source not in expected:
            self.foreign[key] += 1
            return 0
        streams = self._streams.setdefault((key, source, session), [])
        stream = _followed(streams, seq, log_time_ns)
        if stream is None:
            self._start(key, streams, seq, log_time_ns)
            return 0
        missing = max(seq - stream.last_seq - 1, 0)
        if missing:
            self.gaps[key] += missing
        if seq == stream.last_seq:
            self.duplicates[key] += 1
        stream.last_seq, stream.last_ns = seq, log_time_ns
        streams.remove(stream)
        streams.append(stream)  # most recently continued last
        return missing

    def anomalies(self) -> dict[str, dict[str, int]]:
        """The non-empty anomaly counts per kind, then per key."""
        kinds = {
            "restarts": self.restarts,
            "implausible_jumps": self.jumps,
            "duplicates": self.duplicates,
            "foreign_source": self.foreign,
            "no_valid_header": self.headerless,
        }
        return {kind: dict(counts) for kind, counts in kinds.items() if counts}

    def _start(self, key: str, streams: list[_Stream], seq: int, log_time_ns: int) -> None:
        if streams and seq < max(s.last_seq for s in streams):
            self.restarts[key] += 1
        elif streams:
            self.jumps[key] += 1
        streams.append(_Stream(seq, log_time_ns))
        del streams[:-MAX_STREAMS]


def _followed(streams: list[_Stream], seq: int, log_time_ns: int) -> _Stream | None:
    """The stream ``seq`` plausibly continues (or repeats), if any."""
    best = None
    for stream in streams:
        elapsed_s = max(log_time_ns - stream.last_ns, 0) * 1e-9
        plausible = SLACK_MESSAGES + elapsed_s * MAX_RATE_HZ
        if stream.last_seq <= seq <= stream.last_seq + 1 + plausible and (
            best is None or stream.last_seq > best.last_seq
        ):
            best = stream
    return best
