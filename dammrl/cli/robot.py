"""``dammrl robot scan|jog|calibrate|emulate`` (the real arm) and ``dammrl stop``."""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dammrl.cli.common import (
    DEFAULT_CONNECT,
    Commands,
    add_bus_arguments,
    bus_settings,
    positive,
    print_err,
    print_out,
)
from dammrl.core.errors import DammrlError, Exit

if TYPE_CHECKING:
    from dammrl.arm import EmulatedArm
    from dammrl.stop import StopReport
    from services.robot.calibration import Calibration
    from services.robot.config import ArmSettings

PORT_HELP = "the servo bus's serial device, e.g. /dev/ttyUSB0 (default DAMMRL_ARM_PORT)"
CALIBRATION_HELP = "the arm's calibration file (default DAMMRL_ARM_CALIBRATION_FILE)"


def register(commands: Commands) -> None:
    """Add ``robot`` and its actions."""
    robot = commands.add_parser("robot", help="the real arm: scan, jog, calibrate, emulate")
    actions = robot.add_subparsers(required=True, metavar="ACTION")
    helptext = "serial ports, and the servos on a bus: ids, models, firmware"
    scan = actions.add_parser("scan", help=helptext, description=helptext)
    scan.add_argument("--port", help=PORT_HELP)
    scan.add_argument("--baud", type=int, default=1_000_000, help="bus speed (default 1 Mbaud)")
    scan.set_defaults(handler=_scan)
    _add_jog(actions)
    _add_calibrate(actions)
    _add_emulate(actions)


def register_stop(commands: Commands) -> None:
    """Add ``stop``."""
    helptext = "emergency stop: every arm on the bus holds where it is (or --release)"
    stop = commands.add_parser(
        "stop",
        help=helptext,
        description="Stop every arm service (sim or robot) within one control period: it "
        "holds where it is with low gains and gravity compensation (or turns the torque off, "
        "DAMMRL_ARM_STOP_ACTION=torque_off) and takes no command until released. Exit 0 "
        "once every arm on the bus confirmed, 1 otherwise.",
    )
    add_bus_arguments(stop, f"where the stack listens (default {DEFAULT_CONNECT})")
    stop.add_argument("--release", action="store_true",
                      help="release the stop: the arms hold until commands resume")  # fmt: skip
    stop.add_argument("--reason", default="", help="recorded with the stop")
    stop.add_argument("--timeout", type=positive, default=2.0,
                      help="seconds to wait for every arm to confirm")  # fmt: skip
    stop.add_argument("--console", action="store_true",
                      help="stay connected: Enter stops, 'release' releases, Ctrl-D quits "
                           "(a stop then costs no start-up)")  # fmt: skip
    stop.set_defaults(handler=_stop)


def _add_jog(actions: Commands) -> None:
    jog = actions.add_parser(
        "jog",
        help="move one joint slowly, inside its limits (checks its direction)",
        description="Torque on with the soft start, move one joint by --by radians along a "
        "smooth path at --speed, hold the others, report the measured motion. The arm "
        "stays holding at the end (its watchdog stops the servos once this exits).",
    )
    jog.add_argument("joint", type=int, choices=range(6), help="joint index, base = 0")
    jog.add_argument("--by", type=float, default=0.1, help="radians, signed (default 0.1)")
    jog.add_argument("--speed", type=positive, default=0.1, help="rad/s (default 0.1, max 0.3)")
    jog.add_argument("--port", help=PORT_HELP)
    jog.add_argument("--calibration", type=Path, help=CALIBRATION_HELP)
    jog.set_defaults(handler=_jog)


def _add_calibrate(actions: Commands) -> None:
    calibrate = actions.add_parser(
        "calibrate",
        help="guided: directions, zero offsets, comfortable limits; saves a calibration file",
        description="With the torque off, you move the arm by hand: each joint a little in "
        "its positive direction (finds the directions), then the whole arm to the reference "
        "posture (finds the zero offsets), then optionally each joint to the ends of the "
        "person's comfortable range (limits tighter than the URDF's).",
    )
    calibrate.add_argument("--port", help=PORT_HELP)
    calibrate.add_argument("--out", type=Path, default=Path("arm_calibration.json"),
                           help="where to save it (default arm_calibration.json)")  # fmt: skip
    calibrate.add_argument("--ids", default="1,2,3,4,5,6", help="servo ids, base first")
    calibrate.add_argument("--gear-ratios", default="1,1,1,1,1,1",
                           help="servo turns per joint turn, base first")  # fmt: skip
    calibrate.add_argument("--torque-per-amp", help="servo N m/A, base first (default: "
                           "the emulated arm's)")  # fmt: skip
    calibrate.add_argument("--button-id", type=int, default=100,
                           help="the button board's id, -1: none")  # fmt: skip
    calibrate.add_argument("--limits", action="store_true",
                           help="also record each joint's comfortable range")  # fmt: skip
    calibrate.set_defaults(handler=_calibrate)


def _add_emulate(actions: Commands) -> None:
    from services.robot.servo_chain import FAULT_HELP

    emulate = actions.add_parser(
        "emulate",
        help="the emulated arm on a pseudo-terminal (until Ctrl-C)",
        description="A Dynamixel Protocol 2.0 chain with the MuJoCo arm behind it, on a "
        "pseudo-terminal linked at --port, which the robot service opens like a USB "
        f"adapter. {FAULT_HELP}.",
    )
    emulate.add_argument(
        "--port", type=Path, default=Path("/tmp/ttyROBOT"),
        help="path the emulated bus appears at (default /tmp/ttyROBOT)",
    )  # fmt: skip
    emulate.add_argument(
        "--calibration",
        type=Path,
        help="the emulated arm's true calibration (default: the default)",
    )
    emulate.add_argument("--follow-goals", action="store_true",
                         help="place the button at each episode's goal, read from the stack's "
                              "bus (DAMMRL_BUS_*; set by `dammrl up --emulate-robot`)")  # fmt: skip
    emulate.set_defaults(handler=_emulate)


def _settings() -> ArmSettings:
    from services.robot.config import ArmSettings

    return ArmSettings()


def _calibration(path: Path | None) -> Calibration:
    from services.robot.calibration import Calibration, load_calibration

    path = path or _settings().calibration_file
    return Calibration() if path is None else load_calibration(path)


def _scan(args: argparse.Namespace) -> int:
    from dammrl.arm import MODEL_NAMES, scan, serial_ports

    ports = serial_ports()
    print_out("serial ports: " + (", ".join(ports) if ports else "none found"))
    port = args.port or _settings().port
    devices = scan(port, args.baud)
    if not devices:
        print_err(f"dammrl: no device answers on {port} at {args.baud} baud")
        return Exit.FAILED
    print_out(f"{len(devices)} devices on {port} at {args.baud} baud:")
    print_out(f"{'id':>4}  {'model':<12} {'number':>6}  firmware")
    for d in devices:
        name = MODEL_NAMES.get(d.model, "unknown")
        print_out(f"{d.servo_id:>4}  {name:<12} {d.model:>6}  {d.firmware}")
    return Exit.OK


def _jog(args: argparse.Namespace) -> int:
    from dammrl.arm import jog
    from services.robot.driver import DynamixelDriver

    settings = _settings()
    if args.speed > 0.3:
        raise DammrlError("--speed above 0.3 rad/s: jog is for checking, slowly")
    driver = DynamixelDriver(args.port or settings.port, _calibration(args.calibration),
                             settings.baud, settings.watchdog_s)  # fmt: skip
    moved = jog(driver, settings, args.joint, args.by, args.speed, print_err)
    same = np.sign(moved) == np.sign(args.by) and abs(moved) > 0.5 * abs(args.by)
    verdict = "direction as commanded" if same else "CHECK the direction and the offset"
    print_out(f"joint {args.joint}: commanded {args.by:+.3f} rad, measured {moved:+.3f} rad: "
              f"{verdict}")  # fmt: skip
    return Exit.OK if same else Exit.FAILED


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 6:
        raise DammrlError(f"{what}: six comma-separated numbers, base first (got {text!r})")
    return values


def _calibrate(args: argparse.Namespace) -> int:
    from dammrl.arm import guided_calibration
    from services.robot.calibration import Calibration, save_calibration

    constants = {}
    if args.torque_per_amp is not None:
        constants["torque_per_amp_nm"] = _floats(args.torque_per_amp, "--torque-per-amp")
    base = Calibration(
        ids=tuple(int(v) for v in _floats(args.ids, "--ids")),
        gear_ratios=_floats(args.gear_ratios, "--gear-ratios"),
        button_id=None if args.button_id < 0 else args.button_id,
        **constants,
    )
    port = args.port or _settings().port
    try:
        calibration = guided_calibration(port, base, args.limits, _ask, print_out)
    except (KeyboardInterrupt, EOFError):
        print_err("\ncalibration cancelled; nothing saved")
        return Exit.INTERRUPTED
    save_calibration(calibration, args.out)
    print_out(f"saved {args.out}\ncheck it:  dammrl robot jog 0 --by 0.1 --calibration "
              f"{args.out} --port {port}\nuse it:    DAMMRL_ARM_CALIBRATION_FILE="
              f"{args.out.resolve()} dammrl up --mode real --robot-port {port}")  # fmt: skip
    return Exit.OK


def _ask(prompt: str) -> None:
    input(f"{prompt} [Enter] ")


def _emulate(args: argparse.Namespace) -> int:
    """Serve the emulated arm; fault commands from stdin."""
    from dammrl.arm import emulated_arm
    from services.common.runtime import stop_on_signals

    stop = stop_on_signals()
    with emulated_arm(args.port, _calibration(args.calibration)) as arm:
        ids = ", ".join(str(i) for i in arm.chain.servos)
        print_err(f"emulated arm on {args.port} (devices {ids}); Ctrl-C stops")
        if not sys.stdin.isatty():
            threading.Thread(target=_faults, args=(arm, stop), daemon=True).start()
        if args.follow_goals:
            from services.common.config import BusSettings

            arm.follow_goals(BusSettings(), stop)
        stop.wait()
    return Exit.OK


def _faults(arm: EmulatedArm, stop: threading.Event) -> None:
    """Fault commands, one per line on stdin, until it closes."""
    from dammrl.arm import inject

    for line in sys.stdin:
        try:
            said = inject(arm, line)
        except DammrlError as exc:
            said = f"dammrl: {exc}"
        if said:
            print_err(said)
        if stop.is_set():
            return


def _stop(args: argparse.Namespace) -> int:
    from dammrl.stop import StopConsole

    console = StopConsole(bus_settings(args))
    try:
        if not args.console:
            return _say_stop(console.send(not args.release, args.reason, args.timeout),
                             "release" if args.release else "stop", args.timeout)  # fmt: skip
        print_err("stop console: Enter stops every arm, 'release' releases, Ctrl-D quits")
        for line in sys.stdin:
            release = line.strip() == "release"
            report = console.send(not release, args.reason or "from the stop console",
                                  args.timeout)  # fmt: skip
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
