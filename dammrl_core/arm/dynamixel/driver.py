"""The robot service's hardware interface: a driver connects, reads the arm's state,
writes joint commands and disconnects (a context manager), in the style of LeRobot's
``Robot``. Backends register by name; settings choose one.

The Dynamixel backend (Protocol 2.0, the official dynamixel-sdk) realises the joint law
tau = tau_ff + kp (q_ref - q) + kd (dq_ref - dq) through each servo's own position loop
(current-based position mode): the servo's P and D gains are kp and kd through the
calibration, its goal is q_ref shifted by (tau_ff + kd dq_ref) / kp, so that
P (goal - q) - D dq is the law, and its goal current is the torque limit. The servo
closes that loop at its own rate, so the law does not depend on the host's timing and
the arm holds if the host stalls (see docs/tutorials/your-arm.md for the measured
alternative). One sync read per cycle returns position, velocity and current with each
servo's alert bit; one sync write sends the goals (gains and limits only when changed).
The servo's bus watchdog is armed on connect, so the servos stop by themselves if this
process dies.
"""

from __future__ import annotations

import contextlib
import math
import struct
import termios
import time
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from types import TracebackType
from typing import Any, TypeVar

import numpy as np

from dammrl_core.arm.driver import (
    BadReplyError,
    DriveCommand,
    DriveFault,
    DriverError,
    HoldLaw,
    JointState,
    PortLostError,
)
from dammrl_core.arm.dynamixel.calibration import Calibration
from dammrl_core.robot import RobotDescription

RPM_UNIT, CURRENT_UNIT_A = 0.229, 0.00269  # present velocity [rev/min], current [A] per unit
KP_UNIT_A_PER_RAD, KD_UNIT_AS_PER_RAD = 0.01, 0.001  # the position P and D gain units
ADDRESS = {"operating_mode": 11, "torque_enable": 64, "hardware_error": 70, "gains": 80,
           "watchdog": 98, "goal_current": 102, "goal_position": 116, "present": 126,
           "model": 0}  # fmt: skip
VALID = {"operating_mode": {0, 1, 3, 4, 5, 16}, "torque_enable": {0, 1},
         "hardware_error": set(range(256)), "watchdog": set(range(128)) | {0xFF}}  # fmt: skip
"""What each one-byte field read can hold (e-manual); anything else is no answer to it."""
PRESENT_BYTES = 10  # current (2), velocity (4), position (4): one sync read
CURRENT_BASED_POSITION = 5
MAX_GAIN_UNITS, MAX_CURRENT_UNITS = 16383, 1193
ALERT = 0x80
COMM_SUCCESS = 0  # dynamixel_sdk.COMM_SUCCESS
FIRST_PING_S = 0.05  # a rebooted servo is first looked for this long after the REBOOT [s]
PING_EVERY_S = 0.05  # then this often (an unanswered ping costs the SDK's timeout, ~34 ms)
REBOOT_TRIES = 3  # a servo still answering with its error latched is sent REBOOT again
TRIES = 3
"""A request answered late, garbled or not at all is sent again this often before it counts
as failed: on a loaded PC one late answer is common, and a connect or a restore (a dozen
requests) that failed on any one of them would start over or leave a joint without torque
(three in a row is a servo that does not answer; each unanswered try costs the SDK's
timeout, ~34 ms). The cycle's own sync read and write are not retried: the next cycle is
their retry."""
OVERLOAD = 0x20
STATUS_ID, STATUS_LENGTH, STATUS_ERROR, STATUS_PARAMS = 4, 5, 8, 9  # a status packet's fields
PRESENT_RANGE = ((-2047, 2047), (-1023, 1023), (-1_048_575, 1_048_575))
"""What an X-series servo can report in its present current, velocity and position (units;
e-manual: within the largest current limit, the largest velocity limit, the multi-turn
range of current-based position mode); a value beyond them is no reading."""
BUTTON_RANGE_UM = (-1_000, 100_000)
"""What the button board can report as its cap's travel [um]."""
ERROR_BITS = {0x01: "input voltage", 0x04: "overheating", 0x08: "motor encoder",
              0x10: "electrical shock", 0x20: "overload"}  # fmt: skip


PORT_ERRORS = (OSError, termios.error)
"""A serial device that fails or goes away: pyserial raises OSError, or termios.error (not
an OSError) when it flushes a device pulled out (the SDK flushes before every request)."""


@contextlib.contextmanager
def _bus_io(port: str) -> Iterator[None]:
    """The serial device failing (a USB adapter pulled out) is a DriverError, as a silent
    servo is."""
    try:
        yield
    except PORT_ERRORS as exc:
        raise PortLostError(f"the servo bus at {port} failed: {exc}") from None


T = TypeVar("T")


def describe_errors(bits: int) -> str:
    names = [name for bit, name in ERROR_BITS.items() if bits & bit]
    return ", ".join(names) or f"error bits 0x{bits:02x}"


@dataclass
class DynamixelDriver:
    """Dynamixel X-series servos (and the button board) on one Protocol 2.0 bus."""

    port: str
    calibration: Calibration = field(default_factory=Calibration)
    baud: int = 1_000_000
    watchdog_s: float = 0.1  # the servos stop by themselves this long after the last packet
    max_goal_offset_rad: float = 0.5  # the feed-forward's shift of the goal, at most [rad]
    _port: Any = None
    _packet: Any = None
    _written: dict[str, tuple[int, ...]] = field(default_factory=dict)
    _booting: dict[int, float] = field(default_factory=dict)  # servo id -> next ping [s]
    _reboots: dict[int, int] = field(default_factory=dict)  # servo id -> REBOOTs sent
    _last: JointState | None = None

    def __enter__(self) -> DynamixelDriver:
        try:
            self.connect()
        except DriverError:
            self._close()
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 trace: TracebackType | None) -> None:  # fmt: skip
        self.disconnect()

    @property
    def ids(self) -> tuple[int, ...]:
        return self.calibration.ids

    @property
    def stall_s(self) -> float | None:
        """The servos' bus watchdog: they stop by themselves after this much silence."""
        return self.watchdog_s

    def joint_limits(self, robot: RobotDescription) -> tuple[np.ndarray, np.ndarray]:
        return self.calibration.limits(robot)

    def connect(self, torque: bool = True, hold: HoldLaw | None = None) -> bool:
        """Open the port (unless open), find every servo, refuse latched errors, clear a
        watchdog stop, arm the watchdog. Servos with the torque off start holding with
        ``hold``'s law, made from the state read just before (None: where they are, with
        zero gains); servos that hold with the torque on keep their law. True when any
        servo was already holding (a reconnection: no soft start, which would soften the
        joints held). ``torque=False``: the torque goes off (the arm is moved by hand:
        calibration)."""
        import dynamixel_sdk as sdk

        if self._port is None:
            port = sdk.PortHandler(self.port)
            try:
                opened = port.openPort() and port.setBaudRate(self.baud)
            except OSError as exc:  # pyserial's SerialException: no device, no permission
                raise DriverError(f"cannot open the servo bus at {self.port}: {exc}") from None
            if not opened:
                raise DriverError(f"cannot open the servo bus at {self.port}")
            self._port, self._packet = port, sdk.PacketHandler(2.0)
        try:
            with _bus_io(self.port):
                return self._power_up(torque, hold)
        except DriverError:
            # reopened at the next try: a device pulled out, or a port the SDK left "in
            # use" by a request an error cut short (it would refuse every later one)
            self._close()
            raise

    def _power_up(self, torque: bool, hold: HoldLaw | None) -> bool:
        devices = self.ids + (() if self.calibration.button_id is None
                              else (self.calibration.button_id,))  # fmt: skip
        for servo_id in devices:
            self._retried(partial(self._ping, servo_id))
        holding = []
        for servo_id in self.ids:
            bits = self._read1(servo_id, "hardware_error")
            if bits:
                raise DriverError(
                    f"servo {servo_id} reports {describe_errors(bits)}: inspect the arm, "
                    "then power-cycle the servos"
                )
            if (self._read1(servo_id, "torque_enable") == 1
                    and self._read1(servo_id, "operating_mode")
                    == CURRENT_BASED_POSITION):  # fmt: skip
                holding.append(servo_id)
            self._write1(servo_id, ADDRESS["watchdog"], 0)  # clears a watchdog stop
        self._written = {}  # gains and limits are written again with the next law
        if not torque:
            self._start(self.ids, torque=False)
            return False
        if len(holding) < len(self.ids):
            self._start([i for i in self.ids if i not in holding], hold=hold)
        for servo_id in self.ids:
            self._write1(servo_id, ADDRESS["watchdog"], self._watchdog_ticks)
        return bool(holding)

    @property
    def _watchdog_ticks(self) -> int:
        return max(1, min(127, round(self.watchdog_s / 0.02)))

    def rearm(self) -> list[int]:
        """After the host was silent too long: the servos whose watchdog stopped them
        (they hold where they were and refuse goals, silently in a sync write), re-armed."""
        self._require_open()
        stopped = []
        with _bus_io(self.port):
            for servo_id in self.ids:
                if self._read1(servo_id, "watchdog") == 0xFF:  # -1: expired
                    self._write1(servo_id, ADDRESS["watchdog"], 0)
                    self._write1(servo_id, ADDRESS["watchdog"], self._watchdog_ticks)
                    stopped.append(servo_id)
        return stopped

    # ---- a servo's reboot ---------------------------------------------------------------
    def restart(self, joint: int) -> None:
        """Clear the latched error of ``joint``'s servo (REBOOT: the only way, and its
        torque is off until it is up again). Returns at once: the servo is left out of
        every read and write while it boots, and put back holding where its shaft is,
        with the gains last written, as soon as it answers a ping."""
        self._require_open()
        servo_id = self.ids[joint]
        self._reboots[servo_id] = 0
        with _bus_io(self.port):
            self._reboot(servo_id)

    def _reboot(self, servo_id: int) -> None:
        """REBOOT sent (its answer may be lost or late: the pings tell whether it took)."""
        self._packet.reboot(self._port, servo_id)
        self._reboots[servo_id] += 1
        self._booting[servo_id] = time.monotonic() + FIRST_PING_S

    def _poll_booting(self) -> None:
        """Ping one booting servo whose turn it is; one that answers is put back. One
        that answers with its error still latched never got the REBOOT: sent again, and
        after ``REBOOT_TRIES`` left out no more (its fault is read again: the restart did
        not clear it)."""
        now = time.monotonic()
        due = [i for i, at in self._booting.items() if at <= now]
        if not due:
            return
        servo_id = due[0]
        _, result, error = self._packet.ping(self._port, servo_id)
        if result != COMM_SUCCESS:
            self._booting[servo_id] = time.monotonic() + PING_EVERY_S
            return
        if error & ALERT:
            if self._reboots[servo_id] < REBOOT_TRIES:
                self._reboot(servo_id)
            else:
                del self._booting[servo_id]
            return
        self._booting[servo_id] = time.monotonic() + PING_EVERY_S  # if the restore fails
        self._restore(servo_id)
        del self._booting[servo_id]

    def _restore(self, servo_id: int) -> None:
        """A rebooted servo holding where its shaft is: the gains and current limit last
        written, the goal at its present position, the bus watchdog armed, the torque on
        (its operating mode is in its EEPROM, kept through a reboot). Its joint falls
        until then, and on a loaded PC each answer waited for costs most of a restore:
        one read, the writes unanswered (sync writes to it alone), one read confirming the
        torque on. Each step may be repeated (a restore that failed is tried again)."""
        index = self.ids.index(servo_id)
        present = self._read_position(servo_id)
        for name, size in (("gains", 6), ("goal_current", 2)):
            row = self._written.get(name, ())[index * size : (index + 1) * size]
            if row:
                self._send(name, size, {servo_id: list(row)})
        self._send("goal_position", 4, {servo_id: list(struct.pack("<i", present))})
        self._send("watchdog", 1, {servo_id: [self._watchdog_ticks]})
        self._send("torque_enable", 1, {servo_id: [1]})
        if self._read1(servo_id, "torque_enable") != 1:
            raise DriverError(f"servo {servo_id} did not turn its torque on after its restart")

    def _start(self, off: tuple[int, ...] | list[int], torque: bool = True,
               hold: HoldLaw | None = None) -> None:  # fmt: skip
        """The servos ``off`` to current-based position mode (the torque off to set it),
        then (``torque``) on, every servo holding with ``hold``'s law (None: where the arm
        is, with zero gains). The servos that hold meanwhile keep their own law (a start
        retried after a failed packet, a servo back from a brown-out: the arm neither
        drops nor softens where it is held)."""
        for servo_id in off:
            self._write1(servo_id, ADDRESS["torque_enable"], 0)
            self._write1(servo_id, ADDRESS["operating_mode"], CURRENT_BASED_POSITION)
        if not torque:
            return
        state = self.read_state()
        if hold is None:
            zeros = np.zeros(6)
            limit = self.calibration.joint_torque(np.full(6, MAX_CURRENT_UNITS * CURRENT_UNIT_A))
            law = DriveCommand(state.q_rad, zeros, zeros, zeros, zeros, np.abs(limit))
        else:
            law = hold(state)
        self._write_command(law, None if len(off) == len(self.ids) else off)
        for servo_id in off:
            self._write1(servo_id, ADDRESS["torque_enable"], 1)

    # ---- reading -----------------------------------------------------------------------
    def read_state(self) -> JointState:
        """Position, velocity and current of every servo (and the button's travel) in one
        sync read; the error register of any servo whose status raised its alert bit."""
        self._require_open()
        with _bus_io(self.port):
            return self._read_state()

    def _read_state(self) -> JointState:
        import dynamixel_sdk as sdk

        self._poll_booting()
        devices = [i for i in self.ids if i not in self._booting]
        if self.calibration.button_id is not None:
            devices.append(self.calibration.button_id)
        # the SDK's GroupSyncRead drops each status's error byte: its two steps, by hand
        result = self._packet.syncReadTx(self._port, ADDRESS["present"], PRESENT_BYTES,
                                         devices, len(devices), False)  # fmt: skip
        if result != sdk.COMM_SUCCESS:
            raise DriverError(f"sync read failed: {self._packet.getTxRxResult(result)}")
        rows, alerts = {}, []
        for servo_id in devices:
            data, error = self._receive(servo_id, PRESENT_BYTES,
                                        f"servo {servo_id} missing from the sync read")  # fmt: skip
            rows[servo_id] = self._present(servo_id, data)
            if error & ALERT and servo_id in self.ids:
                alerts.append(servo_id)
        button_m = 0.0
        if self.calibration.button_id is not None:
            button_m = rows[self.calibration.button_id][2] * 1e-6  # travel [um]
        state = self._joint_state(rows, button_m)
        faults = tuple(self._fault(i, self._read1(i, "hardware_error")) for i in alerts)
        self._last = replace(state, faults=faults)
        return self._last

    def _present(self, servo_id: int, data: bytes) -> tuple[int, int, int]:
        """Current, velocity and position (the button: its travel) of one sync-read row,
        refused when no such device could report them."""
        row: tuple[int, int, int] = struct.unpack("<hii", data)
        if servo_id == self.calibration.button_id:
            ranges = ((-(2**15), 2**15 - 1), (-(2**31), 2**31 - 1), BUTTON_RANGE_UM)
        else:
            ranges = PRESENT_RANGE
        names = ("current", "velocity", "position")
        for name, value, (low, high) in zip(names, row, ranges, strict=True):
            if not low <= value <= high:
                raise BadReplyError(f"servo {servo_id} reported {name} {value}, outside "
                                    f"[{low}, {high}]: not a reading")  # fmt: skip
        return row

    def _fault(self, servo_id: int, bits: int) -> DriveFault:
        """A servo's error bits; an overload alone is cleared by a restart (a REBOOT)."""
        what = f"servo {servo_id}: {describe_errors(bits)}"
        return DriveFault(self.ids.index(servo_id), what, restartable=bits == OVERLOAD)

    def _joint_state(self, rows: dict[int, tuple[int, int, int]], button_m: float) -> JointState:
        """The read rows in joint units; a rebooting servo's joint keeps its last values
        (and no speed, no torque)."""
        missing = [j for j, i in enumerate(self.ids) if i not in rows]
        ticks = [rows[i][2] if i in rows else 0 for i in self.ids]
        q = self.calibration.to_rad(ticks)
        velocity = np.array([rows[i][1] if i in rows else 0 for i in self.ids])
        current = np.array([rows[i][0] if i in rows else 0 for i in self.ids])
        if missing and self._last is not None:
            q[missing] = self._last.q_rad[missing]
        return JointState(
            q,
            self.calibration.joint_velocity(velocity * RPM_UNIT * 2 * math.pi / 60),
            self.calibration.joint_torque(current * CURRENT_UNIT_A),
            button_travel_m=button_m,
            restarting=frozenset(missing),
        )

    # ---- writing -----------------------------------------------------------------------
    def write_command(self, command: DriveCommand) -> None:
        """The law as servo goals (every call), gains and current limits (when changed)."""
        self._require_open()
        with _bus_io(self.port):
            self._write_command(command)

    def _require_open(self) -> None:
        if self._port is None:
            raise DriverError(f"the servo bus at {self.port} is not open")

    def _write_command(self, command: DriveCommand, only: Collection[int] | None = None) -> None:
        """The law to every servo (``only``: to these, the others keep theirs)."""
        cal = self.calibration
        kp_servo = cal.servo_gain(command.kp)
        kd_servo = cal.servo_gain(command.kd)
        p_units = np.clip(np.round(kp_servo / KP_UNIT_A_PER_RAD), 0, MAX_GAIN_UNITS).astype(int)
        d_units = np.clip(np.round(kd_servo / KD_UNIT_AS_PER_RAD), 0, MAX_GAIN_UNITS).astype(int)
        current = cal.servo_current(command.torque_limit_nm)
        c_units = np.clip(np.round(current / CURRENT_UNIT_A), 0, MAX_CURRENT_UNITS).astype(int)
        gains = [list(struct.pack("<HHH", d, 0, p)) for d, p in zip(d_units, p_units, strict=True)]
        self._sync_write_if_changed("gains", gains, only)
        self._sync_write_if_changed("goal_current", [list(struct.pack("<h", c)) for c in c_units],
                                    only)  # fmt: skip
        # tau_ff + kd dq_ref through the position law: P (goal - q) = tau_ff + kd dq_ref + ...
        kp = np.maximum(command.kp, 1e-9)
        shift = (command.tau_ff + command.kd * command.dq_ref) / kp
        reach = np.minimum(command.torque_limit_nm / kp, self.max_goal_offset_rad)
        goal = command.q_ref + np.where(command.kp > 0, np.clip(shift, -reach, reach), 0.0)
        ticks = [list(struct.pack("<i", t)) for t in cal.to_ticks(goal)]
        self._sync_write("goal_position", ticks, only)

    def _sync_write_if_changed(self, field_name: str, rows: list[list[int]],
                               only: Collection[int] | None = None) -> None:  # fmt: skip
        if only is not None:  # a part of the servos: nothing to remember for all
            self._sync_write(field_name, rows, only)
            return
        flat = tuple(b for row in rows for b in row)
        if self._written.get(field_name) != flat:
            self._sync_write(field_name, rows)
            self._written[field_name] = flat

    def _sync_write(self, field_name: str, rows: list[list[int]],
                    only: Collection[int] | None = None) -> None:  # fmt: skip
        """A row to every servo (``only``: to these), a booting one left out: it would not
        hear it, and is put back later."""
        chosen = {i: row for i, row in zip(self.ids, rows, strict=True)
                  if i not in self._booting and (only is None or i in only)}  # fmt: skip
        self._send(field_name, len(rows[0]), chosen)

    def _send(self, field_name: str, size: int, rows: dict[int, list[int]]) -> None:
        """``size``-byte rows to field ``field_name`` of the servos keyed, in one sync
        write: no answer is waited for."""
        import dynamixel_sdk as sdk

        writer = sdk.GroupSyncWrite(self._port, self._packet, ADDRESS[field_name], size)
        for servo_id, row in rows.items():
            writer.addParam(servo_id, row)
        result = writer.txPacket()
        if result != sdk.COMM_SUCCESS:
            raise DriverError(f"sync write failed: {self._packet.getTxRxResult(result)}")

    def torque_off(self) -> list[int]:
        """Torque off on every servo that answers (the arm goes limp); the servos that did
        not confirm it."""
        failed = []
        for servo_id in self.ids:
            try:
                with _bus_io(self.port):
                    self._write1(servo_id, ADDRESS["torque_enable"], 0)
            except DriverError:
                failed.append(servo_id)
        return failed

    def disconnect(self) -> None:
        """Leave the servos holding where they are, then close the port; their watchdog
        stops them anyway once the host is silent (a rehabilitation arm is not dropped
        on the person because its software stopped)."""
        if self._port is None:
            return
        with contextlib.suppress(DriverError):  # unplugged: the watchdog holds them anyway
            held = self.calibration.to_ticks(self.read_state().q_rad)
            with _bus_io(self.port):
                self._sync_write("goal_position", [list(struct.pack("<i", t)) for t in held])
        self._close()

    def _close(self) -> None:
        if self._port is not None:
            with contextlib.suppress(*PORT_ERRORS):
                self._port.closePort()
        self._port = None

    def _retried(self, transaction: Callable[[], T]) -> T:
        """``transaction`` (a request and its answer), tried up to ``TRIES`` times (the
        SDK flushes the input before each request: a late answer to a failed try that
        came meanwhile is not taken for the next one's)."""
        for _ in range(TRIES - 1):
            with contextlib.suppress(DriverError):
                return transaction()
        return transaction()

    def _ping(self, servo_id: int) -> None:
        _, result, _ = self._packet.ping(self._port, servo_id)
        if result != COMM_SUCCESS:
            raise DriverError(f"servo {servo_id} does not answer on {self.port}")

    def _read(self, servo_id: int, address: int, length: int) -> bytes:
        """``length`` bytes at ``address`` of one servo (one try: callers retry it with
        their check of the value)."""
        if self._packet.readTx(self._port, servo_id, address, length) != COMM_SUCCESS:
            raise DriverError(f"servo {servo_id}: reading address {address} failed (not sent)")
        return self._receive(
            servo_id, length, f"servo {servo_id}: reading address {address} failed"
        )[0]

    def _receive(self, servo_id: int, length: int, failed: str) -> tuple[bytes, int]:
        """The parameters (exactly ``length`` bytes) and error byte of ``servo_id``'s next
        status packet (``failed``: what no answer is called); other servos' are skipped, as
        the SDK's readRx does. A status packet says nothing of what it answers: one that
        comes late (to an earlier request, after the SDK stopped waiting) is met here. The
        SDK's readRx and readNByteTxRx would slice ``length`` bytes out of it checksum
        included, or index past its end."""
        import dynamixel_sdk as sdk

        while True:
            packet, result = self._packet.rxPacket(self._port, False)
            if result != sdk.COMM_SUCCESS:
                why = self._packet.getTxRxResult(result)
                raise DriverError(f"{failed}: {why}")
            if packet[STATUS_ID] == servo_id:
                break
        # LENGTH counts instruction, error, parameters and checksum (after unstuffing; the
        # SDK leaves the bytes stuffing took at the list's end)
        size = packet[STATUS_LENGTH] | packet[STATUS_LENGTH + 1] << 8
        params = bytes(packet[STATUS_PARAMS : STATUS_PARAMS + size - 4])
        if len(params) != length:
            raise BadReplyError(f"servo {servo_id} answered {len(params)} bytes where {length} "
                                "were asked (a late answer to an earlier request?): not a "
                                "reading")  # fmt: skip
        return params, int(packet[STATUS_ERROR])

    def _read1(self, servo_id: int, name: str) -> int:
        """The one-byte field ``name`` (of ADDRESS), refused unless it holds a valid value."""

        def read() -> int:
            value = self._read(servo_id, ADDRESS[name], 1)[0]
            if value not in VALID[name]:
                raise BadReplyError(f"servo {servo_id} reported {name} {value}: not a reading")
            return value

        return self._retried(read)

    def _read_position(self, servo_id: int) -> int:
        """The present position [ticks], refused outside what a servo reports."""

        def read() -> int:
            data = self._read(servo_id, ADDRESS["present"] + 6, 4)
            value = int(struct.unpack("<i", data)[0])
            low, high = PRESENT_RANGE[2]
            if not low <= value <= high:
                raise BadReplyError(f"servo {servo_id} reported position {value}: not a reading")
            return value

        return self._retried(read)

    def _write1(self, servo_id: int, address: int, value: int) -> None:
        self._retried(lambda: self._write_once(servo_id, address, bytes([value])))

    def _write_once(self, servo_id: int, address: int, data: bytes) -> None:
        result, error = self._packet.writeTxRx(self._port, servo_id, address, len(data),
                                               list(data))  # fmt: skip
        if result != COMM_SUCCESS or error & 0x7F:
            raise DriverError(f"servo {servo_id}: writing {list(data)} at {address} failed "
                              f"({self._packet.getTxRxResult(result)}, error {error})")  # fmt: skip
