"""What the recorded raw streams of wearable sensors lost, as their chunks say it.

The intent service counts, per stream, the samples missing between two chunks (a gap in
the stream's timestamps longer than a busy sender's jitter, or samples it had to drop
before the bus) and the correction it applies since the sender's clock jumped
(``SignalChunk.missing``, ``clock_corrected_s``). The recorder sums them per stream into
the file's loss metadata (``dammrl.loss``, key ``raw_streams``), beside the bus's own
sequence gaps (a chunk lost on the bus is one of those).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import msgpack

from schemas import SignalChunk, key


@dataclass
class RawStream:
    chunks: int = 0
    samples: int = 0
    missing_samples: int = 0
    gaps: int = 0  # chunks after a gap
    clock_jumps: int = 0  # changes of the correction of the sender's clock
    clock_corrected_s: float = 0.0  # the correction in force at the end


class RawStreams:
    def __init__(self, namespace: str) -> None:
        self.key = key(namespace, SignalChunk)
        self.streams: dict[str, RawStream] = {}

    def see(self, topic: str, payload: bytes) -> None:
        """Count a recorded message (only raw chunks count; a malformed one is skipped:
        the recorder counts it as invalid)."""
        if topic != self.key:
            return
        try:
            chunk = msgpack.unpackb(payload, raw=False)
        except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
            return
        if not isinstance(chunk, dict) or not isinstance(chunk.get("stream"), str):
            return
        missing, corrected = chunk.get("missing", 0), chunk.get("clock_corrected_s", 0.0)
        stamps = chunk.get("stamps_ns")
        if type(missing) is not int or not isinstance(corrected, int | float):
            return
        stream = self.streams.setdefault(chunk["stream"][:200], RawStream())
        stream.chunks += 1
        stream.samples += len(stamps) if isinstance(stamps, list) else 0
        stream.missing_samples += max(0, missing)
        stream.gaps += missing > 0
        stream.clock_jumps += float(corrected) != stream.clock_corrected_s
        stream.clock_corrected_s = float(corrected)

    def counts(self) -> dict[str, dict[str, float]]:
        """Per stream: chunks, samples, missing samples, gaps, clock jumps, the correction."""
        return {name: asdict(s) for name, s in self.streams.items()}

    def metadata(self) -> str:
        """The counts per stream, as JSON."""
        return json.dumps(self.counts())
