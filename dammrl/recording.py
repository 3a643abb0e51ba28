"""Read recordings: info, repair, exports (Foxglove JSON, CSV), human statistics.

Every reader goes through :func:`read_recording`, which streams records from the start
and stops cleanly at a truncated tail, so a file whose recorder was killed (no footer,
last chunk cut) is read up to its last complete chunk.
"""

from __future__ import annotations

import csv
import json
import struct
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from dammrl.core.errors import DammrlError
from dammrl.core.human import direction_to_goal
from dammrl.core.models import radius_name
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
    complete: bool = False  # the footer was reached
    truncated_reason: str = ""

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
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path} does not exist")
    recording = Recording(path)
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                _collect(recording, record)
        except (McapError, EOFError, ValueError, OSError, struct.error) as exc:
            if not recording.channels and not recording.metadata:
                raise RecordingError(f"{path} is not an MCAP recording: {exc}") from exc
            recording.truncated_reason = f"{type(exc).__name__}: {exc}".strip()
    recording.messages.sort(key=lambda m: m.log_time)
    return recording


def _collect(recording: Recording, record: object) -> None:
    if isinstance(record, Schema):
        recording.schemas[record.id] = record
    elif isinstance(record, Channel):
        recording.channels[record.id] = record
    elif isinstance(record, Message):
        recording.messages.append(record)
    elif isinstance(record, Metadata):
        recording.metadata[record.name] = dict(record.metadata)
    elif isinstance(record, Footer):
        recording.complete = True


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
    return {
        "file": str(recording.path),
        "complete": recording.complete,
        "truncated": recording.truncated_reason or None,
        "messages": len(recording.messages),
        "duration_s": (max(times) - min(times)) * 1e-9 if times else 0.0,
        "topics": topics,
        "sequence_gaps": sequence_gaps(recording),
        "metadata": recording.metadata,
    }


def sequence_gaps(recording: Recording) -> dict[str, int]:
    """Messages missing per topic, from each publisher's sequence numbers."""
    last: dict[tuple[str, str], int] = {}
    gaps: Counter[str] = Counter()
    for message in sorted(recording.messages, key=lambda m: m.publish_time):
        channel = recording.channels[message.channel_id]
        if channel.metadata.get("dammrl.invalid"):
            continue
        header = msgpack.unpackb(message.data).get("header", {})
        source = (channel.topic, str(header.get("source")))
        seq = message.sequence
        if source in last and seq > last[source] + 1:
            gaps[channel.topic] += seq - last[source] - 1
        last[source] = max(seq, last.get(source, seq))
    return dict(gaps)


def _copy_schemas_and_metadata(recording: Recording, writer: Writer) -> dict[int, int]:
    """Register the recording's schemas and metadata in ``writer``; old -> new schema ids."""
    for name, data in recording.metadata.items():
        writer.add_metadata(name, data)
    return {
        sid: writer.register_schema(s.name, s.encoding, s.data)
        for sid, s in recording.schemas.items()
    }


def repair(path: Path, out: Path) -> dict[str, Any]:
    """Rewrite the readable part of ``path`` as a complete MCAP ``out``."""
    recording = read_recording(path)
    with open(out, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="dammrl", library="dammrl recording repair")
        schema_ids = _copy_schemas_and_metadata(recording, writer)
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
            "was_complete": recording.complete}  # fmt: skip


def export_json(path: Path, out: Path) -> int:
    """A copy with ``json`` message encoding (and the jsonschema schemas) for Foxglove."""
    recording = read_recording(path)
    namespace = recording.namespace()
    written = 0
    with open(out, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="dammrl recording export")
        schema_ids = _copy_schemas_and_metadata(recording, writer)
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
            as_json = _as_json(namespace, recording.topic(m), m.data)
            if as_json is None:
                continue
            writer.add_message(
                channel_ids[m.channel_id], m.log_time, as_json, m.publish_time, m.sequence
            )
            written += 1
        writer.finish()  # type: ignore[no-untyped-call]
    return written


def _as_json(namespace: str, topic: str, payload: bytes) -> bytes | None:
    message_type = type_of(namespace, topic)
    if message_type is None:
        return None
    try:
        return decode(message_type, payload).model_dump_json().encode()
    except DecodeError:
        return None


def export_csv(path: Path, out_dir: Path) -> dict[str, int]:
    """One CSV per topic (columns: log_time_ns, then the flattened fields)."""
    recording = read_recording(path)
    namespace = recording.namespace()
    rows: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for m in recording.messages:
        topic = recording.topic(m)
        as_json = _as_json(namespace, topic, m.data)
        if as_json is not None:
            rows[topic].append({"log_time_ns": m.log_time, **_flatten(json.loads(as_json))})
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
        raise RecordingError(f"{path} holds no sensor, robot or task message to plot")
    t0 = decoded[0][0]
    goals: dict[int, np.ndarray] = {}
    pressure: list[tuple[float, float, bool]] = []
    error: list[tuple[float, np.ndarray]] = []
    traces = SessionTraces(*(np.empty(0),) * 2, True, np.empty(0), np.empty((0, 3)), [], [], [])
    current = 0  # the episode in progress
    for log_time, message in decoded:
        t = (log_time - t0) * 1e-9
        if isinstance(message, TaskGoal):
            goals[message.episode], current = np.array(message.goal_m), message.episode
            traces.episodes.append((t, message.episode))
        elif episode is not None and current != episode:
            continue
        elif isinstance(message, SensorSample):
            level = message.level
            pressure.append((t, message.raw if level is None else level, level is not None))
        elif isinstance(message, RobotState) and message.episode in goals:
            error.append((t, np.array(message.ee_pos_m) - goals[message.episode]))
        elif isinstance(message, Intent):
            traces.decisions.append((t, message))
        elif isinstance(message, EpisodeResult):
            traces.results.append((t, message))
    if episode is not None:
        traces.episodes = [(t, n) for t, n in traces.episodes if n == episode]
        if not traces.episodes:
            raise RecordingError(f"{path} has no episode {episode}")
    if pressure:
        traces.pressure_t = np.array([p[0] for p in pressure])
        traces.pressure = np.array([p[1] for p in pressure])
        traces.pressure_normalised = all(p[2] for p in pressure)
    if error:
        traces.error_t = np.array([e[0] for e in error])
        traces.error_m = np.array([e[1] for e in error])
    return traces
