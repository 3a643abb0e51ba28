"""``dammrl study``: statistics, claims computed from data, executors that agree."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dammrl.study.claims import EVENT, FIXED, R1, R2, judge
from dammrl.study.configs import paper_configurations
from dammrl.study.run import Job, run_local, run_ray
from dammrl.study.stats import bootstrap_mean, paired_difference, wilson
from tests.busutil import free_port


def test_wilson_interval_matches_the_textbook_values() -> None:
    rate = wilson(8, 10)  # Wilson 95 %: 0.490 - 0.943
    assert rate.value == 0.8
    assert rate.low == pytest.approx(0.4902, abs=1e-3) and rate.high == pytest.approx(
        0.9433, abs=1e-3
    )
    assert wilson(0, 0).n == 0


@pytest.mark.parametrize(("successes", "n"), [(0, 1), (0, 100), (10, 10), (100, 100), (1, 3)])
def test_every_interval_holds_its_value_within_the_rates_range(successes: int, n: int) -> None:
    """At 0/n and n/n the bounds are the range's ends exactly (a chart's error bars are
    never negative: the study once crashed on 10/10)."""
    rate = wilson(successes, n)
    assert 0.0 <= rate.low <= rate.value <= rate.high <= 1.0
    assert (rate.low == 0.0) == (successes == 0) and (rate.high == 1.0) == (successes == n)
    constant = bootstrap_mean(np.full(7, 0.1 + 0.2), np.random.default_rng(0))
    assert constant.low <= constant.value <= constant.high


def test_bootstrap_and_paired_intervals_cover_the_mean_and_see_a_shift() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(5.0, 1.0, 200)
    mean = bootstrap_mean(a, rng)
    assert mean.low < 5.0 < mean.high and mean.low < mean.value < mean.high
    shifted = paired_difference(a + 0.3, a, rng)
    assert shifted.excludes_zero() and shifted.value == pytest.approx(0.3)
    assert not paired_difference(a, a + rng.normal(0, 1, 200) * 0, rng).excludes_zero()


def _rows(event_time_s: float) -> list[dict[str, Any]]:
    """Synthetic reaches of the four paper configurations on 30 seeds."""
    rng = np.random.default_rng(1)
    times = {FIXED: 5.0, EVENT: event_time_s, R1: 8.0, R2: 7.0}
    rows = []
    for seed in range(30):
        for config, t in times.items():
            rows.append({
                "configuration": config, "seed": seed, "randomize": False,
                "success": True, "reached": True, "t_total_s": t + rng.normal(0, 0.2),
                "n_osc_per_step": 0.2, "final_error_m": 0.01, "sparc": -5.0,
                "near_step_m": 0.01, "mid_step_m": 0.02, "n_decisions": 10,
                "human_stable_after": 0, "robot_stable_after": 0,
            })  # fmt: skip
    return rows


def test_the_claims_table_is_computed_from_the_rows_not_written() -> None:
    slow = {c.key: c for c in judge(_rows(event_time_s=14.0), np.random.default_rng(0))}
    fast = {c.key: c for c in judge(_rows(event_time_s=3.0), np.random.default_rng(0))}
    assert slow["C2"].verdict == "holds"
    assert fast["C2"].verdict == "does not hold"  # the same claim, flipped by the data
    assert slow["C6"].verdict == "holds"  # every choice kept from the first decision
    assert slow["C1"].verdict == "does not hold"  # equal chatter and success: no effect
    assert all("[" in check.text for claim in slow.values() for check in claim.checks)


def _jobs() -> list[Job]:
    configurations = paper_configurations()
    return [Job(configurations[k], 7_000_000 + k, k % 2 == 1, k) for k in range(4)]


@pytest.mark.slow
def test_every_core_and_ray_give_the_records_of_one_process() -> None:
    jobs = _jobs()
    single = run_local(jobs, 1)
    parallel = run_local(jobs, 2)
    pytest.importorskip("ray")
    on_ray = sorted(run_ray(jobs, "local"), key=lambda r: r.row["seed"])
    for records in (parallel, on_ray):
        assert [r.row for r in records] == [r.row for r in single]
        for mine, theirs in zip(records, single, strict=True):
            np.testing.assert_array_equal(mine.steps, theirs.steps)


def test_dammrl_study_writes_the_report_the_table_and_the_results_page(tmp_path: Path) -> None:
    from dammrl.study.report import RESULTS_BEGIN, RESULTS_END

    readme = tmp_path / "results.md"
    readme.write_text(f"# x\n{RESULTS_BEGIN}\nold\n{RESULTS_END}\nrest\n")
    bare = tmp_path / "bare.md"
    bare.write_text("# no markers\n")
    refused = subprocess.run([sys.executable, "-m", "dammrl", "study", "--results", str(bare)],
                             capture_output=True, text=True, timeout=60)  # fmt: skip
    assert refused.returncode == 2 and "has no study markers" in refused.stderr  # at once
    out = tmp_path / "study"
    done = subprocess.run(
        [sys.executable, "-m", "dammrl", "study", "--seeds", "7000000:7000002",
         "--tuning-seeds", "1", "--randomize", "off", "--jobs", "1", "--out", str(out),
         "--results", str(readme)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "nominal: C1 " in done.stdout and "C6 " in done.stdout
    report = (out / "report.md").read_text()
    assert "| C2: " in report and "dammrl study --seeds 7000000:7000002" in report
    for figure in ("summary.png", "trajectory.png", "step_modulation.png", "training.png"):
        assert (out / figure).stat().st_size > 10_000, figure
    with (out / "reaches.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert (
        len(rows) == 2 * 9 and {"success", "reached", "n_osc_per_step", "sparc"} <= rows[0].keys()
    )
    # without sensor noise the measured path is the true one: the two counts agree
    assert all(row["n_osc_true"] == row["n_osc"] for row in rows)
    text = readme.read_text()
    assert (
        "\nold\n" not in text and "| C1: " in text and text.endswith("<!-- study:end -->\nrest\n")
    )


def test_study_refuses_bad_options_in_one_line(tmp_path: Path) -> None:
    for args, message in (
        (["--seeds", "7899990:7900010"], "overlap the tuning seeds"),
        (["--jobs", "0"], "--jobs must be at least 1"),
        (["--reward1", str(tmp_path / "missing")], "no such run"),
        (["--ray", f"127.0.0.1:{free_port()}"], "cannot reach the Ray cluster"),
    ):
        command = [sys.executable, "-m", "dammrl", "study", *args, "--out", str(tmp_path / "o")]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
        assert done.returncode in (1, 2, 3), done.stderr
        assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr


SHROUT_FLEISS = np.array([[9, 2, 5, 8], [6, 1, 3, 2], [8, 4, 6, 8], [7, 1, 2, 6],
                          [10, 5, 6, 9], [6, 2, 4, 7]], float)  # fmt: skip
"""Shrout & Fleiss (1979), Table 2: 6 targets rated by 4 judges."""


def test_icc_reproduces_shrout_and_fleiss_and_pingouin() -> None:
    """ICC(3,1) 0.71 and ICC(2,1) 0.29 as published; the intervals as pingouin 0.7.0
    computes them on the same table ([0.34, 0.95] and [0.02, 0.76])."""
    from dammrl.study.stats import icc

    consistency = icc(SHROUT_FLEISS, "consistency")
    agreement = icc(SHROUT_FLEISS, "agreement")
    assert consistency.value == pytest.approx(0.714841, abs=1e-6)
    assert agreement.value == pytest.approx(0.289764, abs=1e-6)
    assert (round(consistency.low, 2), round(consistency.high, 2)) == (0.34, 0.95)
    assert (round(agreement.low, 2), round(agreement.high, 2)) == (0.02, 0.76)


def test_icc_is_one_for_a_repeated_measure_and_undefined_without_two_occasions() -> None:
    from dammrl.study.stats import icc

    targets = np.array([[1.0, 1.0], [2.0, 2.0], [4.0, 4.0]])
    assert icc(targets).value == pytest.approx(1.0)
    assert icc(targets + np.array([0.0, 5.0]), "agreement").value < 0.5  # shifted: no agreement
    assert icc(targets + np.array([0.0, 5.0]), "consistency").value == pytest.approx(1.0)
    assert icc(targets[:, :1]).n == 0 and np.isnan(icc(np.ones((3, 2))).value)
