"""``dammrl coadapt``: the model table the posterior over M_ij starts from, and the
oracle / shipped / adaptive comparison on simulated persons unlike the training human."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from dammrl.cli.common import Commands, output_dir, progress_bar


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
        help="run every M_ij on the nominal person; write the "
        "model table the posterior starts from",
    )
    table.add_argument("--out", type=Path, help="where (default: the packaged table)")
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
    from dammrl.study.coadaptation import TABLE_SEEDS, build_table
    from dammrl_core.coadaptation import MODELS, TABLE

    update, close = progress_bar(len(MODELS) * len(TABLE_SEEDS), "model table")
    try:
        table = build_table(workers=args.jobs, progress=update)
    finally:
        close()
    out = args.out or TABLE
    out.write_text(table.model_dump_json(indent=1) + "\n")
    print(f"model table of {len(MODELS)} models x {len(TABLE_SEEDS)} seeds: {out}")
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
    total = len(persons) * (len(MODELS) * len(oracle) + 2 * len(test) + 1)
    update, close = progress_bar(total, "co-adaptation")
    try:
        results = compare(persons, targets, args.jobs, oracle, test, update)
    finally:
        close()
    report = write_report(results, targets, args.out)
    print(report.read_text())
    print(json.dumps({"report": str(report)}))
    return 0
