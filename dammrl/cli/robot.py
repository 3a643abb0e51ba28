"""``dammrl robot drivers|scan|jog|calibrate|emulate`` (the real arm, through its driver
plug-in)."""

from __future__ import annotations

import argparse
import json
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dammrl.cli.common import (
    Commands,
    output_file,
    positive,
    print_err,
    print_out,
)
from dammrl_core.errors import DammrlError, Exit, UsageError

if TYPE_CHECKING:
    from dammrl.devices.emulators.arm import EmulatedArm
    from dammrl_core.arm.driver import DriverPlugin
    from dammrl_core.settings import Settings

DRIVER_HELP = "the arm's driver (default DAMMRL_ARM_DRIVER; `dammrl robot drivers` lists them)"
SETTING_HELP = (
    "a setting of the driver, e.g. port=/dev/ttyUSB1 or ids=[1,2,3,4,5,6] (repeatable; the "
    "same as its environment variable, e.g. DAMMRL_DYNAMIXEL_PORT)"
)


def register(commands: Commands) -> None:
    """Add ``robot`` and its actions."""
    robot = commands.add_parser(
        "robot", help="the real arm: drivers, scan, jog, calibrate, emulate"
    )
    actions = robot.add_subparsers(required=True, metavar="ACTION")
    helptext = "the arm drivers installed (built-in and from packages)"
    drivers = actions.add_parser("drivers", help=helptext, description=helptext)
    drivers.set_defaults(handler=_drivers)
    helptext = "the devices on the arm's bus (ids, models, firmware)"
    scan = actions.add_parser("scan", help=helptext, description=helptext)
    _add_driver_arguments(scan)
    scan.set_defaults(handler=_scan)
    _add_jog(actions)
    _add_calibrate(actions)
    _add_emulate(actions)


def _add_driver_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--driver", help=DRIVER_HELP)
    parser.add_argument("-s", "--driver-setting", action="append", default=[],
                        metavar="NAME=VALUE", help=SETTING_HELP)  # fmt: skip
    parser.add_argument("--port", help="shorthand for -s port=PORT")


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
    _add_driver_arguments(jog)
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
    _add_driver_arguments(calibrate)
    calibrate.add_argument("--out", type=output_file(".json"), default=Path("arm_calibration.json"),
                           help="where to save it (default arm_calibration.json)")  # fmt: skip
    calibrate.add_argument("--limits", action="store_true",
                           help="also record each joint's comfortable range")  # fmt: skip
    calibrate.set_defaults(handler=_calibrate)


def _add_emulate(actions: Commands) -> None:
    from dammrl.devices.emulators.servo_chain import FAULT_HELP

    emulate = actions.add_parser(
        "emulate",
        help="the emulated arm on a pseudo-terminal (until Ctrl-C)",
        description="A Dynamixel Protocol 2.0 chain with the MuJoCo arm behind it, on a "
        "pseudo-terminal linked at --port, which the robot service opens like a USB "
        f"adapter; it runs at the arm loop's priority where allowed (it stands in for the "
        f"servos' own processors). {FAULT_HELP}.",
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


def _driver(args: argparse.Namespace) -> tuple[DriverPlugin, Settings]:
    """The driver plug-in and its settings: the environment's, with the command line's
    ``-s NAME=VALUE`` (JSON values where they parse, else strings) and ``--port``."""
    from dammrl_core.arm.driver import driver_plugin
    from dammrl_core.arm.settings import ArmSettings

    plugin = driver_plugin(args.driver or ArmSettings().driver)
    values: dict[str, object] = {}
    for item in args.driver_setting + ([f"port={args.port}"] if args.port else []):
        name, sep, value = item.partition("=")
        if not sep:
            raise UsageError(f"-s {item!r}: expected NAME=VALUE")
        try:
            values[name.strip()] = json.loads(value)
        except ValueError:
            values[name.strip()] = value
    return plugin, plugin.settings(**values)


def _drivers(args: argparse.Namespace) -> int:
    from dammrl_core.arm.driver import driver_plugins

    for name, origin in driver_plugins().items():
        print_out(f"{name:16s} {origin}")
    return Exit.OK


def _scan(args: argparse.Namespace) -> int:
    plugin, settings = _driver(args)
    devices = plugin.scan(settings)
    if not devices:
        print_err(f"dammrl: no device answers ({plugin.name}: {_brief(settings)})")
        return Exit.FAILED
    print_out(f"{len(devices)} devices ({plugin.name}: {_brief(settings)}):")
    for line in devices:
        print_out(f"  {line}")
    return Exit.OK


def _brief(settings: Settings) -> str:
    return ", ".join(f"{k}={v}" for k, v in settings.model_dump().items() if v is not None)


def _jog(args: argparse.Namespace) -> int:
    from dammrl_core.arm.jog import jog
    from dammrl_core.arm.settings import ArmSettings
    from dammrl_core.robot import RobotSettings

    if args.speed > 0.3:
        raise DammrlError("--speed above 0.3 rad/s: jog is for checking, slowly")
    plugin, settings = _driver(args)
    robot = RobotSettings().load()
    driver = plugin.create(settings)
    moved = jog(driver, robot, ArmSettings(), args.joint, args.by, args.speed, print_err)
    same = np.sign(moved) == np.sign(args.by) and abs(moved) > 0.5 * abs(args.by)
    verdict = "direction as commanded" if same else "CHECK the direction and the offset"
    print_out(f"joint {args.joint}: commanded {args.by:+.3f} rad, measured {moved:+.3f} rad: "
              f"{verdict}")  # fmt: skip
    return Exit.OK if same else Exit.FAILED


def _calibrate(args: argparse.Namespace) -> int:
    from dammrl_core.robot import RobotSettings

    plugin, settings = _driver(args)
    robot = RobotSettings().load()
    try:
        calibration = plugin.calibrate(settings, robot, args.limits, _ask, print_out)
    except (KeyboardInterrupt, EOFError):
        print_err("\ncalibration cancelled; nothing saved")
        return Exit.INTERRUPTED
    args.out.write_text(calibration.model_dump_json(indent=2) + "\n")
    print_out(f"saved {args.out}\ncheck it:  dammrl robot jog 0 --by 0.1 -s calibration_file="
              f"{args.out}\nuse it:    the driver's calibration setting, e.g. "
              f"DAMMRL_DYNAMIXEL_CALIBRATION_FILE={args.out.resolve()}")  # fmt: skip
    return Exit.OK


def _ask(prompt: str) -> None:
    input(f"{prompt} [Enter] ")


def _emulate(args: argparse.Namespace) -> int:
    """Serve the emulated arm; fault commands from stdin."""
    from dammrl.devices.emulators.arm import emulated_arm
    from dammrl_core.arm.dynamixel.calibration import Calibration, load_calibration
    from services.common.runtime import prioritise, stop_on_signals

    stop = stop_on_signals()
    prioritise(True)  # it stands in for the servos' own processors: a busy host is not theirs
    calibration = Calibration() if args.calibration is None else load_calibration(args.calibration)
    with emulated_arm(args.port, calibration) as arm:
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
    from dammrl.devices.emulators.arm import inject

    for line in sys.stdin:
        try:
            said = inject(arm, line)
        except DammrlError as exc:
            said = f"dammrl: {exc}"
        if said:
            print_err(said)
        if stop.is_set():
            return
