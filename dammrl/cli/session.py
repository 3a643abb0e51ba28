"""Sessions with people: ``dammrl session run`` and ``list``; the catalogue's actions
(``dammrl/cli/catalogue.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from dammrl.cli.common import Commands, print_err, print_out
from dammrl_core.errors import Exit, UsageError

if TYPE_CHECKING:
    from dammrl.display import ParticipantDisplay

PROTOCOLS = Path(__file__).resolve().parent.parent / "protocols"
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
    """Add ``session run`` and ``session list``."""
    from dammrl.cli.catalogue import add_actions, add_root

    helptext = "sessions with people: a participant, a protocol of blocks and trials"
    session = commands.add_parser("session", aliases=["sessions"], help=helptext,
                                  description=helptext)  # fmt: skip
    actions = session.add_subparsers(required=True, metavar="ACTION")
    _add_run(actions)
    add_actions(actions)
    helptext = "the sessions under a folder, with their progress"
    listing = actions.add_parser("list", help=helptext, description=helptext)
    add_root(listing)
    listing.add_argument("--participant", help="only this participant's sessions")
    listing.set_defaults(handler=_list)


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
    run.add_argument("--mode", choices=["virtual", "semi-virtual"], default="virtual",
                     help="virtual: the simulated patient decides; semi-virtual: the person "
                          "at --port (the pad) or --stream (a wearable)")  # fmt: skip
    run.add_argument("--port", help="the pressure pad's serial device")
    run.add_argument("--stream", help="a wearable sensor's LSL stream")
    run.add_argument("--calibration", type=Path,
                     help="the participant's calibration (kept for later sessions)")  # fmt: skip
    run.add_argument("--operator", default="operator",
                     help="who runs the session (initials or a staff id), logged with "
                          "every action")  # fmt: skip
    run.add_argument("--bus-port", type=int, default=7447, help="the stack's loopback port")
    run.add_argument("--lockstep", action="store_true",
                     help="simulated human only: every service on the robot clock, faster "
                          "than real time")  # fmt: skip
    run.add_argument("--display-port", type=int, default=8080,
                     help="the participant display: http://THIS-MACHINE:PORT in a browser "
                          "(default 8080)")  # fmt: skip
    run.add_argument("--display-host", default="0.0.0.0",
                     help="the address the display listens on (default all: the display "
                          "may be another machine; 127.0.0.1: this one only)")  # fmt: skip
    run.add_argument("--no-display", action="store_true", help="no participant display")
    run.add_argument("--comfort-timeout", type=float, default=120.0, metavar="S",
                     help="how long the comfort question waits for an answer [s]")  # fmt: skip
    run.add_argument("--new", action="store_true",
                     help="start a new session even if the last one is unfinished")  # fmt: skip
    run.add_argument("--accept-changes", metavar="WHY",
                     help="resume although the set-up changed (logged, with why)")  # fmt: skip
    run.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from dammrl.session import SessionRunner, SetUp

    if args.mode == "semi-virtual" and (args.port is None) == (args.stream is None):
        raise UsageError("semi-virtual: give the person's device, --port (pad) or --stream")
    if args.mode == "virtual" and (args.port or args.stream):
        raise UsageError("--port/--stream: a person decides only in --mode semi-virtual")
    intent = "pad" if args.port else "lsl" if args.stream else "simulated"
    setup = SetUp(mode=args.mode, intent=intent, pad_port=args.port, stream=args.stream,
                  calibration=args.calibration, bus_port=args.bus_port,
                  lockstep=args.lockstep, operator=args.operator)  # fmt: skip
    runner = SessionRunner(args.root, args.participant, args.protocol, setup, say=print_err,
                           new=args.new, accept_changes=args.accept_changes,
                           comfort_timeout_s=args.comfort_timeout)  # fmt: skip
    if not args.no_display:  # once the participant and the protocol are known good
        runner.display = open_display(args.display_host, args.display_port, intent)
    try:
        return runner.run()
    finally:
        if runner.display is not None:
            runner.display.close()


DECIDE_WITH = {
    "pad": "Press the pad: firm for forward, light for back. Quick for big steps, held for "
    "small precise ones.",
    "lsl": "Close your hand for forward, open it for back. Briefly for big steps, held for "
    "small precise ones.",
    "simulated": "The simulated patient decides.",
}
"""The decision cue on the participant display, per intent source."""


def open_display(host: str, port: int, intent: str | None) -> ParticipantDisplay:
    """The participant display, its address said."""
    from dammrl.display import ParticipantDisplay
    from dammrl_core.robot import RobotSettings
    from dammrl_core.task import TaskSettings

    with_what = DECIDE_WITH.get(intent or "simulated", f"Forward or back? Use the {intent}.")
    display = ParticipantDisplay(RobotSettings().load(), TaskSettings(), host, port, with_what)
    where = "localhost" if host in ("0.0.0.0", "127.0.0.1") else host
    print_err(f"participant display: open http://{where}:{display.port} in a browser, full "
              "screen (F11)")  # fmt: skip
    return display


def _list(args: argparse.Namespace) -> int:
    from dammrl.cli.common import table_of_rows
    from dammrl.session import session_table

    rows = session_table(args.root, args.participant)
    if not rows:
        print_err(f"no sessions under {args.root}")
        return Exit.FAILED
    print_out(table_of_rows(rows))
    return Exit.OK
