"""The reward effect of the paper, measured: Reward 1 vs Reward 2 on the same seeds.

Greedy policies of two runs on the same unseen seeds (stochastic human). Prints success
rate and total time with 95 % intervals, and writes a figure of the mean step magnitude
the robot agent chose against the distance to the goal (95 % bootstrap bands).

    python benchmarks/reward_effect.py runs/r1 runs/r2 [--episodes 100] [-o reward_effect.png]
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from dammrl.learning.rl.train import Rollout, greedy_rollouts
from dammrl.study.stats import bootstrap_mean, wilson
from dammrl_core.models import ModelSet
from dammrl_core.task import held_out_seeds

BINS_M = np.array([0.0, 0.01, 0.02, 0.04, 0.08, 0.16, 0.5])


def mean_ci(values: np.ndarray, rng: np.random.Generator) -> tuple[float, float, float]:
    """Mean and 95 % bootstrap interval (the study's estimator)."""
    estimate = bootstrap_mean(values, rng)
    return estimate.value, estimate.low, estimate.high


def step_vs_distance(rollouts: list[Rollout]) -> tuple[np.ndarray, np.ndarray]:
    models = ModelSet()
    distance = np.array([d for r in rollouts for d, _, _ in r.decisions])
    magnitude = np.array([models.steps_m(j).mean() for r in rollouts for _, _, j in r.decisions])
    return distance, magnitude


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reward1", type=Path)
    parser.add_argument("reward2", type=Path)
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(100),
                        help="held-out task seeds: N or A:B (default the first 100)")  # fmt: skip
    parser.add_argument("-o", "--out", type=Path, default=Path("reward_effect.png"))
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    centres = (BINS_M[:-1] + BINS_M[1:]) / 2 * 100
    runs = (
        ("Reward 1 (accuracy)", args.reward1, "tab:blue"),
        ("Reward 2 (speed + accuracy)", args.reward2, "tab:orange"),
    )
    for label, run, color in runs:
        rollouts = greedy_rollouts(run, args.seeds)
        wins = sum(r.metrics.success for r in rollouts)
        rate = wilson(wins, len(rollouts))
        lo, hi = rate.low, rate.high
        t = np.array([r.metrics.t_total_s for r in rollouts])
        t_mean, t_lo, t_hi = mean_ci(t, rng)
        print(f"{label}: success {wins}/{len(rollouts)} [{lo:.0%}, {hi:.0%}], "
              f"t_total {t_mean:.1f} s [{t_lo:.1f}, {t_hi:.1f}]")  # fmt: skip
        distance, magnitude = step_vs_distance(rollouts)
        stats = [
            mean_ci(magnitude[(distance >= a) & (distance < b)], rng)
            for a, b in itertools.pairwise(BINS_M)
        ]
        means = np.array([s[0] for s in stats]) * 1000
        ax.plot(centres, means, "o-", color=color, label=label)
        ax.fill_between(centres, [s[1] * 1000 for s in stats], [s[2] * 1000 for s in stats],
                        color=color, alpha=0.2)  # fmt: skip
        near = magnitude[distance < 0.04]
        m, a, b = mean_ci(near, rng)
        print(f"    mean step within 4 cm: {m * 1000:.1f} mm [{a * 1000:.1f}, {b * 1000:.1f}]")
    ax.set(
        xscale="log",
        xlabel="distance to goal when deciding [cm]",
        ylabel="mean step magnitude chosen [mm]",
        title="robot agent's step size vs distance",
    )
    ax.legend()
    fig.savefig(args.out, dpi=120)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
