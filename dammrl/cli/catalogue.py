"""The session catalogue from the command line: ``dammrl session catalogue`` (re)builds
it from the recordings, ``trials`` lists and filters, ``query`` asks it in SQL,
``report`` writes a participant's reports, ``bids`` exports the sessions as BIDS."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

from dammrl.cli.common import Commands, aligned, output_dir, print_err, print_out
from dammrl_core.errors import Exit


def add_actions(actions: Commands) -> None:
    """Add ``catalogue``, ``trials`` and ``query`` to ``dammrl session``."""
    helptext = "build the session catalogue afresh from the recordings (DuckDB and Parquet)"
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
        help="only this condition: a trigger (event, fixed) or a policy (learned, fixed)",
    )
    trials.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    trials.set_defaults(handler=_trials)

    helptext = (
        "ask the catalogue in SQL (read-only; tables participants, sessions, trials, "
        "comfort, actions)"
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
    report.add_argument("--participant", required=True, help="the participant's id")
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
        "--out", type=output_dir, required=True, help="the dataset's folder (replaced)"
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
    """Rebuild the catalogue first when a recording is newer (a session just run is in
    every answer without a step to remember)."""
    from dammrl.catalogue import stale

    if root.is_dir() and stale(root):
        print_err("the catalogue is older than the recordings: rebuilding it")
        _built(root, print_err)  # stdout is for the answer


def _build(args: argparse.Namespace) -> int:
    _built(args.root, print_out)
    return Exit.OK


def _built(root: Path, say: Callable[[str], None]) -> None:
    """Build the catalogue, say what it passed over (stderr) and what it holds (``say``)."""
    from dammrl.catalogue import build, query

    built = build(root)
    for why in built.passed_over[:10]:
        print_err(f"passed over {why}")
    if len(built.passed_over) > 10:
        print_err(f"... and {len(built.passed_over) - 10} more recordings passed over")
    counting = (
        "SELECT (SELECT count(*) FROM participants), (SELECT count(*) FROM sessions), "
        "(SELECT count(*) FROM trials WHERE final)"
    )
    participants, sessions, trials = query(root, counting)[1][0]
    say(
        f"catalogue: {participants} participants, {sessions} sessions, {trials} trials "
        f"-> {built.path}"
    )


def _trials(args: argparse.Namespace) -> int:
    from dammrl.catalogue import trials_of

    _fresh(args.root)
    names, rows = trials_of(args.root, args.participant, args.since, args.condition)
    return _show(names, rows, args.json)


def _query(args: argparse.Namespace) -> int:
    from dammrl.catalogue import query

    _fresh(args.root)
    names, rows = query(args.root, args.sql)
    return _show(names, rows, args.json)


def _report(args: argparse.Namespace) -> int:
    from dammrl.outcomes import participant_report, session_report
    from dammrl.session import check_participant

    participant = check_participant(args.participant)
    _fresh(args.root)
    if args.session:
        path = session_report(args.root, participant, args.session, args.out)
    else:
        path = participant_report(args.root, participant, args.out)
    print_out(f"report: {path} (and {path.with_suffix('.html').name})")
    return Exit.OK


def _bids(args: argparse.Namespace) -> int:
    from dammrl.bids import export

    _fresh(args.root)
    counts = export(args.root, args.out, args.author, args.license)
    print_out(
        f"BIDS: {counts['participants']} participants, {counts['sessions']} sessions, "
        f"{counts['runs']} runs -> {args.out}"
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
