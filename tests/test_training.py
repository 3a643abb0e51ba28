"""Training at research grade: seeds in parallel or on Ray with the same numbers, the
rliable aggregates, the frontier's verdict, the command line."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.stats import trim_mean

from dammrl.study.configs import checkpoint_files
from dammrl.study.frontier import Comparison, analyse, beta_dir, frontier_jobs, verdict
from dammrl.study.stats import (
    Estimate,
    finite_mean,
    iqm,
    stratified_bootstrap,
    stratified_difference,
)
from dammrl.study.training import (
    EVALUATION,
    TrainJob,
    best_on_validation,
    finished,
    group_jobs,
    run_training,
    ship,
    ship_seeds,
    summarize,
    write_group_report,
)
from dammrl_core.models import ModelSet
from dammrl_core.policy.learned import LearnedPolicy
from dammrl_core.task import held_out_seeds


def tiny(jobs: list[TrainJob]) -> list[TrainJob]:
    """A few episodes and reaches: the machinery, not the learning."""
    return [replace(j, validation_seeds=range(7_950_000, 7_950_002)) for j in jobs]


def figures(evaluation: dict[str, object]) -> dict[str, object]:
    """An evaluation without its wall time (the only field that depends on the machine)."""
    return {k: v for k, v in evaluation.items() if k != "wall_s"}


def test_iqm_is_the_25_percent_trimmed_mean() -> None:
    values = np.random.default_rng(1).standard_normal((3, 37))
    assert iqm(values) == pytest.approx(trim_mean(values.ravel(), 0.25), abs=1e-12)
    assert iqm(np.array([1.0, 2.0, np.nan, 3.0, 100.0])) == pytest.approx(2.5)


def test_stratified_bootstrap_brackets_the_estimate_and_is_reproducible() -> None:
    scores = np.random.default_rng(2).normal(7.0, 1.0, (4, 50))
    a = stratified_bootstrap(scores, iqm, np.random.default_rng(0))
    b = stratified_bootstrap(scores, iqm, np.random.default_rng(0))
    assert a == b and a.low < a.value < a.high and a.n == 200
    one_run = stratified_bootstrap(scores[:1], finite_mean, np.random.default_rng(0))
    assert one_run.low == one_run.high == one_run.value  # nothing to resample across runs


def test_stratified_difference_finds_a_real_gap_and_not_a_null_one() -> None:
    rng = np.random.default_rng(3)
    base = rng.normal(8.0, 1.0, (4, 60))
    faster = stratified_difference(base - 1.0, base, iqm, np.random.default_rng(0))
    assert faster.high < 0 and faster.value == pytest.approx(-1.0)
    same = stratified_difference(rng.normal(8.0, 1.0, (4, 60)), base, iqm, rng)
    assert same.low < 0 < same.high


def _evaluation(seed: int, t: float, success: float) -> dict[str, object]:
    rng = np.random.default_rng(seed)
    arm = {"success": list((rng.random(40) < success).astype(float)),
           "t_total_s": list(rng.normal(t, 0.5, 40)),
           "final_error_m": list(rng.normal(0.02, 0.002, 40))}  # fmt: skip
    return {"seed": seed, "arms": {"nominal": arm, "randomised": arm},
            "validation": {"success": [success], "t_total_s": [t]}}  # fmt: skip


def test_frontier_verdict_names_a_faster_weighting_only_at_equal_success(tmp_path: Path) -> None:
    groups = {0.0: (8.0, 1.0), 1.0: (6.0, 1.0), 4.0: (5.0, 0.7)}  # beta: (time, success)
    for beta, (t, success) in groups.items():
        for seed in range(3):
            run = beta_dir(tmp_path, beta) / f"seed-{seed}"
            run.mkdir(parents=True)
            (run / EVALUATION).write_text(json.dumps(_evaluation(seed, t, success)))
    summaries, comparisons = analyse(tmp_path, list(groups))
    assert len(summaries) == 6 and len(comparisons) == 4
    by_beta = {c.beta: c for c in comparisons if c.arm == "nominal"}
    assert by_beta[1.0].faster and by_beta[1.0].equal_success
    assert by_beta[4.0].faster and not by_beta[4.0].equal_success  # 30 points of success lost
    text = verdict(comparisons)
    assert "beta=1 (" in text and "beta=4 (" not in text


def test_a_comparison_without_data_is_neither_faster_nor_equal() -> None:
    nothing = Estimate(float("nan"), float("nan"), float("nan"), 0)
    c = Comparison(1.0, "nominal", nothing, nothing)
    assert not c.faster and not c.equal_success


def test_best_on_validation_prefers_success_then_speed() -> None:
    evaluations = [_evaluation(0, 7.0, 0.9), _evaluation(1, 9.0, 1.0), _evaluation(2, 8.0, 1.0)]
    assert best_on_validation(evaluations) == 2


def test_beta_zero_and_one_are_exactly_the_two_rewards(tmp_path: Path) -> None:
    jobs = frontier_jobs(tmp_path, [0.0, 0.5, 1.0], 2, 10, held_out_seeds(5))
    r1 = [j for j in jobs if j.beta == 0.0]
    r2 = [j for j in jobs if j.beta == 1.0]
    trained_r1 = group_jobs(tmp_path, 1, 2, 10, held_out_seeds(5))
    trained_r2 = group_jobs(tmp_path, 2, 2, 10, held_out_seeds(5))
    assert [(j.reward, j.weights, j.seed) for j in r1] == [
        (j.reward, j.weights, j.seed) for j in trained_r1
    ]
    assert [(j.reward, j.weights) for j in r2] == [(j.reward, j.weights) for j in trained_r2]


def test_seeds_train_in_parallel_with_the_numbers_of_one_process(tmp_path: Path) -> None:
    """Two seeds of a tiny run, in one process and on two: the same files' numbers,
    written where a local run writes them, and a report aggregating them."""
    one = tiny(group_jobs(tmp_path / "one", 1, 2, 3, held_out_seeds(2)))
    two = [replace(j, out=tmp_path / "two" / j.out.name) for j in one]
    serial, parallel = run_training(one, workers=1), run_training(two, workers=2)
    for a, b in zip(serial, parallel, strict=True):
        assert figures(a.evaluation) == figures(b.evaluation)
        assert (b.job.out / "checkpoint.pt").is_file() and (b.job.out / "tensorboard").is_dir()
    assert json.loads((tmp_path / "two/seed-1" / EVALUATION).read_text())["seed"] == 1
    report = write_group_report(tmp_path / "two", "Reward 1", "test", 1.0)
    assert "| Reward 1 | randomised | 2 |" in report
    assert (tmp_path / "two/curves.png").stat().st_size > 10_000
    assert checkpoint_files(tmp_path / "two") == [
        tmp_path / "two/seed-0/checkpoint.pt",
        tmp_path / "two/seed-1/checkpoint.pt",
    ]  # fmt: skip (the study takes a folder of seeds)
    summary = summarize("x", [a.evaluation for a in serial], "nominal")
    assert summary.runs == 2 and summary.success.n == 4
    again = run_training(two, workers=2)  # finished runs are kept, not trained again
    assert [r.wall_s for r in again] == [0.0, 0.0]
    assert figures(again[1].evaluation) == figures(serial[1].evaluation)
    assert finished(replace(two[0], episodes=4)) is None  # other settings: train anew
    best = ship(tmp_path / "two", tmp_path / "shipped")
    record = json.loads((tmp_path / "shipped/seeds.json").read_text())
    assert record["shipped_seed"] == best and len(record["seeds"]) == 2
    assert (tmp_path / "shipped/checkpoint.pt").is_file()
    assert any((tmp_path / "shipped/tensorboard").iterdir())
    (tmp_path / "seeds/seed-7").mkdir(parents=True)  # an older run: removed
    assert ship_seeds(tmp_path / "two", tmp_path / "seeds") == [0, 1]
    assert sorted(p.name for p in (tmp_path / "seeds").iterdir()) == ["seed-0", "seed-1"]
    greedy = LearnedPolicy(ModelSet(), tmp_path / "seeds/seed-1/checkpoint.pt")  # a study's
    full = LearnedPolicy(ModelSet(), tmp_path / "two/seed-1/checkpoint.pt")
    observation = np.linspace(0.1, 0.5, 16, dtype=np.float32)
    assert (
        greedy.network.human(torch.from_numpy(observation)).tolist()
        == full.network.human(torch.from_numpy(observation)).tolist()
    )
    shipped_size = (tmp_path / "seeds/seed-1/checkpoint.pt").stat().st_size
    assert shipped_size < (tmp_path / "two/seed-1/checkpoint.pt").stat().st_size
    assert {p.name for p in (tmp_path / "seeds/seed-1").iterdir()} == {
        "checkpoint.pt", "training.csv", "settings.json", EVALUATION}  # fmt: skip


@pytest.mark.slow
def test_a_grid_on_a_local_ray_cluster_gives_the_local_numbers(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    jobs = tiny(frontier_jobs(tmp_path / "local", [0.0, 2.0], 1, 3, held_out_seeds(2)))
    on_ray = [replace(j, out=tmp_path / "ray" / j.out.relative_to(tmp_path / "local"))
              for j in jobs]  # fmt: skip
    local, remote = run_training(jobs, workers=1), run_training(on_ray, ray="local")
    assert [figures(r.evaluation) for r in local] == [figures(r.evaluation) for r in remote]
    assert (tmp_path / "ray/beta-2/seed-0/checkpoint.pt").is_file()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["train", "--reward", "1", "--out", "x", "--seeds", "0"], "--seeds N takes 1 to 70"),
        (["train", "--reward", "1", "--out", "x", "--seeds", "2", "--seed", "3"], "no --seed"),
        (["frontier", "--out", "x", "--betas", "0,-1"], "expected distinct weights"),
        (["train", "--reward", "2", "--out", "x", "--ship", "y"], "--ship needs --seeds"),
        (["frontier", "--out", "x", "--eval-seeds", "7950000:7950010"], "validation seeds"),
    ],
)
def test_bad_training_options_are_one_line_errors(
    arguments: list[str], message: str, tmp_path: Path
) -> None:
    done = subprocess.run([sys.executable, "-m", "dammrl", *arguments], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    last = done.stderr.strip().splitlines()[-1]  # argparse prints its usage above
    assert done.returncode in (2, 3) and message in last, done.stderr
    assert "Traceback" not in done.stderr
