"""Reports a clinician reads, from the session catalogue: one per session (every trial,
each block and condition with 95 % intervals) and one per participant across sessions
(trends with intervals, test-retest reliability where sessions repeat a block).

Written as Markdown and HTML beside their figures (PNG). Rates carry Wilson intervals,
means percentile-bootstrap intervals (seeded: a report is reproducible to the digit),
reliability the intraclass correlation of single measurements (ICC(C,1) and ICC(A,1),
``dammrl.study.stats.icc``): a block's trials reach the same targets every session, so
they are the targets rated, and the sessions the occasions.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from dammrl.catalogue import CatalogueError, query
from dammrl.study.stats import Estimate, bootstrap_mean, icc, wilson


@dataclass(frozen=True)
class Measure:
    """A column of the trials table as a report shows it."""

    column: str
    label: str
    scale: float = 1.0
    digits: int = 2
    rate: bool = False


MEASURES = (
    Measure("success", "success [%]", 100.0, 0, rate=True),
    Measure("t_total_s", "time to success [s]", 1.0, 1),
    Measure("final_error_m", "final error [mm]", 1000.0, 1),
    Measure("movement_time_s", "movement time [s]", 1.0, 1),
    Measure("peak_speed_m_s", "peak speed [mm/s]", 1000.0, 0),
    Measure("time_to_peak_speed_s", "time to peak speed [s]", 1.0, 2),
    Measure("n_speed_peaks", "speed peaks", 1.0, 1),
    Measure("path_length_ratio", "path-length ratio", 1.0, 3),
    Measure("sparc", "SPARC (0: smoothest)", 1.0, 2),
    Measure("ldlj", "LDLJ (higher: smoother)", 1.0, 2),
)
"""What every report shows, in this order (the clinical kinematic set, then smoothness)."""
FIGURE_MEASURES = (
    "success",
    "t_total_s",
    "path_length_ratio",
    "sparc",
    "peak_speed_m_s",
    "n_speed_peaks",
)
RELIABILITY_MEASURES = (
    "t_total_s",
    "movement_time_s",
    "peak_speed_m_s",
    "path_length_ratio",
    "sparc",
    "ldlj",
)
NONE = "n/a"
"""A cell without a value."""
SEED = 0
"""The bootstrap's seed: the same catalogue gives the same report."""


def estimate(measure: Measure, values: Sequence[Any], rng: np.random.Generator) -> Estimate:
    """A rate (Wilson) or a mean (bootstrap) of ``values`` (None left out)."""
    known = [v for v in values if v is not None]
    if measure.rate:
        return wilson(sum(bool(v) for v in known), len(known))
    return bootstrap_mean(np.array(known, dtype=float), rng)


def shown(measure: Measure, e: Estimate) -> str:
    if e.n == 0 or math.isnan(e.value):
        return NONE
    s, d = measure.scale, measure.digits
    return f"{e.value * s:.{d}f} [{e.low * s:.{d}f}, {e.high * s:.{d}f}]"


# ---- the catalogue's rows ----------------------------------------------------------------

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


def trials(root: Path, participant: str, session: str | None = None) -> list[dict[str, Any]]:
    """The participant's trials (every attempt), in session and time order."""
    where, parameters = "participant = ?", [participant.upper()]
    if session is not None:
        where += " AND session = ?"
        parameters.append(session)
    names, rows = query(
        root,
        f"SELECT {', '.join(TRIAL_FIELDS)} FROM trials WHERE {where} ORDER BY session, start_ns",
        parameters,
    )
    found = [dict(zip(names, row, strict=True)) for row in rows]
    if not found:
        raise CatalogueError(
            f"no trials of {participant}"
            + (f" in {session}" if session else "")
            + " in the catalogue"
        )
    return found


def comfort(root: Path, participant: str) -> dict[tuple[str, str], list[int]]:
    """The participant's comfort ratings, per (session, block)."""
    _, rows = query(
        root,
        "SELECT session, block, rating FROM comfort WHERE participant = ? ORDER BY log_ns",
        [participant.upper()],
    )
    ratings: dict[tuple[str, str], list[int]] = {}
    for session, block, rating in rows:
        ratings.setdefault((session, block), []).append(int(rating))
    return ratings


def session_info(root: Path, participant: str) -> list[dict[str, Any]]:
    names, rows = query(
        root,
        "SELECT session, strftime(started, '%Y-%m-%d %H:%M') AS started, "
        "protocol, protocol_version, protocol_sha256, trials, successes "
        "FROM sessions WHERE participant = ? ORDER BY session",
        [participant.upper()],
    )
    return [dict(zip(names, row, strict=True)) for row in rows]


def blocks_of(rows: list[dict[str, Any]]) -> list[str]:
    """The blocks in the order they were first run."""
    return list(dict.fromkeys(r["block"] for r in rows))


def condition_of(row: dict[str, Any]) -> str:
    model = f", M{row['model_i']},{row['model_j']}" if row["policy"] == "fixed" else ""
    return f"{row['trigger']}, {row['policy'] or 'policy?'}{model}"


# ---- one session ---------------------------------------------------------------------------


def session_report(root: Path, participant: str, session: str, out: Path) -> Path:
    """``out/<participant>_<session>.md`` and ``.html`` with their figure; the Markdown's
    path."""
    rows = trials(root, participant, session)
    info = next(s for s in session_info(root, participant) if s["session"] == session)
    rng = np.random.default_rng(SEED)
    final = [r for r in rows if r["final"]]
    stem = f"{participant.upper()}_{session}"
    figure = block_figure(final, out / f"{stem}_blocks.png", f"{participant.upper()} {session}")
    ratings, blocks = comfort(root, participant), blocks_of(final)
    lines = [
        f"# {participant.upper()}, {session}",
        "",
        f"{info['started']} UTC · protocol **{esc(info['protocol'])}** "
        f"{esc(info['protocol_version'])} "
        f"(SHA-256 `{str(info['protocol_sha256'])[:12]}…`) · {info['trials']} trials, "
        f"{info['successes']} successes",
        "",
        "## Per block (final attempts; 95 % intervals)",
        "",
        *_block_table(final, rng, {b: ratings.get((session, b), []) for b in blocks}),
        "",
        f"![each block's measures]({figure.name})",
        "",
        "## Every trial",
        "",
        *_trial_table(rows),
        "",
        _how_to_read(),
    ]
    return _write(out / f"{stem}.md", lines)


def _block_table(
    rows: list[dict[str, Any]], rng: np.random.Generator, ratings: dict[str, list[int]]
) -> list[str]:
    header = ["block", "condition", "n", *(m.label for m in MEASURES), "comfort (1-5)"]
    lines = [_row(header), _row(["---"] * len(header))]
    for block in blocks_of(rows):
        mine = [r for r in rows if r["block"] == block]
        cells = [shown(m, estimate(m, [r[m.column] for r in mine], rng)) for m in MEASURES]
        given = ratings.get(block, [])
        lines.append(
            _row(
                [
                    block
                    + (" (practice)" if mine[0]["practice"] and "practice" not in block else ""),
                    condition_of(mine[0]),
                    str(len(mine)),
                    *cells,
                    ", ".join(map(str, given)) or NONE,
                ]
            )
        )
    return lines


def _trial_table(rows: list[dict[str, Any]]) -> list[str]:
    header = ["trial", "block", "attempt", "outcome", *(m.label for m in MEASURES[1:]), "recording"]
    lines = [_row(header), _row(["---"] * len(header))]
    for r in rows:
        cells = [
            NONE if r[m.column] is None else f"{r[m.column] * m.scale:.{m.digits}f}"
            for m in MEASURES[1:]
        ]
        attempt = f"{r['attempt']}" + ("" if r["final"] else " (again)")
        lines.append(
            _row(
                [str(r["trial"]), r["block"], attempt, r["outcome"], *cells, f"`{r['recording']}`"]
            )
        )
    return lines


def block_figure(rows: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Each block's key measures with 95 % intervals, one panel a measure."""
    rng = np.random.default_rng(SEED)
    blocks = blocks_of(rows)
    measures = [m for m in MEASURES if m.column in FIGURE_MEASURES]
    colour = colours(rows)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True)
    for ax, measure in zip(axes.flat, measures, strict=True):
        for x, block in enumerate(blocks):
            values = [r[measure.column] for r in rows if r["block"] == block]
            e = estimate(measure, values, rng)
            if e.n:
                s = measure.scale
                ax.errorbar(
                    [x],
                    [e.value * s],
                    yerr=[[(e.value - e.low) * s], [(e.high - e.value) * s]],
                    fmt="o",
                    capsize=5,
                    ms=8,
                    color=colour[block],
                )
        _axes(ax, measure, blocks)
    fig.suptitle(f"{title}: each block (final attempts), 95 % intervals", fontsize=13)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def colours(rows: list[dict[str, Any]]) -> dict[str, str]:
    """One colour per block, the same in every figure (practice in grey)."""
    palette = iter(["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:orange", "tab:brown"])
    practice = {r["block"] for r in rows if r["practice"]}
    return {b: "tab:gray" if b in practice else next(palette, "black") for b in blocks_of(rows)}


def _axes(ax: Any, measure: Measure, ticks: list[str]) -> None:
    ax.set_title(measure.label, fontsize=11)
    ax.set_xticks(range(len(ticks)), ticks, fontsize=10)
    ax.set_xlim(-0.5, len(ticks) - 0.5)
    ax.grid(axis="y", alpha=0.3)
    if measure.rate:
        ax.set_ylim(-5, 105)


# ---- one participant across sessions ------------------------------------------------------


def participant_report(root: Path, participant: str, out: Path) -> Path:
    """``out/<participant>.md`` and ``.html``: trends across sessions with intervals, the
    test-retest reliability of each block repeated across sessions, and each session's
    own report linked; the Markdown's path."""
    out.mkdir(parents=True, exist_ok=True)
    rows = trials(root, participant)
    sessions = session_info(root, participant)
    names = [s["session"] for s in sessions]
    reports = [session_report(root, participant, name, out) for name in names]
    final = [r for r in rows if r["final"] and not r["practice"]]
    who = participant.upper()
    figure = trend_figure(final, names, out / f"{who}_trends.png", who)
    listing = [
        f"- [{s['session']}]({p.name}): {s['started']} UTC, {esc(s['protocol'])} "
        f"{esc(s['protocol_version'])}, {s['trials']} trials, {s['successes']} successes"
        for s, p in zip(sessions, reports, strict=True)
    ]
    lines = [
        f"# {who} across sessions",
        "",
        *listing,
        "",
        "## Trends (final attempts of the test blocks; 95 % intervals)",
        "",
        f"![trends across sessions]({figure.name})",
        "",
        *_trend_table(final, names),
        "",
        "## Test-retest reliability",
        "",
        *_reliability(final, names),
        "",
        _how_to_read(),
    ]
    return _write(out / f"{who}.md", lines)


def _trend_table(rows: list[dict[str, Any]], sessions: list[str]) -> list[str]:
    rng = np.random.default_rng(SEED)
    header = ["block", "session", "n", *(m.label for m in MEASURES)]
    lines = [_row(header), _row(["---"] * len(header))]
    for block in blocks_of(rows):
        for session in sessions:
            mine = [r for r in rows if r["block"] == block and r["session"] == session]
            if mine:
                cells = [shown(m, estimate(m, [r[m.column] for r in mine], rng)) for m in MEASURES]
                lines.append(_row([block, session, str(len(mine)), *cells]))
    return lines


def trend_figure(rows: list[dict[str, Any]], sessions: list[str], path: Path, title: str) -> Path:
    """Each measure per session, one line a block (its condition), 95 % intervals."""
    rng = np.random.default_rng(SEED)
    measures = [m for m in MEASURES if m.column in FIGURE_MEASURES]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True)
    blocks, colour = blocks_of(rows), colours(rows)
    for ax, measure in zip(axes.flat, measures, strict=True):
        for k, block in enumerate(blocks):
            xs, ys, lows, highs = [], [], [], []
            for x, session in enumerate(sessions):
                values = [
                    r[measure.column]
                    for r in rows
                    if r["block"] == block and r["session"] == session
                ]
                e = estimate(measure, values, rng)
                if e.n:
                    s = measure.scale
                    xs.append(x + 0.08 * (k - (len(blocks) - 1) / 2))
                    ys.append(e.value * s)
                    lows.append((e.value - e.low) * s)
                    highs.append((e.high - e.value) * s)
            ax.errorbar(
                xs, ys, yerr=[lows, highs], fmt="o-", capsize=4, label=block, color=colour[block]
            )
        _axes(ax, measure, sessions)
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="outside right upper", fontsize=10)
    fig.suptitle(f"{title}: each test block across sessions, 95 % intervals", fontsize=13)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _reliability(rows: list[dict[str, Any]], sessions: list[str]) -> list[str]:
    """ICC per block repeated in two or more sessions, on the trials every one of them
    finished (the same targets)."""
    measures = [m for m in MEASURES if m.column in RELIABILITY_MEASURES]
    header = ["block", "sessions", "trials", *(m.label for m in measures)]
    lines = [_row(header), _row(["---"] * len(header))]
    for block in blocks_of(rows):
        table = _ratings(rows, block, sessions)
        if table is None:
            continue
        cells = [
            _icc_cell(np.array([[t[m.column] for t in trial] for trial in table[1]], dtype=float))
            for m in measures
        ]
        lines.append(_row([block, ", ".join(table[0]), str(len(table[1])), *cells]))
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
    rows: list[dict[str, Any]],
    block: str,
    sessions: list[str],
) -> tuple[list[str], list[list[dict[str, Any]]]] | None:
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


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(esc(c).replace("|", "/") for c in cells) + " |"


def esc(text: object) -> str:
    """A value from the catalogue as Markdown text: HTML in it stays text in the HTML
    report (a crafted protocol version or recording must not run in a browser)."""
    return html.escape(str(text), quote=False)


def _how_to_read() -> str:
    return (
        "*How to read it.* Movement time runs from the speed's first rise above to its "
        "last fall below 5 % of its peak; speed peaks count the local maxima that stand "
        "out by 10 % of the peak (this task's micro-steps make about one per step); a "
        "path-length ratio of 1 is a straight path; SPARC and LDLJ are closer to 0 when "
        "smoother. Intervals are 95 %: Wilson for rates, bootstrap for means."
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
