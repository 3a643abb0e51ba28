"""The catalogue's tables: their columns, and the ones derived from the others."""

from __future__ import annotations

from dataclasses import fields

from dammrl_core.errors import DammrlError
from dammrl_core.metrics import ReachMetrics

VERSION = "2"
"""The catalogue's layout; a catalogue of another layout is rebuilt before it is read."""


class CatalogueError(DammrlError):
    """A catalogue that cannot be built or read."""


class UnreadableCatalogueError(CatalogueError):
    """A catalogue file that is damaged (bit flips, cut, not a database): rebuilt."""


METRICS = tuple(f.name for f in fields(ReachMetrics))
"""The metric columns of ``trials``: exactly the one metrics module's."""
_BOOL_METRICS = {"success", "reached", "button_pressed"}
_TEXT_METRICS = {"outcome", "reason"}
_INT_METRICS = {"n_osc", "n_steps", "n_decisions", "n_speed_peaks"}


def _metric_type(name: str) -> str:
    if name in _BOOL_METRICS:
        return "BOOLEAN"
    if name in _TEXT_METRICS:
        return "VARCHAR"
    return "INTEGER" if name in _INT_METRICS else "DOUBLE"


Columns = tuple[tuple[str, str], ...]

TRIAL_COLUMNS: Columns = (
    ("participant", "VARCHAR"),
    ("session", "VARCHAR"),
    ("block", "VARCHAR"),
    ("trial", "INTEGER"),
    ("attempt", "INTEGER"),
    ("final", "BOOLEAN"),
    ("practice", "BOOLEAN"),
    ("policy", "VARCHAR"),
    ("trigger", "VARCHAR"),
    ("model_i", "INTEGER"),
    ("model_j", "INTEGER"),
    ("seed", "BIGINT"),
    *((name, _metric_type(name)) for name in METRICS),
    ("recording", "VARCHAR"),
    ("episode", "INTEGER"),
    ("start_ns", "BIGINT"),
    ("end_ns", "BIGINT"),
)
"""The ``trials`` table: what the trial was, its metrics, where its reach is recorded."""

RUN_COLUMNS: Columns = (
    ("participant", "VARCHAR"),
    ("session", "VARCHAR"),
    ("protocol", "VARCHAR"),
    ("protocol_version", "VARCHAR"),
    ("protocol_sha256", "VARCHAR"),
    ("recording", "VARCHAR"),
    ("first_ns", "BIGINT"),
    ("last_ns", "BIGINT"),
)
"""Each recording read (a working table: ``sessions`` is derived from it)."""

TABLES: dict[str, Columns] = {
    "trials": TRIAL_COLUMNS,
    "comfort": (
        ("participant", "VARCHAR"),
        ("session", "VARCHAR"),
        ("block", "VARCHAR"),
        ("trial", "INTEGER"),
        ("rating", "INTEGER"),
        ("asked_s", "DOUBLE"),
        ("recording", "VARCHAR"),
        ("log_ns", "BIGINT"),
    ),
    "actions": (
        ("participant", "VARCHAR"),
        ("session", "VARCHAR"),
        ("trial", "INTEGER"),
        ("action", "VARCHAR"),
        ("who", "VARCHAR"),
        ("why", "VARCHAR"),
        ("detail", "VARCHAR"),
        ("recording", "VARCHAR"),
        ("log_ns", "BIGINT"),
    ),
    "completeness": (
        ("participant", "VARCHAR"),
        ("session", "VARCHAR"),
        ("trial", "INTEGER"),
        ("block", "VARCHAR"),
        ("line", "INTEGER"),
        ("recording", "VARCHAR"),
        ("episode", "INTEGER"),
        ("status", "VARCHAR"),
        ("reason", "VARCHAR"),
    ),
    "recordings": (
        ("participant", "VARCHAR"),
        ("session", "VARCHAR"),
        ("recording", "VARCHAR"),
        ("used", "BOOLEAN"),
        ("complete", "BOOLEAN"),
        ("messages", "BIGINT"),
        ("problem", "VARCHAR"),
    ),
    "runs": RUN_COLUMNS,
    "sources": (("path", "VARCHAR"), ("bytes", "BIGINT"), ("mtime_ns", "BIGINT")),
    "about": (("version", "VARCHAR"), ("built", "TIMESTAMP")),
}
"""The tables filled by the build (``runs`` is dropped once the others are derived)."""

STATUSES = ("recorded", "partial", "missing", "skipped", "unlogged")
"""``completeness.status``: each line of a session's ``trials.jsonl`` is a reach
``recorded`` whole, in ``partial`` (its result, not all of the arm's states),
``missing`` from the recordings (with the reason), or ``skipped`` (no reach: the
operator ended its block); ``unlogged``: a reach recorded with no line (the session
stopped before logging it, so it ran again)."""

DERIVED = {
    "sessions": """
        WITH run AS (
            SELECT participant, session, any_value(protocol) AS protocol,
                   any_value(protocol_version) AS protocol_version,
                   any_value(protocol_sha256) AS protocol_sha256,
                   make_timestamp(min(first_ns) // 1000) AS started,
                   make_timestamp(max(last_ns) // 1000) AS last_message,
                   count(DISTINCT recording) AS recordings
            FROM runs GROUP BY participant, session),
        done AS (
            SELECT participant, session, count(*) AS trials,
                   count(*) FILTER (WHERE success) AS successes
            FROM trials WHERE final GROUP BY participant, session),
        logged AS (
            SELECT participant, session,
                   count(*) FILTER (WHERE status IN ('recorded', 'partial', 'missing'))
                       AS reaches_logged,
                   count(*) FILTER (WHERE status = 'recorded') AS recorded_whole,
                   count(*) FILTER (WHERE status = 'partial') AS recorded_in_part,
                   count(*) FILTER (WHERE status = 'missing') AS missing,
                   count(*) FILTER (WHERE status = 'unlogged') AS unlogged
            FROM completeness GROUP BY participant, session),
        ids AS (SELECT participant, session FROM run
                UNION SELECT participant, session FROM logged)
        SELECT ids.participant, ids.session, protocol, protocol_version, protocol_sha256,
               started, last_message, coalesce(recordings, 0) AS recordings,
               coalesce(done.trials, 0) AS trials, coalesce(done.successes, 0) AS successes,
               reaches_logged, recorded_whole, recorded_in_part, missing, unlogged
        FROM ids LEFT JOIN run USING (participant, session)
        LEFT JOIN done USING (participant, session)
        LEFT JOIN logged USING (participant, session)""",
    "participants": """
        SELECT participant, count(*) AS sessions, min(started) AS first_session,
               max(started) AS last_session
        FROM sessions GROUP BY participant""",
}
"""Tables derived from the others (in this order). ``sessions``: every session with a
recording or a trial log; its ``reaches_logged`` ... ``unlogged`` are NULL without a log."""
