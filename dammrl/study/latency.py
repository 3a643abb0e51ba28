"""The reference machine's IK cost, fitted from a study's saved latencies.

A study that measured its solves (``ikpy-measured``, or v2's ``ikpy-real`` and
``dls-real``) saved each reach's processor times. Replaying those reaches runs the same
solves in the same order, so each saved time pairs with the work of its solve, the
forward-kinematics evaluations counted here. A solve of n evaluations took
n * c * exp(sigma * z) there: c is the geometric mean of time per evaluation, sigma the
spread of its logarithm. ``dammrl_core.ik.REFERENCE_COST`` holds the fit of the shipped
latencies; ``python -m dammrl.study.latency FILE`` fits any saved file again (and says how
many replays matched the reaches they came from: a pairing is only kept when the replayed
reach spent exactly the saved latencies).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.study.configs import CONDITIONS, PAPER_KEYS, paper_configurations
from dammrl.study.run import Job, reach
from dammrl.study.study import load_latencies

REPLAY_CONDITION = {"ikpy": "ikpy-measured", "pinocchio": "dls-real"}  # the solver's condition


@dataclass(frozen=True)
class Fit:
    solver: str
    per_evaluation_s: float
    sigma: float
    solves: int
    reaches: int
    skipped: int  # replays whose solves did not match the saved latencies
    r2_log: float  # share of log-time variance the evaluations explain

    def text(self) -> str:
        return (f"{self.solver}: {self.per_evaluation_s * 1e6:.2f} µs per evaluation, "
                f"log-sd {self.sigma:.3f} ({self.solves} solves of {self.reaches} reaches; "
                f"{self.skipped} replays did not match; R² of log time on log evaluations "
                f"{self.r2_log:.2f})")  # fmt: skip


def pairs(saved: dict[str, tuple[float, ...]], condition: str, solver: str,
          per_configuration: int, first_seed: int) -> tuple[np.ndarray, int, int]:  # fmt: skip
    """(evaluations, seconds) of every solve of up to ``per_configuration`` saved reaches of
    each paper configuration, by replaying them; the reaches used and skipped."""
    configurations = {c.key: c for c in paper_configurations()}
    found, used, skipped = [], 0, 0
    for key in PAPER_KEYS:
        seeds = sorted(int(k.rsplit("/", 1)[1]) for k in saved
                       if k.startswith(f"{condition}/{key}/"))[:per_configuration]  # fmt: skip
        for seed in seeds:
            latencies = saved[f"{condition}/{key}/{seed}"]
            job = Job(configurations[key], seed, REPLAY_CONDITION[solver], seed - first_seed,
                      0, latencies)  # fmt: skip
            result = reach(job)
            if tuple(result.ik_latencies_s) != tuple(latencies):
                skipped += 1
                continue
            found += list(zip(result.ik_evaluations, latencies, strict=True))
            used += 1
    return np.array(found, dtype=float).reshape(-1, 2), used, skipped


def fit(solver: str, data: np.ndarray, used: int, skipped: int) -> Fit:
    """The proportional fit of time on evaluations, on logarithms."""
    n, t = data[:, 0], data[:, 1]
    keep = (n > 0) & (t > 0)
    log_ratio = np.log(t[keep] / n[keep])
    log_t = np.log(t[keep])
    residual = log_t - np.log(n[keep]) - log_ratio.mean()
    r2 = 1 - float(residual.var()) / float(log_t.var()) if log_t.var() > 0 else math.nan
    return Fit(solver, float(np.exp(log_ratio.mean())), float(log_ratio.std(ddof=1)),
               int(keep.sum()), used, skipped, r2)  # fmt: skip


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("latencies", type=Path, help="a study's ik_latencies.json.gz")
    parser.add_argument("--per-configuration", type=int, default=40, metavar="N",
                        help="reaches replayed per paper configuration (default 40)")  # fmt: skip
    parser.add_argument("--first-seed", type=int, default=7_500_000,
                        help="the study's first evaluation seed (picks each reach's training "
                        "run, as the study did; default 7,500,000, study v2's)")  # fmt: skip
    args = parser.parse_args(argv)
    saved = load_latencies(args.latencies)
    for solver, condition in (("ikpy", "ikpy-real"), ("pinocchio", "dls-real")):
        named = [k for k in saved if k.startswith(f"{condition}/")]
        if not named:
            continue
        data, used, skipped = pairs(saved, condition, solver, args.per_configuration,
                                    args.first_seed)  # fmt: skip
        print(fit(solver, data, used, skipped).text(), flush=True)
    replayed = ", ".join(CONDITIONS[c].key for c in REPLAY_CONDITION.values())
    print(f"(replayed as the conditions {replayed})")


if __name__ == "__main__":
    main()
