"""Every multi-model M_ij under both progression rules on the same seeds.

Prints, per (trigger, model): success rate with a 95 % Wilson interval, mean total time,
mean N_osc, mean final error and the share of reaches that pressed the button.

    python benchmarks/model_sweep.py --seeds 50|A:B [--trigger event|fixed|both] [--models 1,1 2,1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dammrl.stack.runner import ReachRunner
from dammrl.study.stats import wilson
from dammrl_core.metrics import ReachMetrics
from dammrl_core.models import HUMAN_MODELS, ROBOT_MODELS, parse_model
from dammrl_core.task import held_out_seeds


def summarise(trigger: str, model: tuple[int, int], rows: list[ReachMetrics]) -> str:
    n, wins = len(rows), sum(m.success for m in rows)
    rate = wilson(wins, n)
    lo, hi = rate.low, rate.high
    mean = lambda key: float(np.mean([getattr(m, key) for m in rows]))  # noqa: E731
    failures: dict[str, int] = {}
    for m in rows:
        if not m.success:
            cause = m.outcome if m.outcome == "timeout" else m.reason.split(":")[0][:40]
            failures[cause] = failures.get(cause, 0) + 1
    return (
        f"{trigger:6s} M_{model[0]},{model[1]}  success {wins / n:5.0%} [{lo:4.0%}, {hi:4.0%}]  "
        f"t_total {mean('t_total_s'):5.1f} s  N_osc {mean('n_osc'):5.1f}  "
        f"error {mean('final_error_m') * 1000:5.1f} mm  reached {mean('reached'):4.0%}  "
        f"{failures or ''}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(50),
                        help="held-out task seeds: N or A:B (default the first 50)")  # fmt: skip
    parser.add_argument("--trigger", choices=["event", "fixed", "both"], default="both")
    parser.add_argument("--models", nargs="*", type=parse_model)
    args = parser.parse_args()
    models = args.models or [(i, j) for i in HUMAN_MODELS for j in ROBOT_MODELS]
    triggers = ["event", "fixed"] if args.trigger == "both" else [args.trigger]
    runner = ReachRunner()
    start = time.perf_counter()
    for trigger in triggers:
        for model in models:
            rows = [runner.run(seed, model, trigger=trigger).metrics for seed in args.seeds]
            print(summarise(trigger, model, rows), flush=True)
    print(
        f"{len(args.seeds)} seeds ({args.seeds.start}:{args.seeds.stop}) x {len(models)} "
        f"models x {len(triggers)} triggers "
        f"in {time.perf_counter() - start:.0f} s"
    )


if __name__ == "__main__":
    main()
