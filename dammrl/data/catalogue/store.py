"""The catalogue file: built whole or not at all, read so that no query can harm anything.

*Building.* One build at a time under ``<root>/catalogue/`` (an exclusive lock on its
``.lock``, held by whoever builds; another builder or a reader that needs a fresh
catalogue waits, saying so in one line). A build writes a new database in a private
folder beside the old one and puts it in place with one atomic rename: a reader sees
the last complete catalogue or the new one, never a half-written one.

*Reading.* Every query runs on a read-only connection with DuckDB's external access off
and its configuration locked: ``COPY ... TO``, ``read_csv``, ``ATTACH``, ``INSTALL`` and
the like are refused, so a query can touch no file, recordings included.

*Freshness.* The catalogue keeps the size and modification time of every file it was
built from (recordings and trial logs); it is stale when they differ from the files
now, or when it was built by another layout (``tables.VERSION``). A damaged catalogue
file (bit flips, cut, not a database) is :class:`UnreadableCatalogueError`: rebuilt.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import socket
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from dammrl.data.catalogue.ledger import Line, reconcile
from dammrl.data.catalogue.recordings import FileCheck, Rows, Run, find_runs, read_run
from dammrl.data.catalogue.tables import (
    DERIVED,
    TABLES,
    TRIAL_COLUMNS,
    VERSION,
    CatalogueError,
    Columns,
    UnreadableCatalogueError,
)

LOCK_WAIT_S = 900.0
"""The longest a build or a reader waits for another process's build [s]."""
READ_ONLY: dict[str, str | bool | int | float | list[str]] = {
    "enable_external_access": False,
    "autoinstall_known_extensions": False,
    "autoload_known_extensions": False,
    "lock_configuration": True,
}
"""How every query's connection is opened (with ``read_only``)."""
NO_CATALOGUE = "no catalogue yet"
Say = Callable[[str], None]
Table = tuple[list[str], list[tuple[Any, ...]]]
"""Column names and rows."""


@dataclass
class Built:
    """A catalogue built: where, and what a person should know of its sources."""

    path: Path
    passed_over: list[str] = field(default_factory=list)
    """Recordings not used, each with why."""
    damaged: list[str] = field(default_factory=list)
    """Recordings used although cut or damaged, each with what was kept."""
    incomplete: list[str] = field(default_factory=list)
    """Trials of the logs missing from the recordings, or recorded in part, with why."""


def catalogue_path(root: Path) -> Path:
    return root / "catalogue" / "catalogue.duckdb"


# ---- building -----------------------------------------------------------------------------


def build(root: Path, say: Say | None = None) -> Built:
    """Build the catalogue of every session under ``root`` afresh (waiting for another
    build first, if one runs: ``say`` hears that once)."""
    if not root.is_dir():
        raise CatalogueError(f"no sessions' folder at {root}")
    with building(root, say):
        return _build(root)


def ensure(root: Path, say: Say) -> Built | None:
    """Make the catalogue under ``root`` fresh and readable: rebuilt (``say`` hears why,
    in one line) when it is missing, stale, damaged or of another layout; None when it
    was fresh (or another process has just built it)."""
    why = stale(root)
    if why is None:
        return None
    say(f"{why}: {'building' if why == NO_CATALOGUE else 'rebuilding'} it")
    with building(root, say):
        if stale(root) is None:
            return None  # built meanwhile by the process we waited for
        return _build(root)


@contextlib.contextmanager
def building(root: Path, say: Say | None = None) -> Iterator[None]:
    """Hold the catalogue's build lock (waiting at most ``LOCK_WAIT_S`` for another)."""
    folder = root / "catalogue"
    folder.mkdir(parents=True, exist_ok=True)
    handle = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        _lock(handle, folder, say)
        os.ftruncate(handle, 0)
        holder = (
            f"pid {os.getpid()} on {socket.gethostname()} since {datetime.now(UTC):%H:%M:%S} UTC"
        )
        os.pwrite(handle, holder.encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            fcntl.flock(handle, fcntl.LOCK_UN)
        os.close(handle)


def _lock(handle: int, folder: Path, say: Say | None) -> None:
    deadline = time.monotonic() + LOCK_WAIT_S
    while True:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if say is not None:
                holder = os.pread(handle, 200, 0).decode(errors="replace").strip()
                say(f"waiting for another build of the catalogue ({holder or 'starting'})")
                say = None  # once
            if time.monotonic() > deadline:
                raise CatalogueError(
                    f"the catalogue in {folder} has been being built by "
                    f"another process for {LOCK_WAIT_S:.0f} s"
                ) from None
            time.sleep(0.1)


def _build(root: Path) -> Built:
    """Build under the lock: into a private folder, then one atomic rename."""
    import duckdb

    listing = sources(root)  # before reading: a file written meanwhile makes it stale
    rows, built = _rows(root)
    rows["sources"] = listing
    rows["about"] = [(VERSION, datetime.now(UTC).replace(tzinfo=None))]
    folder = root / "catalogue"
    for leftover in folder.glob(".build-*"):  # of a build that died (we hold the lock)
        shutil.rmtree(leftover, ignore_errors=True)
    private = folder / f".build-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    private.mkdir()
    try:
        with duckdb.connect(str(private / "catalogue.duckdb")) as db:
            _fill(db, rows, private)
        os.replace(private / "catalogue.duckdb", catalogue_path(root))
        _swap(private / "trials", folder / "trials", private / "old-trials")
    finally:
        shutil.rmtree(private, ignore_errors=True)
    built.path = catalogue_path(root)
    return built


def _rows(root: Path) -> tuple[Rows, Built]:
    """Every table's rows from the recordings and the trial logs, and what to say."""
    runs, strays = find_runs(root)
    rows: Rows = {name: [] for name in TABLES}
    for run in runs:
        read_run(root, run, rows)
    lines = _reconciled(root, runs)
    rows["trials"] = _number_attempts(rows["trials"])
    rows["completeness"] = [line.row() for line in lines]
    checks = [(run, check) for run in runs for check in run.checks]
    rows["recordings"] = [(r.participant, r.session, c.path, c.used, c.complete, c.messages,
                           c.problem or None) for r, c in checks]  # fmt: skip
    built = Built(
        catalogue_path(root),
        passed_over=strays + [_said(c) for _, c in checks if not c.used],
        damaged=[_said(c) for _, c in checks if c.used and c.problem],
        incomplete=[line.said() for line in lines if line.status in ("missing", "partial")],
    )
    return rows, built


def _said(check: FileCheck) -> str:
    return f"{check.path}: {check.problem.removeprefix('passed over: ')}"


def _reconciled(root: Path, runs: list[Run]) -> list[Line]:
    """Every session folder's trial log against its runs."""
    by_session: dict[tuple[str, str], list[Run]] = {}
    for run in runs:
        by_session.setdefault((run.participant, run.session), []).append(run)
    folders = {(p.parent.name, p.name) for p in root.glob("*/ses-*") if p.is_dir()}
    lines = []
    for participant, session in sorted(folders | set(by_session)):
        folder = root / participant / session
        lines += reconcile(folder, participant, session, by_session.get((participant, session), []))
    return lines


def _fill(db: Any, rows: Rows, folder: Path) -> None:
    for table, columns in TABLES.items():
        _create(db, table, columns, rows[table])
    for view, sql in DERIVED.items():
        db.execute(f"CREATE TABLE {view} AS {sql} ORDER BY ALL")
    db.execute("DROP TABLE runs")
    if rows["trials"]:
        target = (folder / "trials").as_posix().replace("'", "''")
        db.execute(
            "COPY (SELECT * FROM trials ORDER BY participant, session, start_ns) "
            f"TO '{target}' (FORMAT PARQUET, PARTITION_BY (participant, session))"
        )


def _create(db: Any, table: str, columns: Columns, rows: list[tuple[Any, ...]]) -> None:
    db.execute(f"CREATE TABLE {table} ({', '.join(f'{n} {t}' for n, t in columns)})")
    if rows:
        marks = ", ".join("?" for _ in columns)
        db.executemany(f"INSERT INTO {table} VALUES ({marks})", rows)


def _swap(new: Path, live: Path, old: Path) -> None:
    """The Parquet folder replaced (for tools that read it; two renames under the lock,
    the old one put back if the second fails)."""
    if live.exists():
        live.rename(old)
    try:
        if new.exists():
            new.rename(live)
    except OSError:
        if old.exists() and not live.exists():
            old.rename(live)
        raise


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


# ---- freshness ------------------------------------------------------------------------------


def sources(root: Path) -> list[tuple[str, int, int]]:
    """(path, bytes, modification time ns) of every file a catalogue is built from."""
    files = [*root.glob("*/ses-*/recordings/*.mcap"), *root.glob("*/ses-*/trials.jsonl"),
             *root.glob("*/ses-*/events.jsonl")]  # fmt: skip
    listing = []
    for path in sorted(files):
        with contextlib.suppress(OSError):  # gone since the glob
            stat = path.stat()
            listing.append((path.relative_to(root).as_posix(), stat.st_size, stat.st_mtime_ns))
    return listing


def stale(root: Path) -> str | None:
    """Why the catalogue under ``root`` must be (re)built before it is read: missing,
    unreadable, of another layout, or older than its sources; None when it is fresh."""
    path = catalogue_path(root)
    if not path.is_file():
        return NO_CATALOGUE
    try:
        with connect(root) as db:
            version = _ask(db, "SELECT version FROM about")
            built_from = _ask(db, "SELECT path, bytes, mtime_ns FROM sources ORDER BY ALL")
    except UnreadableCatalogueError as exc:
        return str(exc)
    except CatalogueError:
        return "the catalogue is of an older layout"
    if version != [(VERSION,)]:
        return "the catalogue is of another layout"
    if built_from != sources(root):
        return "the catalogue is older than the recordings"
    return None


# ---- reading --------------------------------------------------------------------------------


def connect(root: Path) -> Any:
    """The catalogue under ``root``, read-only and with no access to any other file;
    CatalogueError when none was built, UnreadableCatalogueError when it is damaged."""
    import duckdb

    path = catalogue_path(root)
    if not path.is_file():
        raise CatalogueError(
            f"no catalogue at {path} (build it: dammrl session catalogue --root {root})"
        )
    try:
        return duckdb.connect(str(path), read_only=True, config=READ_ONLY)
    except duckdb.Error as exc:
        raise _unreadable(path, exc) from exc


def query(root: Path, sql: str, parameters: list[Any] | None = None) -> Table:
    """Column names and rows of ``sql`` on the catalogue (nothing can be changed, no file
    touched: a refused query is a CatalogueError saying why)."""
    import duckdb

    with connect(root) as db:
        try:
            cursor = db.execute(sql, parameters or [])
            names = [d[0] for d in cursor.description or []]
            return names, cursor.fetchall()
        except duckdb.Error as exc:
            if _damaged(exc):
                raise _unreadable(catalogue_path(root), exc) from exc
            raise CatalogueError(f"query refused: {str(exc).splitlines()[0]}") from exc


def _ask(db: Any, sql: str) -> list[tuple[Any, ...]]:
    import duckdb

    try:
        return list(db.execute(sql).fetchall())
    except duckdb.Error as exc:
        if _damaged(exc):
            raise UnreadableCatalogueError(
                f"the catalogue is unreadable ({_first_line(exc)})"
            ) from exc
        raise CatalogueError(_first_line(exc)) from exc


def _damaged(exc: Exception) -> bool:
    """An error of the file, not of the query."""
    import duckdb

    kinds = (duckdb.IOException, duckdb.SerializationException, duckdb.FatalException,
             duckdb.InternalException)  # fmt: skip
    return isinstance(exc, kinds) or "Corrupt database file" in str(exc)


def _unreadable(path: Path, exc: Exception) -> UnreadableCatalogueError:
    return UnreadableCatalogueError(f"the catalogue {path} is unreadable ({_first_line(exc)})")


def _first_line(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__
