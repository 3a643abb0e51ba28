"""``dammrl stop``: the emergency stop from a terminal.

A stop must not wait for Python: this module, and what ``dammrl stop`` loads with it,
imports the bus and the messages only (no MuJoCo, torch, pinocchio or SciPy, none of the
other commands); ``dammrl.cli.main`` builds this command's parser alone.
"""

from __future__ import annotations

import argparse
import sys

from dammrl.cli.common import (
    CONNECT_HELP,
    Commands,
    add_bus_arguments,
    bus_settings,
    positive,
    print_err,
    print_out,
)
from dammrl.stack.stop import StopConsole, StopReport
from dammrl_core.errors import Exit


def register(commands: Commands) -> None:
    """Add ``stop``."""
    helptext = "emergency stop: every arm on the bus holds where it is (or --release)"
    stop = commands.add_parser(
        "stop",
        help=helptext,
        description="Stop every arm service (sim or robot) within one control period: it "
        "holds where it is with low gains and gravity compensation (or turns the torque off, "
        "DAMMRL_ARM_STOP_ACTION=torque_off) and takes no command until released. Exit 0 "
        "once every arm on the bus confirmed, 1 otherwise. Where allowed (root or "
        "CAP_SYS_NICE) it runs at the arm loop's priority, ahead of whatever keeps the PC busy.",
    )
    add_bus_arguments(stop, CONNECT_HELP)
    stop.add_argument("--release", action="store_true",
                      help="release the stop: the arms hold until commands resume")  # fmt: skip
    stop.add_argument("--reason", default="", help="recorded with the stop")
    stop.add_argument("--timeout", type=positive, default=2.0,
                      help="seconds to wait for every arm to confirm")  # fmt: skip
    stop.add_argument("--console", action="store_true",
                      help="stay connected: Enter stops, 'release' releases, Ctrl-D quits "
                           "(a stop then costs no start-up)")  # fmt: skip
    stop.set_defaults(handler=_stop)


def _stop(args: argparse.Namespace) -> int:
    console = StopConsole(bus_settings(args))
    try:
        if not args.console:
            return _say_stop(console.send(not args.release, args.reason, args.timeout),
                             "release" if args.release else "stop", args.timeout)  # fmt: skip
        print_err("stop console: Enter stops every arm, 'release' releases, Ctrl-D quits")
        for line in sys.stdin:
            release = line.strip() == "release"
            reason = args.reason or "from the stop console"
            report = console.send(not release, reason, args.timeout)
            if not report.acknowledged:  # the run may be a new one (a session's next block:
                # new credentials on the same port), which this session cannot reach
                print_err("stop console: no arm heard it: joining the run on the bus again")
                console.close()
                console = StopConsole(bus_settings(args))
                report = console.send(not release, reason, args.timeout)
            _say_stop(report, "release" if release else "stop", args.timeout)
        return Exit.OK
    finally:
        console.close()


def _say_stop(report: StopReport, what: str, timeout_s: float) -> int:
    for service, seconds in sorted(report.acknowledged.items()):
        print_out(f"{service}: {what} confirmed after {seconds * 1000:.0f} ms")
    for service in report.silent:
        print_err(f"dammrl: {service} did not confirm the {what} within {timeout_s:.1f} s")
    if not report.acknowledged:
        print_err(f"dammrl: no arm confirmed the {what}: is a stack running (dammrl status)?")
    return Exit.OK if report.acknowledged and not report.silent else Exit.FAILED
