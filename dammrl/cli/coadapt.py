"""``dammrl coadapt``: the model table the posterior over M_ij starts from, and the
oracle / shipped / adaptive comparison on simulated persons unlike the training human."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from dammrl.cli.common import Commands, output_dir, output_file, progress_bar


def register(commands: Commands) -> None:
    """Add ``coadapt``."""
    coadapt = commands.add_parser(
        "coadapt",
        help="co-adaptation: the model table, and adaptive vs shipped vs oracle per person",
        description="The posterior over M_ij and the adaptive policy (S2's narrowing, S3's "
        "re-selection), measured on simulated persons unlike the training human.",
    )
    sub = coadapt.add_subparsers(required=True, metavar="ACTION")
    table = sub.add_parser(
        "table",
        help="run every option on a grid of persons; write the model table the posterior "
        "predicts every option from",
    )
    table.add_argument("--out", type=output_file(".gz"),
                       help="where (a .json.gz; default: the packaged table)")  # fmt: skip
    table.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes on this machine (default: every core)",
    )
    table.set_defaults(handler=_table)
    compare = sub.add_parser(
        "compare",
        help="oracle, shipped and adaptive policy for each kind of person; report.md, results.json",
    )
    compare.add_argument(
        "--out",
        type=output_dir,
        default=Path("coadaptation"),
        help="report directory (default: coadaptation)",
    )
    compare.add_argument(
        "--persons",
        nargs="+",
        metavar="KIND",
        help="kinds of person (default: all; see the report)",
    )
    compare.add_argument(
        "--test-seeds",
        type=int,
        default=40,
        metavar="N",
        help="test seeds (from 7,700,000; one adaptive session; default 40)",
    )
    compare.add_argument(
        "--oracle-seeds",
        type=int,
        default=20,
        metavar="N",
        help="seeds of the oracle's search (from 7,600,000; default 20)",
    )
    compare.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes on this machine (default: every core)",
    )
    compare.set_defaults(handler=_compare)


def _table(args: argparse.Namespace) -> int:
    from dammrl.study.coadaptation_table import TABLE_SEEDS, build_table, table_jobs
    from dammrl_core.model_table import OPTIONS, TABLE

    jobs = len(table_jobs())
    update, close = progress_bar(jobs, "model table")
    try:
        table = build_table(workers=args.jobs, progress=update)
    finally:
        close()
    out = args.out or TABLE
    out.write_bytes(table.dumps())
    models, seeds = len(OPTIONS) - 1, len(TABLE_SEEDS)
    print(f"model table, {models} models and the base policy on a grid of persons, {seeds} "
          f"seeds per person ({jobs} reaches): {out}")  # fmt: skip
    return 0


def _compare(args: argparse.Namespace) -> int:
    from dammrl.study.coadaptation import ORACLE_SEEDS, PERSONS, TEST_SEEDS, compare
    from dammrl.study.coadaptation_report import write_report
    from dammrl_core.coadaptation import MODELS
    from dammrl_core.errors import ConfigurationError
    from dammrl_core.policy.settings import PolicySettings

    persons = args.persons or list(PERSONS)
    if unknown := [p for p in persons if p not in PERSONS]:
        raise ConfigurationError(f"unknown person {unknown[0]!r}; one of: {', '.join(PERSONS)}")
    oracle = range(ORACLE_SEEDS.start, ORACLE_SEEDS.start + args.oracle_seeds)
    test = range(TEST_SEEDS.start, TEST_SEEDS.start + args.test_seeds)
    targets = PolicySettings().targets
    total = len(persons) * (len(MODELS) * len(oracle) + 2 * len(test) + 2)
    update, close = progress_bar(total, "co-adaptation")
    try:
        results = compare(persons, targets, args.out, args.jobs, oracle, test, progress=update)
    finally:
        close()
    report = write_report(results, targets, args.out)
    print(report.read_text())
    print(json.dumps({"report": str(report)}))
    return 0


def register_adapt(commands: Commands) -> None:
    """Add ``adapt``: per-person refinement from recordings."""
    adapt = commands.add_parser(
        "adapt",
        help="refine the policy for one person from their recorded sessions",
        description="Fine-tune the dual-agent DQN on a person's recorded reaches (conservative "
        "Q-learning) and on simulated reaches with a simulated person fitted to them. With "
        "--participant the refined policy goes into their folder, and their next "
        "`dammrl session run` loads it.",
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
                       help="the refined run's directory (default with --participant: their "
                       "policy folder)")  # fmt: skip
    adapt.add_argument(
        "--sim-reaches",
        type=int,
        default=100,
        metavar="N",
        help="simulated reaches with the fitted person (default 100)",
    )
    adapt.add_argument(
        "--updates", type=int, default=1000, metavar="N", help="gradient steps (default 1000)"
    )
    adapt.add_argument(
        "--conservative",
        type=float,
        default=1.0,
        metavar="ALPHA",
        help="weight of the conservative (CQL) term; 0: plain DQN (default 1)",
    )
    adapt.add_argument("--seed", type=int, default=0, help="seed of the refinement (default 0)")
    adapt.add_argument("--json", action="store_true", help="one JSON object on stdout")
    adapt.set_defaults(handler=_adapt)


def _adapt(args: argparse.Namespace) -> int:
    from dammrl.adapt import RefineSettings, describe, refine
    from dammrl.session import Participant
    from dammrl_core.errors import ConfigurationError

    recordings, out = args.recordings, args.out
    if args.participant is not None:
        participant = Participant(args.root, args.participant)
        recordings = sorted(participant.folder.glob("ses-*/recordings/*.mcap"))
        out = out or participant.policy_folder
        if not recordings:
            raise ConfigurationError(f"no recording of {participant.id} under {args.root}")
    if out is None:
        raise ConfigurationError("--out is needed with --recordings")
    settings = RefineSettings(sim_reaches=args.sim_reaches, updates=args.updates,
                              conservative=args.conservative, seed=args.seed)  # fmt: skip
    update, close = progress_bar(settings.sim_reaches + settings.updates, "refinement", "step")
    try:
        refined = refine(list(recordings), args.start, out, settings, update)
    finally:
        close()
    summary = describe(refined)
    if args.json:
        print(json.dumps(summary))
    else:
        fit = refined.fit
        print(f"{len(recordings)} recording(s): {fit.decisions} decisions of the person, "
              f"{fit.accuracy:.0%} toward the goal, decision times x{fit.decision_time_factor:.2f} "
              f"the sub-models'; {refined.recorded} recorded and {refined.simulated} simulated "
              f"transitions")  # fmt: skip
        print(
            f"refined policy: {refined.out} (load it with "
            f"DAMMRL_POLICY_CHECKPOINT={refined.out}, or let the participant's next session)"
        )
    return 0
