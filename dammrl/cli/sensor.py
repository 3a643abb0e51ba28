"""``dammrl sensor list|calibrate|monitor|emulate``: the pressure sensor (semi-virtual mode)."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

from dammrl.cli.common import (
    DEFAULT_CONNECT,
    Commands,
    add_bus_arguments,
    bus_settings,
    output_file,
    positive,
    print_err,
)
from dammrl_core.errors import DammrlError

if TYPE_CHECKING:
    from collections.abc import Callable

    from dammrl.devices.emulators.pad import SensorEmulator
    from dammrl.devices.emulators.patient import SimulatedPatient
    from dammrl_core.intent.pad.decoder import Calibration
    from services.common.bus import Bus
    from services.common.runs import RunCard

PORT_HELP = "serial device, e.g. /dev/ttyUSB0"


def register(commands: Commands) -> None:
    """Add ``sensor`` and its actions."""
    sensor = commands.add_parser("sensor", help="the pressure sensor (semi-virtual mode)")
    actions = sensor.add_subparsers(required=True, metavar="ACTION")
    listing = actions.add_parser("list", help="serial ports found, with descriptions")
    listing.set_defaults(handler=_list)
    _add_calibrate(actions)
    _add_monitor(actions)
    _add_emulate(actions)


def _add_calibrate(actions: Commands) -> None:
    calibrate = actions.add_parser(
        "calibrate",
        help="guided: rest, light press, firm press; saves a calibration file",
        description="Record the pad at rest, under a light and under a firm press, and save "
        "the calibration the intent service reads (DAMMRL_PAD_CALIBRATION_FILE).",
    )
    calibrate.add_argument("--port", required=True, help=PORT_HELP)
    calibrate.add_argument("--out", type=output_file(".json"),
                           default=Path("sensor_calibration.json"),
                           help="where to save it (default sensor_calibration.json)")  # fmt: skip
    calibrate.add_argument("--seconds", type=positive, default=3.0, help="recording per step [s]")
    calibrate.add_argument("--yes", action="store_true",
                           help="do not wait for Enter before each step (scripts)")  # fmt: skip
    calibrate.set_defaults(handler=_calibrate)


def _add_monitor(actions: Commands) -> None:
    monitor = actions.add_parser(
        "monitor", help="live pressure, decoded command and radius choice (until Ctrl-C)"
    )
    monitor.add_argument("--port", required=True, help=PORT_HELP)
    monitor.add_argument(
        "--calibration", type=Path, help="calibration file (default DAMMRL_PAD_CALIBRATION_FILE)"
    )
    monitor.add_argument("--seconds", type=positive, help="stop after this long")
    monitor.set_defaults(handler=_monitor)


def _add_emulate(actions: Commands) -> None:
    emulate = actions.add_parser(
        "emulate",
        help="a virtual sensor on a pseudo-terminal (until Ctrl-C)",
        description="A virtual pressure sensor: frames of the wire protocol on a "
        "pseudo-terminal linked at --link, which the stack opens like a real port; it runs "
        "at the arm loop's priority where allowed (it stands in for the pad's own "
        "microcontroller).",
    )
    emulate.add_argument("--link", type=Path, default=Path("/tmp/ttySENSOR"),
                         help="path the emulated port appears at")  # fmt: skip
    emulate.add_argument(
        "--pattern",
        choices=["taps", "keyboard", "patient"],
        default="taps",
        help="taps: a quick firm press every --period s; keyboard: you press keys; "
        "patient: a simulated patient answers the stack's decision requests",
    )
    emulate.add_argument(
        "--period", type=positive, default=1.0, help="taps: seconds between presses"
    )
    emulate.add_argument("--patient-model", type=int, choices=[1, 2], default=2,
                         help="patient: 1 hurried (quick presses, E_big), 2 careful (held, "
                         "E_small)")  # fmt: skip
    emulate.add_argument("--seed", type=int, default=0, help="patient's decisions, ADC noise")
    add_bus_arguments(
        emulate,
        "patient: the stack's endpoint (default: the local `dammrl up` "
        f"that reads this --link, else {DEFAULT_CONNECT})",
    )
    emulate.add_argument("--rate", type=positive, default=100.0, help="frames per second")
    emulate.add_argument("--seconds", type=positive, help="stop after this long")
    emulate.set_defaults(handler=_emulate)


def _list(args: argparse.Namespace) -> int:
    """Print the serial ports, or where a USB sensor would appear."""
    from serial.tools import list_ports

    ports = sorted(list_ports.comports(), key=lambda p: p.device)
    if not ports:
        print("no serial port found (a USB sensor appears as /dev/ttyUSB* or /dev/ttyACM*)")
    for port in ports:
        print(f"{port.device:20s} {port.description}  [{port.hwid}]")
    return 0


def _calibrate(args: argparse.Namespace) -> int:
    """Three guided recordings, then save the calibration; 130 if the person cancels."""
    from dammrl.devices.sensor import calibrate, quiet_reader
    from dammrl_core.intent.pad.serial import SerialSensor
    from dammrl_core.intent.pad.source import PadSettings

    quiet_reader()
    decoder = PadSettings().decoder  # the service's thresholds: the levels must suit them
    if not args.out.parent.is_dir():  # say so before the person does three recordings
        raise DammrlError(f"cannot save the calibration: {args.out.parent} is not a directory")

    def ready(step: str) -> None:
        print(f"\n{step}")
        if not args.yes:
            input(f"  Press Enter to start the {args.seconds:.0f} s recording... ")

    print(f"Calibrating the pressure sensor on {args.port}: three {args.seconds:.0f} s recordings.")
    try:
        with SerialSensor(args.port, reconnect_max_s=1.0) as sensor:
            calibration = calibrate(sensor, args.seconds, ready, _show, decoder=decoder)
    except (KeyboardInterrupt, EOFError):
        print("\ncalibration cancelled; nothing saved (--yes runs without Enter)")
        return 130
    args.out.write_text(calibration.model_dump_json(indent=2) + "\n")
    _say_saved(args, calibration)
    return 0


def _say_saved(args: argparse.Namespace, calibration: Calibration) -> None:
    """The saved levels, and the commands that check and use the file."""
    print(
        f"\nSaved {args.out}: rest {calibration.rest_raw:.0f} (noise +/-"
        f"{calibration.rest_noise_raw or 0:.0f}), light {calibration.light_raw:.0f},"
        f" firm {calibration.firm_raw:.0f} raw.\nCheck it:   dammrl sensor monitor --port "
        f"{args.port} --calibration {args.out}\nUse it:     DAMMRL_PAD_CALIBRATION_FILE="
        f"{args.out.resolve()} dammrl up --mode semi-virtual --port {args.port}"
    )


def _show(line: str) -> None:
    """A calibration progress line; on a terminal the recording line rewrites itself."""
    end = "\r" if line.startswith("  recording") else "\n"
    print(f"\x1b[2K{line}" if sys.stdout.isatty() else line, end=end, flush=True)


def _monitor(args: argparse.Namespace) -> int:
    """Live pressure, decoded command and radius choice, with the intent service's thresholds."""
    from dammrl.devices.sensor import Monitor, quiet_reader, wait_for_frames
    from dammrl_core.intent.pad.calibration import load_calibration
    from dammrl_core.intent.pad.decoder import PressDecoder
    from dammrl_core.intent.pad.serial import SerialSensor
    from dammrl_core.intent.pad.source import PadSettings
    from dammrl_core.models import ModelSet
    from services.common.runtime import stop_on_signals

    quiet_reader()
    settings = PadSettings()  # the intent service's pad settings: the same thresholds
    calibration = load_calibration(args.calibration or settings.calibration_file)
    stop = stop_on_signals()
    with SerialSensor(args.port, reconnect_max_s=1.0) as sensor:
        wait_for_frames(sensor)
        stop_after(stop, args.seconds)
        Monitor(sensor, PressDecoder(calibration, settings.decoder), ModelSet()).run(stop)
    return 0


def _emulate(args: argparse.Namespace) -> int:
    """Serve frames on a pseudo-terminal: taps, keys pressed, or a simulated patient."""
    from dammrl.devices.emulators.pad import Press, SensorEmulator
    from dammrl.devices.sensor import KEYS, keyboard
    from services.common.runtime import prioritise, stop_on_signals

    if args.pattern == "keyboard" and not sys.stdin.isatty():
        raise DammrlError("the keyboard pattern needs a terminal (run it in its own tmux pane)")
    stop = stop_on_signals()
    prioritise(True)  # it stands in for the pad's own microcontroller: a busy host is not its
    stop_after(stop, args.seconds)
    script = [Press(0.2, 0.2, 1.0)] if args.pattern == "taps" else []
    loop_s = args.period if args.pattern == "taps" else None
    with SensorEmulator(args.link, script, loop_s=loop_s, seed=args.seed, rate_hz=args.rate) as pad:
        print(f"emulated sensor on {args.link} ({args.rate:.0f} frames/s); Ctrl-C stops")
        if args.pattern == "taps":
            print(f"a quick firm press (+1, E_big) every {args.period} s")
            stop.wait()
        elif args.pattern == "keyboard":
            print(KEYS, flush=True)
            keyboard(pad, stop)
        else:
            _patient(args, pad, stop)
        print(f"\nsent {pad.sent} frames")
    return 0


def stop_after(stop: threading.Event, seconds: float | None) -> None:
    """Set ``stop`` after ``seconds`` [s] (never if None), from a daemon timer."""
    if seconds is not None:
        timer = threading.Timer(seconds, stop.set)
        timer.daemon = True
        timer.start()


def _patient(args: argparse.Namespace, pad: SensorEmulator, stop: threading.Event) -> None:
    """A simulated patient pressing the emulated pad to answer the stack's requests. It
    may start before the stack: until a stack lets it in it says so once and tries again.
    Without --connect or --bus-port it joins the local `dammrl up` that reads this pad
    (``--port`` the same device), whatever its port, once it runs; it rejoins a stack that
    went away and came back."""
    from dammrl.devices.emulators.patient import SimulatedPatient
    from services.common.runs import run_reading

    patient = SimulatedPatient(pad, args.patient_model, seed=args.seed)
    kind = "hurried: quick presses, E_big" if args.patient_model == 1 else "careful: held, E_small"
    print(f"simulated patient (M_{args.patient_model}, {kind}) answering decision requests")
    said = False
    while not stop.is_set():
        said = answer_while_joined(args, patient, stop, said, lambda: run_reading(args.link))
    print(f"answered {patient.answered} requests")


def answer_while_joined(
    args: argparse.Namespace,
    patient: SimulatedPatient,
    stop: threading.Event,
    said: bool,
    beside: Callable[[], RunCard | None],
) -> bool:
    """One session: answer requests while it reaches a stack (the flags', else the run
    ``beside`` finds, else the default endpoint); whether the patient has said it is
    alone."""
    from services.common.bus import JOIN_S, Bus, linked, not_joined_line

    settings = bus_settings(args, beside=beside)  # the run may have come up meanwhile
    with Bus(settings, "patient") as bus:
        deadline = time.monotonic() + JOIN_S
        while not linked(bus.session) and time.monotonic() < deadline and not stop.is_set():
            stop.wait(0.1)
        if not linked(bus.session):
            if not said and not stop.is_set():
                print_err(not_joined_line(settings) + "; still trying (a `dammrl up` that "
                          "reads this input is joined, whatever its port)")  # fmt: skip
            return True
        print_err(f"joined the stack at {', '.join(settings.connect)}")
        session = threading.Event()  # ends when the patient stops or the stack is gone
        watcher = threading.Thread(target=_watch_link, args=(bus, stop, session), daemon=True)
        watcher.start()
        patient.run(bus, session)
        if not stop.is_set():
            print_err("the stack went away: waiting for it to come back")
    return False


def _watch_link(bus: Bus, stop: threading.Event, session: threading.Event) -> None:
    """Set ``session`` when ``stop`` is set or the bus reached no stack for JOIN_S."""
    from services.common.bus import JOIN_S, linked

    alone_since: float | None = None
    while not stop.wait(0.2):
        if linked(bus.session):
            alone_since = None
        elif alone_since is None:
            alone_since = time.monotonic()
        elif time.monotonic() - alone_since > JOIN_S:
            break
    session.set()
