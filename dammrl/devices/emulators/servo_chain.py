"""An emulated chain of Dynamixel X-series servos behind Protocol 2.0: control tables,
PING / READ / WRITE / SYNC READ / SYNC WRITE / REBOOT, hardware error bits, the bus
watchdog and faults on demand (CRC errors, short or late status packets, a missing servo,
no answer, an overload or overheating, unplugged).

REBOOT is the only way to clear a latched hardware error (the e-manual): the servo
answers, then boots for ``ServoChain.boot_s`` (silent, torque off: its joint is free),
and comes back with its RAM at the factory values (torque off, default gains, no
watchdog, no error, the goal where the shaft is); the operating mode (EEPROM) stays.

Each servo's motion comes from a ``Physics`` callback (the MuJoCo arm in the robot
service's emulation; a first-order servo by default), so the driver under test sees a
plausible arm. Time is passed in, never read, so tests are deterministic.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Protocol

import dynamixel_sdk as sdk

from dammrl.devices.emulators.protocol2 import (
    BROADCAST_ID,
    CorruptPacket,
    Instruction,
    status_packet,
)

# Protocol 2.0 instructions and error numbers (the SDK's constants, typed)
INST_PING: int = sdk.INST_PING
INST_READ: int = sdk.INST_READ
INST_WRITE: int = sdk.INST_WRITE
INST_SYNC_READ: int = sdk.INST_SYNC_READ
INST_SYNC_WRITE: int = sdk.INST_SYNC_WRITE
INST_REBOOT: int = sdk.INST_REBOOT
ERRNUM_INSTRUCTION: int = sdk.ERRNUM_INSTRUCTION
ERRNUM_DATA_RANGE: int = sdk.ERRNUM_DATA_RANGE
ERRNUM_DATA_LENGTH: int = sdk.ERRNUM_DATA_LENGTH
ERRNUM_ACCESS: int = sdk.ERRNUM_ACCESS

# X-series control table (XM430-W350, e-manual), the addresses the driver uses
MODEL_NUMBER, FIRMWARE_VERSION, SERVO_ID = 0, 6, 7
OPERATING_MODE, TORQUE_ENABLE, HARDWARE_ERROR_STATUS = 11, 64, 70
POSITION_D_GAIN, POSITION_I_GAIN, POSITION_P_GAIN = 80, 82, 84
BUS_WATCHDOG, GOAL_CURRENT, GOAL_POSITION = 98, 102, 116
PRESENT_CURRENT, PRESENT_VELOCITY, PRESENT_POSITION = 126, 128, 132
PRESENT_INPUT_VOLTAGE, PRESENT_TEMPERATURE = 144, 146
XM430_W350 = 1020
CURRENT_BASED_POSITION = 5  # operating mode: position PID, current limited, multi-turn
TABLE_SIZE = 256
WRITABLE = {OPERATING_MODE: 1, TORQUE_ENABLE: 1, POSITION_D_GAIN: 2, POSITION_I_GAIN: 2,
            POSITION_P_GAIN: 2, BUS_WATCHDOG: 1, GOAL_CURRENT: 2, GOAL_POSITION: 4}  # fmt: skip
"""Address -> size of the fields a host may write (others answer an access error); a
write may cover several adjacent fields (the gains in one packet)."""
WATCHDOG_UNIT_S = 0.020
ALERT = 0x80  # status-packet error byte: a hardware error is latched
OVERLOAD_BIT, OVERHEAT_BIT, VOLTAGE_BIT = 0x20, 0x04, 0x01
TICKS_PER_RAD = 4096 / (2 * math.pi)  # position resolution: 0.088 deg
CENTRE_TICKS = 2048  # the horn's middle: angle 0 of the servo frame
RPM_UNIT = 0.229  # present velocity unit [rev/min]
CURRENT_UNIT_A = 0.00269  # present and goal current unit [A]
# The emulated firmware's position law, in the servo's frame, at every physics step:
#   i = clip(P * KP_UNIT (goal - angle) - D * KD_UNIT * velocity, +-goal current)  [A]
# (D acts on the measured velocity). These two units are the emulator's model, stated
# here; a real servo's gain units come from its e-manual and go in the arm's calibration.
KP_UNIT_A_PER_RAD = 0.01
KD_UNIT_AS_PER_RAD = 0.001
BUTTON_MODEL = 0x4254  # the emulated button board on the same bus ("BT")
BUTTON_TRAVEL_UM = 132  # int32: the cap's travel [um], where a servo has its position, so
# one sync read covers the servos and the button


@dataclass(frozen=True)
class ServoDrive:
    """What a powered servo's firmware asks of its motor (servo frame, SI)."""

    goal_rad: float
    kp_a_per_rad: float
    kd_as_per_rad: float
    current_limit_a: float


@dataclass(frozen=True)
class ServoReading:
    angle_rad: float
    velocity_rad_s: float
    current_a: float


class Physics(Protocol):
    """What moves the servos: a first-order stand-in, or the MuJoCo arm."""

    def step(self, drives: dict[int, ServoDrive | None], dt_s: float) -> dict[int, ServoReading]:
        """Advance ``dt_s`` under the drives (None: torque off); every servo's reading."""
        ...

    def button_travel_m(self) -> float:
        """How far the button cap is pressed [m] (0 without a button)."""
        ...


@dataclass
class EmulatedServo:
    servo_id: int
    model: int = XM430_W350
    table: bytearray = field(default_factory=lambda: bytearray(TABLE_SIZE))
    watchdog_deadline_s: float | None = None
    angle_rad: float = 0.0  # the shaft's true angle; the encoder reports it in ticks
    booting_until_s: float | None = None  # rebooting: silent and powerless until then
    heard_s: float | None = None  # when an instruction last reached it (emulator time)
    stopped_s: float | None = None  # when its watchdog stopped it: its deadline, as firmware

    def __post_init__(self) -> None:
        self.factory_ram()

    def factory_ram(self) -> None:
        """The control table as the servo boots (its EEPROM's operating mode kept)."""
        mode = self.table[OPERATING_MODE] or CURRENT_BASED_POSITION
        present = self.read(PRESENT_CURRENT, 10)  # current, velocity, position
        self.table[:] = bytearray(TABLE_SIZE)
        self.table[PRESENT_CURRENT : PRESENT_CURRENT + 10] = present
        self.table[GOAL_POSITION : GOAL_POSITION + 4] = present[6:10]  # where the shaft is
        self.watchdog_deadline_s = None
        struct.pack_into("<H", self.table, MODEL_NUMBER, self.model)
        self.table[FIRMWARE_VERSION] = 46
        self.table[SERVO_ID] = self.servo_id
        self.table[OPERATING_MODE] = mode
        struct.pack_into("<H", self.table, PRESENT_INPUT_VOLTAGE, 120)  # 12.0 V
        struct.pack_into("<H", self.table, POSITION_P_GAIN, 800)  # factory-like defaults
        struct.pack_into("<H", self.table, POSITION_D_GAIN, 0)
        struct.pack_into("<h", self.table, GOAL_CURRENT, 1193)  # 3.2 A
        self.table[PRESENT_TEMPERATURE] = 30

    def read(self, address: int, length: int) -> bytes:
        return bytes(self.table[address : address + length])

    def value(self, address: int, size: int) -> int:
        return int.from_bytes(self.table[address : address + size], "little", signed=True)

    @property
    def torque_on(self) -> bool:
        return self.table[TORQUE_ENABLE] == 1

    @property
    def hardware_error(self) -> int:
        return self.table[HARDWARE_ERROR_STATUS]

    @property
    def watchdog_expired(self) -> bool:
        return self.table[BUS_WATCHDOG] == 0xFF  # -1: the servo stopped itself

    def write(self, address: int, data: bytes, now_s: float) -> int:
        """Write a field; 0 or the Protocol 2.0 error number."""
        size = _span(address, len(data))
        if size is None:
            return ERRNUM_ACCESS
        if size != len(data):
            return ERRNUM_DATA_LENGTH
        if address == GOAL_POSITION and (self.watchdog_expired or self.hardware_error):
            return ERRNUM_DATA_RANGE  # stopped: goals are refused until reset
        if address == TORQUE_ENABLE and data[0] == 1 and self.hardware_error:
            return ERRNUM_DATA_RANGE  # a latched error keeps the torque off (reboot clears)
        self.table[address : address + size] = data
        if address == BUS_WATCHDOG:
            value = data[0]
            self.watchdog_deadline_s = now_s + value * WATCHDOG_UNIT_S if 0 < value < 128 else None
        return 0

    def heard(self, now_s: float) -> None:
        """Any instruction for this servo refreshes its watchdog."""
        self.heard_s = now_s
        value = self.table[BUS_WATCHDOG]
        if 0 < value < 128:
            self.watchdog_deadline_s = now_s + value * WATCHDOG_UNIT_S

    def status_error(self) -> int:
        return ALERT if self.hardware_error else 0

    def drive(self) -> ServoDrive | None:
        """The firmware's law as configured (None: torque off)."""
        if not self.torque_on:
            return None
        return ServoDrive(
            (self.value(GOAL_POSITION, 4) - CENTRE_TICKS) / TICKS_PER_RAD,
            self.value(POSITION_P_GAIN, 2) * KP_UNIT_A_PER_RAD,
            self.value(POSITION_D_GAIN, 2) * KD_UNIT_AS_PER_RAD,
            self.value(GOAL_CURRENT, 2) * CURRENT_UNIT_A,
        )

    def show(self, reading: ServoReading) -> None:
        """The encoder, tachometer and current sensor report ``reading``."""
        self.angle_rad = reading.angle_rad
        rpm = reading.velocity_rad_s * 60 / (2 * math.pi) / RPM_UNIT
        ticks = round(reading.angle_rad * TICKS_PER_RAD) + CENTRE_TICKS
        struct.pack_into("<i", self.table, PRESENT_POSITION, ticks)
        struct.pack_into("<i", self.table, PRESENT_VELOCITY, round(rpm))
        current = max(-32768, min(32767, round(reading.current_a / CURRENT_UNIT_A)))
        struct.pack_into("<h", self.table, PRESENT_CURRENT, current)


def _status_params(packet: bytes) -> bytes:
    """The parameters of a status packet built by ``status_packet`` (stuffing undone)."""
    unstuffed = bytes(packet[:7]) + bytes(packet[7:]).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")
    return unstuffed[9:-2]


def _span(address: int, length: int) -> int | None:
    """Bytes of the writable fields from ``address`` covering ``length`` (None: not one)."""
    covered = 0
    while address + covered in WRITABLE and covered < length:
        covered += WRITABLE[address + covered]
    return covered or None


@dataclass
class FirstOrder:
    """A servo that follows its goal with a first-order lag (the stand-in physics)."""

    time_constant_s: float = 0.05
    angles: dict[int, float] = field(default_factory=dict)

    def step(self, drives: dict[int, ServoDrive | None], dt_s: float) -> dict[int, ServoReading]:
        alpha = 1.0 - math.exp(-dt_s / self.time_constant_s)
        readings = {}
        for servo_id, drive in drives.items():
            before = self.angles.get(servo_id, 0.0)
            after = before if drive is None else before + alpha * (drive.goal_rad - before)
            self.angles[servo_id] = after
            readings[servo_id] = ServoReading(after, (after - before) / dt_s, 0.0)
        return readings

    def button_travel_m(self) -> float:
        return 0.0


FAULT_HELP = (
    "faults on stdin, one per line: overload ID | overheat ID | missing ID | present ID | "
    "corrupt N | short N | late N | silent | talk | unplug | replug"
)


@dataclass
class Faults:
    """Faults on demand."""

    corrupt_responses: int = 0  # the next N status packets go out with a broken CRC
    short_responses: int = 0  # the next N lose their last parameter byte (a valid CRC)
    late_responses: int = 0  # the next N go out only after the next instruction came in
    missing: set[int] = field(default_factory=set)  # servos that never answer
    silent: bool = False  # no servo answers (a timeout on every request)
    unplugged: bool = False  # the bus is gone: nothing in, nothing out


BOOT_S = 0.3
"""How long an emulated servo takes to boot after a REBOOT [s]. An assumption: a real
servo's boot time was not measured here (``dammrl robot`` on the lab's arm can); the
fall of a joint whose servo reboots grows with it."""


class ServoChain:
    """The servos on one bus: instruction packets in, status packets out."""

    def __init__(
        self,
        ids: list[int],
        physics: Physics | None = None,
        button_id: int | None = None,
        boot_s: float = BOOT_S,
    ) -> None:
        """``button_id``: the goal button's sensor board answers on the bus at this id;
        ``boot_s``: a servo's boot time after a REBOOT [s]."""
        self.servos = {i: EmulatedServo(i) for i in ids}
        if button_id is not None:
            self.servos[button_id] = EmulatedServo(button_id, model=BUTTON_MODEL)
        self.button_id = button_id
        self.boot_s = boot_s
        self.physics: Physics = physics or FirstOrder()
        self.faults = Faults()
        self.writes: list[tuple[float, int]] = []  # (time, address) of sync writes, if kept
        self.keep_writes = False  # benchmarks: when the goals arrive
        self.now_s = 0.0
        self._last_step_s = 0.0
        self._held: list[bytes] = []  # late status packets: sent before the next answers

    @property
    def motors(self) -> dict[int, EmulatedServo]:
        return {i: s for i, s in self.servos.items() if i != self.button_id}

    # ---- time and motion -----------------------------------------------------------
    def advance(self, now_s: float) -> None:
        """Move the arm to ``now_s``: watchdogs first (a stopped servo holds), then physics."""
        dt = now_s - self._last_step_s
        self.now_s = now_s
        for servo in self.motors.values():
            if servo.booting_until_s is not None and now_s >= servo.booting_until_s:
                servo.booting_until_s = None
                servo.factory_ram()  # up again: torque off, factory RAM
            deadline = servo.watchdog_deadline_s
            if servo.torque_on and deadline is not None and now_s >= deadline:
                servo.table[BUS_WATCHDOG] = 0xFF  # stops by itself: goal := present
                servo.watchdog_deadline_s = None
                servo.stopped_s = deadline
                servo.table[GOAL_POSITION : GOAL_POSITION + 4] = servo.read(PRESENT_POSITION, 4)
        if dt <= 0:
            return
        self._last_step_s = now_s
        drives = {i: s.drive() for i, s in self.motors.items()}
        for servo_id, reading in self.physics.step(drives, dt).items():
            self.servos[servo_id].show(reading)
        if self.button_id is not None:
            travel_um = round(self.physics.button_travel_m() * 1e6)
            struct.pack_into("<i", self.servos[self.button_id].table, BUTTON_TRAVEL_UM, travel_um)

    def overload(self, servo_id: int) -> None:
        """Latch an overload error: torque off, the alert bit in every status."""
        self.latch(servo_id, OVERLOAD_BIT)

    def overheat(self, servo_id: int) -> None:
        """Latch an overheating error (one a restart does not clear while the motor is
        hot): torque off, the alert bit in every status."""
        self.latch(servo_id, OVERHEAT_BIT)

    def latch(self, servo_id: int, bit: int) -> None:
        """Latch the hardware error ``bit``, as the firmware does: torque off."""
        servo = self.servos[servo_id]
        servo.table[HARDWARE_ERROR_STATUS] |= bit
        servo.table[TORQUE_ENABLE] = 0

    # ---- the protocol --------------------------------------------------------------
    def handle(self, packet: Instruction | CorruptPacket) -> list[bytes]:
        """The status packets answering one instruction (in bus order)."""
        if self.faults.unplugged or isinstance(packet, CorruptPacket):
            return []  # a device ignores a packet whose CRC fails
        late, self._held = self._held, []
        responses = self._answer(packet)
        if self.faults.silent:
            return late
        return late + self._hold_late([self._maybe_corrupt(self._maybe_short(r))
                                       for r in responses])  # fmt: skip

    def _answer(self, packet: Instruction) -> list[bytes]:
        kind = packet.instruction
        if kind == INST_SYNC_WRITE:
            self._sync_write(packet.params)
            return []
        if kind == INST_SYNC_READ:
            return self._sync_read(packet.params)
        targets = self._targets(packet.servo_id)
        for servo in targets:
            servo.heard(self.now_s)  # any instruction feeds the watchdog
        if kind == INST_PING:
            return [self._ping(s) for s in targets]
        if packet.servo_id == BROADCAST_ID:
            return []  # broadcast reads and writes are not answered
        if kind == INST_READ:
            return [self._read(s, packet.params) for s in targets]
        if kind == INST_WRITE:
            return [self._write(s, packet.params) for s in targets]
        if kind == INST_REBOOT:
            return [self._reboot(s) for s in targets]
        return [status_packet(s.servo_id, ERRNUM_INSTRUCTION | s.status_error()) for s in targets]

    def _targets(self, servo_id: int) -> list[EmulatedServo]:
        present = {i: s for i, s in self.servos.items()
                   if i not in self.faults.missing and s.booting_until_s is None}  # fmt: skip
        if servo_id == BROADCAST_ID:
            return [present[i] for i in sorted(present)]
        return [present[servo_id]] if servo_id in present else []

    @staticmethod
    def _ping(servo: EmulatedServo) -> bytes:
        identity = servo.read(MODEL_NUMBER, 2) + servo.read(FIRMWARE_VERSION, 1)
        return status_packet(servo.servo_id, servo.status_error(), identity)

    @staticmethod
    def _read(servo: EmulatedServo, params: bytes) -> bytes:
        if len(params) != 4:
            return status_packet(servo.servo_id, ERRNUM_DATA_LENGTH)
        address, length = struct.unpack("<HH", params)
        if address + length > TABLE_SIZE:
            return status_packet(servo.servo_id, ERRNUM_DATA_RANGE)
        return status_packet(servo.servo_id, servo.status_error(), servo.read(address, length))

    def _write(self, servo: EmulatedServo, params: bytes) -> bytes:
        if len(params) < 3:
            return status_packet(servo.servo_id, ERRNUM_DATA_LENGTH)
        address = params[0] | params[1] << 8
        error = servo.write(address, params[2:], self.now_s)
        return status_packet(servo.servo_id, error | servo.status_error())

    def _reboot(self, servo: EmulatedServo) -> bytes:
        """Answer, then boot: the torque goes off at once (the joint is free) and the
        servo is silent for ``boot_s``."""
        servo.table[TORQUE_ENABLE] = 0
        servo.booting_until_s = self.now_s + self.boot_s
        return status_packet(servo.servo_id, 0)

    def _sync_read(self, params: bytes) -> list[bytes]:
        if len(params) < 5:
            return []
        address, length = struct.unpack("<HH", params[:4])
        answers = []
        for servo_id in params[4:]:  # each answers in the order the host listed them
            targets = self._targets(servo_id)
            for servo in targets:
                servo.heard(self.now_s)
                answers.append(status_packet(servo_id, servo.status_error(),
                                             servo.read(address, length)))  # fmt: skip
        return answers

    def _sync_write(self, params: bytes) -> None:
        if len(params) < 4:
            return
        address, length = struct.unpack("<HH", params[:4])
        if self.keep_writes:
            self.writes.append((self.now_s, address))
        block = 1 + length
        for start in range(4, len(params) - block + 1, block):
            servo_id = params[start]
            for servo in self._targets(servo_id):
                servo.heard(self.now_s)
                servo.write(address, params[start + 1 : start + block], self.now_s)

    def _hold_late(self, responses: list[bytes]) -> list[bytes]:
        """A servo answering after the host stopped waiting (a busy host or firmware): the
        host meets this answer while it waits for the next one."""
        now = []
        for response in responses:
            if self.faults.late_responses > 0:
                self.faults.late_responses -= 1
                self._held.append(response)
            else:
                now.append(response)
        return now

    def _maybe_short(self, response: bytes) -> bytes:
        """A status packet one parameter byte short, framed and checksummed as sent."""
        params = _status_params(response)
        if self.faults.short_responses <= 0 or not params:
            return response
        self.faults.short_responses -= 1
        return status_packet(response[4], response[8], params[:-1])

    def _maybe_corrupt(self, response: bytes) -> bytes:
        if self.faults.corrupt_responses <= 0:
            return response
        self.faults.corrupt_responses -= 1
        return response[:-1] + bytes([response[-1] ^ 0xFF])
