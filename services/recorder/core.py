"""Writes bus traffic to MCAP: the bytes exactly as they travelled.

One channel per key expression, message encoding ``msgpack``, schema encoding
``jsonschema`` from the pydantic models; ``log_time`` is the receipt time and
``publish_time`` the header stamp. Payloads that do not decode are still written, on a
channel ``_invalid/<key>`` (schema-less), so nothing that crossed the bus is dropped.
Sequence numbers are accounted per publisher (``gaps.SequenceAccount``), and the samples
a wearable's raw stream lost as its chunks say (``raw.RawStreams``); the counts go into a
``dammrl.loss`` metadata record when the file is finished.

A chunk is closed by size (the writer) or by age (:meth:`McapRecorder.flush_due`, the
node calls :meth:`McapRecorder.flush`), and a closed chunk goes to the OS at once: a
killed recorder loses at most the chunk in progress. Write errors (a full disk) are
``OSError``; the node decides what to do with them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
from collections import Counter
from pathlib import Path
from typing import IO, Any

import msgpack
from mcap.writer import CompressionType, Writer

from dammrl_core import __version__
from dammrl_core.errors import DammrlError
from schemas import (
    ComfortRating,
    EmergencyStop,
    EpisodeResult,
    Message,
    SessionControl,
    type_of,
)
from services.recorder.gaps import SequenceAccount
from services.recorder.raw import RawStreams

PROFILE = "dammrl"
AT_ONCE: tuple[type[Message], ...] = (EpisodeResult, ComfortRating, SessionControl, EmergencyStop)
"""The rare messages a study is built on (a reach's result, the participant's rating, the
therapist's acts): their chunk is closed and handed to the OS as each one comes, so even
a recorder killed right after one keeps it."""
log = logging.getLogger("dammrl.recorder")


MCAP_MAGIC = b"\x89MCAP0\r\n"


def complete_mcap(path: Path) -> bool:
    """Whether ``path`` ends as a finished MCAP file does (its closing magic bytes)."""
    try:
        with open(path, "rb") as stream:
            stream.seek(-len(MCAP_MAGIC), 2)
            return stream.read() == MCAP_MAGIC
    except OSError:
        return False


def header_of(payload: bytes) -> dict[str, Any] | None:
    """The header map of a msgpack message, without validating the rest (None if absent)."""
    try:
        obj = msgpack.unpackb(payload, raw=False)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
        return None
    header = obj.get("header") if isinstance(obj, dict) else None
    if not isinstance(header, dict):
        return None
    stamp, seq = header.get("stamp_ns"), header.get("seq")
    ok = type(stamp) is int and type(seq) is int and seq >= 0  # bool is no number here
    return header if ok else None


class McapRecorder:
    """One MCAP file being written. ``finish()`` (or, after a write error, ``abandon()``)
    must be called (see the node)."""

    def __init__(self, path: Path, namespace: str, metadata: dict[str, str], chunk_bytes: int):
        """Open ``path`` and write the file's start through to the OS (a recorder killed
        at once still leaves a valid, empty recording). DammrlError: the file cannot be
        created; OSError: it cannot be written (the file is closed)."""
        self.path = path
        self.namespace = namespace
        try:
            self._stream: IO[bytes] = open(path, "wb")  # noqa: SIM115 - closed in finish()
        except OSError as exc:
            raise DammrlError(f"cannot record to {path}: {exc}") from exc
        self.writer = Writer(self._stream, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[str, int] = {}
        self.loss = SequenceAccount(namespace)
        self.raw_streams = RawStreams(namespace)
        self.invalid: Counter[str] = Counter()
        self.first_ns: int | None = None
        self.unflushed_ns: int | None = None  # receipt time of the oldest unflushed message
        self.finished = False
        try:
            self.writer.start(profile=PROFILE, library=f"dammrl {__version__}")
            self.writer.add_metadata(
                "dammrl.session",
                {"version": __version__, "host": socket.gethostname(), "namespace": namespace}
                | metadata,
            )
            self._stream.flush()
        except OSError:
            self.abandon()
            raise

    def record(self, key: str, payload: bytes, log_time_ns: int, session: str = "") -> None:
        """Write one received payload; ``session``: the publishing Zenoh session, if known."""
        self.first_ns = log_time_ns if self.first_ns is None else self.first_ns
        self.unflushed_ns = log_time_ns if self.unflushed_ns is None else self.unflushed_ns
        header = header_of(payload)
        message_type = type_of(self.namespace, key)
        if header is None or message_type is None:
            self.invalid[key] += 1
            channel = self._channel(f"_invalid/{key}", None)
            self.writer.add_message(channel, log_time_ns, payload, log_time_ns)
            return
        seq = header["seq"]
        missing = self.loss.see(key, str(header.get("source")), seq, log_time_ns, session)
        if missing:
            log.warning("%d message(s) missing on %s before seq %d", missing, key, seq)
        self.raw_streams.see(key, payload)
        channel = self._channel(key, message_type)
        publish_ns = header["stamp_ns"] if header["stamp_ns"] >= 0 else log_time_ns
        self.writer.add_message(channel, log_time_ns, payload, publish_ns, seq % 2**32)
        if message_type in AT_ONCE:
            self.flush()

    def flush_due(self, now_ns: int, chunk_s: float) -> bool:
        """Whether the oldest message not yet handed to the OS is ``chunk_s`` old."""
        return self.unflushed_ns is not None and now_ns - self.unflushed_ns >= chunk_s * 1e9

    def flush(self) -> None:
        """Close the chunk in progress and hand everything written to the OS (a process
        kill then loses nothing of it; a power cut may: no fsync)."""
        self.writer.flush()  # type: ignore[no-untyped-call]
        self.unflushed_ns = None

    def bytes_written(self) -> int:
        return self._stream.tell()

    def finish(self) -> None:
        """Write the loss counts, the summary and the footer, and close the file."""
        if self.finished:
            return
        self.writer.add_metadata("dammrl.loss", self.loss_metadata())
        self.writer.finish()  # type: ignore[no-untyped-call]
        self.finished = True
        self._stream.close()

    def abandon(self) -> None:
        """Close the file after a write error: it stays readable up to its last chunk
        that reached the disk (``dammrl recording repair``)."""
        self.finished = True
        with contextlib.suppress(OSError):  # the buffer's tail cannot be written either
            self._stream.close()

    def loss_metadata(self) -> dict[str, str]:
        loss = self.loss
        return {
            "gaps": json.dumps(dict(loss.gaps)),
            "messages": json.dumps(dict(loss.messages)),
            "invalid": json.dumps(dict(self.invalid)),
            "anomalies": json.dumps(loss.anomalies()),
            "raw_streams": self.raw_streams.metadata(),
        }

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
