"""The reports: one per session, one per participant across sessions, and an index of
every participant's (Markdown and HTML, figures beside them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dammrl.data.outcomes.cells import (
    FEW_NOTE,
    INTERVALS,
    MEASURES,
    NONE,
    RELIABILITY_MEASURES,
    esc,
    estimate,
    shown,
    table_row,
)
from dammrl.data.outcomes.figures import block_figure, trend_figure
from dammrl.data.outcomes.rows import (
    Row,
    blocks_of,
    comfort,
    completeness,
    condition_of,
    gaps,
    participants,
    session_info,
    trials,
)
from dammrl.study.stats import icc

# ---- one session ---------------------------------------------------------------------------


def session_report(root: Path, participant: str, session: str, out: Path) -> Path:
    """``out/<participant>_<session>.md`` and ``.html`` with their figure; the Markdown's
    path."""
    out.mkdir(parents=True, exist_ok=True)
    rows = trials(root, participant, session)
    info = next(s for s in session_info(root, participant) if s["session"] == session)
    missing = [g for g in gaps(root, participant) if g["session"] == session]
    final = [r for r in rows if r["final"]]
    stem = f"{participant.upper()}_{session}"
    figure = block_figure(final, out / f"{stem}_blocks.png", f"{participant.upper()} {session}")
    ratings, blocks = comfort(root, participant), blocks_of(final)
    lines = [
        f"# {participant.upper()}, {session}",
        "",
        _session_line(info),
        "",
        completeness(info, missing),
        "",
        f"## Per block (final attempts; {INTERVALS})",
        "",
        *_block_table(final, {b: ratings.get((session, b), []) for b in blocks}),
        "",
        FEW_NOTE,
        "",
        f"![each block's measures]({figure.name})",
        "",
        "## Every trial",
        "",
        *_trial_table(rows, [g for g in missing if g["status"] == "missing"]),
        "",
        _how_to_read(),
    ]
    return _write(out / f"{stem}.md", lines)


def _session_line(info: Row) -> str:
    return (f"{info['started']} UTC · protocol **{esc(info['protocol'])}** "
            f"{esc(info['protocol_version'])} (SHA-256 `{str(info['protocol_sha256'])[:12]}…`)"
            f" · {info['trials']} trials, {info['successes']} successes")  # fmt: skip


def _block_table(rows: list[Row], ratings: dict[str, list[int]]) -> list[str]:
    header = ["block", "condition", "n", *(m.label for m in MEASURES), "comfort (1-5)"]
    lines = [table_row(header), table_row(["---"] * len(header))]
    for block in blocks_of(rows):
        mine = [r for r in rows if r["block"] == block]
        cells = [shown(m, estimate(m, [r[m.column] for r in mine])) for m in MEASURES]
        practice = " (practice)" if mine[0]["practice"] and "practice" not in block else ""
        given = ", ".join(map(str, ratings.get(block, []))) or NONE
        lines.append(table_row([block + practice, condition_of(mine[0]), str(len(mine)), *cells,
                                given]))  # fmt: skip
    return lines


def _trial_table(rows: list[Row], missing: list[Row]) -> list[str]:
    """Every attempt, and every trial of the log missing from the recordings, in trial
    order."""
    header = ["trial", "block", "attempt", "outcome", *(m.label for m in MEASURES[1:]),
              "recording"]  # fmt: skip
    lines = [table_row(header), table_row(["---"] * len(header))]
    entries: list[tuple[int, int, list[str]]] = []
    for r in rows:
        cells = [NONE if r[m.column] is None else f"{r[m.column] * m.scale:.{m.digits}f}"
                 for m in MEASURES[1:]]  # fmt: skip
        attempt = f"{r['attempt']}" + ("" if r["final"] else " (again)")
        entries.append((r["trial"], r["attempt"], [str(r["trial"]), r["block"], attempt,
                                                   r["outcome"], *cells,
                                                   f"`{r['recording']}`"]))  # fmt: skip
    for g in missing:
        cells = [NONE] * (len(MEASURES) - 1)
        entries.append((g["trial"] or 0, 99, [str(g["trial"]), g["block"] or NONE, NONE,
                                              "missing from the recordings", *cells,
                                              g["reason"]]))  # fmt: skip
    return lines + [table_row(cells) for *_, cells in sorted(entries, key=lambda e: e[:2])]


# ---- one participant across sessions ------------------------------------------------------


def participant_report(root: Path, participant: str, out: Path) -> Path:
    """``out/<participant>.md`` and ``.html``: trends across sessions with intervals, the
    test-retest reliability of each block repeated across sessions, and each session's
    own report linked; the Markdown's path."""
    out.mkdir(parents=True, exist_ok=True)
    rows = trials(root, participant)
    sessions = [s for s in session_info(root, participant) if s["trials"]]
    names = [s["session"] for s in sessions]
    reports = [session_report(root, participant, name, out) for name in names]
    final = [r for r in rows if r["final"] and not r["practice"]]
    who = participant.upper()
    figure = trend_figure(final, names, out / f"{who}_trends.png", who)
    missing = gaps(root, participant)
    listing = [
        f"- [{s['session']}]({p.name}): {s['started']} UTC, {esc(s['protocol'])} "
        f"{esc(s['protocol_version'])}, {s['trials']} trials, {s['successes']} successes. "
        + completeness(s, missing).removeprefix("**Data completeness:** ")
        for s, p in zip(sessions, reports, strict=True)
    ]
    lines = [
        f"# {who} across sessions",
        "",
        *listing,
        "",
        f"## Trends (final attempts of the test blocks; {INTERVALS})",
        "",
        f"![trends across sessions]({figure.name})",
        "",
        *_trend_table(final, names),
        "",
        FEW_NOTE,
        "",
        "## Test-retest reliability",
        "",
        *_reliability(final, names),
        "",
        _how_to_read(),
    ]
    return _write(out / f"{who}.md", lines)


def every_participant_report(root: Path, out: Path) -> Path:
    """Every participant's reports (as :func:`participant_report`) and ``out/index.md``
    and ``.html`` linking them; the index's path."""
    lines = ["# Every participant", ""]
    for participant in participants(root):
        report = participant_report(root, participant, out)
        info = session_info(root, participant)
        missing = sum(s["missing"] or 0 for s in info)
        note = f", **{missing} trials missing from the recordings**" if missing else ""
        lines.append(f"- [{participant}]({report.name}): {len(info)} sessions, "
                     f"{sum(s['trials'] for s in info)} trials{note}")  # fmt: skip
    return _write(out / "index.md", lines)


def _trend_table(rows: list[Row], sessions: list[str]) -> list[str]:
    header = ["block", "session", "n", *(m.label for m in MEASURES)]
    lines = [table_row(header), table_row(["---"] * len(header))]
    for block in blocks_of(rows):
        for session in sessions:
            mine = [r for r in rows if r["block"] == block and r["session"] == session]
            if mine:
                cells = [shown(m, estimate(m, [r[m.column] for r in mine])) for m in MEASURES]
                lines.append(table_row([block, session, str(len(mine)), *cells]))
    return lines


def _reliability(rows: list[Row], sessions: list[str]) -> list[str]:
    """ICC per block repeated in two or more sessions, on the trials every one of them
    finished (the same targets)."""
    measures = [m for m in MEASURES if m.column in RELIABILITY_MEASURES]
    header = ["block", "sessions", "trials", *(m.label for m in measures)]
    lines = [table_row(header), table_row(["---"] * len(header))]
    for block in blocks_of(rows):
        table = _ratings(rows, block, sessions)
        if table is None:
            continue
        cells = [
            _icc_cell(np.array([[t[m.column] for t in trial] for trial in table[1]], dtype=float))
            for m in measures
        ]
        lines.append(table_row([block, ", ".join(table[0]), str(len(table[1])), *cells]))
    if len(lines) == 2:
        return [
            "No block was repeated in two sessions with the same trials yet: reliability "
            "needs at least two sessions of the same protocol."
        ]
    return [
        *lines,
        "",
        "Each cell: ICC(C,1) consistency [95 % interval]; ICC(A,1) absolute "
        "agreement. Above 0.9 excellent, 0.75-0.9 good, 0.5-0.75 moderate "
        "(Koo & Li 2016).",
    ]


def _ratings(
    rows: list[Row], block: str, sessions: list[str]
) -> tuple[list[str], list[list[Row]]] | None:
    """The sessions that ran ``block`` and, per trial every one of them finished, its row
    in each session."""
    by_session = {
        s: {r["trial"]: r for r in rows if r["block"] == block and r["session"] == s}
        for s in sessions
    }
    ran = [s for s in sessions if by_session[s]]
    if len(ran) < 2:
        return None
    common = sorted(set.intersection(*(set(by_session[s]) for s in ran)))
    return (ran, [[by_session[s][t] for s in ran] for t in common]) if len(common) >= 2 else None


def _icc_cell(ratings: np.ndarray) -> str:
    consistency, agreement = icc(ratings, "consistency"), icc(ratings, "agreement")
    if consistency.n == 0:
        return NONE
    return (
        f"{consistency.value:.2f} [{consistency.low:.2f}, {consistency.high:.2f}]; "
        f"{agreement.value:.2f}"
    )


# ---- writing --------------------------------------------------------------------------------


def _how_to_read() -> str:
    return (
        "*How to read it.* Movement time runs from the speed's first rise above to its "
        "last fall below 5 % of its peak; speed peaks count the local maxima that stand "
        "out by 10 % of the peak (this task's micro-steps make about one per step); a "
        "path-length ratio of 1 is a straight path; SPARC and LDLJ are closer to 0 when "
        f"smoother. {INTERVALS[0].upper()}{INTERVALS[1:]}: n is the number of trials; a "
        "figure's point without bars has too few. Practice blocks are in each session's "
        "table, never in the trends."
    )


def _write(path: Path, lines: list[str]) -> Path:
    import markdown

    path.parent.mkdir(parents=True, exist_ok=True)
    text = "\n".join(lines) + "\n"
    path.write_text(text)
    body = markdown.markdown(text, extensions=["tables"])
    path.with_suffix(".html").write_text(HTML.format(title=lines[0].lstrip("# "), body=body))
    return path


HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: sans-serif; max-width: 1400px; margin: 2em auto; padding: 0 1em;
       color: #222; line-height: 1.45; }}
table {{ border-collapse: collapse; font-size: 0.9em; margin: 1em 0; }}
th, td {{ border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }}
th {{ background: #f2f2f2; }} td:first-child, th:first-child {{ text-align: left; }}
img {{ max-width: 100%; }} code {{ font-size: 0.85em; }}
</style></head><body>
{body}
</body></html>
"""
