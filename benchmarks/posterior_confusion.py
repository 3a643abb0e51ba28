"""Which sub-model the human-model posterior picks for people unlike its model.

For each simulated person (the model itself, other accuracies, slower or quicker decision
times, drift-diffusion deciders) and each radius they keep (i = 1, 2: the truth), sample
sequences of decisions with the stack's own SimulatedHuman, score them with the posterior
on the nominal sub-models, and print per cell: the share of sequences whose MAP is the
truth after 5, 10 and 20 decisions (95 % Wilson intervals), the median decisions until
the MAP settled, the mean probability of the MAP model, the same among wrong MAPs
(over-confidence) and the share of sequences with > 0.99 on the wrong model.
No physics: the posterior sees only (correct, decision time).

    python benchmarks/posterior_confusion.py [--sequences 300] [--scale-sd 0 0.15 0.25]
        [--out docs/posterior_confusion]
"""

from __future__ import annotations

import argparse
import csv
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.study.stats import wilson
from dammrl_core.human import HumanModel
from dammrl_core.intent.simulated import SimulatedHuman
from dammrl_core.models import HUMAN_MODELS, ModelSet
from dammrl_core.person import SimulatedPerson
from dammrl_core.posterior import HumanModelPosterior

CHECKPOINTS = (5, 10, 20)  # decisions after which the MAP is compared with the truth
GOAL = np.array([0.5, 0.0, -0.2])
PEOPLE: dict[str, SimulatedPerson] = {
    "model": SimulatedPerson(),
    "accuracy 0.85": SimulatedPerson(accuracy=0.85),
    "times x1.5": SimulatedPerson(decision_time_factor=1.5),
    "accuracy 0.85, times x1.5": SimulatedPerson(accuracy=0.85, decision_time_factor=1.5),
    "times x0.7": SimulatedPerson(decision_time_factor=0.7),
    "ddm v=2 a=0.7/1.1 t0=0.15": SimulatedPerson(behaviour="ddm"),
    "ddm v=1.2 a=0.9/1.5 t0=0.3": SimulatedPerson(
        behaviour="ddm",
        ddm_drift_per_s=1.2,
        ddm_boundary_big=0.9,
        ddm_boundary_small=1.5,
        ddm_non_decision_s=0.3,
    ),
}
HEADER = (
    "person",
    "truth i",
    *(f"MAP right @{n}" for n in CHECKPOINTS),
    "settled after",
    "p(MAP) @20",
    "p(MAP) when wrong",
    "p(wrong)>0.99",
)


@dataclass(frozen=True)
class Cell:
    """One (person, truth) cell scored with one posterior setting."""

    person: str
    truth: int
    right: dict[int, int]  # checkpoint -> sequences whose MAP is the truth
    settled: list[int]
    p_map: list[float]  # probability of the MAP model after the last decision
    p_map_wrong: list[float]  # the same, for sequences whose last MAP is wrong
    sure_wrong: int  # sequences with > 0.99 on the wrong model at the end
    n: int

    def row(self) -> tuple[str, ...]:
        shares = (_share(self.right[k], self.n) for k in CHECKPOINTS)
        wrong = f"{np.mean(self.p_map_wrong):.2f}" if self.p_map_wrong else "-"
        return (
            self.person,
            str(self.truth),
            *shares,
            f"{np.median(self.settled):.0f}",
            f"{np.mean(self.p_map):.2f}",
            f"{wrong} (n={len(self.p_map_wrong)})",
            _share(self.sure_wrong, self.n),
        )


def _share(k: int, n: int) -> str:
    rate = wilson(k, n)
    return f"{rate.value:.0%} [{rate.low:.0%}, {rate.high:.0%}]"


def sample(person: SimulatedPerson, truth: int, sequences: int, decisions: int) -> np.ndarray:
    """(correct, decision time [s]) per decision, shape (sequences, decisions, 2); sequence
    k uses seed k, so every cell meets the same random numbers."""
    human = HumanModel(person=person)
    out = np.empty((sequences, decisions, 2))
    for seed in range(sequences):
        simulated = SimulatedHuman(human, ModelSet(), seed)
        for k in range(decisions):
            d = simulated.decide(0.0, np.zeros(3), GOAL, 0, truth)
            out[seed, k] = (d.correct, d.decision_s)
    return out


def score(name: str, truth: int, draws: np.ndarray, scale_sd: float) -> Cell:
    """Run a fresh posterior (nominal sub-models) over each sequence."""
    model = HumanModel(decision_scale_sd=scale_sd)
    right = dict.fromkeys(CHECKPOINTS, 0)
    settled, p_map, p_wrong, sure_wrong = [], [], [], 0
    for sequence in draws:
        posterior = HumanModelPosterior(model)
        for k, (correct, decision_s) in enumerate(sequence, start=1):
            p = posterior.update(bool(correct), float(decision_s))
            if k in right:
                right[k] += posterior.map_model == truth
        settled.append(posterior.settled_after())
        p_map.append(float(p.max()))
        if posterior.map_model != truth:
            p_wrong.append(float(p.max()))
        sure_wrong += float(p[HUMAN_MODELS.index(truth)]) < 0.01
    return Cell(name, truth, right, settled, p_map, p_wrong, sure_wrong, len(draws))


def markdown(rows: list[tuple[str, ...]]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=int, default=300, help="per cell (default 300)")
    parser.add_argument("--decisions", type=int, default=max(CHECKPOINTS))
    parser.add_argument("--scale-sd", type=float, nargs="+", default=[0.0, 0.15, 0.25],
                        help="posterior settings DAMMRL_HUMAN_DECISION_SCALE_SD to compare "
                        "(0: the original posterior)")  # fmt: skip
    parser.add_argument("--out", type=Path, help="write <out>.md and <out>.csv")
    args = parser.parse_args()
    start = time.perf_counter()
    draws = {
        (name, truth): sample(person, truth, args.sequences, args.decisions)
        for name, person in PEOPLE.items()
        for truth in HUMAN_MODELS
    }
    tables: dict[float, list[tuple[str, ...]]] = {}
    for scale_sd in args.scale_sd:
        tables[scale_sd] = [score(n, t, d, scale_sd).row() for (n, t), d in draws.items()]
        print(f"\nposterior decision_scale_sd = {scale_sd}\n{markdown(tables[scale_sd])}")
    seconds = time.perf_counter() - start
    print(f"\n{args.sequences} sequences x {len(draws)} cells in {seconds:.0f} s")
    if args.out:
        write(args.out, tables)


def write(out: Path, tables: dict[float, list[tuple[str, ...]]]) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    text = [f"### decision_scale_sd = {sd}\n\n{markdown(rows)}\n" for sd, rows in tables.items()]
    out.with_suffix(".md").write_text("\n".join(text))
    with out.with_suffix(".csv").open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(("decision_scale_sd", *HEADER))
        writer.writerows((sd, *row) for sd, rows in tables.items() for row in rows)


if __name__ == "__main__":
    main()
