"""Writes bus traffic to MCAP: the bytes exactly as they travelled.

One channel per key expression, message encoding ``msgpack``, schema encoding
``jsonschema`` from the pydantic models; ``log_time`` is the receipt time and
``publish_time`` the header stamp. Payloads that do not decode are still written, on a
channel ``_invalid/<key>`` (schema-less), so nothing that crossed the bus is dropped.
Per-publisher sequence numbers are checked and gaps counted; the counts go into a
``dammrl.loss`` metadata record when the file is finished.
"""

from __future__ import annotations

import json
import logging
import socket
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgpack
from mcap.writer import CompressionType, Writer

from dammrl import __version__
from dammrl.core.errors import DammrlError
from schemas import Message, type_of

PROFILE = "dammrl"
log = logging.getLogger("dammrl.recorder")


@dataclass
class LossCounter:
    """Sequence-number bookkeeping per (key, source)."""

    last_seq: dict[tuple[str, str], int] = field(default_factory=dict)
    gaps: Counter[str] = field(default_factory=Counter)  # missing messages per key
    messages: Counter[str] = field(default_factory=Counter)

    def see(self, key: str, source: str, seq: int) -> int:
        """Record one message; return how many before it are missing."""
        self.messages[key] += 1
        previous = self.last_seq.get((key, source))
        self.last_seq[(key, source)] = seq
        if previous is None or seq <= previous:  # first, or the publisher restarted
            return 0
        missing = seq - previous - 1
        self.gaps[key] += missing
        return missing


def header_of(payload: bytes) -> dict[str, Any] | None:
    """The header map of a msgpack message, without validating the rest (None if absent)."""
    try:
        obj = msgpack.unpackb(payload, raw=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
        return None
    header = obj.get("header") if isinstance(obj, dict) else None
    if not isinstance(header, dict):
        return None
    ok = isinstance(header.get("stamp_ns"), int) and isinstance(header.get("seq"), int)
    return header if ok else None


class McapRecorder:
    """One MCAP file being written. ``finish()`` must be called (see the node)."""

    def __init__(self, path: Path, namespace: str, metadata: dict[str, str], chunk_bytes: int):
        self.path = path
        self.namespace = namespace
        try:
            self._stream: IO[bytes] = open(path, "wb")  # noqa: SIM115 - closed in finish()
        except OSError as exc:
            raise DammrlError(f"cannot record to {path}: {exc}") from exc
        self.writer = Writer(self._stream, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self.writer.start(profile=PROFILE, library=f"dammrl {__version__}")
        self.writer.add_metadata(
            "dammrl.session",
            {"version": __version__, "host": socket.gethostname(), "namespace": namespace}
            | metadata,
        )
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[str, int] = {}
        self.loss = LossCounter()
        self.invalid: Counter[str] = Counter()
        self.first_ns: int | None = None
        self.finished = False

    def record(self, key: str, payload: bytes, log_time_ns: int) -> None:
        self.first_ns = log_time_ns if self.first_ns is None else self.first_ns
        header = header_of(payload)
        message_type = type_of(self.namespace, key)
        if header is None or message_type is None:
            self.invalid[key] += 1
            channel = self._channel(f"_invalid/{key}", None)
            self.writer.add_message(channel, log_time_ns, payload, log_time_ns)
            return
        seq = header["seq"]
        missing = self.loss.see(key, str(header.get("source")), seq)
        if missing:
            log.warning("%d message(s) missing on %s before seq %d", missing, key, seq)
        channel = self._channel(key, message_type)
        publish_ns = header["stamp_ns"] if header["stamp_ns"] >= 0 else log_time_ns
        self.writer.add_message(channel, log_time_ns, payload, publish_ns, seq % 2**32)

    def bytes_written(self) -> int:
        return self._stream.tell()

    def finish(self) -> None:
        if self.finished:
            return
        self.finished = True
        self.writer.add_metadata(
            "dammrl.loss",
            {
                "gaps": json.dumps(dict(self.loss.gaps)),
                "messages": json.dumps(dict(self.loss.messages)),
                "invalid": json.dumps(dict(self.invalid)),
            },
        )
        self.writer.finish()  # type: ignore[no-untyped-call]
        self._stream.close()

    def _channel(self, topic: str, message_type: type[Message] | None) -> int:
        if topic not in self._channels:
            schema_id = 0 if message_type is None else self._schema(message_type)
            metadata = {"dammrl.invalid": "true"} if message_type is None else {}
            self._channels[topic] = self.writer.register_channel(
                topic, "msgpack", schema_id, metadata
            )
        return self._channels[topic]

    def _schema(self, message_type: type[Message]) -> int:
        if message_type not in self._schemas:
            schema = json.dumps(message_type.model_json_schema()).encode()
            self._schemas[message_type] = self.writer.register_schema(
                message_type.__name__, "jsonschema", schema
            )
        return self._schemas[message_type]
