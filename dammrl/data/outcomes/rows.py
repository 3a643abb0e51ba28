"""What the reports read from the catalogue."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dammrl.data.catalogue import CatalogueError, query
from dammrl.data.outcomes.cells import MEASURES, esc

Row = dict[str, Any]

TRIAL_FIELDS = (
    "participant",
    "session",
    "block",
    "trial",
    "attempt",
    "final",
    "practice",
    "policy",
    "trigger",
    "model_i",
    "model_j",
    "outcome",
    "recording",
    *(m.column for m in MEASURES if m.column != "success"),
    "success",
)


def _rows(root: Path, sql: str, parameters: list[Any]) -> list[Row]:
    names, rows = query(root, sql, parameters)
    return [dict(zip(names, row, strict=True)) for row in rows]


def participants(root: Path) -> list[str]:
    """Every participant with a session in the catalogue."""
    return [r["participant"] for r in _rows(root, "SELECT participant FROM participants "
                                                  "ORDER BY participant", [])]  # fmt: skip


def trials(root: Path, participant: str, session: str | None = None) -> list[Row]:
    """The participant's trials (every attempt), in session and time order."""
    where, parameters = "participant = ?", [participant.upper()]
    if session is not None:
        where += " AND session = ?"
        parameters.append(session)
    found = _rows(
        root,
        f"SELECT {', '.join(TRIAL_FIELDS)} FROM trials WHERE {where} ORDER BY session, start_ns",
        parameters,
    )
    if not found:
        raise CatalogueError(
            f"no trials of {participant}"
            + (f" in {session}" if session else "")
            + " in the catalogue"
        )
    return found


def comfort(root: Path, participant: str) -> dict[tuple[str, str], list[int]]:
    """The participant's comfort ratings, per (session, block)."""
    ratings: dict[tuple[str, str], list[int]] = {}
    for r in _rows(root, "SELECT session, block, rating FROM comfort WHERE participant = ? "
                         "ORDER BY log_ns", [participant.upper()]):  # fmt: skip
        ratings.setdefault((r["session"], r["block"]), []).append(int(r["rating"]))
    return ratings


def session_info(root: Path, participant: str) -> list[Row]:
    """The participant's sessions: when, which protocol, trials, and data completeness."""
    return _rows(
        root,
        "SELECT session, strftime(started, '%Y-%m-%d %H:%M') AS started, "
        "protocol, protocol_version, protocol_sha256, trials, successes, reaches_logged, "
        "recorded_whole, recorded_in_part, missing, unlogged "
        "FROM sessions WHERE participant = ? ORDER BY session",
        [participant.upper()],
    )


def gaps(root: Path, participant: str) -> list[Row]:
    """Each trial of the participant's logs missing from the recordings or recorded in
    part, and each reach recorded without a line in the log, with why."""
    return _rows(
        root,
        "SELECT session, trial, block, status, reason FROM completeness "
        "WHERE participant = ? AND status IN ('missing', 'partial', 'unlogged') "
        "ORDER BY session, line NULLS LAST, trial",
        [participant.upper()],
    )


def blocks_of(rows: list[Row]) -> list[str]:
    """The blocks in the order they were first run."""
    return list(dict.fromkeys(r["block"] for r in rows))


def condition_of(row: Row) -> str:
    model = f", M{row['model_i']},{row['model_j']}" if row["policy"] == "fixed" else ""
    return f"{row['trigger']}, {row['policy'] or 'policy?'}{model}"


def completeness(info: Row, gaps: list[Row]) -> str:
    """A session's data completeness in one line (Markdown)."""
    if info.get("reaches_logged") is None:
        return "**Data completeness:** no trial log (trials.jsonl) to check the recordings against."
    logged, whole = info["reaches_logged"], info["recorded_whole"]
    said = [f"{whole} recorded whole"]
    if info["recorded_in_part"]:
        said.append(f"{info['recorded_in_part']} in part")
    if info["missing"]:
        said.append(f"**{info['missing']} missing from the recordings**")
    if info["unlogged"]:
        said.append(f"{info['unlogged']} recorded reaches not in the log")
    listed = "".join(
        f"; trial {g['trial']} {_status(g['status'])}: {esc(g['reason'])}"
        for g in gaps
        if g["session"] == info["session"]
    )
    return f"**Data completeness:** {logged} reaches in the trial log: {', '.join(said)}{listed}."


def _status(status: str) -> str:
    return {"missing": "missing", "partial": "in part", "unlogged": "not in the log"}[status]
