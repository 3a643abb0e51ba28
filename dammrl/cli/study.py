"""``dammrl study``: the paper's comparison in one command."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from dammrl.cli.common import Commands, output_dir, print_err, progress_bar, seeds_arg
from dammrl.study.configs import CONDITIONS, DEFAULT_CONDITIONS

DEFAULT_SEEDS, DEFAULT_SETS = "120", 3  # 3 x 40 seeds: the default study in ~15 min on 2 cores


if TYPE_CHECKING:
    from dammrl.study.study import StudyOptions


def register(commands: Commands) -> None:
    """Add ``study`` and ``verdicts``."""
    _add_verdicts(commands)
    _add_study(commands)


def _add_verdicts(commands: Commands) -> None:
    verdicts = commands.add_parser(
        "verdicts",
        help="saved studies' verdicts side by side: which are findings",
        description="Set the verdicts of studies on disjoint seed ranges side by side (each "
        "study's verdicts.json, written by dammrl study): a verdict is a finding when it is "
        "the same on every range and stable within each.",
    )
    verdicts.add_argument("studies", type=Path, nargs="+", metavar="STUDY",
                          help="a study's folder (or its verdicts.json)")  # fmt: skip
    verdicts.add_argument("--results", type=Path, action="append", default=[], metavar="PAGE",
                          help="also regenerate this page's side-by-side section (the "
                          "ranges markers)")  # fmt: skip
    verdicts.set_defaults(handler=_verdicts)


def _add_study(commands: Commands) -> None:
    study = commands.add_parser(
        "study",
        help="the paper's comparison: every configuration, claims C1-C6, report",
        description="Run the paper's configurations, our variants and the reviewer's rows on "
        "disjoint sets of held-out seeds under each condition; judge claims C1-C6 on every set "
        "under both success criteria; write report.md, reaches.csv, the measured IK latencies "
        "and the figures into --out.",
    )
    _add_study_rows(study.add_argument_group("what runs"))
    _add_study_outputs(study.add_argument_group("where it runs and what it writes"))
    study.set_defaults(handler=_study)


def _add_study_rows(study: argparse._ArgumentGroup) -> None:
    """The seeds, conditions, rows and policies a study runs."""
    study.add_argument("--seeds", default=DEFAULT_SEEDS, metavar="N|A:B", type=seeds_arg,
                       help="every evaluation seed, split into --sets in order: N (the first N "
                       "from 7,000,000) or A:B (seeds A to B-1, all >= 7,000,000: training "
                       f"never uses them); default {DEFAULT_SEEDS}")  # fmt: skip
    study.add_argument("--sets", type=int, default=DEFAULT_SETS, metavar="K",
                       help="disjoint seed sets: every verdict is judged on each, and called "
                       f"unstable when they differ (default {DEFAULT_SETS})")  # fmt: skip
    study.add_argument("--tuning-seeds", type=int, default=None, metavar="N",
                       help="search the best fixed models on N tuning seeds (from 7,900,000; "
                       "never evaluated on; 1-10000). Default: the shipped search when it was "
                       "made with these settings, else one on as many tuning seeds as "
                       "evaluation seeds, at most 20")  # fmt: skip
    study.add_argument("--conditions", type=_conditions, default=None, metavar="A,B",
                       help="arm and IK timing, comma-separated from: " + ", ".join(CONDITIONS)
                       + " (default: " + ",".join(DEFAULT_CONDITIONS) + "; ikpy-real times "
                       "each solve as the reference machine did, ikpy-measured as this "
                       "computer does)")  # fmt: skip
    study.add_argument("--ik-latencies", type=Path, metavar="FILE",
                       help="replay a study's measured IK latencies (its ik_latencies.json.gz) "
                       "instead of measuring: the same reaches, byte for byte")  # fmt: skip
    study.add_argument("--reward1", type=Path, nargs="+", default=[], metavar="RUN",
                       help="Reward 1 runs or checkpoints (default: every shipped training seed of "
                       "Reward 1); several runs aggregate")  # fmt: skip
    study.add_argument(
        "--reward2",
        type=Path,
        nargs="+",
        default=[],
        metavar="RUN",
        help="Reward 2 runs or checkpoints (default: every shipped training seed of Reward 2)",
    )
    study.add_argument("--rows", choices=["all", "paper"], default="all",
                       help="all: the paper's configurations, our variants and the reviewer's "
                       "rows (default); paper: configurations 1-4 only, which every verdict "
                       "needs (a third of the reaches, no best-fixed search)")  # fmt: skip
    study.add_argument(
        "--adaptive",
        action="store_true",
        help="also configuration 4 inside the adaptive mode: each seed set as one "
        "session, re-selecting when DAMMRL_POLICY_TARGETS__* are missed",
    )


def _add_study_outputs(study: argparse._ArgumentGroup) -> None:
    """Where a study runs, and what it writes besides its report."""
    study.add_argument("--out", type=output_dir, default=Path("study"), help="report directory")
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
        action="append",
        default=[],
        metavar="PAGE",
        help="also regenerate this page's generated sections (docs/results.md, README.md; "
        "may be given more than once)",
    )


def _conditions(text: str) -> tuple[str, ...]:
    """Comma-separated names; StudyOptions.check refuses unknown ones in one line."""
    return tuple(c.strip() for c in text.split(",") if c.strip())


def _study(args: argparse.Namespace) -> int:
    from dammrl.study.report import SEARCH_FILE, update_page, write_report
    from dammrl.study.study import run_study

    options = _study_options(args)
    if len(args.seeds) < 20 * args.sets:
        print_err(
            f"note: {len(args.seeds) // args.sets} seeds per set: with a handful of reaches "
            "per training run, verdicts this small are a smoke test, not a finding"
        )
    closers = []

    def progress(total: int, description: str):  # type: ignore[no-untyped-def]
        update, close = progress_bar(total, description)
        closers.append(close)
        return update

    try:
        result = run_study(options, progress, (args.out / SEARCH_FILE,))
    finally:
        for close in closers:
            close()
    command = "dammrl " + shlex.join(sys.argv[1:])
    report = write_report(result, args.out, command, say=print_err)
    for page in args.results:
        kinds = update_page(page, result)
        print_err(f"{' and '.join(kinds)} section of {page} regenerated")
    for condition in options.conditions:
        for criterion in ("press", "eps_g"):
            claims = result.claims(condition, criterion)
            verdicts = [
                f"{c.key} {c.verdict}" + ("" if options.sets < 2 or result.stable(
                    condition, criterion, k) else " (unstable)")
                for k, c in enumerate(claims)
            ]  # fmt: skip
            print(f"{condition} ({criterion}): " + ", ".join(verdicts))
    print(f"report: {report}")
    return 0


def _study_options(args: argparse.Namespace) -> StudyOptions:
    """The study the command line asks for, every input checked before hours of reaches:
    a refusal is one line."""
    from dammrl.study.report import check_page
    from dammrl.study.study import TUNING_START, StudyOptions, load_latencies
    from dammrl_core.errors import UsageError
    from dammrl_core.policy.learned import resolve_run

    if args.jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {args.jobs}")
    if not 1 <= args.sets <= len(args.seeds):
        raise UsageError(f"--sets must be 1 to the number of seeds ({len(args.seeds)}), "
                         f"got {args.sets}")  # fmt: skip
    if args.tuning_seeds is not None and not 1 <= args.tuning_seeds <= 10_000:
        raise UsageError(f"--tuning-seeds must be 1 to 10000, got {args.tuning_seeds}")
    runs = {reward: [resolve_run(run) for run in getattr(args, reward)]
            for reward in ("reward1", "reward2")}  # fmt: skip
    for run in [*runs["reward1"], *runs["reward2"]]:
        if not run.exists():
            raise UsageError(f"no such run or checkpoint: {run}")
    if args.recording is not None:  # read it now: a bad file fails before the study runs
        from dammrl.stack.recording import session_traces

        if not args.recording.is_file():
            raise UsageError(f"no such recording: {args.recording}")
        session_traces(args.recording)
    for page in args.results:
        check_page(page)
    tuning = None
    if args.tuning_seeds is not None:
        tuning = range(TUNING_START, TUNING_START + args.tuning_seeds)
    options = StudyOptions(
        seeds=args.seeds,
        sets=args.sets,
        conditions=DEFAULT_CONDITIONS if args.conditions is None else args.conditions,
        ik_latencies=None if args.ik_latencies is None else load_latencies(args.ik_latencies),
        tuning_seeds=tuning,
        reward1=tuple(runs["reward1"]),
        reward2=tuple(runs["reward2"]),
        workers=args.jobs,
        ray=args.ray,
        recording=args.recording,
        adaptive=args.adaptive,
        rows=args.rows,
    )
    options.check()  # every refusal before the note, so a refusal is one line
    return options


def _verdicts(args: argparse.Namespace) -> int:
    from dammrl.study.report import RANGES, check_page, load_verdicts, side_by_side, update_ranges

    for page in args.results:
        check_page(page, (RANGES,))
    table = side_by_side([load_verdicts(path) for path in args.studies])
    for page in args.results:
        update_ranges(page, table)
        print_err(f"ranges section of {page} regenerated")
    print(table)
    return 0
