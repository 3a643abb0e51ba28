"""The reward-weight frontier: train a grid of time weights beta, several seeds each, and
plot speed against accuracy on the held-out seeds, Reward 1 (beta = 0) and Reward 2 (the
shipped weighting, beta = 1) marked on it.

The verdict compares every beta with Reward 1 under rules fixed before any result:
"faster" when the 95 % interval of the difference in t_total (IQM) lies below zero;
"at equal or better success" when the success rate is not lower by more than ``SUCCESS_MARGIN``
(the lower end of its difference's 95 % interval).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from dammrl.study.stats import Estimate, finite_mean, iqm, stratified_difference
from dammrl.study.training import (
    ARMS,
    GroupSummary,
    TrainJob,
    group_jobs,
    load_evaluations,
    summarize,
)

SUCCESS_MARGIN = 0.02  # 2 points lower still counts as "equal success"
REWARD1_BETA, REWARD2_BETA = 0.0, 1.0


def beta_dir(out: Path, beta: float) -> Path:
    return out / f"beta-{beta:g}"


def frontier_jobs(out: Path, betas: list[float], seeds: int, episodes: int,
                  eval_seeds: range) -> list[TrainJob]:  # fmt: skip
    """Every (beta, seed) run of the grid: Reward 2's terms with the time weight beta.
    beta = 0 is Reward 1 and beta = 1 Reward 2 exactly: those runs are the ones
    ``dammrl train --reward 1|2 --seeds N`` makes."""
    jobs = []
    for beta in betas:
        reward: Literal[1, 2] = 1 if beta == REWARD1_BETA else 2
        jobs += group_jobs(beta_dir(out, beta), reward, seeds, episodes, eval_seeds, beta)
    return jobs


@dataclass
class Comparison:
    beta: float
    arm: str
    dt_s: Estimate  # t_total IQM: this beta minus Reward 1
    dsuccess: Estimate  # success rate: this beta minus Reward 1

    @property
    def faster(self) -> bool:
        return self.dt_s.n > 0 and self.dt_s.high < 0

    @property
    def equal_success(self) -> bool:
        return self.dsuccess.n > 0 and self.dsuccess.low >= -SUCCESS_MARGIN


def analyse(out: Path, betas: list[float]) -> tuple[list[GroupSummary], list[Comparison]]:
    """Per beta and arm: the aggregates, and the comparison with Reward 1 (beta = 0)."""
    evaluations = {beta: load_evaluations(beta_dir(out, beta)) for beta in betas}
    summaries = [summarize(f"beta={beta:g}", evaluations[beta], arm)
                 for beta in betas for arm in ARMS]  # fmt: skip
    comparisons = []
    if REWARD1_BETA in evaluations:
        rng = np.random.default_rng(0)
        for beta in betas:
            if beta == REWARD1_BETA:
                continue
            for arm in ARMS:
                a, b = _matrices(evaluations[beta], arm), _matrices(evaluations[REWARD1_BETA], arm)
                comparisons.append(Comparison(
                    beta, arm,
                    stratified_difference(a["t_total_s"], b["t_total_s"], iqm, rng),
                    stratified_difference(a["success"], b["success"], finite_mean, rng),
                ))  # fmt: skip
    return summaries, comparisons


def _matrices(evaluations: list[dict[str, Any]], arm: str) -> dict[str, np.ndarray]:
    return {k: np.array([e["arms"][arm][k] for e in evaluations], dtype=float)
            for k in ("success", "t_total_s", "final_error_m")}  # fmt: skip


def verdict(comparisons: list[Comparison]) -> str:
    """One paragraph per arm: is any weighting faster than Reward 1 at equal or better
    success?"""
    lines = []
    for arm in ARMS:
        rows = [c for c in comparisons if c.arm == arm]
        winners = [c for c in rows if c.faster and c.equal_success]
        shipped = next((c for c in rows if c.beta == REWARD2_BETA), None)
        found = ", ".join(f"beta={c.beta:g} ({c.dt_s.text()} s)" for c in winners)
        claim = "faster than Reward 1 at equal or better success"
        text = f"**{arm} arms**: " + (f"{claim}: {found}" if winners else f"nothing is {claim}")
        if shipped is not None:
            text += (f". Reward 2 (beta=1, shipped) vs Reward 1: t_total {shipped.dt_s.text()} s,"
                     f" success {shipped.dsuccess.text(100, 1)} points")  # fmt: skip
        lines.append(text + ".")
    return "\n\n".join(lines)


def plot(summaries: list[GroupSummary], path: Path) -> None:
    """Success and final error against t_total (IQM, 95 % intervals), one column per arm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(ARMS), figsize=(11, 7.5), constrained_layout=True,
                             sharex="col")  # fmt: skip
    for column, arm in enumerate(ARMS):
        rows = sorted((s for s in summaries if s.arm == arm), key=_beta)
        for row, (name, scale, label) in enumerate(
            (("success", 100, "success [%]"), ("final_error_m", 1000, "final error [mm] (IQM)"))
        ):
            ax = axes[row, column]
            x = [s.t_total_s for s in rows]
            y = [getattr(s, name) for s in rows]
            ax.errorbar([e.value for e in x], [e.value * scale for e in y],
                        xerr=_bars(x), yerr=_bars(y, scale), fmt="o-", color="0.35",
                        ecolor="0.6", capsize=3)  # fmt: skip
            for s, ex, ey in zip(rows, x, y, strict=True):
                ax.annotate(_mark(_beta(s)), (ex.value, ey.value * scale), fontsize=8,
                            textcoords="offset points", xytext=(5, 5))  # fmt: skip
            ax.set(ylabel=label, title=f"{arm} arms" if row == 0 else None)
            if row == 1:
                ax.set_xlabel("t_total [s] (IQM over seeds x held-out reaches)")
    fig.suptitle("Reward-weight frontier: the time weight beta, 95 % stratified-bootstrap CIs")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _beta(summary: GroupSummary) -> float:
    return float(summary.label.removeprefix("beta="))


def _mark(beta: float) -> str:
    names = {REWARD1_BETA: " = Reward 1", REWARD2_BETA: " = Reward 2"}
    return f"beta={beta:g}{names.get(beta, '')}"


def _bars(estimates: list[Estimate], scale: float = 1.0) -> np.ndarray:
    return np.array([[(e.value - e.low) * scale for e in estimates],
                     [(e.high - e.value) * scale for e in estimates]])  # fmt: skip


def write_report(out: Path, betas: list[float], command: str, wall_s: float) -> str:
    """frontier.md, frontier.json and frontier.png in ``out``; returns the markdown."""
    from dammrl.study.training import summary_table, to_json

    summaries, comparisons = analyse(out, betas)
    plot(summaries, out / "frontier.png")
    (out / "frontier.json").write_text(to_json(summaries))
    rows = ["| beta | arm | Δ t_total vs Reward 1 [s] | Δ success [points] | faster, success "
            "not lower |", "|---|---|---|---|---|"]  # fmt: skip
    rows += [
        f"| {c.beta:g} | {c.arm} | {c.dt_s.text()} | {c.dsuccess.text(100, 1)} | "
        f"{'yes' if c.faster and c.equal_success else 'no'} |"
        for c in comparisons
    ]
    text = "\n\n".join([
        "# Reward-weight frontier", f"`{command}` ({wall_s / 60:.0f} min)",
        "![frontier](frontier.png)", summary_table(summaries), "\n".join(rows),
        "## Verdict", verdict(comparisons),
        f"Rules (fixed before the results): faster = the 95 % interval of Δ t_total below 0; "
        f"equal success = success not lower by more than {SUCCESS_MARGIN * 100:.0f} points "
        "(lower end of its 95 % interval).",
    ])  # fmt: skip
    (out / "frontier.md").write_text(text + "\n")
    return text
