"""``dammrl study``: statistics, claims computed from data, executors that agree."""

from __future__ import annotations

import csv
import hashlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dammrl.study.claims import HORIZON_S, judge, restricted_time
from dammrl.study.configs import EVENT, FIXED, R1, R2, paper_configurations
from dammrl.study.run import Job, run_local, run_ray
from dammrl.study.stats import (
    bootstrap_mean,
    hierarchical_draws,
    holm,
    paired_difference,
    time_to_success,
    tost_mean,
    wilson,
)
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


def _rows(event_time_s: float, runs: int = 1) -> list[dict[str, Any]]:
    """Synthetic reaches of the four paper configurations on 30 seeds."""
    rng = np.random.default_rng(1)
    times = {FIXED: 5.0, EVENT: event_time_s, R1: 8.0, R2: 7.0}
    rows = []
    for seed in range(30):
        for config, t in times.items():
            t_total = t + rng.normal(0, 0.2)
            rows.append({
                "configuration": config, "seed": seed, "run": seed % runs if config in (R1, R2)
                else 0, "success": True, "reached": True, "t_total_s": t_total,
                "t_success_s": t_total, "t_reached_s": t_total - 1.0, "n_osc": 4,
                "n_osc_per_step": 0.2, "final_error_m": 0.01, "sparc": -5.0,
                "near_step_m": 0.01, "mid_step_m": 0.02,
            })  # fmt: skip
    return rows


def _curves(settled: bool) -> dict[str, list[dict[str, np.ndarray]]]:
    """Q-value curves of 4 training seeds per reward: rising, then flat (or still rising)."""
    rng = np.random.default_rng(2)
    episodes = np.arange(1000)
    rise = 5 * (1 - np.exp(-episodes / 100)) + (0 if settled else episodes / 100)
    return {reward: [{f"q_{agent}": rise + rng.normal(0, 0.3, episodes.size)
                      for agent in ("human", "robot")} for _ in range(4)]
            for reward in (R1, R2)}  # fmt: skip


def test_the_claims_table_is_computed_from_the_rows_not_written() -> None:
    slow = {c.key: c for c in judge(_rows(event_time_s=14.0), "press", _curves(settled=True))}
    fast = {c.key: c for c in judge(_rows(event_time_s=3.0), "press", _curves(settled=False))}
    assert slow["C2"].verdict == "holds"
    assert fast["C2"].verdict == "does not hold"  # the same claim, flipped by the data
    assert slow["C6"].verdict == "holds" and fast["C6"].verdict == "does not hold"
    assert slow["C1"].verdict == "does not hold"  # equal chatter and success: no effect
    assert all("[" in check.text for claim in slow.values() for check in claim.checks)
    assert judge(_rows(14.0))[5].verdict == "not tested"  # no training curves: no C6


def test_time_counts_a_failure_at_the_horizon_however_early_it_ended() -> None:
    held = {"success": False, "t_success_s": None, "t_total_s": 4.0}
    timed_out = {"success": False, "t_success_s": None, "t_total_s": 60.0}
    assert restricted_time(held) == restricted_time(timed_out) == HORIZON_S == 60.0
    assert restricted_time({"success": True, "t_success_s": 7.5}) == 7.5
    eps_g = {"reached": True, "t_reached_s": 3.0, "success": False}
    assert restricted_time(eps_g, "t_reached_s", "reached") == 3.0


def test_success_and_time_are_judged_under_both_criteria() -> None:
    rows = _rows(event_time_s=14.0)
    for row in rows:  # the fixed baseline never presses but comes within eps_g
        if row["configuration"] == FIXED:
            row.update(success=False, t_success_s=None)
    press = {c.key: c for c in judge(rows, "press")}
    eps_g = {c.key: c for c in judge(rows, "eps_g")}
    assert any(ch.passed and "higher success" in ch.text for ch in press["C1"].checks)
    assert not any(ch.passed and "higher success" in ch.text for ch in eps_g["C1"].checks)
    assert press["C2"].checks[0].estimate.value < 0 < eps_g["C2"].checks[0].estimate.value


def test_holm_adjusts_as_the_step_down_procedure_does() -> None:
    """Holm (1979): sorted p times (m, m-1, ...), kept monotone; computed by hand."""
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm([0.5]) == [0.5] and holm([0.02, 0.3]) == pytest.approx([0.04, 0.3])
    assert holm([0.9, 0.8]) == [1.0, 1.0]  # capped at 1, never below an earlier step


def test_a_claim_passes_a_check_only_after_the_correction() -> None:
    """A check at p ~ 0.02 alone passes; in a family of four with three others that do
    not pass, Holm multiplies it by 3 (its rank after one tiny p) and it fails."""
    rows = _rows(event_time_s=14.0)
    spread = np.linspace(-1.0, 1.0, 30)
    spread = (spread - spread.mean()) / spread.std()  # mean 0, standard deviation 1
    gap = 2.33 * 0.001 / np.sqrt(30) + 0.001 * spread  # R2 - R1 error: z ~ 2.33, p ~ 0.02
    for row in rows:
        if row["configuration"] == R1:
            row["final_error_m"] = 0.01 - gap[row["seed"]]
    c3 = {c.key: c for c in judge(rows)}["C3"]
    accurate = next(ch for ch in c3.checks if "more accurate" in ch.text)
    assert 0.01 < accurate.p < 0.05 <= accurate.p_holm and not accurate.passed
    assert accurate.p_holm == pytest.approx(3 * accurate.p)


def test_every_check_draws_from_its_own_random_stream() -> None:
    """A check's interval is the same whichever other checks ran before it."""
    rows = _rows(event_time_s=14.0)
    alone = judge([r for r in rows if r["configuration"] in (EVENT, FIXED)])[0]
    together = judge(rows)[0]
    assert [c.text for c in alone.checks] == [c.text for c in together.checks]


def test_training_seeds_widen_the_intervals_of_the_learned_configurations() -> None:
    """Reach times that differ by training seed: the two-level bootstrap (seeds, then
    reaches) gives a wider interval than reaches alone."""
    rows = _rows(event_time_s=14.0, runs=4)
    for row in rows:
        if row["configuration"] == R2:
            row["t_success_s"] += 1.5 * row["run"]
    nested = judge(rows)[1].checks[2].estimate  # C2: 2-event - 4-dammrl-r2
    for row in rows:
        row["run"] = 0
    flat = judge(rows)[1].checks[2].estimate
    assert nested.value == pytest.approx(flat.value)
    assert nested.high - nested.low > 1.5 * (flat.high - flat.low)


def test_hierarchical_draws_of_one_cluster_are_the_plain_bootstrap() -> None:
    values = np.random.default_rng(0).normal(2.0, 1.0, 200)
    draws = hierarchical_draws(values, np.zeros(200), np.random.default_rng(1), 4000)
    assert draws.mean() == pytest.approx(values.mean(), abs=0.01)
    assert draws.std() == pytest.approx(values.std() / np.sqrt(200), rel=0.05)


def test_tost_passes_inside_the_margins_and_fails_outside() -> None:
    inside, _ = tost_mean(np.array([0.01, -0.02, 0.03, 0.0]), -0.1, 0.1)
    outside, estimate = tost_mean(np.array([0.2, 0.25, 0.15, 0.3]), -0.1, 0.1)
    assert inside < 0.05 < outside and estimate.low > 0.1
    # the larger one-sided p of the two t-tests, doubled (as scipy computes them)
    from scipy.stats import ttest_1samp

    x = np.array([0.01, -0.02, 0.03, 0.0])
    one_sided = max(ttest_1samp(x, -0.1, alternative="greater").pvalue,
                    ttest_1samp(x, 0.1, alternative="less").pvalue)  # fmt: skip
    assert inside == pytest.approx(2 * one_sided)


def test_time_to_success_agrees_with_lifelines_under_any_censoring() -> None:
    """Kaplan-Meier median, its interval and the restricted mean, against lifelines (an
    independent library) on times censored at random."""
    lifelines = pytest.importorskip("lifelines")
    from lifelines.utils import median_survival_times, restricted_mean_survival_time

    rng = np.random.default_rng(0)
    t, c = rng.exponential(10, 300), rng.uniform(0, 30, 300)
    observed, succeeded = np.minimum(t, c), t <= c
    ours = time_to_success(observed, succeeded, 20.0)
    fit = lifelines.KaplanMeierFitter().fit(observed, succeeded)
    low, high = median_survival_times(fit.confidence_interval_).to_numpy().ravel()
    assert ours.median_s == pytest.approx(fit.median_survival_time_)
    assert (ours.median_low_s, ours.median_high_s) == pytest.approx((low, high))
    assert ours.rmst_s == pytest.approx(restricted_mean_survival_time(fit, t=20.0))


def test_the_restricted_mean_of_a_study_is_the_mean_of_capped_times() -> None:
    """Every reach is observed to its end, so the only censoring is at the horizon: the
    Kaplan-Meier restricted mean equals the mean the claims bootstrap."""
    times = np.array([3.0, 5.0, 60.0, 7.0, 60.0])
    km = time_to_success(times, times < 60.0, 60.0)
    assert km.rmst_s == pytest.approx(times.mean()) and km.median_s == 7.0
    assert time_to_success(np.full(3, 60.0), np.zeros(3, bool), 60.0).median_s == np.inf


def test_the_seeds_split_into_disjoint_sets_in_order() -> None:
    from dammrl.study.study import StudyOptions

    options = StudyOptions(seeds=range(7_000_000, 7_000_150), sets=3)
    assert [options.set_seeds(k) for k in range(3)] == [
        range(7_000_000 + 50 * k, 7_000_050 + 50 * k) for k in range(3)
    ]
    uneven = StudyOptions(seeds=range(7_000_000, 7_000_007), sets=3)
    assert [len(uneven.set_seeds(k)) for k in range(3)] == [3, 2, 2]


REGISTERED_RULES = {
    2: "90ca596a5cf41b8cb2a7025f97648db857ad9153c45ed1abf9b21042741f6497",
}
"""The SHA-256 of ``dammrl/study/claims.py`` for each rules version: a change of the rules
must come with a new CLAIMS_VERSION and its hash here (reports print both)."""


def test_the_claim_rules_do_not_change_without_a_new_version() -> None:
    import dammrl.study.claims as rules

    digest = hashlib.sha256(Path(rules.__file__).read_bytes()).hexdigest()
    assert rules.CLAIMS_VERSION in REGISTERED_RULES, "register the new version's hash"
    assert digest == REGISTERED_RULES[rules.CLAIMS_VERSION], (
        f"dammrl/study/claims.py changed (SHA-256 {digest}) but CLAIMS_VERSION is still "
        f"{rules.CLAIMS_VERSION}: bump it and register the new hash"
    )


def _jobs() -> list[Job]:
    configurations = paper_configurations()
    conditions = ("nominal", "randomised")
    return [Job(configurations[k], 7_000_000 + k, conditions[k % 2], k) for k in range(4)]


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


def _study(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "dammrl", "study", "--seeds", "7000000:7000002",
               "--sets", "2", "--tuning-seeds", "1", "--jobs", "1", "--out", str(out),
               "--reward1", "reward1", "--reward2", "reward2", *extra]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=900)


def test_dammrl_study_writes_the_report_the_table_and_the_generated_sections(
    tmp_path: Path,
) -> None:
    """Two seed sets, each verdict on each with its stability, both success criteria, ikpy
    with its measured latencies saved; a replay of those latencies gives the same reaches
    byte for byte."""
    from dammrl.study.report import MARKERS, RESULTS_BEGIN, RESULTS_END

    results, readme = tmp_path / "results.md", tmp_path / "README.md"
    results.write_text(f"# x\n{RESULTS_BEGIN}\nold\n{RESULTS_END}\nrest\n")
    begin, end = MARKERS["verdicts"]
    readme.write_text(f"# y\n{begin}\nold\n{end}\ntail\n")
    bare = tmp_path / "bare.md"
    bare.write_text("# no markers\n")
    refused = subprocess.run([sys.executable, "-m", "dammrl", "study", "--results", str(bare)],
                             capture_output=True, text=True, timeout=60)  # fmt: skip
    assert refused.returncode == 2 and "has no study markers" in refused.stderr  # at once
    out = tmp_path / "study"
    done = _study(out, "--conditions", "nominal,ikpy-real", "--results", str(results),
                  "--results", str(readme))  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "nominal (press): C1 " in done.stdout and "ikpy-real (eps_g): C1 " in done.stdout
    report = (out / "report.md").read_text()
    assert "| C2: " in report and "dammrl study --seeds 7000000:7000002" in report
    assert "press: **" in report and "eps_g: **" in report and "stable" in report
    assert "Claim rules version 2" in report and "restricted mean" in report
    assert "| ikpy-real | 1-fixed |" in report  # the measured latencies' own table
    for figure in ("summary.png", "trajectory.png", "step_modulation.png", "training.png"):
        assert (out / figure).stat().st_size > 10_000, figure
    with (out / "reaches.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * (14 + 4)  # every row on the nominal arm, the paper's with ikpy
    assert {"success", "reached", "t_success_s", "t_reached_s", "seed_set"} <= rows[0].keys()
    assert {r["seed_set"] for r in rows} == {"0", "1"}
    # without sensor noise the measured path is the true one: the two counts agree
    assert all(row["n_osc_true"] == row["n_osc"] for row in rows)
    text = results.read_text()
    assert "\nold\n" not in text and "| C1: " in text and text.endswith(f"{RESULTS_END}\nrest\n")
    verdicts = readme.read_text()
    assert "\nold\n" not in verdicts and "| C1: " in verdicts and "## Results" not in verdicts
    replayed = _study(tmp_path / "again", "--conditions", "nominal,ikpy-real",
                      "--ik-latencies", str(out / "ik_latencies.json.gz"))  # fmt: skip
    assert replayed.returncode == 0, replayed.stderr
    assert (tmp_path / "again" / "reaches.csv").read_bytes() == (out / "reaches.csv").read_bytes()
    from dammrl.study.study import load_latencies

    saved = load_latencies(out / "ik_latencies.json.gz")
    assert load_latencies(tmp_path / "again" / "ik_latencies.json.gz") == saved
    assert sorted({key.split("/")[0] for key in saved}) == ["ikpy-real"] and len(saved) == 8


def test_study_refuses_bad_options_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from dammrl.cli import main

    for args, message in (
        (["--seeds", "7899990:7900010"], "overlap the tuning seeds"),
        (["--jobs", "0"], "--jobs must be at least 1"),
        (["--reward1", str(tmp_path / "missing")], "no such run"),
        (["--ray", f"127.0.0.1:{free_port()}"], "cannot reach the Ray cluster"),
        (["--sets", "0"], "--sets must be 1 to the number of seeds"),
        (["--conditions", "nominal,bogus"], "unknown condition bogus"),
        (["--ik-latencies", str(tmp_path / "missing.gz")], "is not a study's saved IK latencies"),
        (["--ik-latencies", __file__], "is not a study's saved IK latencies"),
    ):
        code = main(["study", *args, "--out", str(tmp_path / "o")])  # in process: one import
        stderr = capsys.readouterr().err
        assert code in (1, 2, 3), stderr
        assert message in stderr and len(stderr.strip().splitlines()) == 1, stderr
        assert not (tmp_path / "o").exists()  # refused before anything ran


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
