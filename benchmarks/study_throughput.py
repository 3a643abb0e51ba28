"""Study throughput: reaches per second in one process, on every core, and on Ray.

The same jobs (the paper's four configurations on held-out seeds) through each executor
in one run; the records must be identical. Prints reaches/s and the speed-up over one
process (goal: >= 0.8 x the core count).

    python benchmarks/study_throughput.py [--seeds 20]
"""

from __future__ import annotations

import argparse
import os
import time

from dammrl.study.configs import paper_configurations
from dammrl.study.run import Job, Record, ordered, run_local, run_ray
from dammrl_core.task import held_out_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=held_out_seeds, default=held_out_seeds(20))
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    jobs = [
        Job(c, s, "nominal", k) for c in paper_configurations() for k, s in enumerate(args.seeds)
    ]
    executors = {
        "1 process": lambda: run_local(jobs, 1),
        f"{cores} processes": lambda: run_local(jobs, cores),
        f"Ray (local, {cores} CPUs)": lambda: run_ray(jobs, "local"),
    }
    reference: list[Record] | None = None
    single_rate = 0.0
    for name, execute in executors.items():
        start = time.perf_counter()
        records = ordered(execute())
        wall = time.perf_counter() - start
        rate = len(jobs) / wall
        single_rate = single_rate or rate
        if reference is None:
            reference = records
        same = [r.row for r in records] == [r.row for r in reference]
        print(f"{name:24s} {len(jobs)} reaches in {wall:6.1f} s: {rate:5.1f} reaches/s, "
              f"x{rate / single_rate:.2f} of one process, records identical: {same}")  # fmt: skip


if __name__ == "__main__":
    main()
