"""``dammrl coadapt``: the model table the posterior over M_ij starts from, and the
oracle / shipped / adaptive comparison on simulated persons unlike the training human."""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Callable
from pathlib import Path

from dammrl.cli.common import Commands, output_dir, output_file, progress_bar

SIM_SEEDS_PER_SEED = 7_500
GATE_SEEDS_PER_SEED = 5_000
"""dammrl.learning.adapt's (not imported here: the command line loads torch only when it runs; a
test holds them equal)."""


def register(commands: Commands) -> None:
    """Add ``coadapt``."""
    coadapt = commands.add_parser(
        "coadapt",
        help="co-adaptation: the model table, and adaptive vs shipped vs oracle per person",
        description="The posterior over M_ij and the adaptive policy (S2's narrowing, S3's "
        "re-selection), measured on simulated persons unlike the training human.",
    )
    sub = coadapt.add_subparsers(required=True, metavar="ACTION")
    _add_table(sub)
    _add_compare(sub)
    _add_gate_rates(sub)


def _add_table(sub: Commands) -> None:
    """``coadapt table``."""
    table = sub.add_parser(
        "table",
        help="run every option on a grid of persons; write the model table the posterior "
        "predicts every option from",
    )
    table.add_argument("--out", type=output_file(".gz"),
                       help="where (a .json.gz; default: the packaged table)")  # fmt: skip
    table.add_argument("--seeds", type=_count(1, 100), default=12, metavar="N",
                       help="task seeds per person of the grid, from 6,900,000 (1-100; default "
                       "12; the shipped table: 4)")  # fmt: skip
    table.add_argument("--cache", type=output_dir, metavar="DIR",
                       help="keep every finished reach here and reuse those of an earlier "
                       "run with the same code (resume a long build)")  # fmt: skip
    table.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes on this machine (default: every core)",
    )
    table.set_defaults(handler=_table)


def _add_compare(sub: Commands) -> None:
    """``coadapt compare``."""
    compare = sub.add_parser(
        "compare",
        help="shipped, adaptive, refined and oracle policy for kinds of person; report.md, "
        "results.json and figures",
        description="The registered comparison (docs/coadaptation/registration.md): for each "
        "kind of person, the oracle's search, the shipped policy, the adaptive mode, the "
        "refined policy behind its gate, on held-out seeds; the verdict of every goal.",
    )
    compare.add_argument(
        "--out",
        type=output_dir,
        default=Path("coadaptation"),
        help="report directory (default: coadaptation)",
    )
    compare.add_argument(
        "--person",
        nargs="+",
        type=Path,
        metavar="FILE.yaml",
        help="kinds of person, each a file of SimulatedPerson fields with a name and source "
        "(default: the registered eight, dammrl/study/persons/)",
    )
    compare.add_argument("--test-seeds", type=_count(1, 1000), default=100, metavar="N",
                         help="test seeds (from 7,700,000; default 100)")  # fmt: skip
    compare.add_argument("--oracle-seeds", type=_count(1, 1000), default=30, metavar="N",
                         help="seeds per M_ij of the oracle's search (from 7,600,000; default "
                         "30; fewer than 30 and the report says it is no oracle)")  # fmt: skip
    compare.add_argument(
        "--replicates",
        type=_count(1, 20),
        default=2,
        metavar="R",
        help="adaptive sessions per person, Thompson seeds 0..R-1 (default 2)",
    )
    compare.add_argument(
        "--interpolated",
        type=_count(0, 20),
        default=1,
        metavar="R",
        help="adaptive sessions with the bounded interpolation on (default 1; 0: none)",
    )
    compare.add_argument(
        "--sim-reaches",
        type=_count(0, SIM_SEEDS_PER_SEED),
        default=50,
        metavar="N",
        help="the refinement's simulated reaches (default 50)",
    )
    compare.add_argument(
        "--gate-seeds",
        type=_count(10, GATE_SEEDS_PER_SEED),
        default=40,
        metavar="N",
        help="the refinement gate's reaches per policy (default 40)",
    )
    compare.add_argument("--cache", type=output_dir, metavar="DIR",
                         help="keep every finished job here and reuse those of an earlier run "
                         "with the same job and code (resume a long comparison)")  # fmt: skip
    compare.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes on this machine (default: every core)",
    )
    compare.set_defaults(handler=_compare)


def _add_gate_rates(sub: Commands) -> None:
    """``coadapt gate-rates``."""
    rates = sub.add_parser(
        "gate-rates",
        help="how often dammrl adapt's gate deploys a candidate no better (false positives) "
        "or one better by a margin (power), for per-reach gains of a stated shape",
        description="Per-reach gains (in use minus candidate, seconds of time to success): "
        "normal with sd --sd, a share --identical exactly 0 (both policies reached alike), and "
        "a share --swing each of +50 s and -50 s (one policy failed where the other "
        "succeeded). Each of --gates gates draws --gate-seeds of them, shifted to a true mean "
        "gain of 0 and of --margin-s.",
    )
    rates.add_argument("--gate-seeds", type=_count(10, GATE_SEEDS_PER_SEED), nargs="+",
                       default=[40, 200], metavar="N",
                       help="gate sizes (10-5000 each; default 40 200)")  # fmt: skip
    rates.add_argument("--sd", type=_within(0.0, 60.0), default=2.0, metavar="S",
                       help="sd of the gains when both succeed (0-60 s; default 2)")  # fmt: skip
    rates.add_argument("--identical", type=_within(0.0, 1.0), default=0.5, metavar="P",
                       help="share of reaches alike under both (0-1; default 0.5)")  # fmt: skip
    rates.add_argument("--swing", type=_within(0.0, 0.5), default=0.03, metavar="P",
                       help="share each of +50 s and -50 s (0-0.5; default 0.03)")  # fmt: skip
    rates.add_argument("--margin-s", type=_within(0.0, 60.0), default=2.5, metavar="S",
                       help="the true gain of the power (0-60 s; default 2.5)")  # fmt: skip
    rates.add_argument("--gates", type=_count(10, 100_000), default=1000, metavar="N",
                       help="gates per figure (10-100000; default 1000)")  # fmt: skip
    rates.set_defaults(handler=_gate_rates)


def _within(low: float, high: float) -> Callable[[str], float]:
    """Argument type: a finite number within [low, high]."""

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a number {low:g}-{high:g}, got {text!r}")
        return value

    convert.__name__ = "number"
    return convert


def _count(low: int, high: int) -> Callable[[str], int]:
    """Argument type: a whole number within [low, high]."""

    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected a whole number {low}-{high}, got {text!r}")
        return value

    convert.__name__ = "count"
    return convert


def _table(args: argparse.Namespace) -> int:
    from dammrl.study.coadaptation_table import TABLE_SEEDS, build_table, table_jobs
    from dammrl_core.model_table import OPTIONS, TABLE

    seeds = range(TABLE_SEEDS.start, TABLE_SEEDS.start + args.seeds)
    jobs = len(table_jobs(seeds))
    update, close = progress_bar(jobs, "model table")
    try:
        table = build_table(seeds, workers=args.jobs, progress=update, cache=args.cache)
    finally:
        close()
    out = args.out or TABLE
    out.write_bytes(table.dumps())
    models = len(OPTIONS) - 1
    print(f"model table, {models} models and the base policy on a grid of persons, {len(seeds)} "
          f"seeds per person ({jobs} reaches): {out}")  # fmt: skip
    return 0


def _compare(args: argparse.Namespace) -> int:
    from dammrl.learning.adapt import RefineSettings
    from dammrl.study.coadaptation import (
        ORACLE_SEEDS,
        TEST_SEEDS,
        Kind,
        Plan,
        compare,
        registered_kinds,
    )
    from dammrl.study.coadaptation_report import write_report
    from dammrl.study.report import file_identity

    kinds = [Kind.of(path) for path in args.person] if args.person else registered_kinds()
    if len({k.key for k in kinds}) != len(kinds):
        from dammrl_core.errors import ConfigurationError

        raise ConfigurationError("two person files share a name (their file stem): rename one")
    plan = Plan(
        kinds=kinds,
        oracle_seeds=range(ORACLE_SEEDS.start, ORACLE_SEEDS.start + args.oracle_seeds),
        test_seeds=range(TEST_SEEDS.start, TEST_SEEDS.start + args.test_seeds),
        replicates=args.replicates,
        interpolated_replicates=args.interpolated,
        refine=RefineSettings(sim_reaches=args.sim_reaches, gate_seeds=args.gate_seeds),
    )
    update, close = progress_bar(plan.reaches(), "co-adaptation")
    try:
        results = compare(plan, args.jobs, progress=update, cache=args.cache)
    finally:
        close()
    rules = Path(__file__).parents[1] / "study" / "coadaptation.py"
    sha, commit = file_identity(rules)
    registration = (f"Rules and targets: `dammrl/study/coadaptation.py` (SHA-256 `{sha[:16]}`, "
                    f"last changed in {commit}), registered in docs/coadaptation/registration.md "
                    "before this run.")  # fmt: skip
    report = write_report(results, plan, args.out, registration)
    print(report.read_text())
    print(json.dumps({"report": str(report)}))
    return 0


def _gate_rates(args: argparse.Namespace) -> int:
    import numpy as np

    from dammrl.learning.adapt import deployment_rate
    from dammrl.study.stats import wilson

    rng = np.random.default_rng(0)
    gains = rng.normal(0.0, args.sd, 10_000)
    gains[rng.random(gains.size) < args.identical] = 0.0
    swing = rng.random(gains.size)
    gains[swing < args.swing] += 50.0
    gains[(swing >= args.swing) & (swing < 2 * args.swing)] -= 50.0
    print(f"gains: sd {args.sd:g} s, {args.identical:.0%} identical, {args.swing:.0%} each of "
          f"+-50 s; {args.gates} gates per figure (95 % Wilson intervals)")  # fmt: skip
    for seeds in args.gate_seeds:
        false = wilson(*deployment_rate(gains, 0.0, seeds, gates=args.gates))
        power = wilson(*deployment_rate(gains, args.margin_s, seeds, gates=args.gates, seed=1))
        print(f"{seeds} reaches: false positives {false.text(100, 1)} % (nominal 2.5 %), "
              f"power at {args.margin_s:g} s {power.text(100, 0)} %")  # fmt: skip
    return 0


def register_adapt(commands: Commands) -> None:
    """Add ``adapt``: per-person refinement from recordings."""
    adapt = commands.add_parser(
        "adapt",
        help="refine the policy for one person from their recorded sessions",
        description="Fine-tune the dual-agent DQN on a person's recorded reaches (conservative "
        "Q-learning) and on simulated reaches with a simulated person fitted to them, then "
        "judge the candidate against the policy in use on that fitted person: it is deployed "
        "only when the lower 95 % bound of its gain in time to success is above --min-gain-s. "
        "With --participant a deployed policy goes into their folder (their next `dammrl "
        "session run` loads it); a candidate not deployed stays in policy-candidates/.",
    )
    source = adapt.add_mutually_exclusive_group(required=True)
    source.add_argument("--recordings", type=Path, nargs="+", metavar="MCAP",
                        help="the person's recordings")  # fmt: skip
    source.add_argument(
        "--participant",
        metavar="ID",
        help="every recording of this participant's sessions under --root",
    )
    adapt.add_argument(
        "--root",
        type=Path,
        default=Path("sessions"),
        help="the sessions' folder (with --participant; default: sessions)",
    )
    adapt.add_argument("--from", dest="start", type=Path, default=Path("reward2"),
                       help="the policy to refine: a run, a .pt or a shipped policy "
                       "(default: reward2)")  # fmt: skip
    adapt.add_argument("--out", type=Path,
                       help="the candidate run's directory (default with --participant: the "
                       "next of their policy-candidates/)")  # fmt: skip
    adapt.add_argument(
        "--sim-reaches",
        type=_count(0, SIM_SEEDS_PER_SEED),
        default=100,
        metavar="N",
        help=f"simulated reaches with the fitted person (0-{SIM_SEEDS_PER_SEED}; default 100)",
    )
    adapt.add_argument("--updates", type=_count(1, 1_000_000), default=1000, metavar="N",
                       help="gradient steps (1-1000000; default 1000)")  # fmt: skip
    adapt.add_argument(
        "--conservative",
        type=_within(0.0, 100.0),
        default=1.0,
        metavar="ALPHA",
        help="weight of the conservative (CQL) term, 0-100; 0: plain DQN (default 1)",
    )
    adapt.add_argument("--seed", type=_count(0, 3), default=0,
                       help="seed of the refinement, 0-3; each has task seeds of its own for "
                       "the simulated reaches and the gate (default 0)")  # fmt: skip
    adapt.add_argument(
        "--gate-seeds",
        type=_count(10, GATE_SEEDS_PER_SEED),
        default=200,
        metavar="N",
        help="reaches of the fitted person per policy when the candidate is judged against "
        "the policy in use (10-5000; default 200: see `dammrl coadapt gate-rates`)",
    )
    adapt.add_argument(
        "--min-gain-s",
        type=_within(0.0, 60.0),
        default=0.0,
        metavar="S",
        help="deploy only when the gain's lower 95 %% bound in time to success exceeds this "
        "(0-60 s; default 0)",
    )
    adapt.add_argument("--json", action="store_true", help="one JSON object on stdout")
    adapt.set_defaults(handler=_adapt)


def _adapt(args: argparse.Namespace) -> int:
    from dammrl.learning.adapt import RefineSettings, describe, refine
    from dammrl.people.session import Participant
    from dammrl_core.errors import ConfigurationError

    recordings, out, in_use = args.recordings, args.out, args.start
    participant = None
    if args.participant is not None:
        participant = Participant(args.root, args.participant)
        recordings = sorted(participant.folder.glob("ses-*/recordings/*.mcap"))
        if not recordings:
            raise ConfigurationError(f"no recording of {participant.id} under {args.root}")
        in_use = participant.refined_policy() or args.start
        out = out or participant.next_candidate_folder()
    if out is None:
        raise ConfigurationError("--out is needed with --recordings")
    settings = RefineSettings(sim_reaches=args.sim_reaches, updates=args.updates,
                              conservative=args.conservative, seed=args.seed,
                              gate_seeds=args.gate_seeds, min_gain_s=args.min_gain_s)  # fmt: skip
    steps = settings.sim_reaches + settings.updates + 2 * settings.gate_seeds
    update, close = progress_bar(steps, "refinement and its gate", "step")
    try:
        refined, verdict = refine(list(recordings), in_use, out, settings, update)
    finally:
        close()
    deployed_to = None
    if participant is not None and verdict.deployed:
        deployed_to = participant.deploy_policy(refined.out)
    if args.json:
        print(json.dumps(describe(refined, verdict) | {"deployed_to": str(deployed_to or "")}))
        return 0
    fit = refined.fit
    print(f"{len(recordings)} recording(s): {fit.decisions} decisions of the person, "
          f"{fit.accuracy:.0%} toward the goal ({fit.accuracy_big:.0%} under E_big, "
          f"{fit.accuracy_small:.0%} under E_small), decision times "
          f"x{fit.decision_time_factor:.2f} the sub-models'; {refined.recorded} recorded and "
          f"{refined.simulated} simulated transitions")  # fmt: skip
    if not verdict.deployed:
        print(f"not deployed: the candidate ({refined.out}) is not better than the policy in use "
              f"({in_use}): {verdict.reason}; keep using {in_use}")  # fmt: skip
    elif deployed_to is not None:
        print(f"deployed to {deployed_to} (their next session loads it): {verdict.reason}")
    else:
        print(f"better than {in_use}: {verdict.reason}; load it with "
              f"DAMMRL_POLICY_CHECKPOINT={refined.out}")  # fmt: skip
    return 0
