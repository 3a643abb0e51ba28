"""The Dynamixel arm's tools: find the servos on a bus, calibrate the arm moved by hand
(directions, zero offsets and, optionally, the person's comfortable range per joint)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dammrl_core.arm.dynamixel.calibration import Calibration
from dammrl_core.arm.dynamixel.driver import DynamixelDriver
from dammrl_core.errors import DammrlError
from dammrl_core.robot import RobotDescription


@dataclass(frozen=True)
class Device:
    servo_id: int
    model: int
    firmware: int


MODEL_NAMES = {1020: "XM430-W350", 1030: "XM430-W210", 1060: "XL430-W250", 0x4254: "button"}


def serial_ports() -> list[str]:
    """The serial devices of this machine (USB adapters first)."""
    from serial.tools import list_ports

    return sorted(p.device for p in list_ports.comports())


def scan(port: str, baud: int = 1_000_000) -> list[Device]:
    """Every device on the bus at ``port`` (a broadcast ping)."""
    import dynamixel_sdk as sdk

    handler = sdk.PortHandler(port)
    try:
        if not (handler.openPort() and handler.setBaudRate(baud)):
            raise DammrlError(f"cannot open {port} at {baud} baud")
    except OSError as exc:
        raise DammrlError(f"cannot open {port}: {exc}") from None
    try:
        found, result = sdk.PacketHandler(2.0).broadcastPing(handler)
    finally:
        handler.closePort()
    if result not in (sdk.COMM_SUCCESS, sdk.COMM_RX_TIMEOUT) and not found:
        raise DammrlError(f"ping on {port} failed (result {result})")
    return [Device(i, int(v[0]), int(v[1])) for i, v in sorted(found.items())]


def offsets_at_reference(servo_rad: np.ndarray, calibration: Calibration,
                         reference_q_rad: np.ndarray) -> tuple[float, ...]:  # fmt: skip
    """Zero offsets that make the servos' angles read as ``reference_q_rad``."""
    scale = np.asarray(calibration.directions) * np.asarray(calibration.gear_ratios)
    return tuple(float(v) for v in np.asarray(servo_rad) / scale - reference_q_rad)


def guided_calibration(
    port: str,
    base: Calibration,
    robot: RobotDescription,
    limits: bool,
    ask: Callable[[str], None],
    say: Callable[[str], None] = print,
) -> Calibration:
    """Directions and zero offsets (and, with ``limits``, each joint's comfortable range)
    of the arm on ``port``, moved by hand with the torque off. ``base`` gives the ids,
    gears, torque constants and the button; ``ask`` waits for the person."""
    identity = base.model_copy(update={"offsets_rad": (0.0,) * 6, "directions": (1,) * 6,
                                       "q_min_rad": None, "q_max_rad": None})  # fmt: skip
    driver = DynamixelDriver(port, identity)
    driver.connect(torque=False)
    try:
        read = driver.read_state  # servo angle / gear: the joint's up to direction and offset
        say("The torque is off: move the arm by hand.")
        directions = []
        for j, name in enumerate(robot.joint_names):
            ask(f"joint {j} ({name}): hold the arm still")
            before = float(read().q_rad[j])
            ask(f"move {name} about 10 deg in its positive direction, and hold")
            directions.append(direction_of(before, float(read().q_rad[j])))
        ask("put the arm in its reference posture (every joint at 0 rad) and hold")
        offsets = tuple(float(d * a) for d, a in zip(directions, read().q_rad, strict=True))
        found = base.model_copy(update={"directions": tuple(directions), "offsets_rad": offsets})
        say(f"directions {directions}, offsets {np.round(offsets, 4).tolist()} rad")
        if limits:
            found = _record_limits(found, driver, robot, ask)
    finally:
        driver.disconnect()
    return Calibration.model_validate(found.model_dump())  # checked as a whole


def _record_limits(calibration: Calibration, driver: DynamixelDriver, robot: RobotDescription,
                   ask: Callable[[str], None]) -> Calibration:  # fmt: skip
    """Each joint's comfortable range, inside the URDF's."""
    low, high = robot.q_min.copy(), robot.q_max.copy()
    for j, name in enumerate(robot.joint_names):
        ends = []
        for end in ("lower", "upper"):
            ask(f"move {name} to the {end} end of the person's comfortable range, and hold")
            q = calibration.to_rad(_ticks(driver))[j]
            ends.append(float(q))
        low[j] = max(low[j], min(ends))
        high[j] = min(high[j], max(ends))
    return calibration.model_copy(update={"q_min_rad": tuple(float(v) for v in low),
                                          "q_max_rad": tuple(float(v) for v in high)})  # fmt: skip


def _ticks(driver: DynamixelDriver) -> list[int]:
    """The servos' raw positions (through the driver's identity calibration)."""
    return driver.calibration.to_ticks(driver.read_state().q_rad)


def direction_of(before_rad: float, after_rad: float, min_motion_rad: float = 0.05) -> int:
    """+1 when the servo turned positive while the joint moved positive, else -1."""
    if abs(after_rad - before_rad) < min_motion_rad:
        raise DammrlError(
            f"the joint moved only {math.degrees(after_rad - before_rad):+.1f} deg: move it "
            f"at least {math.degrees(min_motion_rad):.0f} deg in its positive direction"
        )
    return 1 if after_rad > before_rad else -1
