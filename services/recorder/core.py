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
killed recorder loses at most the chunk in progress, and leaves a file that any MCAP
reader opens as it is (``tail.CommittedFile``: it always ends with a footer). Write
errors (a full disk) are ``OSError``; the node decides what to do with them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import struct
from collections import Counter
from pathlib import Path
from typing import IO, Any, cast

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
from services.recorder.tail import FOOTER, MAGIC, TAIL_BYTES, CommittedFile

PROFILE = "dammrl"
AT_ONCE: tuple[type[Message], ...] = (EpisodeResult, ComfortRating, SessionControl, EmergencyStop)
"""The rare messages a study is built on (a reach's result, the participant's rating, the
therapist's acts): their chunk is closed and handed to the OS as each one comes, so even
a recorder killed right after one keeps it."""
log = logging.getLogger("dammrl.recorder")
LOSS_WARNING_S = 10.0
"""A key's lost messages are logged at most this often [s]."""


def complete_mcap(path: Path) -> bool:
    """Whether ``path`` was finished by its writer: it ends with a footer that points to
    a summary (a recorder killed leaves a provisional footer, without one)."""
    try:
        with open(path, "rb") as stream:
            stream.seek(-TAIL_BYTES, 2)
            tail = stream.read()
    except OSError:
        return False
    opcode, _, summary_start = struct.unpack_from("<BQQ", tail)
    return tail.endswith(MAGIC) and opcode == FOOTER and summary_start > 0


def header_of(payload: bytes) -> dict[str, Any] | None:
    """The header map of a msgpack message, without validating the rest (None if absent)."""
    fields = message_map(payload)
    return None if fields is None else fields["header"]


def message_map(payload: bytes) -> dict[str, Any] | None:
    """The map of a msgpack message whose header is well formed, the rest unvalidated
    (None otherwise)."""
    try:
        obj = msgpack.unpackb(payload, raw=False)
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError):
        return None
    header = obj.get("header") if isinstance(obj, dict) else None
    if not isinstance(header, dict):
        return None
    stamp, seq, source = header.get("stamp_ns"), header.get("seq"), header.get("source")
    ok = type(stamp) is int and type(seq) is int and seq >= 0  # bool is no number here
    return obj if ok and type(source) is str else None  # (a list as source crashed it)


def loss_record(account: SequenceAccount, invalid: Counter[str],
                raw_streams: RawStreams) -> dict[str, str]:  # fmt: skip
    """The ``dammrl.loss`` metadata: per key, the messages, what the file's sequence
    numbers lack (``gaps``), the payloads without a valid header, and the anomalies; per
    wearable stream, the samples its chunks say were missing (``raw_streams``)."""
    return {
        "gaps": json.dumps(dict(account.gaps)),
        "messages": json.dumps(dict(account.messages)),
        "invalid": json.dumps(dict(invalid)),
        "anomalies": json.dumps(account.anomalies()),
        "raw_streams": raw_streams.metadata(),
    }


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
            self._stream = CommittedFile(path)  # closed in finish() or abandon()
        except OSError as exc:
            raise DammrlError(f"cannot record to {path}: {exc}") from exc
        stream = cast("IO[bytes]", self._stream)  # the writer only writes, tells and flushes
        self.writer = Writer(stream, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
        self._schemas: dict[type[Message], int] = {}
        self._channels: dict[str, int] = {}
        self.loss = SequenceAccount(namespace)
        self.raw_streams = RawStreams(namespace)
        self._loss_said: dict[str, int] = {}  # key -> when its loss was last logged [ns]
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
            self._stream.commit()
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
        source, stamp = str(header.get("source")), header["stamp_ns"]
        if self.loss.see(key, source, seq, log_time_ns, session, stamp):
            self._say_loss(key, log_time_ns)
        self.raw_streams.see(key, payload)
        channel = self._channel(key, message_type)
        publish_ns = header["stamp_ns"] if header["stamp_ns"] >= 0 else log_time_ns
        self.writer.add_message(channel, log_time_ns, payload, publish_ns, seq % 2**32)
        if message_type in AT_ONCE:
            self.flush()
        elif self._stream.pending:  # the writer closed a chunk by size: to the OS at once
            self._stream.commit()

    def _say_loss(self, key: str, now_ns: int) -> None:
        """A warning when ``key`` lost messages, at most every ``LOSS_WARNING_S`` per key
        (a loaded machine must not flood the log; the file's figures are the account)."""
        if now_ns - self._loss_said.get(key, -(2**62)) < LOSS_WARNING_S * 1e9:
            return
        self._loss_said[key] = now_ns
        log.warning("%s: %d message(s) missing so far in %s", key, self.loss.gaps[key],
                    self.path.name)  # fmt: skip

    def flush_due(self, now_ns: int, chunk_s: float) -> bool:
        """Whether the oldest message not yet handed to the OS is ``chunk_s`` old."""
        return self.unflushed_ns is not None and now_ns - self.unflushed_ns >= chunk_s * 1e9

    def flush(self) -> None:
        """Close the chunk in progress and hand everything written to the OS (a process
        kill then loses nothing of it; a power cut may: no fsync)."""
        self.writer.flush()  # type: ignore[no-untyped-call]
        self._stream.commit()
        self.unflushed_ns = None

    def sync(self) -> None:
        """Flush, and have the OS write the file to the disk (fsync): what an
        acknowledgement promises survives a power cut too."""
        self.flush()
        self._stream.sync()

    def bytes_written(self) -> int:
        return self._stream.tell()

    def finish(self) -> None:
        """Write the loss counts, the summary and the footer, and close the file."""
        if self.finished:
            return
        self.writer.add_metadata("dammrl.loss", self.loss_metadata())
        self.writer.finish()  # type: ignore[no-untyped-call]
        self.finished = True
        self._stream.finish()

    def abandon(self) -> None:
        """Close the file after a write error: it stays readable up to its last chunk
        that reached the disk, by any MCAP reader (``dammrl recording repair`` adds the
        summary)."""
        self.finished = True
        with contextlib.suppress(OSError):
            self._stream.close()

    def loss_metadata(self) -> dict[str, str]:
        return loss_record(self.loss, self.invalid, self.raw_streams)

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
