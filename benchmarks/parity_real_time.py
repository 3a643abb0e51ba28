"""The real-time bus stack beside the in-process runner on the same seeds (prints figures).

The lockstep stack is exact (tests/test_parity.py); in real time a late command shifts a
reach by a period. Per seed: the same decisions?, t_total, final error, N_osc, steps and
the largest difference of the end-effector paths at equal robot times.

    python benchmarks/parity_real_time.py [--trigger event|fixed] [--seeds 6]
"""

from __future__ import annotations

import argparse

from dammrl.stack.runner import ReachRunner
from tests.test_parity import _in_process, _path_difference, _run_stack


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trigger", choices=["event", "fixed"], default="fixed")
    parser.add_argument("--seeds", type=int, default=6)
    args = parser.parse_args()
    seeds = range(7_000_100, 7_000_100 + args.seeds)
    bus = _run_stack(seeds, DAMMRL_BUS_LOCKSTEP="false", DAMMRL_CONTROLLER_TRIGGER=args.trigger,
                     DAMMRL_POLICY_KIND="fixed", DAMMRL_POLICY_HUMAN_MODEL="2",
                     DAMMRL_POLICY_ROBOT_MODEL="1")  # fmt: skip
    local = _in_process(ReachRunner(), seeds, args.trigger, None)
    for seed in seeds:
        seen, ref = bus[seed], local[seed]
        assert seen.result is not None
        same = [(i.u_h, i.radius_m) for i in seen.intents] == [
            (d.intent.u_h, d.intent.radius_m) for d in ref.decisions
        ]
        print(f"seed {seed}: decisions same {same}, t_total {seen.result.t_total_s:.2f} / "
              f"{ref.metrics.t_total_s:.2f} s, final error {seen.result.final_error_m * 1e3:.2f}"
              f" / {ref.metrics.final_error_m * 1e3:.2f} mm, N_osc {seen.result.n_osc} / "
              f"{ref.metrics.n_osc}, path difference "
              f"{_path_difference(seen.states, ref) * 1e3:.3f} mm")  # fmt: skip


if __name__ == "__main__":
    main()
