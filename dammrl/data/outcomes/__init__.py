"""Reports a clinician reads, from the session catalogue: one per session (its data
completeness, every trial, each block with 95 % intervals), one per participant across
sessions (trends with intervals, test-retest reliability where sessions repeat a
block), and an index of every participant's.

Written as Markdown and HTML beside their figures (PNG). Intervals fit the few trials a
block has: means carry Student-t intervals, rates Wilson intervals, and a cell of fewer
than ``cells.MIN_N`` trials carries none (its value is marked). Both are exact
formulas, so the same trials give the same interval in any report, whatever else it
holds. Reliability is the intraclass correlation of single measurements (ICC(C,1) and
ICC(A,1), ``dammrl.study.stats.icc``): a block's trials reach the same targets every
session, so they are the targets rated, and the sessions the occasions. Every figure
says how many trials each point stands on.

The modules, bottom up: ``cells`` (an estimate and its cell), ``rows`` (what is read from
the catalogue), ``figures``, ``reports``. They read the catalogue (``dammrl.data.catalogue``)
and the study's statistics (``dammrl.study.stats``) only.
"""

from dammrl.data.outcomes.cells import MEASURES, MIN_N, Measure, estimate, shown
from dammrl.data.outcomes.reports import (
    every_participant_report,
    participant_report,
    session_report,
)
from dammrl.data.outcomes.rows import trials

__all__ = [
    "MEASURES",
    "MIN_N",
    "Measure",
    "estimate",
    "every_participant_report",
    "participant_report",
    "session_report",
    "shown",
    "trials",
]
