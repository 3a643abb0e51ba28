"""``dammrl study``: the paper's comparison in one command."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from dammrl.cli.common import SEEDS_HELP, Commands, output_dir, print_err, progress_bar, seeds_arg

RANDOMIZE = {"both": (False, True), "off": (False,), "on": (True,)}


def register(commands: Commands) -> None:
    """Add ``study``."""
    study = commands.add_parser(
        "study",
        help="the paper's comparison: every configuration, claims C1-C6, report",
        description="Run the paper's four configurations and the reviewer's rows on held-out "
        "seeds; write report.md, reaches.csv and the figures into --out.",
    )
    study.add_argument("--out", type=output_dir, default=Path("study"), help="report directory")
    study.add_argument("--seeds", default="100", metavar="N|A:B", type=seeds_arg,
                       help=SEEDS_HELP)  # fmt: skip
    study.add_argument("--tuning-seeds", type=int, default=20, metavar="N",
                       help="seeds of the best-fixed search (from 7,900,000; never evaluated "
                       "on; default 20)")  # fmt: skip
    study.add_argument("--randomize", choices=sorted(RANDOMIZE), default="both",
                       help="domain randomisation (arm and sensor noise): both (default), "
                       "off or on")  # fmt: skip
    study.add_argument("--reward1", type=Path, nargs="+", default=[], metavar="RUN",
                       help="Reward 1 runs or checkpoints (default: the shipped policy reward1); "
                       "several runs aggregate")  # fmt: skip
    study.add_argument(
        "--reward2",
        type=Path,
        nargs="+",
        default=[],
        metavar="RUN",
        help="Reward 2 runs or checkpoints (default: the shipped policy reward2)",
    )
    study.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                       help="processes on this machine (default: every core)")  # fmt: skip
    study.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="run on a Ray cluster (no address: a local Ray instance)",
    )
    study.add_argument(
        "--recording",
        type=Path,
        metavar="MCAP",
        help="a semi-virtual session: its pressure/error figure in the report",
    )
    study.add_argument(
        "--results",
        type=Path,
        metavar="PAGE",
        help="also regenerate this page's results section (docs/results.md)",
    )
    study.add_argument(
        "--adaptive",
        action="store_true",
        help="also configuration 4 inside the adaptive mode: the seeds as one "
        "session, re-selecting when DAMMRL_POLICY_TARGETS__* are missed",
    )
    study.set_defaults(handler=_study)


def _study(args: argparse.Namespace) -> int:
    from dammrl.study.report import (
        check_results_page,
        results_section,
        update_results,
        write_report,
    )
    from dammrl.study.study import TUNING_START, StudyOptions, run_study
    from dammrl_core.errors import UsageError

    if args.jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {args.jobs}")
    if not 1 <= args.tuning_seeds <= 10_000:
        raise UsageError(f"--tuning-seeds must be 1 to 10000, got {args.tuning_seeds}")
    from dammrl_core.policy.learned import resolve_run

    args.reward1 = [resolve_run(run) for run in args.reward1]
    args.reward2 = [resolve_run(run) for run in args.reward2]
    for run in [*args.reward1, *args.reward2]:
        if not run.exists():
            raise UsageError(f"no such run or checkpoint: {run}")
    if args.recording is not None:  # read it now: a bad file fails before the study runs
        from dammrl.recording import session_traces

        if not args.recording.is_file():
            raise UsageError(f"no such recording: {args.recording}")
        session_traces(args.recording)
    if args.results is not None:
        check_results_page(args.results)  # before hours of reaches, not after
    options = StudyOptions(
        seeds=args.seeds,
        randomize=RANDOMIZE[args.randomize],
        tuning_seeds=range(TUNING_START, TUNING_START + args.tuning_seeds),
        reward1=tuple(args.reward1),
        reward2=tuple(args.reward2),
        workers=args.jobs,
        ray=args.ray,
        recording=args.recording,
        adaptive=args.adaptive,
    )
    closers = []

    def progress(total: int, description: str):  # type: ignore[no-untyped-def]
        update, close = progress_bar(total, description)
        closers.append(close)
        return update

    try:
        result = run_study(options, progress)
    finally:
        for close in closers:
            close()
    command = "dammrl " + shlex.join(sys.argv[1:])
    report = write_report(result, args.out, command, say=print_err)
    if args.results is not None:
        update_results(args.results, results_section(result, heading="##"))
        print_err(f"results section of {args.results} regenerated")
    for randomize, claims in result.claims.items():
        condition = "randomised" if randomize else "nominal"
        print(f"{condition}: " + ", ".join(f"{c.key} {c.verdict}" for c in claims))
    print(f"report: {report}")
    return 0
