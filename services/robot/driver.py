"""The robot service's hardware interface: a driver connects, reads the arm's state,
writes joint commands and disconnects (a context manager), in the style of LeRobot's
``Robot``. Backends register by name; settings choose one.

The Dynamixel backend (Protocol 2.0, the official dynamixel-sdk) runs the servos in
position mode: each servo's own PID holds q_ref at its internal rate, the driver writes
goals by group sync write and reads position, velocity and current by one group sync
read. Joint angles go through the arm's calibration (servo ids, zero offsets,
directions). The servo's bus watchdog is armed on connect, so the servos stop by
themselves if this process dies.
"""

from __future__ import annotations

import contextlib
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol

import numpy as np

from dammrl.core.errors import DammrlError

TICKS_PER_RAD = 4096 / (2 * math.pi)
CENTRE_TICKS = 2048
RPM_UNIT, CURRENT_UNIT_A = 0.229, 0.00269  # present velocity [rev/min], current [A] per unit
ADDRESS = {"torque_enable": 64, "hardware_error": 70, "watchdog": 98, "goal_position": 116,
           "present": 126}  # fmt: skip
PRESENT_BYTES = 10  # current (2), velocity (4), position (4): one sync read


class DriverError(DammrlError):
    """The servo bus failed: a timeout, a corrupt answer, a missing servo, an error bit."""


@dataclass(frozen=True)
class JointState:
    q_rad: np.ndarray
    dq_rad_s: np.ndarray
    tau_nm: np.ndarray
    hardware_errors: dict[int, int]  # servo id -> its error bits, where any are set


@dataclass(frozen=True)
class Calibration:
    """One arm's servos: ids, zero offsets [rad], directions (+1/-1), current to torque."""

    ids: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    offsets_rad: tuple[float, ...] = (0.0,) * 6
    directions: tuple[int, ...] = (1,) * 6
    torque_per_amp_nm: tuple[float, ...] = (1.8,) * 6

    def to_ticks(self, q_rad: np.ndarray) -> list[int]:
        servo = np.asarray(self.directions) * (np.asarray(q_rad) + self.offsets_rad)
        return [round(float(a) * TICKS_PER_RAD) + CENTRE_TICKS for a in servo]

    def to_rad(self, ticks: list[int]) -> np.ndarray:
        servo = (np.asarray(ticks, dtype=float) - CENTRE_TICKS) / TICKS_PER_RAD
        return np.asarray(servo * self.directions - self.offsets_rad)


class Driver(Protocol):
    def connect(self) -> None: ...
    def read_state(self) -> JointState: ...
    def write_command(self, q_ref_rad: np.ndarray) -> None: ...
    def disconnect(self) -> None: ...


DRIVERS: dict[str, Callable[..., Driver]] = {}


def register(name: str) -> Callable[[Callable[..., Driver]], Callable[..., Driver]]:
    def add(factory: Callable[..., Driver]) -> Callable[..., Driver]:
        DRIVERS[name] = factory
        return factory

    return add


def make_driver(name: str, **options: object) -> Driver:
    if name not in DRIVERS:
        raise DammrlError(f"unknown robot driver {name!r}: one of {sorted(DRIVERS)}")
    return DRIVERS[name](**options)


@register("dynamixel")
@dataclass
class DynamixelDriver:
    """Dynamixel X-series servos on one Protocol 2.0 bus."""

    port: str
    calibration: Calibration = field(default_factory=Calibration)
    baud: int = 1_000_000
    watchdog_s: float = 0.1  # the servos stop by themselves this long after the last packet
    _port: object = None
    _packet: object = None

    def __enter__(self) -> DynamixelDriver:
        self.connect()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:  # fmt: skip
        self.disconnect()

    def connect(self) -> None:
        """Open the port, find every servo, arm the watchdog, hold where they are."""
        import dynamixel_sdk as sdk

        port = sdk.PortHandler(self.port)
        try:
            opened = port.openPort() and port.setBaudRate(self.baud)
        except OSError as exc:  # pyserial's SerialException: no such device, no permission
            raise DriverError(f"cannot open the servo bus at {self.port}: {exc}") from None
        if not opened:
            raise DriverError(f"cannot open the servo bus at {self.port}")
        self._port, self._packet = port, sdk.PacketHandler(2.0)
        for servo_id in self.calibration.ids:
            _, result, _ = self._packet.ping(port, servo_id)  # type: ignore[attr-defined]
            if result != sdk.COMM_SUCCESS:
                self.disconnect()
                raise DriverError(f"servo {servo_id} does not answer on {self.port}")
        held = self.read_state().q_rad
        self.write_command(held)  # the goal is where the arm is before the torque comes on
        ticks = max(1, min(127, round(self.watchdog_s / 0.02)))
        for servo_id in self.calibration.ids:
            self._write1(servo_id, ADDRESS["watchdog"], 0)  # a stopped servo restarts
            self._write1(servo_id, ADDRESS["torque_enable"], 1)
            self._write1(servo_id, ADDRESS["watchdog"], ticks)

    def read_state(self) -> JointState:
        import dynamixel_sdk as sdk

        reader = sdk.GroupSyncRead(self._port, self._packet, ADDRESS["present"], PRESENT_BYTES)
        for servo_id in self.calibration.ids:
            reader.addParam(servo_id)
        result = reader.txRxPacket()
        if result != sdk.COMM_SUCCESS:
            raise DriverError(f"sync read failed: {self._packet.getTxRxResult(result)}")  # type: ignore[attr-defined]
        current, velocity, position = [], [], []
        for servo_id in self.calibration.ids:
            if not reader.isAvailable(servo_id, ADDRESS["present"], PRESENT_BYTES):
                raise DriverError(f"servo {servo_id} missing from the sync read")
            raw = bytes(reader.data_dict[servo_id])
            c, v, p = struct.unpack("<hii", raw)
            current.append(c)
            velocity.append(v)
            position.append(p)
        directions = np.asarray(self.calibration.directions)
        dq = np.asarray(velocity) * RPM_UNIT * 2 * math.pi / 60 * directions
        tau = (np.asarray(current) * CURRENT_UNIT_A * directions
               * np.asarray(self.calibration.torque_per_amp_nm))  # fmt: skip
        return JointState(self.calibration.to_rad(position), dq, tau, self._hardware_errors())

    def _hardware_errors(self) -> dict[int, int]:
        """Each servo's hardware error bits (overload, overheating, voltage...), where set.
        The SDK's sync read drops the status error byte, so the register is read."""
        import dynamixel_sdk as sdk

        reader = sdk.GroupSyncRead(self._port, self._packet, ADDRESS["hardware_error"], 1)
        for servo_id in self.calibration.ids:
            reader.addParam(servo_id)
        if reader.txRxPacket() != sdk.COMM_SUCCESS:
            raise DriverError("sync read of the hardware error status failed")
        bits = {i: reader.getData(i, ADDRESS["hardware_error"], 1) for i in self.calibration.ids}
        return {i: int(b) for i, b in bits.items() if b}

    def write_command(self, q_ref_rad: np.ndarray) -> None:
        import dynamixel_sdk as sdk

        writer = sdk.GroupSyncWrite(self._port, self._packet, ADDRESS["goal_position"], 4)
        for servo_id, ticks in zip(self.calibration.ids, self.calibration.to_ticks(q_ref_rad),
                                   strict=True):  # fmt: skip
            writer.addParam(servo_id, list(struct.pack("<i", ticks)))
        result = writer.txPacket()
        if result != sdk.COMM_SUCCESS:
            raise DriverError(f"sync write failed: {self._packet.getTxRxResult(result)}")  # type: ignore[attr-defined]

    def disconnect(self) -> None:
        """Torque off on every servo that answers, then close the port."""
        if self._port is None:
            return
        for servo_id in self.calibration.ids:
            with contextlib.suppress(DriverError):  # unplugged: its watchdog stops it anyway
                self._write1(servo_id, ADDRESS["torque_enable"], 0)
        self._port.closePort()  # type: ignore[attr-defined]
        self._port = None

    def _write1(self, servo_id: int, address: int, value: int) -> None:
        import dynamixel_sdk as sdk

        result, error = self._packet.write1ByteTxRx(self._port, servo_id, address, value)  # type: ignore[attr-defined]
        if result != sdk.COMM_SUCCESS or error:
            raise DriverError(f"servo {servo_id}: writing {value} at {address} failed "
                              f"(result {result}, error {error})")  # fmt: skip
