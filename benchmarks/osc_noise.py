"""N_osc measures motion, not sensor noise.

Event-triggered M_2,1 on held-out seeds, two measurements:

1. The same noise-free paths, counted as they are and with the simulator's end-effector
   noise (0.25 mm, white, at the control rate) added: the count's own sensitivity, with
   the motion estimate (``dammrl_core.metrics.motion_estimate``) and with the deadband
   alone.
2. Closed loop: the reaches run again with only the sensor noise switched on (masses,
   damping and friction nominal). N_osc on the measured path and on the simulator's
   noise-free path of the same reaches: the change of the count splits into the arm's
   motion (the controller reacts to noisy feedback) and the count's own error.

    python benchmarks/osc_noise.py [--seeds 100]
"""

from __future__ import annotations

import argparse

import numpy as np

from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl.study.stats import bootstrap_mean, paired_difference
from dammrl_core.metrics import MOTION_CUTOFF_HZ, n_oscillations
from dammrl_core.sim.settings import DomainRandomization, SimSettings
from dammrl_core.task import held_out_seeds

NOISE_M = 2.5e-4


def _counts(result: ReachResult, x: np.ndarray, rate_hz: float) -> int:
    subgoals = np.array([s.subgoal for s in result.steps]).reshape(-1, 3)
    radii = np.array([s.radius_m for s in result.steps])
    return n_oscillations(x, subgoals, radii, rate_hz)


def same_paths(runner: ReachRunner, seeds: range) -> None:
    rate = 1.0 / runner.control_dt_s
    no_filter = 2 * MOTION_CUTOFF_HZ  # a rate at which the filter stands aside
    rng = np.random.default_rng(0)
    counts: dict[str, list[int]] = {k: [] for k in ("f", "f+n", "d", "d+n")}
    for seed in seeds:
        result = runner.run(seed, (2, 1), "event")
        x = result.trajectory.x
        noisy = x + rng.normal(0, NOISE_M, x.shape)
        counts["f"].append(_counts(result, x, rate))
        counts["f+n"].append(_counts(result, noisy, rate))
        counts["d"].append(_counts(result, x, no_filter))
        counts["d+n"].append(_counts(result, noisy, no_filter))
    print(f"1. the same {len(seeds)} paths, noise added:")
    for name, key in (("motion estimate", "f"), ("deadband alone", "d")):
        clean, noisy_mean = np.mean(counts[key]), np.mean(counts[key + "+n"])
        print(
            f"   {name:16s} N_osc {clean:6.2f} -> {noisy_mean:6.2f} ({noisy_mean / clean - 1:+.1%})"
        )


def closed_loop(seeds: range) -> None:
    noise_only = DomainRandomization(enabled=True, mass_scale=0, damping_scale=0,
                                     friction_max_nm=0)  # fmt: skip
    quiet = ReachRunner(ReachSettings())
    noisy = ReachRunner(ReachSettings(sim=SimSettings(randomization=noise_only)))
    rate = 1.0 / quiet.control_dt_s
    off, on, on_true = [], [], []
    for seed in seeds:
        off.append(quiet.run(seed, (2, 1), "event").metrics.n_osc)
        result = noisy.run(seed, (2, 1), "event")
        kept = result.trajectory.t <= result.metrics.t_total_s + 1e-9
        on.append(result.metrics.n_osc)
        on_true.append(_counts(result, result.trajectory.x_true[kept], rate))
    rng = np.random.default_rng(0)
    a, b, c = (np.array(v, dtype=float) for v in (on, off, on_true))
    print(f"2. closed loop, {len(seeds)} seeds, only the sensor noise switched on:")
    print(
        f"   N_osc noise off {bootstrap_mean(b, rng).text()}, on {bootstrap_mean(a, rng).text()}"
        f" ({a.mean() / b.mean() - 1:+.1%}); paired {paired_difference(a, b, rng).text()}"
    )
    print(
        f"   of which the motion (noise-free path of the noisy reaches): "
        f"{paired_difference(c, b, rng).text()} ({c.mean() / b.mean() - 1:+.1%})"
    )
    print(f"   and the count's own error (measured - noise-free, same reaches): "
          f"{paired_difference(a, c, rng).text()} ({a.mean() / c.mean() - 1:+.1%})")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(100))
    args = parser.parse_args()
    same_paths(ReachRunner(), args.seeds)
    closed_loop(args.seeds)


if __name__ == "__main__":
    main()
