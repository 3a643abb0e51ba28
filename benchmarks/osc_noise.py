"""N_osc measures motion, not sensor noise: the same paths with and without noise.

Event-triggered M_2,1 reaches without sensor noise; each path's N_osc, then the same path
with the simulator's end-effector noise added (0.25 mm, white, at the control rate).
The motion estimate (dammrl.core.metrics.motion_estimate) is on; for comparison the
deadband alone (the filter skipped).

    python benchmarks/osc_noise.py [--seeds 60]
"""

from __future__ import annotations

import argparse

import numpy as np

from dammrl.core.metrics import MOTION_CUTOFF_HZ, n_oscillations
from dammrl.core.task import held_out_seeds
from dammrl.runner import ReachRunner

NOISE_M = 2.5e-4


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(60))
    args = parser.parse_args()
    runner = ReachRunner()
    rate = 1.0 / runner.control_dt_s
    rng = np.random.default_rng(0)
    counts: dict[str, list[int]] = {"filtered": [], "filtered+noise": [],
                                    "deadband only": [], "deadband only+noise": []}  # fmt: skip
    for seed in args.seeds:
        result = runner.run(seed, (2, 1), "event")
        x = result.trajectory.x
        subgoals = np.array([s.subgoal for s in result.steps]).reshape(-1, 3)
        radii = np.array([s.radius_m for s in result.steps])
        noisy = x + rng.normal(0, NOISE_M, x.shape)
        no_filter = 2 * MOTION_CUTOFF_HZ  # a rate at which the filter stands aside
        counts["filtered"].append(n_oscillations(x, subgoals, radii, rate))
        counts["filtered+noise"].append(n_oscillations(noisy, subgoals, radii, rate))
        counts["deadband only"].append(n_oscillations(x, subgoals, radii, no_filter))
        counts["deadband only+noise"].append(n_oscillations(noisy, subgoals, radii, no_filter))
    for name in ("filtered", "deadband only"):
        clean, noisy_mean = np.mean(counts[name]), np.mean(counts[name + "+noise"])
        print(f"{name:14s} N_osc {clean:6.2f} without noise, {noisy_mean:6.2f} with "
              f"({noisy_mean / clean - 1:+.1%}), {len(args.seeds)} seeds")  # fmt: skip


if __name__ == "__main__":
    main()
