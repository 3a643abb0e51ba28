"""Statistics a clinician can read: intervals fit for a handful of trials (Student t for
means, Wilson for rates, none below the minimum n), the same cell for the same trials in
any report, n beside every point of a figure, practice kept out of a condition."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
from scipy import stats

from dammrl.cli import main
from dammrl.data.catalogue import build, trials_of
from dammrl.data.outcomes import MEASURES, MIN_N, estimate, shown
from dammrl.data.outcomes.figures import _point
from dammrl.data.outcomes.reports import session_report
from tests.test_catalogue import MS, _study, write_run

TIME = next(m for m in MEASURES if m.column == "t_total_s")
SUCCESS = next(m for m in MEASURES if m.column == "success")


def test_a_mean_carries_a_student_t_interval_and_a_rate_a_wilson_interval() -> None:
    values = [4.0, 5.0, 6.5, 5.5]
    e = estimate(TIME, values)
    half = stats.t.ppf(0.975, 3) * np.std(values, ddof=1) / 2
    np.testing.assert_allclose([e.value, e.low, e.high], [5.25, 5.25 - half, 5.25 + half])
    rate = estimate(SUCCESS, [True, True, True, False])
    np.testing.assert_allclose([rate.low, rate.high], [0.3006418, 0.9544127], atol=1e-6)


def test_below_the_minimum_n_a_cell_is_its_value_alone_and_marked() -> None:
    assert MIN_N == 3
    two = estimate(TIME, [4.0, 6.0])
    assert two.value == 5.0 and math.isnan(two.low) and shown(TIME, two) == "5.0 †"
    assert shown(SUCCESS, estimate(SUCCESS, [True, False])) == "50 †"
    assert shown(TIME, estimate(TIME, [None, None])) == "n/a"


@pytest.fixture
def two_sessions(tmp_path: Path) -> Path:
    """P007's ses-01 and ses-02 ran the same trials to the same times (a practice block
    of two reaches first, then a test block of four), and P008 one session."""
    for participant, session, t0 in (
        ("P007", "ses-01", 0),
        ("P007", "ses-02", 1),
        ("P008", "ses-01", 2),
    ):
        recordings = Path(participant) / session / "recordings"
        tag = {"participant": participant, "session": session}
        write_run(tmp_path / recordings / "part-01.mcap",
                  _study("practice", [1, 2], session) | tag | {"practice": True},
                  [(1, 3.0), (2, 3.5)], (10_000 + 100_000 * t0) * MS)  # fmt: skip
        reaches = [(1, 5.0), (2, 6.0), (3, 5.5), (4, 7.0)]
        write_run(tmp_path / recordings / "part-02.mcap",
                  _study("event", [3, 4, 5, 6], session) | tag, reaches,
                  (20_000 + 100_000 * t0) * MS)  # fmt: skip
    build(tmp_path)
    return tmp_path


def test_the_same_trials_give_the_same_interval_in_any_report(two_sessions: Path,
                                                              tmp_path: Path) -> None:  # fmt: skip
    def block_row(session: str) -> str:
        report = session_report(two_sessions, "P007", session, tmp_path / "out").read_text()
        return next(line for line in report.splitlines() if line.startswith("| event |"))

    assert block_row("ses-01") == block_row("ses-02")
    report = session_report(two_sessions, "P007", "ses-01", tmp_path / "out").read_text()
    practice = next(line for line in report.splitlines() if line.startswith("| practice |"))
    assert "3.2 †" in practice  # two practice reaches: the mean alone


def test_every_point_of_a_figure_says_its_n() -> None:
    fig, ax = plt.subplots()
    _point(ax, 0.0, estimate(TIME, [4.0, 5.0, 6.0]), TIME, "tab:red")
    _point(ax, 1.0, estimate(TIME, [4.0, 5.0]), TIME, "tab:red")
    assert [t.get_text() for t in ax.texts] == ["n=3", "n=2"]
    plt.close(fig)


def test_a_conditions_trials_leave_practice_out_unless_asked(two_sessions: Path) -> None:
    learned = trials_of(two_sessions, condition="learned")[1]  # every block's policy
    assert len(learned) == 12 and all(not row[5] for row in learned)  # the practice column
    assert len(trials_of(two_sessions, condition="learned", practice=True)[1]) == 18


def test_one_command_writes_every_participants_report_and_an_index(
    two_sessions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "reports"
    assert (
        main(["sessions", "report", "--all", "--root", str(two_sessions), "--out", str(out)]) == 0
    )
    index = (out / "index.md").read_text()
    assert "[P007](P007.md): 2 sessions, 12 trials" in index and "[P008](P008.md)" in index
    for name in ("P007.html", "P008.html", "P007_ses-02.html", "index.html"):
        assert (out / name).is_file()
