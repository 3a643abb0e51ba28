"""The session catalogue from the command line: ``dammrl session catalogue`` (re)builds
it from the recordings, ``trials`` lists and filters, ``query`` asks it in SQL,
``report`` writes a participant's reports, ``bids`` exports the sessions as BIDS."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from dammrl.cli.common import Commands, aligned, counted, output_dir, print_err, print_out
from dammrl_core.errors import Exit, UsageError

if TYPE_CHECKING:
    from dammrl.data.catalogue import Built

T = TypeVar("T")


def add_actions(actions: Commands) -> None:
    """Add ``catalogue``, ``trials`` and ``query`` to ``dammrl session``."""
    helptext = (
        "build the session catalogue afresh from the recordings (DuckDB and Parquet), "
        "checking each session's trial log against them"
    )
    build = actions.add_parser("catalogue", help=helptext, description=helptext)
    add_root(build)
    build.set_defaults(handler=_build)

    helptext = "every trial (its final attempt) from the catalogue, filtered"
    trials = actions.add_parser("trials", help=helptext, description=helptext)
    add_root(trials)
    trials.add_argument("--participant", help="only this participant's trials")
    trials.add_argument("--since", metavar="YYYY-MM-DD", help="only sessions from this day on")
    trials.add_argument(
        "--condition",
        metavar="NAME",
        help="only this condition: a trigger (event, fixed) or a policy (learned, fixed); "
        "its practice trials only with --practice",
    )
    trials.add_argument("--practice", action="store_true", help="a condition's practice trials too")
    trials.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    trials.set_defaults(handler=_trials)

    helptext = (
        "ask the catalogue in SQL (read-only, no file access; tables participants, "
        "sessions, trials, comfort, actions, completeness, recordings)"
    )
    ask = actions.add_parser("query", help=helptext, description=helptext)
    ask.add_argument("sql", help='e.g. "SELECT trigger, avg(t_total_s) FROM trials GROUP BY 1"')
    add_root(ask)
    ask.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    ask.set_defaults(handler=_query)
    _add_report(actions)
    _add_bids(actions)


def _add_report(actions: Commands) -> None:
    helptext = (
        "a participant's reports: across sessions (trends, test-retest reliability) "
        "and one per session (every trial, each block), Markdown and HTML"
    )
    report = actions.add_parser("report", help=helptext, description=helptext)
    who = report.add_mutually_exclusive_group(required=True)
    who.add_argument("--participant", help="the participant's id")
    who.add_argument("--all", action="store_true",
                     help="every participant's, with an index (index.md, index.html)")  # fmt: skip
    report.add_argument("--session", help="only this session's report (e.g. ses-02)")
    report.add_argument("--out", type=output_dir, required=True, help="the reports' folder")
    add_root(report)
    report.set_defaults(handler=_report)


def _add_bids(actions: Commands) -> None:
    helptext = (
        "export every session in the catalogue as a BIDS dataset (motion, events, "
        "the person's raw input), for the BIDS validator and the field's tools"
    )
    bids = actions.add_parser("bids", help=helptext, description=helptext)
    bids.add_argument(
        "--out",
        type=output_dir,
        required=True,
        help="the dataset's folder (an earlier export's files replaced, the lab's kept)",
    )
    bids.add_argument(
        "--author", action="append", default=[], help="an author of the dataset (repeat for each)"
    )
    bids.add_argument("--license", help="the dataset's licence, e.g. CC0 or CC-BY-4.0")
    add_root(bids)
    bids.set_defaults(handler=_bids)


def add_root(parser: argparse.ArgumentParser) -> None:
    """``--root``: the sessions' folder every catalogue action reads."""
    parser.add_argument(
        "--root",
        type=Path,
        default=Path("sessions"),
        help="the sessions' folder (default ./sessions)",
    )


def _fresh(root: Path) -> None:
    """Rebuild the catalogue first when it is missing, stale or damaged (a session just
    run is in every answer without a step to remember); one line says why."""
    from dammrl.data.catalogue import ensure

    if root.is_dir():
        built = ensure(root, print_err)
        if built is not None:
            _tell(root, built, print_err)  # stdout is for the answer


def _answer(root: Path, ask: Callable[[], T]) -> T:
    """``ask`` on a fresh catalogue; rebuilt once if it turns out damaged meanwhile."""
    from dammrl.data.catalogue import UnreadableCatalogueError, build

    _fresh(root)
    try:
        return ask()
    except UnreadableCatalogueError as exc:
        print_err(f"{exc}: rebuilding it")
        _tell(root, build(root, print_err), print_err)
        return ask()


def _build(args: argparse.Namespace) -> int:
    from dammrl.data.catalogue import build

    _tell(args.root, build(args.root, print_err), print_out)
    return Exit.OK


def _tell(root: Path, built: Built, say: Callable[[str], None]) -> None:
    """Say on stderr every recording passed over or used although damaged, and every
    trial of the logs missing or recorded in part; what the catalogue holds to ``say``."""
    from dammrl.data.catalogue import query

    for line in built.passed_over:
        print_err(f"passed over {line}")
    for line in built.damaged:
        print_err(f"used in part {line}")
    for line in built.incomplete:
        print_err(line)
    counting = (
        "SELECT (SELECT count(*) FROM participants), (SELECT count(*) FROM sessions), "
        "(SELECT count(*) FROM trials WHERE final), sum(reaches_logged), "
        "sum(recorded_whole), sum(recorded_in_part), sum(missing), sum(unlogged) FROM sessions"
    )
    participants, sessions, trials, *logged = query(root, counting)[1][0]
    say(
        f"catalogue: {counted(participants, 'participant')}, {counted(sessions, 'session')}, "
        f"{counted(trials, 'trial')} "
        f"-> {built.path}"
    )
    if logged[0] is not None:
        said = (
            f"data completeness: {logged[0]} reaches in the trial logs, {logged[1]} recorded whole"
        )
        said += f", {logged[2]} in part, {logged[3]} missing from the recordings"
        said += f"; {logged[4]} recorded reaches not in a log" if logged[4] else ""
        say(said)


def _trials(args: argparse.Namespace) -> int:
    from dammrl.data.catalogue import trials_of

    names, rows = _answer(args.root, lambda: trials_of(
        args.root, args.participant, args.since, args.condition, args.practice))  # fmt: skip
    return _show(names, rows, args.json)


def _query(args: argparse.Namespace) -> int:
    from dammrl.data.catalogue import query

    names, rows = _answer(args.root, lambda: query(args.root, args.sql))
    return _show(names, rows, args.json)


def _report(args: argparse.Namespace) -> int:
    from dammrl.data.outcomes import every_participant_report, participant_report, session_report
    from dammrl.people.session import check_participant

    if args.all:
        if args.session:
            raise UsageError("--session goes with --participant, not --all")
        path = _answer(args.root, lambda: every_participant_report(args.root, args.out))
    elif args.session:
        participant = check_participant(args.participant)
        path = _answer(args.root, lambda: session_report(args.root, participant, args.session,
                                                         args.out))  # fmt: skip
    else:
        participant = check_participant(args.participant)
        path = _answer(args.root, lambda: participant_report(args.root, participant, args.out))
    print_out(f"report: {path} (and {path.with_suffix('.html').name})")
    return Exit.OK


def _bids(args: argparse.Namespace) -> int:
    from dammrl.data.bids import export

    done = _answer(args.root, lambda: export(args.root, args.out, args.author, args.license))
    for line in done.kept.lines():
        print_err(line)
    if done.without_motion:
        print_err(f"{done.without_motion} reaches hold fewer than two of the arm's states: "
                  "no run of theirs (the catalogue's completeness says why)")  # fmt: skip
    print_out(
        f"BIDS: {counted(done.participants, 'participant')}, {counted(done.sessions, 'session')}, "
        f"{counted(done.runs, 'run')} -> {args.out}"
    )
    return Exit.OK


def _show(names: list[str], rows: list[tuple[object, ...]], as_json: bool) -> int:
    if as_json:
        for row in rows:
            print_out(json.dumps(dict(zip(names, row, strict=True)), default=str))
    elif rows:
        print_out(aligned(names, [["" if v is None else str(v) for v in row] for row in rows]))
    if not rows:
        print_err("no rows")
    return Exit.OK
