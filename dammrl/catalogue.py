"""The session catalogue: every participant, session, block and trial found again, in an
embedded database (DuckDB), built from the recordings alone.

MCAP stays the raw record. Each recording a session made carries, in its metadata, which
participant, session, protocol (name, version, SHA-256), block and trials its stack run
served (``dammrl.session`` -> ``study``); each reach in it ends with its EpisodeResult.
The catalogue reads them and nothing else, so it can be deleted and rebuilt identically
at any time (``dammrl session catalogue``), and every row points back into its
recording: the file and the reach's time range (log times, ns).

Tables (``<root>/catalogue/catalogue.duckdb``):

* ``participants``: one row per participant, their number of sessions.
* ``sessions``: participant, session, protocol, its version and SHA-256, the first and
  last message's time, the reaches and successes.
* ``trials``: one row per reach of a trial (``attempt``; ``final`` marks the attempt that
  counts: a trial the therapist ran again keeps its earlier attempts), its block and
  condition, every metric of the one metrics module, the recording and time range.
* ``comfort``: the participant's ratings after each block; ``actions``: the therapist's
  pauses, skips and takeovers.

``trials`` is also written as Parquet, one file per session under
``<root>/catalogue/trials/participant=<id>/session=<ses>/`` (Hive partitioning), for
tools that read Parquet (pandas, R's arrow, DuckDB itself).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from dammrl.recording import RecordingError, read_recording
from dammrl_core.errors import DammrlError
from dammrl_core.metrics import ReachMetrics
from dammrl_core.protocol import StudyTag
from dammrl_core.settings import error_line
from schemas import ComfortRating, EpisodeResult, SessionControl, TaskGoal

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


TRIAL_COLUMNS: tuple[tuple[str, str], ...] = (
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

TABLES: dict[str, tuple[tuple[str, str], ...]] = {
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
        ("recording", "VARCHAR"),
        ("log_ns", "BIGINT"),
    ),
}
"""The tables filled from the recordings (participants and sessions are derived)."""

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
            FROM trials WHERE final GROUP BY participant, session)
        SELECT run.*, coalesce(done.trials, 0) AS trials,
               coalesce(done.successes, 0) AS successes
        FROM run LEFT JOIN done USING (participant, session)""",
    "participants": """
        SELECT participant, count(*) AS sessions, min(started) AS first_session,
               max(started) AS last_session
        FROM sessions GROUP BY participant""",
}
"""Tables derived from the others (in this order)."""


class CatalogueError(DammrlError):
    """A catalogue that cannot be built or read."""


@dataclass
class Run:
    """One stack run of a session: its recordings (a restarted recorder's continuations
    included) and what its metadata says it served."""

    study: StudyTag
    files: list[Path] = field(default_factory=list)


@dataclass
class Built:
    """A catalogue built: where, and the recordings passed over with why."""

    path: Path
    passed_over: list[str]


def catalogue_path(root: Path) -> Path:
    return root / "catalogue" / "catalogue.duckdb"


def stale(root: Path) -> bool:
    """Whether a recording under ``root`` changed since the catalogue was built (or there
    is none): what a reader of the catalogue would miss."""
    path = catalogue_path(root)
    if not path.is_file():
        return True
    built = path.stat().st_mtime
    recordings = root.glob("*/ses-*/recordings/*.mcap")
    return any(recording.stat().st_mtime > built for recording in recordings)


def build(root: Path) -> Built:
    """Build the catalogue of every session recording under ``root`` afresh (the old one
    is replaced)."""
    import duckdb

    if not root.is_dir():
        raise CatalogueError(f"no sessions' folder at {root}")
    runs, passed_over = find_runs(root)
    rows = _rows(root, runs)
    folder = root / "catalogue"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    with duckdb.connect(str(catalogue_path(root))) as db:
        for table, columns in TABLES.items():
            _create(db, table, columns, rows[table])
        _create(db, "runs", RUN_COLUMNS, rows["runs"])
        for view, query in DERIVED.items():
            db.execute(f"CREATE TABLE {view} AS {query} ORDER BY ALL")
        db.execute("DROP TABLE runs")
        if rows["trials"]:
            target = (folder / "trials").as_posix().replace("'", "''")
            db.execute(
                "COPY (SELECT * FROM trials ORDER BY participant, session, start_ns) "
                f"TO '{target}' (FORMAT PARQUET, PARTITION_BY (participant, session))"
            )
    return Built(catalogue_path(root), passed_over)


RUN_COLUMNS = (
    ("participant", "VARCHAR"),
    ("session", "VARCHAR"),
    ("protocol", "VARCHAR"),
    ("protocol_version", "VARCHAR"),
    ("protocol_sha256", "VARCHAR"),
    ("recording", "VARCHAR"),
    ("first_ns", "BIGINT"),
    ("last_ns", "BIGINT"),
)


def _create(
    db: Any, table: str, columns: tuple[tuple[str, str], ...], rows: list[tuple[Any, ...]]
) -> None:
    db.execute(f"CREATE TABLE {table} ({', '.join(f'{n} {t}' for n, t in columns)})")
    if rows:
        marks = ", ".join("?" for _ in columns)
        db.executemany(f"INSERT INTO {table} VALUES ({marks})", rows)


def find_runs(root: Path) -> tuple[list[Run], list[str]]:
    """The stack runs of sessions under ``root``, each with its recordings in the order
    they were written; and the recordings passed over, each with why (not a recording,
    no valid study tag, or a tag that names another participant or session than the
    folder it is in: a file copied there must not join someone else's data)."""
    runs, passed_over = [], []
    for first in sorted(root.glob("*/ses-*/recordings/part-[0-9][0-9].mcap")):
        files = [first, *sorted(first.parent.glob(f"{first.stem}-[0-9][0-9][0-9].mcap"))]
        study, why = _study(first)
        if study is None:
            passed_over.append(f"{first.relative_to(root)}: {why}")
        else:
            runs.append(Run(study, files))
    return runs, passed_over


def _study(path: Path) -> tuple[StudyTag | None, str]:
    """The recording's study tag, checked against the folder it lies in; or why not."""
    try:
        text = read_recording(path).metadata.get("dammrl.session", {}).get("study", "")
    except RecordingError as exc:
        return None, str(exc)
    if not text:
        return None, "no session's recording (no study tag)"
    try:
        study = StudyTag.model_validate_json(text)
    except ValidationError as exc:
        return None, f"its study tag is not valid: {error_line(exc)}"
    session, participant = path.parents[1].name, path.parents[2].name
    if (study.participant, study.session) != (participant, session):
        return None, (f"its tag says {study.participant}/{study.session}, its folder "
                      f"{participant}/{session}")  # fmt: skip
    return study, ""


def _rows(root: Path, runs: Iterable[Run]) -> dict[str, list[tuple[Any, ...]]]:
    rows: dict[str, list[tuple[Any, ...]]] = {
        "trials": [],
        "comfort": [],
        "actions": [],
        "runs": [],
    }
    for run in runs:
        RunReader(root, run).read_into(rows)
    rows["trials"] = _number_attempts(rows["trials"])
    return rows


class RunReader:
    """The rows of one stack run, from its recordings."""

    def __init__(self, root: Path, run: Run) -> None:
        self.root, self.run, self.study = root, run, run.study
        self.who = (run.study.participant, run.study.session)
        self.starts: dict[int, int] = {}  # episode -> its TaskGoal's log time
        self.episode = 0  # the reach under way (for the console's acts)

    def read_into(self, rows: dict[str, list[tuple[Any, ...]]]) -> None:
        for path in self.run.files:
            try:
                recording = read_recording(path)
            except RecordingError:
                continue  # a continuation cut before its start holds nothing
            where = path.relative_to(self.root).as_posix()
            times = [m.log_time for m in recording.messages]
            if times:
                rows["runs"].append((*self.who, *self._protocol(), where, min(times), max(times)))
            types = (TaskGoal, EpisodeResult, ComfortRating, SessionControl)
            for log_ns, message in recording.decoded(*types):
                self._take(message, log_ns, where, rows)

    def _protocol(self) -> tuple[str, str, str]:
        return self.study.protocol, self.study.version, self.study.sha256

    def _take(
        self, message: Any, log_ns: int, where: str, rows: dict[str, list[tuple[Any, ...]]]
    ) -> None:
        if isinstance(message, TaskGoal):
            self.starts.setdefault(message.episode, log_ns)
            self.episode = message.episode
        elif isinstance(message, EpisodeResult):
            trial = self._trial(message.episode)
            if trial is not None:
                rows["trials"].append(self._trial_row(trial, message, log_ns, where))
        elif isinstance(message, ComfortRating):
            rows["comfort"].append(
                (
                    *self.who,
                    message.block,
                    message.trial,
                    message.rating,
                    message.asked_s,
                    where,
                    log_ns,
                )
            )
        elif isinstance(message, SessionControl):
            trial = self._trial(message.episode)
            rows["actions"].append(
                (*self.who, trial, message.action, message.who, message.why, where, log_ns)
            )

    def _trial(self, episode: int) -> int | None:
        trials = self.study.trials
        return trials[episode - 1] if 0 < episode <= len(trials) else None

    def _trial_row(
        self, trial: int, result: EpisodeResult, log_ns: int, where: str
    ) -> tuple[Any, ...]:
        condition = self.study.condition
        metrics = result.model_dump()
        return (
            *self.who,
            self.study.block,
            trial,
            0,
            False,
            self.study.practice,
            None if condition is None else condition.policy,
            result.trigger,
            result.model[0],
            result.model[1],
            result.seed,
            *(metrics[name] for name in METRICS),
            where,
            result.episode,
            self.starts.get(result.episode, log_ns),
            log_ns,
        )


def _number_attempts(rows: list[tuple[Any, ...]]) -> list[tuple[Any, ...]]:
    """Number each trial's reaches in time order; the last one is the trial's ``final``."""
    names = [name for name, _ in TRIAL_COLUMNS]
    at = {
        name: names.index(name)
        for name in ("participant", "session", "trial", "attempt", "final", "start_ns")
    }
    rows = sorted(rows, key=lambda r: (r[at["participant"]], r[at["session"]], r[at["start_ns"]]))
    count: dict[tuple[Any, ...], int] = {}
    for row in rows:
        trial = (row[at["participant"]], row[at["session"]], row[at["trial"]])
        count[trial] = count.get(trial, 0) + 1
    seen: dict[tuple[Any, ...], int] = {}
    numbered = []
    for row in rows:
        trial = (row[at["participant"]], row[at["session"]], row[at["trial"]])
        seen[trial] = seen.get(trial, 0) + 1
        values = list(row)
        values[at["attempt"]], values[at["final"]] = seen[trial], seen[trial] == count[trial]
        numbered.append(tuple(values))
    return numbered


# ---- reading -----------------------------------------------------------------------------


def connect(root: Path) -> Any:
    """The catalogue under ``root``, read-only; CatalogueError when none was built."""
    import duckdb

    path = catalogue_path(root)
    if not path.is_file():
        raise CatalogueError(
            f"no catalogue at {path} (build it: dammrl session catalogue --root {root})"
        )
    return duckdb.connect(str(path), read_only=True)


Table = tuple[list[str], list[tuple[Any, ...]]]
"""Column names and rows."""


def query(root: Path, sql: str, parameters: list[Any] | None = None) -> Table:
    """Column names and rows of ``sql`` on the catalogue (read-only: nothing is changed)."""
    import duckdb

    with connect(root) as db:
        try:
            cursor = db.execute(sql, parameters or [])
        except duckdb.Error as exc:
            raise CatalogueError(f"query refused: {str(exc).splitlines()[0]}") from exc
        names = [d[0] for d in cursor.description or []]
        return names, cursor.fetchall()


def trials_of(
    root: Path,
    participant: str | None = None,
    since: str | None = None,
    condition: str | None = None,
) -> Table:
    """The final attempt of every trial, filtered by participant, first day (ISO date)
    and condition (a trigger, ``event`` or ``fixed``, or a policy, ``learned`` ...)."""
    where, parameters = ["t.final"], []
    if participant:
        where.append("t.participant = ?")
        parameters.append(participant.upper())
    if since:
        where.append("s.started >= CAST(? AS TIMESTAMP)")
        parameters.append(_iso_day(since))
    if condition:
        where.append("(t.trigger = ? OR t.policy = ?)")
        parameters += [condition, condition]
    sql = (
        "SELECT t.participant, t.session, strftime(s.started, '%Y-%m-%d') AS day, t.block, "
        "t.trial, t.trigger, t.policy, t.outcome, round(t.t_total_s, 2) AS t_total_s, "
        "round(1000 * t.final_error_m, 1) AS final_error_mm, t.recording "
        "FROM trials t JOIN sessions s USING (participant, session) "
        f"WHERE {' AND '.join(where)} ORDER BY t.participant, t.session, t.trial"
    )
    return query(root, sql, parameters)


def _iso_day(text: str) -> str:
    try:
        return datetime.fromisoformat(text).replace(tzinfo=UTC).strftime("%Y-%m-%d")
    except ValueError as exc:
        raise CatalogueError(f"--since {text!r}: give a date as YYYY-MM-DD") from exc
