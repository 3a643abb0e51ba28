"""The service stack on the bus: ``dammrl up``, ``status``, ``echo`` and ``schemas``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from dammrl.cli.common import (
    CONNECT_HELP,
    Commands,
    add_bus_arguments,
    add_credentials,
    bus_settings,
    display_port,
    model_arg,
    outcome_seconds,
    output_dir,
    print_err,
    print_out,
)
from dammrl.people.display.screens import OUTCOME_S
from dammrl_core.errors import Exit, UsageError
from schemas import DEFAULT_NAMESPACE, TOPICS

LOCKSTEP_HELP = (
    "run on the robot clock: each state is answered before the next physics step and each "
    "decision before it is due (deterministic, the in-process runner's exact twin; faster "
    "than real time; simulation only)"
)


def register(commands: Commands) -> None:
    """Add ``up``, ``status`` and ``echo``."""
    _add_up(commands)
    helptext = "services alive on the bus, their health and rates"
    status = commands.add_parser("status", help=helptext, description=helptext)
    add_bus_arguments(status, CONNECT_HELP)
    status.set_defaults(handler=_status)
    helptext = "print the decoded messages of one topic"
    echo = commands.add_parser("echo", help=helptext, description=helptext)
    add_bus_arguments(echo, CONNECT_HELP)
    echo.add_argument("topic", help="e.g. robot/state, task/result, health/*")
    echo.add_argument("--hz", action="store_true", help="print the rate instead")
    echo.add_argument("--count", type=int, help="stop after this many messages")
    echo.add_argument("--duration", type=float, help="stop after this many seconds")
    echo.set_defaults(handler=_echo)


def register_schemas(commands: Commands) -> None:
    """Add ``schemas`` (last in ``dammrl --help``, hence apart from ``register``)."""
    schemas = commands.add_parser("schemas", help="write the JSON Schema of every message")
    schemas.add_argument("--out", type=output_dir, required=True, metavar="DIR",
                         help="where the JSON Schemas are written")  # fmt: skip
    schemas.set_defaults(handler=_schemas)


def _add_up(commands: Commands) -> None:
    up = commands.add_parser(
        "up",
        help="launch the service stack of a mode",
        description="Start the services as processes on the bus; Ctrl-C stops them all.",
    )
    up.add_argument("--mode", choices=["virtual", "semi-virtual", "real"], default="virtual",
                    help="virtual: simulated human and arm; semi-virtual: a person at a "
                         "sensor (--port, --stream), simulated arm; real: the arm on a servo "
                         "bus (--robot-port), the human "
                         "simulated or at the sensor (--port)")  # fmt: skip
    up.add_argument(
        "--episodes", type=int, help="run this many episodes, then stop (default: until Ctrl-C)"
    )
    up.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    up.add_argument("--model", type=model_arg, metavar="I,J",
                    help="a fixed M_ij (default: the learned DAMMRL policy)")  # fmt: skip
    up.add_argument("--trigger", choices=["event", "fixed"], default="event",
                    help="progression: event-triggered (default) or fixed-frequency")  # fmt: skip
    up.add_argument("--lockstep", action="store_true", help=LOCKSTEP_HELP)
    up.add_argument("--port", help="semi-virtual (or real): the pressure sensor's serial device")
    up.add_argument("--robot-port", help="real: the servo bus's serial device")
    up.add_argument("--robot-calibration", type=Path,
                    help="real: the arm's file from `dammrl robot calibrate`")  # fmt: skip
    up.add_argument("--emulate-robot", action="store_true",
                    help="real: serve the emulated arm at --robot-port (no hardware)")  # fmt: skip
    up.add_argument("--intent", metavar="SOURCE",
                    help="who decides: simulated, pad (--port), lsl (--stream) or an installed "
                    "source (`dammrl intent sources`); default from --port/--stream")  # fmt: skip
    up.add_argument("--stream", help="semi-virtual (or real): a wearable sensor's LSL stream "
                    "(its classifier from --calibration)")  # fmt: skip
    up.add_argument("--calibration", type=Path,
                    help="the person's file: `dammrl sensor calibrate` (the pad) or `dammrl "
                    "intent calibrate` (a wearable)")  # fmt: skip
    up.add_argument(
        "--bus-port", type=int, default=7447, help="loopback port of the stack's endpoint"
    )
    up.add_argument("--namespace", default=DEFAULT_NAMESPACE,
                    help=f"the stack's key prefix (default {DEFAULT_NAMESPACE})")  # fmt: skip
    add_credentials(up)
    up.add_argument("--insecure", action="store_true",
                    help="plain tcp on loopback: any local process can join (default: this "
                         "run's own credentials, found by status/echo)")  # fmt: skip
    up.add_argument("--json", action="store_true", help="one JSON object per episode")
    up.add_argument("--record", type=Path, metavar="MCAP",
                    help="also run the recorder into this new file, in a folder that exists "
                         "(after a recorder restart: NAME-001.mcap, ...)")  # fmt: skip
    up.add_argument("--display", type=display_port, nargs="?", const=8080, metavar="PORT",
                    help="serve the participant display at http://THIS-MACHINE:PORT "
                         "(default 8080)")  # fmt: skip
    up.add_argument("--display-port", type=display_port, dest="display", metavar="PORT",
                    help="the same as --display PORT (as `session run` spells it)")  # fmt: skip
    up.add_argument("--large-text", action="store_true",
                    help="with --display: larger words on the participant display (they "
                         "fill about 70%% of the screen instead of 58%%)")  # fmt: skip
    up.add_argument("--outcome-s", type=outcome_seconds, metavar="S",
                    help=f"with --display: how long each reach's outcome stays on the "
                         f"display before the next reach begins [s] (0-30, default "
                         f"{OUTCOME_S:g})")  # fmt: skip
    up.set_defaults(handler=_up)


def _up(args: argparse.Namespace) -> int:
    """Launch the stack; runs until the episodes are done, a signal, or a dead service."""
    from dammrl.stack.launch import Stack
    from dammrl.stack.options import StackOptions, check_options

    if args.display is None and (args.large_text or args.outcome_s is not None):
        raise UsageError("--large-text and --outcome-s are the participant display's: "
                         "give --display with them")  # fmt: skip
    outcome_s = OUTCOME_S if args.outcome_s is None else args.outcome_s
    options = StackOptions(
        mode=args.mode, episodes=args.episodes, seed=args.seed, model=args.model,
        trigger=args.trigger, port=args.bus_port, namespace=args.namespace, json=args.json,
        pad_port=args.port, lsl_stream=args.stream, intent=args.intent,
        calibration=args.calibration,
        record=args.record,
        lockstep=args.lockstep, credentials=args.credentials, insecure=args.insecure,
        robot_port=args.robot_port, robot_calibration=args.robot_calibration,
        emulate_robot=args.emulate_robot,
        outcome_hold_s=0.0 if args.display is None else outcome_s,  # the page shows it
    )  # fmt: skip
    check_options(options)  # before anything starts, the display's server included
    if args.display is None:
        return Stack(options, out=print_out, info=print_err).run()
    from dammrl.cli.session import open_display
    from dammrl.people.display import BusFeed
    from services.common.security import DISPLAY

    intent = args.intent or ("pad" if args.port else "lsl" if args.stream else "simulated")
    display = open_display("0.0.0.0", args.display, intent, args.large_text)
    try:
        feed = BusFeed(display, args.namespace)
        stack = Stack(options, out=print_out, info=print_err,
                      on_up=lambda hub: feed.attach(stack.join(DISPLAY)))  # fmt: skip
        return stack.run()
    finally:
        display.close()


def _status(args: argparse.Namespace) -> int:
    """Print the services on the bus; exit 1 unless every one is alive and reporting."""
    from dammrl.stack.inspect import status

    table, healthy = status(bus_settings(args))
    print_out(table)
    return Exit.OK if healthy else Exit.FAILED


def _echo(args: argparse.Namespace) -> int:
    """Print one topic's messages (or its rate) until a count, a duration or Ctrl-C; exit 1
    if nothing arrived."""
    from dammrl.cli.common import bus_settings_found_later
    from dammrl.stack.inspect import echo

    seen = echo(bus_settings(args), args.topic, args.hz, args.count, args.duration, print_out,
                say=print_err, found_later=bus_settings_found_later(args))  # fmt: skip
    if seen == 0:
        print_err(f"dammrl: nothing received on {args.topic}")
    return Exit.OK if seen else Exit.FAILED


def _schemas(args: argparse.Namespace) -> int:
    """Write ``<Type>.json`` per message type, tagged with its topic."""
    args.out.mkdir(parents=True, exist_ok=True)
    for topic, message_type in TOPICS.items():
        path = args.out / f"{message_type.__name__}.json"
        schema = message_type.model_json_schema() | {"x-dammrl-topic": topic}
        path.write_text(json.dumps(schema, indent=2) + "\n")
        print(f"{topic:16s} -> {path}")
    return 0
