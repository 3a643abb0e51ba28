"""The reports' figures: each measure per block or per session, with its interval and the
number of trials under every point."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from dammrl.data.outcomes.cells import (
    FIGURE_MEASURES,
    INTERVALS,
    MEASURES,
    Measure,
    estimate,
    has_interval,
)
from dammrl.data.outcomes.rows import Row, blocks_of
from dammrl.study.stats import Estimate


def block_figure(rows: list[Row], path: Path, title: str) -> Path:
    """Each block's key measures with 95 % intervals, one panel a measure."""
    blocks = blocks_of(rows)
    measures = [m for m in MEASURES if m.column in FIGURE_MEASURES]
    colour = colours(rows)
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True)
    for ax, measure in zip(axes.flat, measures, strict=True):
        for x, block in enumerate(blocks):
            values = [r[measure.column] for r in rows if r["block"] == block]
            _point(ax, float(x), estimate(measure, values), measure, colour[block])
        _axes(ax, measure, blocks)
    fig.suptitle(f"{title}: each block (final attempts); {INTERVALS}; n: trials per point",
                 fontsize=12)  # fmt: skip
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def trend_figure(rows: list[Row], sessions: list[str], path: Path, title: str) -> Path:
    """Each measure per session, one line a block (its condition), 95 % intervals."""
    measures = [m for m in MEASURES if m.column in FIGURE_MEASURES]
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True)
    blocks, colour = blocks_of(rows), colours(rows)
    for ax, measure in zip(axes.flat, measures, strict=True):
        for k, block in enumerate(blocks):
            xs, ys = [], []
            for x, session in enumerate(sessions):
                values = [r[measure.column] for r in rows
                          if r["block"] == block and r["session"] == session]  # fmt: skip
                e = estimate(measure, values)
                if e.n:
                    at = x + 0.08 * (k - (len(blocks) - 1) / 2)
                    _point(ax, at, e, measure, colour[block], row=k)
                    xs.append(at)
                    ys.append(e.value * measure.scale)
            ax.plot(xs, ys, "-", color=colour[block], label=block)
        _axes(ax, measure, sessions)
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="outside right upper", fontsize=10)
    fig.suptitle(f"{title}: each test block across sessions; {INTERVALS}; n: trials per point",
                 fontsize=12)  # fmt: skip
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _point(ax: Any, x: float, e: Estimate, measure: Measure, colour: str, row: int = 0) -> None:
    """One estimate: its interval when it has one (a hollow marker when it has none),
    and how many trials it stands on (``row``: the line's, so that labels of points at
    one height stack instead of overlapping)."""
    if not e.n:
        return
    s = measure.scale
    if has_interval(e):
        error = [[(e.value - e.low) * s], [(e.high - e.value) * s]]
        ax.errorbar([x], [e.value * s], yerr=error, fmt="o", capsize=5, ms=8, color=colour)
    else:
        ax.plot([x], [e.value * s], "o", ms=8, mfc="white", color=colour)
    ax.annotate(f"n={e.n}", (x, e.value * s), textcoords="offset points",
                xytext=(7, 4 - 10 * row), fontsize=8, color=colour)  # fmt: skip


def colours(rows: list[Row]) -> dict[str, str]:
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
