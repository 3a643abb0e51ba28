"""Training at research grade: several seeds per reward weighting, in parallel on this
machine's cores or on a Ray cluster, each run evaluated on held-out seeds on the nominal
and on randomised arms, and aggregated across seeds with the rliable methodology.

A training job is a pure function of its settings (every random draw is seeded), so it
can run anywhere: it trains in a scratch directory and returns the run's files, which the
caller writes where a local run would have written them. The numbers are the same
whichever executor ran the job.
"""

from __future__ import annotations

import csv
import io
import json
import math
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from dammrl.study.run import Progress, map_jobs
from dammrl.study.stats import Estimate, finite_mean, iqm, stratified_bootstrap
from dammrl_core.errors import ConfigurationError
from dammrl_core.task import HELD_OUT_START

VALIDATION_START = 7_950_000
"""Seeds for choosing the run to ship: held out from training, apart from the evaluation
seeds (7,000,000 on) and the study's tuning seeds (7,900,000 on)."""
VALIDATION_SEEDS = range(VALIDATION_START, VALIDATION_START + 50)
ARMS = {"nominal": False, "randomised": True}
EVALUATION = "evaluation.json"


@dataclass(frozen=True)
class TrainJob:
    """One training run and its evaluation."""

    out: Path  # the run directory (written by the caller)
    reward: Literal[1, 2]  # the preset the weights start from
    seed: int
    episodes: int
    eval_seeds: range
    beta: float | None = None  # the time weight, when not the preset's
    randomize: bool = True  # train on randomised arms
    validation_seeds: range = VALIDATION_SEEDS

    @property
    def weights(self) -> Any:
        from dammrl.learning.rl.config import RewardWeights

        preset = RewardWeights.preset(self.reward)
        return preset if self.beta is None else preset.model_copy(update={"beta": self.beta})


@dataclass
class RunResult:
    """A finished run: its files (relative path -> bytes) and its evaluation."""

    job: TrainJob
    files: dict[str, bytes]
    evaluation: dict[str, Any]
    wall_s: float


def train_and_evaluate(job: TrainJob) -> RunResult:
    """Train one run in a scratch directory, evaluate it, return everything it wrote."""
    import time

    from dammrl.learning.rl.config import TrainSettings
    from dammrl.learning.rl.train import train

    started = time.monotonic()
    settings = TrainSettings(episodes=job.episodes, seed=job.seed, randomize=job.randomize)
    with tempfile.TemporaryDirectory(prefix="dammrl-run-") as scratch:
        run = Path(scratch)
        train(job.reward, run, settings, "auto", progress=lambda _: None, weights=job.weights)
        evaluation = {
            "weights": job.weights.model_dump(), "seed": job.seed, "episodes": job.episodes,
            "trained_randomized": job.randomize,
            "eval_seeds": [job.eval_seeds.start, job.eval_seeds.stop],
            "validation_seeds": [job.validation_seeds.start, job.validation_seeds.stop],
            "arms": {arm: _rollouts(run, job.eval_seeds, on) for arm, on in ARMS.items()},
            "validation": _rollouts(run, job.validation_seeds, True),
        }  # fmt: skip
        evaluation["wall_s"] = time.monotonic() - started  # training and evaluation
        (run / EVALUATION).write_text(json.dumps(evaluation))
        files = {str(p.relative_to(run)): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    return RunResult(job, files, evaluation, time.monotonic() - started)


def _rollouts(run: Path, seeds: range, randomize: bool) -> dict[str, list[float]]:
    """Per held-out reach: success, time and final error of the greedy policy."""
    from dammrl.learning.rl.train import greedy_rollouts

    metrics = [r.metrics for r in greedy_rollouts(run, seeds, randomize)]
    return {
        "success": [float(m.success) for m in metrics],
        "t_total_s": [m.t_total_s for m in metrics],
        "final_error_m": [m.final_error_m for m in metrics],
    }


def finished(job: TrainJob) -> RunResult | None:
    """The run of ``job`` if its directory holds one made with the same settings."""
    try:
        evaluation = json.loads((job.out / EVALUATION).read_text())
    except (OSError, ValueError):
        return None
    same = (
        evaluation.get("weights") == job.weights.model_dump()
        and evaluation.get("seed") == job.seed
        and evaluation.get("episodes") == job.episodes
        and evaluation.get("trained_randomized") == job.randomize
        and evaluation.get("eval_seeds") == [job.eval_seeds.start, job.eval_seeds.stop]
        and len(evaluation.get("validation", {}).get("success", ())) == len(job.validation_seeds)
    )
    return RunResult(job, {}, evaluation, 0.0) if same else None


def write_run(result: RunResult) -> None:
    """Write a run's files where a local run writes them (replacing an older run)."""
    for relative, data in result.files.items():
        path = result.job.out / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)


def run_training(
    jobs: Sequence[TrainJob],
    workers: int = 1,
    ray: str | None = None,
    progress: Progress | None = None,
) -> list[RunResult]:
    """Every job on ``workers`` local processes or on a Ray cluster; each run is written
    as soon as it finishes, and a run already finished with the same settings is kept
    (an interrupted grid resumes where it stopped)."""
    if not jobs:
        raise ConfigurationError("no training runs to do")
    done = {job.out: result for job in jobs if (result := finished(job)) is not None}
    if progress is not None and done:
        progress(len(done))
    todo = [job for job in jobs if job.out not in done]
    results = list(done.values())
    for result in map_jobs(train_and_evaluate, todo, workers, ray, progress, batch=1,
                           in_order=False):  # fmt: skip
        write_run(result)
        results.append(result)
    order = {job.out: k for k, job in enumerate(jobs)}
    return sorted(results, key=lambda r: order[r.job.out])


# ---- aggregation -----------------------------------------------------------------------
@dataclass
class GroupSummary:
    """One weighting's runs on one arm: rliable aggregates across seeds."""

    label: str
    arm: str
    runs: int
    success: Estimate  # mean over runs x reaches, stratified bootstrap
    t_total_s: Estimate  # interquartile mean
    final_error_m: Estimate  # interquartile mean
    per_run: list[dict[str, float]] = field(default_factory=list)

    def row(self) -> dict[str, Any]:
        return {
            "label": self.label, "arm": self.arm, "runs": self.runs,
            **{f"{k}_{part}": getattr(getattr(self, k), part)
               for k in ("success", "t_total_s", "final_error_m")
               for part in ("value", "low", "high")},
        }  # fmt: skip


def summarize(label: str, evaluations: Sequence[dict[str, Any]], arm: str,
              seed: int = 0) -> GroupSummary:  # fmt: skip
    """Aggregate the runs of one weighting on one arm (a (runs, reaches) matrix each)."""
    rng = np.random.default_rng(seed)

    def matrix(name: str) -> np.ndarray:
        return np.array([e["arms"][arm][name] for e in evaluations], dtype=float)

    per_run = [
        {k: float(np.mean(e["arms"][arm][k])) for k in ("success", "t_total_s", "final_error_m")}
        for e in evaluations
    ]
    return GroupSummary(
        label, arm, len(evaluations),
        success=stratified_bootstrap(matrix("success"), finite_mean, rng),
        t_total_s=stratified_bootstrap(matrix("t_total_s"), iqm, rng),
        final_error_m=stratified_bootstrap(matrix("final_error_m"), iqm, rng),
        per_run=per_run,
    )  # fmt: skip


def load_evaluations(group: Path) -> list[dict[str, Any]]:
    """The evaluations of a folder of runs (``seed-*/evaluation.json``), by seed."""
    paths = sorted(group.glob(f"seed-*/{EVALUATION}"), key=lambda p: int(p.parent.name[5:]))
    if not paths:
        raise ConfigurationError(f"{group}: no evaluated runs (seed-*/{EVALUATION})")
    return [json.loads(p.read_text()) for p in paths]


def best_on_validation(evaluations: Sequence[dict[str, Any]]) -> int:
    """The run to ship: highest validation success, then shortest mean time (validation
    seeds only, never the evaluation seeds)."""

    def key(k: int) -> tuple[float, float]:
        v = evaluations[k]["validation"]
        return (-float(np.mean(v["success"])), float(np.mean(v["t_total_s"])))

    return min(range(len(evaluations)), key=key)


def curves(group: Path, width: int = 50) -> dict[str, np.ndarray]:
    """Training curves of a folder of runs: per episode, the mean across seeds of each
    run's moving mean, with a 95 % t-interval across seeds (few seeds: no bootstrap)."""
    from scipy.stats import t as student

    runs = [_read_csv(p) for p in sorted(group.glob("seed-*/training.csv"))]
    length = min(len(r["ret"]) for r in runs)
    out: dict[str, np.ndarray] = {"episode": np.arange(1, length + 1)}
    for name in ("ret", "success", "t_total_s"):
        smooth = np.array([_moving_mean(r[name][:length], width) for r in runs])
        mean = smooth.mean(axis=0)
        half = (student.ppf(0.975, len(runs) - 1) * smooth.std(axis=0, ddof=1)
                / math.sqrt(len(runs)) if len(runs) > 1 else np.zeros(length))  # fmt: skip
        out[name], out[f"{name}_low"], out[f"{name}_high"] = mean, mean - half, mean + half
    return out


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path) as handle:
        rows = list(csv.DictReader(handle))
    return {k: np.array([float(r[k] == "True") if r[k] in ("True", "False") else float(r[k])
                         for r in rows]) for k in rows[0]}  # fmt: skip


def _moving_mean(values: np.ndarray, width: int) -> np.ndarray:
    kernel = np.ones(min(width, len(values)))
    return np.convolve(values, kernel, "same") / np.convolve(np.ones(len(values)), kernel, "same")


def summary_table(summaries: Sequence[GroupSummary]) -> str:
    """Markdown table of group summaries."""
    lines = ["| runs | arm | seeds | success | t_total [s] (IQM) | final error [mm] (IQM) |",
             "|---|---|---:|---|---|---|"]  # fmt: skip
    for s in summaries:
        lines.append(f"| {s.label} | {s.arm} | {s.runs} | {s.success.text(100, 1)} % | "
                     f"{s.t_total_s.text()} | {s.final_error_m.text(1000, 1)} |")  # fmt: skip
    return "\n".join(lines)


def to_json(summaries: Sequence[GroupSummary]) -> str:
    return json.dumps([{**s.row(), "per_run": s.per_run} for s in summaries], indent=2)


def write_csv(summaries: Sequence[GroupSummary], path: Path) -> None:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, list(summaries[0].row()))
    writer.writeheader()
    writer.writerows(s.row() for s in summaries)
    path.write_text(buffer.getvalue())


def check_seeds(eval_seeds: range) -> None:
    if eval_seeds.start < HELD_OUT_START:
        raise ConfigurationError("evaluation seeds must be held out (>= 7,000,000)")
    if set(eval_seeds) & set(VALIDATION_SEEDS):
        raise ConfigurationError(
            f"evaluation seeds overlap the validation seeds ({VALIDATION_START:,}...)"
        )


def group_jobs(out: Path, reward: Literal[1, 2], seeds: int, episodes: int, eval_seeds: range,
               beta: float | None = None, randomize: bool = True) -> list[TrainJob]:  # fmt: skip
    """The runs of one weighting: ``out/seed-0`` ... ``out/seed-(n-1)``."""
    return [TrainJob(out / f"seed-{k}", reward, k, episodes, eval_seeds, beta, randomize)
            for k in range(seeds)]  # fmt: skip


def plot_curves(groups: dict[str, Path], path: Path) -> None:
    """Training curves, mean across seeds with a 95 % band, one line per group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("ret", "episode return"), ("success", "success (moving mean)"),
              ("t_total_s", "t_total [s] (moving mean)"))  # fmt: skip
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), constrained_layout=True)
    for label, group in groups.items():
        c = curves(group)
        for ax, (name, title) in zip(axes, panels, strict=True):
            line = ax.plot(c["episode"], c[name], label=label)[0]
            ax.fill_between(c["episode"], c[f"{name}_low"], c[f"{name}_high"],
                            color=line.get_color(), alpha=0.2)  # fmt: skip
            ax.set(title=title, xlabel="episode")
    axes[0].legend()
    fig.suptitle("Training across seeds: mean and 95 % interval (t over seeds)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def ship(group: Path, destination: Path) -> int:
    """Copy the best-on-validation run of a folder of seeds to ``destination`` (checkpoint,
    curves, TensorBoard log), with every seed's results in ``seeds.json``; its seed."""
    import shutil

    evaluations = load_evaluations(group)
    best = evaluations[best_on_validation(evaluations)]["seed"]
    if destination.exists():
        shutil.rmtree(destination)
    shutil.copytree(group / f"seed-{best}", destination)
    record = {
        "shipped_seed": best,
        "rule": "highest success on the validation seeds (randomised arms), then shortest "
        f"mean t_total; validation seeds {VALIDATION_SEEDS.start}-{VALIDATION_SEEDS.stop - 1}",
        "seeds": [_seed_record(e) for e in evaluations],
    }  # fmt: skip
    (destination / "seeds.json").write_text(json.dumps(record, indent=2))
    if (group / "curves.png").exists():
        shutil.copy(group / "curves.png", destination / "curves.png")
    return int(best)


SHIPPED_FILES = ("training.csv", "settings.json", EVALUATION)


def ship_seeds(group: Path, destination: Path) -> list[int]:
    """Every run of a folder of seeds into ``destination/seed-k``, as a study reads them:
    each checkpoint with its greedy networks alone (no target networks, optimiser or
    counters: a quarter of the size, nothing to resume from), its training log, settings
    and evaluation; runs already there are replaced, others removed. The seeds shipped."""
    import shutil

    import torch

    evaluations = load_evaluations(group)  # every run finished and evaluated
    seeds = [int(e["seed"]) for e in evaluations]
    for old in destination.glob("seed-*"):
        shutil.rmtree(old)
    for seed in seeds:
        source, target = group / f"seed-{seed}", destination / f"seed-{seed}"
        target.mkdir(parents=True)
        checkpoint = torch.load(source / "checkpoint.pt", map_location="cpu", weights_only=False)
        agent = checkpoint["agent"]
        checkpoint["agent"] = {"q_human": agent["q_human"], "q_robot": agent["q_robot"]}
        torch.save(checkpoint, target / "checkpoint.pt")
        for name in SHIPPED_FILES:
            shutil.copy(source / name, target / name)
    return seeds


def _seed_record(evaluation: dict[str, Any]) -> dict[str, Any]:
    """One seed's mean results: validation, and every arm's evaluation."""
    validation = evaluation["validation"]
    return {
        "seed": evaluation["seed"],
        "validation_success": float(np.mean(validation["success"])),
        "validation_t_total_s": float(np.mean(validation["t_total_s"])),
        **{f"{arm}_{name}": float(np.mean(values))
           for arm, figures in evaluation["arms"].items() for name, values in figures.items()},
    }  # fmt: skip


def write_group_report(out: Path, label: str, command: str, wall_s: float) -> str:
    """summary.md, summary.json, summary.csv and curves.png for a folder of seeds."""
    evaluations = load_evaluations(out)
    summaries = [summarize(label, evaluations, arm) for arm in ARMS]
    plot_curves({label: out}, out / "curves.png")
    (out / "summary.json").write_text(to_json(summaries))
    write_csv(summaries, out / "summary.csv")
    best = best_on_validation(evaluations)
    text = "\n\n".join([
        f"# {label}: {len(evaluations)} seeds", f"`{command}` ({wall_s / 60:.1f} min)",
        "![curves](curves.png)", summary_table(summaries),
        f"Best on the validation seeds ({VALIDATION_SEEDS.start:,}-"
        f"{VALIDATION_SEEDS.stop - 1:,}, randomised arms): seed-{evaluations[best]['seed']}.",
    ])  # fmt: skip
    (out / "summary.md").write_text(text + "\n")
    return text
