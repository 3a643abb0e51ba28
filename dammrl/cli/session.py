"""Sessions with people: ``dammrl session run``, ``check``, ``withdraw`` and ``list``; the
catalogue's actions (``dammrl/cli/catalogue.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dammrl.cli.common import Commands, display_port, outcome_seconds, print_err, print_out
from dammrl.people.display.screens import OUTCOME_S
from dammrl_core.errors import Exit, UsageError
from dammrl_core.protocol import ProtocolError

if TYPE_CHECKING:
    from dammrl.people.display import ParticipantDisplay
    from dammrl.people.session import SetUp

PROTOCOLS = Path(__file__).resolve().parent.parent / "people" / "protocols"
"""The protocols shipped with dammrl, addressable by name."""


def protocol_file(text: str) -> Path:
    """A protocol file, or the name of a shipped one (``event-vs-fixed``)."""
    path = Path(text)
    if path.is_file():
        return path
    shipped = PROTOCOLS / f"{text}.yaml"
    if shipped.is_file():
        return shipped
    names = ", ".join(sorted(p.stem for p in PROTOCOLS.glob("*.yaml")))
    raise argparse.ArgumentTypeError(f"no protocol file {text!r} (shipped: {names})")


def register(commands: Commands) -> None:
    """Add ``session run``, ``check``, ``withdraw`` and ``list``."""
    from dammrl.cli.catalogue import add_actions, add_root

    helptext = "sessions with people: a participant, a protocol of blocks and trials"
    session = commands.add_parser("session", aliases=["sessions"], help=helptext,
                                  description=helptext)  # fmt: skip
    actions = session.add_subparsers(required=True, metavar="ACTION")
    _add_run(actions)
    _add_check(actions)
    _add_withdraw(actions)
    add_actions(actions)
    helptext = "the sessions under a folder, with their progress"
    listing = actions.add_parser("list", help=helptext, description=helptext)
    add_root(listing)
    listing.add_argument("--participant", help="only this participant's sessions")
    listing.set_defaults(handler=_list)


def _add_setup(parser: argparse.ArgumentParser) -> None:
    """What a session runs with: the options `session run` and `session check` share."""
    parser.add_argument("--mode", choices=["virtual", "semi-virtual"], default="virtual",
                        help="virtual: the simulated patient decides; semi-virtual: the "
                             "person at --port (the pad) or --stream (a wearable)")  # fmt: skip
    parser.add_argument("--port", help="the pressure pad's serial device")
    parser.add_argument("--stream", help="a wearable sensor's LSL stream")
    parser.add_argument("--calibration", type=Path,
                        help="the participant's calibration (kept for later sessions)")  # fmt: skip
    parser.add_argument("--lockstep", action="store_true",
                        help="simulated human only: every service on the robot clock, "
                             "faster than real time")  # fmt: skip


def _add_run(actions: Commands) -> None:
    helptext = (
        "run a participant's session of a protocol, or resume their unfinished one at its "
        "first unfinished trial (after any crash); one stack run per block"
    )
    run = actions.add_parser("run", help=helptext, description=helptext)
    run.add_argument("--participant", required=True,
                     help="a pseudonymous id such as P012 (no names are stored)")  # fmt: skip
    run.add_argument("--protocol", type=protocol_file, required=True,
                     help="a protocol file (YAML), or a shipped one: event-vs-fixed")  # fmt: skip
    run.add_argument("--root", type=Path, default=Path("sessions"),
                     help="where participants' folders are kept (default ./sessions)")  # fmt: skip
    _add_setup(run)
    run.add_argument("--rehearsal", action="store_true",
                     help="a rehearsal with the simulated patient (an id such as T001): it "
                          "takes no row of the enrolment ledger and runs the block order "
                          "the next participant will run")  # fmt: skip
    run.add_argument("--operator", default="operator",
                     help="who runs the session (initials or a staff id), logged with "
                          "every action")  # fmt: skip
    run.add_argument("--names", type=Path, metavar="FILE",
                     help="your participant registry, one name a line (read, never "
                          "copied): a reason typed at the console is stored without any "
                          "name in it")  # fmt: skip
    run.add_argument("--bus-port", type=int, default=7447, help="the stack's loopback port")
    run.add_argument("--display-port", type=display_port, default=8080,
                     help="the participant display: http://THIS-MACHINE:PORT in a browser "
                          "(default 8080)")  # fmt: skip
    run.add_argument("--display-host", default="0.0.0.0",
                     help="the address the display listens on (default all: the display "
                          "may be another machine; 127.0.0.1: this one only)")  # fmt: skip
    run.add_argument(
        "--display",
        action="store_true",
        help="serve the participant display (the default; as `up` spells it)",
    )
    run.add_argument("--no-display", action="store_true", help="no participant display")
    run.add_argument("--large-text", action="store_true",
                     help="larger words on the participant display (they fill about 70%% "
                          "of the screen instead of 58%%)")  # fmt: skip
    run.add_argument("--outcome-s", type=outcome_seconds, default=OUTCOME_S, metavar="S",
                     help=f"how long each reach's outcome stays on the display before the "
                          f"next reach begins [s] (0-30, default {OUTCOME_S:g})")  # fmt: skip
    run.add_argument("--comfort-timeout", type=float, default=120.0, metavar="S",
                     help="how long the comfort question waits for an answer [s] "
                          "(1-3600)")  # fmt: skip
    run.add_argument("--new", action="store_true",
                     help="start a new session even if the last one is unfinished")  # fmt: skip
    run.add_argument("--accept-changes", metavar="WHY",
                     help="resume although the set-up changed (logged, with why)")  # fmt: skip
    run.set_defaults(handler=_run)


def _add_check(actions: Commands) -> None:
    helptext = (
        "check a protocol completely, as `session run` does before it enrols anyone: its "
        "fields, the intent sources it names, its seeds, and each block's stack with the "
        "devices and calibration given (one line per problem)"
    )
    check = actions.add_parser("check", help=helptext, description=helptext)
    check.add_argument("protocol", type=protocol_file, metavar="PROTOCOL",
                       help="a protocol file (YAML), or a shipped one: event-vs-fixed")  # fmt: skip
    _add_setup(check)
    check.set_defaults(handler=_check)


def _add_withdraw(actions: Commands) -> None:
    helptext = (
        "record in the enrolment ledger that a participant withdrew (or was a rehearsal): "
        "their row stays used, so nobody else's order changes; their folder is kept"
    )
    withdraw = actions.add_parser("withdraw", help=helptext, description=helptext)
    withdraw.add_argument("--participant", required=True, help="their pseudonymous id")
    withdraw.add_argument("--why", required=True, help="the reason, for the ledger")
    withdraw.add_argument("--root", type=Path, default=Path("sessions"),
                          help="where participants' folders are kept (default "
                               "./sessions)")  # fmt: skip
    withdraw.set_defaults(handler=_withdraw)


def _setup(args: argparse.Namespace, **more: Any) -> SetUp:
    from dammrl.people.session import SetUp

    if args.mode == "semi-virtual" and (args.port is None) == (args.stream is None):
        raise UsageError("semi-virtual: give the person's device, --port (pad) or --stream")
    if args.mode == "virtual" and (args.port or args.stream):
        raise UsageError("--port/--stream: a person decides only in --mode semi-virtual")
    intent = "pad" if args.port else "lsl" if args.stream else "simulated"
    return SetUp(mode=args.mode, intent=intent, pad_port=args.port, stream=args.stream,
                 calibration=args.calibration, lockstep=args.lockstep, **more)  # fmt: skip


def _run(args: argparse.Namespace) -> int:
    from dammrl.people.console import Names
    from dammrl.people.session import SessionRunner

    if not 1.0 <= args.comfort_timeout <= 3600.0:
        raise UsageError(f"--comfort-timeout {args.comfort_timeout:g}: allowed 1 to 3600 s")
    if args.display and args.no_display:
        raise UsageError("--display and --no-display: give one of them")
    setup = _setup(args, bus_port=args.bus_port, operator=args.operator,
                   outcome_s=args.outcome_s, rehearsal=args.rehearsal,
                   names=None if args.names is None else Names.read(args.names))  # fmt: skip
    try:
        runner = SessionRunner(args.root, args.participant, args.protocol, setup,
                               say=print_err, new=args.new, accept_changes=args.accept_changes,
                               comfort_timeout_s=args.comfort_timeout)  # fmt: skip
        problems = runner.problems()
    except ProtocolError as exc:
        problems = list(exc.problems)
    if problems:  # before anyone is enrolled or the display opens
        return _problems(args.protocol, problems)
    if not args.no_display:
        runner.display = open_display(args.display_host, args.display_port, setup.intent,
                                      args.large_text)  # fmt: skip
    try:
        return runner.run()
    finally:
        if runner.display is not None:
            runner.display.close()


def _check(args: argparse.Namespace) -> int:
    from dammrl.people.session import session_problems
    from dammrl_core.protocol import load_protocol, plan_trials

    try:
        protocol = load_protocol(args.protocol)
    except ProtocolError as exc:
        return _problems(args.protocol, list(exc.problems))
    problems = session_problems(protocol, _setup(args), args.calibration)
    if problems:
        return _problems(args.protocol, problems)
    trials = len(plan_trials(protocol, 0))
    print_out(f"{args.protocol}: ok ({protocol.name} {protocol.version}: {len(protocol.blocks)} "
              f"blocks, {trials} trials, SHA-256 {protocol.sha256[:12]})")  # fmt: skip
    return Exit.OK


def _problems(protocol: Path, problems: list[str]) -> int:
    """Every problem on its own line; the exit code of a file that cannot be used."""
    count = "1 problem" if len(problems) == 1 else f"{len(problems)} problems"
    print_err(f"dammrl: error: protocol {protocol}: {count}")
    for problem in problems:
        print_err(f"  {problem}")
    return Exit.BAD_INPUT


def _withdraw(args: argparse.Namespace) -> int:
    from dammrl.people.enrolment import Ledger
    from dammrl.people.participants import check_participant

    participant = check_participant(args.participant)
    row = Ledger(args.root).withdraw(participant, args.why)
    print_err(f"{participant} withdrawn ({args.why}): row {row} stays used, nobody else's "
              f"order changes; their folder {args.root / participant} is kept")  # fmt: skip
    return Exit.OK


def open_display(host: str, port: int, intent: str | None, large_text: bool = False
                 ) -> ParticipantDisplay:  # fmt: skip
    """The participant display, its address said."""
    from dammrl.people.display import ParticipantDisplay, inputs_for
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings

    display = ParticipantDisplay(RobotSettings().load(), TaskSettings(), host, port,
                                 inputs_for(intent or "simulated"), large_text)  # fmt: skip
    print_err(f"participant display: open {display.url} in a browser, full screen (F11)")
    return display


def _list(args: argparse.Namespace) -> int:
    from dammrl.cli.common import table_of_rows
    from dammrl.people.session import session_table

    rows = session_table(args.root, args.participant)
    if not rows:
        print_err(f"no sessions under {args.root}")
        return Exit.FAILED
    print_out(table_of_rows(rows))
    return Exit.OK
