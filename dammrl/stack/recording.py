"""Read recordings: info, repair, exports (Foxglove JSON, CSV), human statistics.

Every reader goes through :func:`read_recording`, which streams records from the start
and stops cleanly at a truncated tail, so a file whose recorder was killed (no footer,
last chunk cut) is read up to its last complete chunk. Damage inside the file is
skipped and counted, never raised: a chunk that does not decompress or fails its CRC
(the next ones are still read), a message on a channel the file never declared. A file
with no readable start is a :class:`RecordingError` saying where and why it stops.
"""

from __future__ import annotations

import csv
import json
import os
import struct
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from dammrl_core.errors import DammrlError, JobFailedError
from dammrl_core.human import direction_to_goal
from dammrl_core.models import radius_name
from schemas import (
    DecisionRequest,
    DecodeError,
    EpisodeResult,
    Intent,
    RobotState,
    SensorSample,
    TaskGoal,
    decode,
    type_of,
)
from schemas import Message as BusMessage
from services.recorder.core import header_of, loss_record
from services.recorder.gaps import SequenceAccount
from services.recorder.raw import RawStreams

MAGIC = b"\x89MCAP0\r\n"
COMPRESSIONS = ("", "zstd", "lz4")
MAX_CHUNK_BYTES = 2**31
"""A chunk claiming more (uncompressed) is skipped rather than allocated."""


class RecordingError(DammrlError):
    """A file that cannot be read as a recording."""


@dataclass
class Recording:
    """Everything readable in one MCAP file, in file order."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    started: bool = False  # the MCAP header record was read
    data_end: bool = False  # the data section's end record was read
    complete: bool = False  # the footer after the data section's end: finished by its writer
    truncated_reason: str = ""
    skipped: Counter[str] = field(default_factory=Counter)  # unreadable records, by kind

    def topic(self, message: Message) -> str:
        return self.channels[message.channel_id].topic

    def namespace(self) -> str:
        return self.metadata.get("dammrl.session", {}).get("namespace", "dammrl")

    def decoded(self, *types: type[BusMessage]) -> Iterator[tuple[int, BusMessage]]:
        """(log time ns, message) of the recorded messages of these types that decode."""
        namespace = self.namespace()
        for record in self.messages:
            message_type = type_of(namespace, self.topic(record))
            if message_type not in types:
                continue
            try:
                yield record.log_time, decode(message_type, record.data)
            except DecodeError:
                continue


def read_recording(path: Path) -> Recording:
    """Everything readable in ``path``; RecordingError when not even its start is."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path} {'is not a file' if path.exists() else 'does not exist'}")
    size = path.stat().st_size
    recording = Recording(path)
    with open(path, "rb") as stream:
        resume_at: int | None = 0
        while resume_at is not None:
            resume_at = _read_from(recording, stream, size, resume_at)
    _drop_orphans(recording)
    recording.messages.sort(key=lambda m: m.log_time)
    if recording.started and not recording.complete and not recording.truncated_reason:
        recording.truncated_reason = ("not finished by its writer (a recorder killed): it ends "
                                      "after its last complete chunk")  # fmt: skip
    return recording


def _read_from(recording: Recording, stream: BinaryIO, size: int, start: int) -> int | None:
    """Collect records from byte ``start`` (0: the magic) on; where to resume after a
    complete but unreadable record, None when done (footer, end or a cut)."""
    stream.seek(start)
    end = start  # where the last readable record ends
    try:
        reader = StreamReader(stream, skip_magic=start > 0, emit_chunks=True,
                              record_size_limit=max(size, 1))  # fmt: skip
        for record in reader.records:
            _collect(recording, record)
            end = stream.tell()
    except (McapError, EOFError, ValueError, OSError, struct.error) as exc:
        reason, unreadable = _why_it_stops(stream, size, end, exc)
        if not recording.started:
            raise RecordingError(f"{recording.path} is not an MCAP recording: {reason}") from exc
        if unreadable is not None:
            recording.skipped[f"{unreadable[0]} records"] += 1
            return unreadable[1]
        if not recording.complete:
            recording.truncated_reason = reason
    return None


def _collect(recording: Recording, record: object) -> None:
    if isinstance(record, Header):
        recording.started = True
    elif isinstance(record, Chunk):
        for inner in _chunk_records(recording, record):
            _collect(recording, inner)
    elif isinstance(record, Schema):
        recording.schemas[record.id] = record
    elif isinstance(record, Channel):
        recording.channels[record.id] = record
    elif isinstance(record, Message):
        recording.messages.append(record)
    elif isinstance(record, Metadata):
        recording.metadata[record.name] = dict(record.metadata)
    elif isinstance(record, DataEnd):
        recording.data_end = True
    elif isinstance(record, Footer):
        recording.complete = recording.data_end


def _chunk_records(recording: Recording, chunk: Chunk) -> list[object]:
    """The records of a chunk; none (counted) when it cannot be trusted."""
    if chunk.compression not in COMPRESSIONS:
        recording.skipped[f"chunks with unknown compression {chunk.compression!r}"] += 1
        return []
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        recording.skipped[f"chunks claiming over {MAX_CHUNK_BYTES} bytes"] += 1
        return []
    try:
        return list(breakup_chunk(chunk, validate_crc=True))
    except (McapError, EOFError, ValueError, RuntimeError, struct.error, zstandard.ZstdError):
        recording.skipped["chunks that do not decompress or fail their CRC"] += 1
        return []


def _drop_orphans(recording: Recording) -> None:
    """Messages on a channel the file never declared are unreadable: skip, count."""
    known = [m for m in recording.messages if m.channel_id in recording.channels]
    if len(known) < len(recording.messages):
        recording.skipped["messages on an undeclared channel"] += len(recording.messages) - len(
            known
        )
        recording.messages = known


def _why_it_stops(
    stream: BinaryIO, size: int, end: int, exc: Exception
) -> tuple[str, tuple[str, int] | None]:
    """Where and why reading stopped, for a person: the byte and the record; and, when
    that record is complete but unreadable, its name and where the next one starts."""
    if size == 0:
        return "the file is empty (0 bytes): nothing reached the disk", None
    if end == 0:
        stream.seek(0)
        start = stream.read(len(MAGIC))
        if start != MAGIC:
            if MAGIC.startswith(start):
                return f"cut at byte {size}, inside the 8-byte MCAP magic", None
            return f"it does not start with the MCAP magic (found {start!r})", None
        end = len(MAGIC)
    stream.seek(end)
    head = stream.read(9)  # opcode (1 byte) and record length (8 bytes, little endian)
    after = "the MCAP magic" if end == len(MAGIC) else "its last complete record"
    if not head:
        return f"cut at byte {size}, right after {after} (no footer)", None
    if len(head) < 9:
        return f"cut at byte {size}, inside the record header after {after}", None
    name = _record_name(head[0])
    length = 9 + int.from_bytes(head[1:], "little")
    if end + length > size:
        there = f"({length} bytes long, {size - end} there)"
        return f"cut at byte {size}, inside the {name} record at byte {end} {there}", None
    reason = f"unreadable {name} record at byte {end}: {type(exc).__name__} {exc}".strip()
    return reason, (name, end + length)


def _record_name(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"unknown (opcode {opcode:#04x})"


def info(path: Path) -> dict[str, Any]:
    """Topics, types, counts, rates, duration, sequence gaps, metadata, completeness."""
    recording = read_recording(path)
    by_topic: dict[str, list[Message]] = defaultdict(list)
    for message in recording.messages:
        by_topic[recording.topic(message)].append(message)
    topics = {}
    for topic, messages in sorted(by_topic.items()):
        channel = recording.channels[messages[0].channel_id]
        span_s = (messages[-1].log_time - messages[0].log_time) * 1e-9
        schema = recording.schemas.get(channel.schema_id)
        topics[topic] = {
            "type": schema.name if schema else "(undecodable)",
            "count": len(messages),
            "rate_hz": (len(messages) - 1) / span_s if span_s > 0 else 0.0,
        }
    times = [m.log_time for m in recording.messages]
    account = sequence_account(recording)
    return {
        "file": str(recording.path),
        "complete": recording.complete,
        "truncated": recording.truncated_reason or None,
        "messages": len(recording.messages),
        "duration_s": (max(times) - min(times)) * 1e-9 if times else 0.0,
        "topics": topics,
        "sequence_gaps": dict(account.gaps),
        "sequence_anomalies": account.anomalies(),
        "raw_streams": raw_streams_of(recording).counts(),
        "skipped": dict(recording.skipped),
        "metadata": recording.metadata,
    }


def sequence_account(recording: Recording) -> SequenceAccount:
    """Each publisher's sequence numbers and stamps in receipt order, accounted as the
    recorder accounted them: the same figures as its ``dammrl.loss`` metadata."""
    account = SequenceAccount(recording.namespace())
    for message in recording.messages:
        channel = recording.channels[message.channel_id]
        if channel.metadata.get("dammrl.invalid"):
            continue
        header = header_of(message.data)
        if header is None:  # never written so by the recorder: a crafted or damaged file
            account.headerless[channel.topic] += 1
            continue
        account.see(channel.topic, str(header.get("source")), header["seq"], message.log_time,
                    stamp_ns=header["stamp_ns"])  # fmt: skip
    return account


LOSS, SESSION = "dammrl.loss", "dammrl.session"
"""The recorder's metadata records: its loss figures, and the session's description."""


def loss_of(recording: Recording) -> dict[str, str]:
    """The ``dammrl.loss`` figures of what ``recording`` holds, as its recorder counts."""
    channels = recording.channels
    invalid = Counter(channels[m.channel_id].topic.removeprefix("_invalid/")
                      for m in recording.messages
                      if channels[m.channel_id].metadata.get("dammrl.invalid"))  # fmt: skip
    return loss_record(sequence_account(recording), invalid, raw_streams_of(recording))


def raw_streams_of(recording: Recording) -> RawStreams:
    """What its wearables' raw chunks say they lost, counted as its recorder counts."""
    streams = RawStreams(recording.namespace())
    for message in recording.messages:
        streams.see(recording.topic(message), message.data)
    return streams


def sequence_gaps(recording: Recording) -> dict[str, int]:
    """Messages missing per topic, in the streams of each topic's publisher."""
    return dict(sequence_account(recording).gaps)


def _copy_schemas_and_metadata(
    recording: Recording, writer: Writer, convert: Callable[[bytes], bytes] | None = None
) -> dict[int, int]:
    """Register the recording's schemas (through ``convert``) and metadata in ``writer``;
    old -> new schema ids."""
    for name, data in recording.metadata.items():
        writer.add_metadata(name, data)
    return {
        sid: writer.register_schema(s.name, s.encoding, convert(s.data) if convert else s.data)
        for sid, s in recording.schemas.items()
    }


FOXGLOVE_TIME = {"type": "object", "title": "time", "required": ["sec", "nsec"],
                 "properties": {"sec": {"type": "integer", "minimum": 0},
                                "nsec": {"type": "integer", "minimum": 0,
                                         "maximum": 999_999_999}}}  # fmt: skip


def foxglove_times(value: Any) -> Any:
    """Every ``*_ns`` integer as Foxglove's ``{sec, nsec}`` under the name without ``_ns``
    (19-digit nanoseconds lose their last digits in JavaScript); null stays null."""
    if isinstance(value, dict):
        return dict(_time_item(k, v) for k, v in value.items())
    if isinstance(value, list):
        return [foxglove_times(v) for v in value]
    return value


def _time_item(key: str, value: Any) -> tuple[str, Any]:
    if not key.endswith("_ns"):
        return key, foxglove_times(value)
    if isinstance(value, int) and not isinstance(value, bool):
        return key[:-3], {"sec": value // 10**9, "nsec": value % 10**9}
    return key[:-3], value


def foxglove_times_schema(data: bytes) -> bytes:
    """A message JSON Schema with its ``*_ns`` properties as ``{sec, nsec}`` (see
    :func:`foxglove_times`)."""

    def convert(node: Any) -> Any:
        if isinstance(node, list):
            return [convert(n) for n in node]
        if not isinstance(node, dict):
            return node
        out = {k: convert(v) for k, v in node.items()}
        if isinstance(out.get("properties"), dict):
            out["properties"] = {
                (k[:-3] if k.endswith("_ns") else k): (_time_schema(v) if k.endswith("_ns") else v)
                for k, v in out["properties"].items()
            }
            if isinstance(out.get("required"), list):
                out["required"] = [r[:-3] if r.endswith("_ns") else r for r in out["required"]]
        return out

    return json.dumps(convert(json.loads(data))).encode()


def _time_schema(schema: dict[str, Any]) -> dict[str, Any]:
    """``{sec, nsec}``, or null where the nanoseconds could be null."""
    nullable = any(option.get("type") == "null" for option in schema.get("anyOf", []))
    time = {**FOXGLOVE_TIME, "description": schema.get("description", "")}
    return {"anyOf": [time, {"type": "null"}]} if nullable else time


def repair(path: Path, out: Path) -> dict[str, Any]:
    """Rewrite the readable part of ``path`` as a complete MCAP ``out``; a file its
    recorder could not finish gets the ``dammrl.loss`` figures of what it holds (marked
    as recounted)."""
    recording = read_recording(path)
    if LOSS not in recording.metadata and recording.metadata.get(SESSION) is not None:
        recording.metadata[LOSS] = loss_of(recording) | {"recounted": "dammrl recording repair"}
    with open(out, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="dammrl", library="dammrl recording repair")
        schema_ids = _copy_schemas_and_metadata(recording, writer, foxglove_times_schema)
        channel_ids = {
            cid: writer.register_channel(
                c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), c.metadata
            )
            for cid, c in recording.channels.items()
        }
        for m in recording.messages:
            writer.add_message(
                channel_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence
            )
        writer.finish()  # type: ignore[no-untyped-call]
    return {"from": str(path), "to": str(out), "messages": len(recording.messages),
            "was_complete": recording.complete, "why": recording.truncated_reason,
            "skipped": dict(recording.skipped)}  # fmt: skip


def repair_in_place(path: Path) -> dict[str, Any]:
    """Complete ``path`` (cut by a crash) where it is: its readable part rewritten to a
    temporary file that then replaces it."""
    temporary = path.with_name(f".{path.name}.repairing")
    summary = repair(path, temporary)
    os.replace(temporary, path)
    return summary | {"to": str(path)}


def export_json(path: Path, out: Path, progress: Callable[[int], None] | None = None) -> int:
    """A copy with ``json`` message encoding (and the jsonschema schemas) for Foxglove;
    ``progress(1)`` after each recorded message."""
    recording = read_recording(path)
    namespace = recording.namespace()
    written = 0
    with open(out, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="dammrl recording export")
        schema_ids = _copy_schemas_and_metadata(recording, writer, foxglove_times_schema)
        channel_ids = {}
        for cid, c in recording.channels.items():
            if c.metadata.get("dammrl.invalid") or c.schema_id not in schema_ids:
                continue  # undecodable traffic has no JSON form
            channel_ids[cid] = writer.register_channel(
                c.topic, "json", schema_ids[c.schema_id], c.metadata
            )
        for m in recording.messages:
            if m.channel_id not in channel_ids:
                continue
            fields = _as_dict(namespace, recording.topic(m), m.data)
            if progress is not None:
                progress(1)
            if fields is None:
                continue
            data = json.dumps(foxglove_times(fields)).encode()
            writer.add_message(channel_ids[m.channel_id], m.log_time, data, m.publish_time,
                               m.sequence)  # fmt: skip
            written += 1
        writer.finish()  # type: ignore[no-untyped-call]
    return written


def _as_dict(namespace: str, topic: str, payload: bytes) -> dict[str, Any] | None:
    """A recorded message as JSON-ready fields; None when it is not a valid message."""
    message_type = type_of(namespace, topic)
    if message_type is None:
        return None
    try:
        return decode(message_type, payload).model_dump(mode="json")
    except DecodeError:
        return None


def export_csv(path: Path, out_dir: Path, progress: Callable[[int], None] | None = None
               ) -> dict[str, int]:  # fmt: skip
    """One CSV per topic (columns: log_time_ns, then the flattened fields, times in ns)."""
    recording = read_recording(path)
    namespace = recording.namespace()
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for m in recording.messages:
        topic = recording.topic(m)
        fields = _as_dict(namespace, topic, m.data)
        if progress is not None:
            progress(1)
        if fields is not None:
            rows[topic].append({"log_time_ns": m.log_time, **_flatten(fields)})
    out_dir.mkdir(parents=True, exist_ok=True)
    for topic, table in rows.items():
        columns = list(dict.fromkeys(k for row in table for k in row))
        with open(out_dir / f"{topic.replace('/', '.')}.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, columns)
            writer.writeheader()
            writer.writerows(table)
    return {topic: len(table) for topic, table in rows.items()}


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        return {
            k: v
            for key, item in value.items()
            for k, v in _flatten(item, f"{prefix}{key}.").items()
        }
    if isinstance(value, list):
        return {
            k: v for i, item in enumerate(value) for k, v in _flatten(item, f"{prefix}{i}.").items()
        }
    return {prefix.rstrip("."): value}


def human_statistics(path: Path) -> dict[str, Any]:
    """The human's empirical error rate per admission radius and decision frequency.

    A decision is correct when its u_h points toward the goal along the primary axis as
    the request showed it (so real sensor decisions are scored like simulated ones).
    """
    recording = read_recording(path)
    requests: dict[tuple[int, int], DecisionRequest] = {}
    intents: list[tuple[int, Intent]] = []
    for log_time, message in recording.decoded(DecisionRequest, Intent):
        if isinstance(message, DecisionRequest):
            requests[(message.episode, message.request)] = message
        elif isinstance(message, Intent):
            intents.append((log_time, message))
    per_radius: dict[str, list[bool]] = defaultdict(list)
    decision_times: dict[str, list[float]] = defaultdict(list)
    for _, intent in intents:
        request = requests.get((intent.episode, intent.request))
        if request is None:
            continue
        toward = direction_to_goal(request.ee_pos_m, request.goal_m, request.primary_axis)
        radius = radius_name(intent.human_model)
        per_radius[radius].append(intent.u_h == toward)
        decision_times[radius].append(intent.decision_s)
    times = [t for t, _ in intents]
    span_s = (max(times) - min(times)) * 1e-9 if len(times) > 1 else 0.0
    return {
        "decisions": sum(len(v) for v in per_radius.values()),
        "decision_frequency_hz": (len(times) - 1) / span_s if span_s > 0 else 0.0,
        "per_radius": {
            radius: {
                "decisions": len(flags),
                "error_rate": float(1 - np.mean(flags)),
                "mean_decision_s": float(np.mean(decision_times[radius])),
            }
            for radius, flags in sorted(per_radius.items())
        },
    }


@dataclass
class SessionTraces:
    """Time series of a recording for the S2 figure; times in s from the first message."""

    pressure_t: np.ndarray  # SensorSample arrivals
    pressure: np.ndarray  # normalised level (raw counts when the level was not recorded)
    pressure_normalised: bool
    error_t: np.ndarray  # RobotState arrivals during an episode
    error_m: np.ndarray  # (n, 3) end-effector minus goal
    decisions: list[tuple[float, Intent]]
    episodes: list[tuple[float, int]]  # (start time, episode number)
    results: list[tuple[float, EpisodeResult]]


def session_traces(path: Path, episode: int | None = None) -> SessionTraces:
    """Pressure, end-effector error and decisions of a recording (optionally one episode)."""
    recording = read_recording(path)
    types = (SensorSample, RobotState, TaskGoal, Intent, EpisodeResult)
    decoded = list(recording.decoded(*types))
    if not decoded:
        raise JobFailedError(f"{path} holds no sensor, robot or task message to plot")
    t0 = decoded[0][0]
    goals: dict[int, np.ndarray] = {}
    pressure: list[tuple[float, float, bool]] = []
    # states by the episode they carry: the arm's reset state may be heard before its goal
    states: list[tuple[float, RobotState]] = []
    traces = SessionTraces(*(np.empty(0),) * 2, True, np.empty(0), np.empty((0, 3)), [], [], [])
    current = 0  # the episode in progress
    for log_time, message in decoded:
        t = (log_time - t0) * 1e-9
        if isinstance(message, TaskGoal):
            goals[message.episode], current = np.array(message.goal_m), message.episode
            traces.episodes.append((t, message.episode))
        elif isinstance(message, RobotState):
            if episode in (None, message.episode):
                states.append((t, message))
        elif episode is not None and current != episode:
            continue
        elif isinstance(message, SensorSample):
            level = message.level
            pressure.append((t, message.raw if level is None else level, level is not None))
        elif isinstance(message, Intent):
            traces.decisions.append((t, message))
        elif isinstance(message, EpisodeResult):
            traces.results.append((t, message))
    if episode is not None:
        traces.episodes = [(t, n) for t, n in traces.episodes if n == episode]
        if not traces.episodes:
            raise JobFailedError(f"{path} has no episode {episode}")
    if pressure:
        traces.pressure_t = np.array([p[0] for p in pressure])
        traces.pressure = np.array([p[1] for p in pressure])
        traces.pressure_normalised = all(p[2] for p in pressure)
    error = [(t, np.array(s.ee_pos_m) - goals[s.episode]) for t, s in states if s.episode in goals]
    if error:
        traces.error_t = np.array([e[0] for e in error])
        traces.error_m = np.array([e[1] for e in error])
    return traces
