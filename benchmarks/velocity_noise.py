"""How much end-effector velocity noise the event trigger takes before it changes anything.

The trigger fires when the end-effector is inside the admission sphere and dV/dt =
-e^T W v <= 0, with v the measured velocity. The randomised arm's velocity noise is the
joint-velocity noise through the Jacobian (1 mm/s per axis, ``ee_vel_noise_m_per_s``).
Here the same randomised arms and seeds run event-triggered M_2,1 and the shipped Reward 2
policy at several noise levels, every other setting equal; against the noise-free run of
the same seed: the share of reaches whose trigger fired at another time at least once
(their step start times differ), and the paired change of time, steps, N_osc and holds.

    python benchmarks/velocity_noise.py [--seeds 100] [--levels 0.001,0.003,0.01,0.03]
"""

from __future__ import annotations

import argparse

import numpy as np

from dammrl.stack.runner import ReachResult, ReachRunner, ReachSettings
from dammrl.study.stats import paired_difference, wilson
from dammrl_core.policy import FixedPolicy, Policy
from dammrl_core.policy.learned import LearnedPolicy
from dammrl_core.policy.settings import SHIPPED_POLICY
from dammrl_core.task import held_out_seeds


def _runner(noise_m_per_s: float) -> ReachRunner:
    base = ReachSettings().randomized(True)
    randomization = base.sim.randomization.model_copy(
        update={"ee_vel_noise_m_per_s": noise_m_per_s}
    )
    return ReachRunner(base.model_copy(update={"sim": base.sim.model_copy(
        update={"randomization": randomization})}))  # fmt: skip


def _reaches(runner: ReachRunner, policy: Policy, seeds: range) -> list[ReachResult]:
    return [runner.run(seed, trigger="event", policy=policy) for seed in seeds]


def _row(name: str, level: float, noisy: list[ReachResult], quiet: list[ReachResult]) -> str:
    rng = np.random.default_rng(0)
    moved = sum(
        [s.start_s for s in a.steps] != [s.start_s for s in b.steps]
        for a, b in zip(noisy, quiet, strict=True)
    )
    changed = wilson(moved, len(noisy))

    def diff(figure: str) -> str:
        a = np.array([float(getattr(r.metrics, figure)) for r in noisy])
        b = np.array([float(getattr(r.metrics, figure)) for r in quiet])
        return paired_difference(a, b, rng).text(1, 2)

    holds = [float(r.metrics.outcome == "hold") for r in noisy]
    return (f"{name:10s} {level * 1000:5.1f} mm/s: trigger moved in {changed.text(100, 0)} % "
            f"of reaches; t_total {diff('t_total_s')} s, steps {diff('n_steps')}, "
            f"N_osc {diff('n_osc')}, holds {100 * np.mean(holds):.0f} %")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(100))
    parser.add_argument("--levels", default="0.001,0.003,0.01,0.03",
                        help="velocity noise standard deviations [m/s]")  # fmt: skip
    args = parser.parse_args()
    quiet = _runner(0.0)
    models = quiet.settings.models
    policies: dict[str, Policy] = {
        "M_2,1": FixedPolicy(models, 2, 1),
        "reward2": LearnedPolicy(models, SHIPPED_POLICY),
    }
    reference = {name: _reaches(quiet, p, args.seeds) for name, p in policies.items()}
    print(f"{len(args.seeds)} randomised seeds from {args.seeds.start:,}; against no noise:")
    for level in (float(v) for v in args.levels.split(",")):
        runner = _runner(level)
        for name, policy in policies.items():
            print(_row(name, level, _reaches(runner, policy, args.seeds), reference[name]))


if __name__ == "__main__":
    main()
