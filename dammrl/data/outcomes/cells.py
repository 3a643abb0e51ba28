"""What a report shows of a group of trials: each measure's estimate with an interval fit
for few trials, and how a cell is written."""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from dammrl.study.stats import Estimate, t_mean, wilson


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
MIN_N = 3
"""The fewest trials a cell needs for an interval: with fewer, its value stands alone
(marked ``FEW``), as an interval from one or two trials says next to nothing."""
FEW = "†"
FEW_NOTE = f"{FEW} fewer than {MIN_N} trials: the value alone, no interval."
INTERVALS = f"95 % intervals: Student t for means, Wilson for rates; none below {MIN_N} trials"
"""How every interval of the reports is made, as their figures and notes say it."""


def estimate(measure: Measure, values: Sequence[Any]) -> Estimate:
    """A rate (Wilson interval) or a mean (Student-t interval) of ``values`` (None left
    out); below ``MIN_N`` values the estimate alone (NaN bounds). Exact formulas: the
    same values give the same cell in any report."""
    known = [v for v in values if v is not None]
    if measure.rate:
        found = wilson(sum(bool(v) for v in known), len(known))
    else:
        found = t_mean(np.array(known, dtype=float))
    if 0 < found.n < MIN_N:
        return Estimate(found.value, math.nan, math.nan, found.n)
    return found


def has_interval(e: Estimate) -> bool:
    return e.n > 0 and not math.isnan(e.low)


def shown(measure: Measure, e: Estimate) -> str:
    """A cell: the value and its interval, the value marked ``FEW``, or ``NONE``."""
    if e.n == 0 or math.isnan(e.value):
        return NONE
    s, d = measure.scale, measure.digits
    if not has_interval(e):
        return f"{e.value * s:.{d}f} {FEW}"
    return f"{e.value * s:.{d}f} [{e.low * s:.{d}f}, {e.high * s:.{d}f}]"


def esc(text: object) -> str:
    """A value from the catalogue as Markdown text: HTML in it stays text in the HTML
    report (a crafted protocol version or recording must not run in a browser)."""
    return html.escape(str(text), quote=False)


def table_row(cells: list[str]) -> str:
    """One row of a Markdown table (a ``|`` in a value cannot split it)."""
    return "| " + " | ".join(esc(c).replace("|", "/") for c in cells) + " |"
