"""The questions a lab asks the catalogue most: every trial, filtered."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from dammrl.data.catalogue.store import Table, query
from dammrl.data.catalogue.tables import CatalogueError


def trials_of(
    root: Path,
    participant: str | None = None,
    since: str | None = None,
    condition: str | None = None,
    practice: bool = False,
) -> Table:
    """The final attempt of every trial, filtered by participant, first day (ISO date)
    and condition (a trigger, ``event`` or ``fixed``, or a policy, ``learned`` ...). A
    condition's trials leave the practice blocks out unless ``practice`` is asked for
    (practice reaches under the same trigger are no trials of the condition)."""
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
        if not practice:
            where.append("NOT t.practice")
    sql = (
        "SELECT t.participant, t.session, strftime(s.started, '%Y-%m-%d') AS day, t.block, "
        "t.trial, t.practice, t.trigger, t.policy, t.outcome, "
        "round(t.t_total_s, 2) AS t_total_s, round(1000 * t.final_error_m, 1) AS final_error_mm, "
        "t.recording FROM trials t JOIN sessions s USING (participant, session) "
        f"WHERE {' AND '.join(where)} ORDER BY t.participant, t.session, t.trial"
    )
    return query(root, sql, parameters)


def _iso_day(text: str) -> str:
    try:
        return datetime.fromisoformat(text).replace(tzinfo=UTC).strftime("%Y-%m-%d")
    except ValueError as exc:
        raise CatalogueError(f"--since {text!r}: give a date as YYYY-MM-DD") from exc
