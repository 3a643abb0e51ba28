"""The emulated Dynamixel chain answers the official dynamixel-sdk like real servos:
ping, sync read/write, error bits, the bus watchdog, and faults on demand."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    ERRBIT_ALERT,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from dammrl.devices.emulators.protocol2 import PacketReader, instruction_packet, status_packet
from dammrl.devices.emulators.servo_bus import ServoBusEmulator
from dammrl.devices.emulators.servo_chain import (
    BUS_WATCHDOG,
    GOAL_POSITION,
    HARDWARE_ERROR_STATUS,
    OVERLOAD_BIT,
    PRESENT_POSITION,
    TORQUE_ENABLE,
    XM430_W350,
    ServoChain,
)

IDS = [1, 2, 3, 4, 5, 6]


def test_frames_match_the_protocol_manual() -> None:
    """The e-manual's example: READ of present position (4 bytes) from ID 1."""
    packet = instruction_packet(1, 0x02, bytes([0x84, 0x00, 0x04, 0x00]))
    assert packet.hex(" ") == "ff ff fd 00 01 07 00 02 84 00 04 00 1d 15"
    reader = PacketReader()
    assert reader.feed(b"\x00\xff" + packet[:6]) == []  # noise, then half a packet
    (parsed,) = reader.feed(packet[6:])
    assert (parsed.servo_id, parsed.instruction, parsed.params) == (1, 2, packet[8:12])
    stuffed = status_packet(1, 0, bytes([0xFF, 0xFF, 0xFD, 0x01]))
    assert b"\xff\xff\xfd\xfd" in stuffed  # byte stuffing


@pytest.fixture()
def bus(tmp_path: Path) -> Iterator[tuple[ServoBusEmulator, PortHandler, PacketHandler]]:
    chain = ServoChain(IDS)
    with ServoBusEmulator(chain, tmp_path / "ttyROBOT") as emulator:
        port = PortHandler(str(tmp_path / "ttyROBOT"))
        assert port.openPort() and port.setBaudRate(1_000_000)
        yield emulator, port, PacketHandler(2.0)
        port.closePort()


def _sync_write_goals(port: PortHandler, packet: PacketHandler, ticks: int) -> None:
    writer = GroupSyncWrite(port, packet, GOAL_POSITION, 4)
    for servo_id in IDS:
        assert writer.addParam(servo_id, list(int(ticks).to_bytes(4, "little", signed=True)))
    assert writer.txPacket() == COMM_SUCCESS


def _sync_read_positions(port: PortHandler, packet: PacketHandler) -> tuple[int, dict[int, int]]:
    reader = GroupSyncRead(port, packet, PRESENT_POSITION, 4)
    for servo_id in IDS:
        assert reader.addParam(servo_id)
    result = reader.txRxPacket()
    values = {i: reader.getData(i, PRESENT_POSITION, 4) for i in IDS
              if reader.isAvailable(i, PRESENT_POSITION, 4)}  # fmt: skip
    return result, values


def test_the_official_sdk_pings_moves_and_reads_the_chain(bus) -> None:  # type: ignore[no-untyped-def]
    _, port, packet = bus
    for servo_id in IDS:
        model, result, error = packet.ping(port, servo_id)
        assert (model, result, error) == (XM430_W350, COMM_SUCCESS, 0)
    _, result, _ = packet.ping(port, 9)
    assert result == COMM_RX_TIMEOUT  # nobody there
    for servo_id in IDS:
        assert packet.write1ByteTxRx(port, servo_id, TORQUE_ENABLE, 1)[:2] == (COMM_SUCCESS, 0)
    _sync_write_goals(port, packet, 2048 + 300)
    time.sleep(0.4)  # the first-order servos settle (time constant 50 ms)
    result, positions = _sync_read_positions(port, packet)
    assert result == COMM_SUCCESS and set(positions) == set(IDS)
    assert all(abs(p - 2348) <= 2 for p in positions.values()), positions
    result, error = packet.write4ByteTxRx(port, 1, PRESENT_POSITION, 0)
    assert result == COMM_SUCCESS and error != 0  # read-only: an access error


def test_faults_on_demand(bus) -> None:  # type: ignore[no-untyped-def]
    emulator, port, packet = bus
    chain = emulator.chain
    with emulator.lock:
        chain.faults.corrupt_responses = 1
    assert packet.ping(port, 1)[1] == COMM_RX_CORRUPT  # a broken CRC is seen as such
    assert packet.ping(port, 1)[1] == COMM_SUCCESS  # and only once
    with emulator.lock:
        chain.faults.missing = {3}
    result, positions = _sync_read_positions(port, packet)
    assert result != COMM_SUCCESS and 3 not in positions  # one servo gone: the read fails
    with emulator.lock:
        chain.faults.missing = set()
        chain.overload(2)
    value, result, error = packet.read1ByteTxRx(port, 2, HARDWARE_ERROR_STATUS)
    assert result == COMM_SUCCESS and value & OVERLOAD_BIT and error & ERRBIT_ALERT
    assert packet.read1ByteTxRx(port, 2, TORQUE_ENABLE)[0] == 0  # the overload cut the torque
    with emulator.lock:
        chain.faults.unplugged = True
    assert packet.ping(port, 1)[1] == COMM_RX_TIMEOUT
    with emulator.lock:
        chain.faults.unplugged = False
    assert packet.ping(port, 1)[1] == COMM_SUCCESS  # replugged


def test_the_bus_watchdog_stops_a_servo_whose_host_went_quiet(bus) -> None:  # type: ignore[no-untyped-def]
    _, port, packet = bus
    assert packet.write1ByteTxRx(port, 1, TORQUE_ENABLE, 1)[:2] == (COMM_SUCCESS, 0)
    assert packet.write1ByteTxRx(port, 1, BUS_WATCHDOG, 5)[:2] == (COMM_SUCCESS, 0)  # 100 ms
    assert packet.write4ByteTxRx(port, 1, GOAL_POSITION, 2048 + 500)[:2] == (COMM_SUCCESS, 0)
    time.sleep(0.3)  # the host is silent for longer than the watchdog
    value, result, _ = packet.read1ByteTxRx(port, 1, BUS_WATCHDOG)
    assert result == COMM_SUCCESS and value == 0xFF  # expired: -1
    result, error = packet.write4ByteTxRx(port, 1, GOAL_POSITION, 2048)
    assert result == COMM_SUCCESS and error != 0  # goals refused until the watchdog is reset
    held = packet.read4ByteTxRx(port, 1, PRESENT_POSITION)[0]
    time.sleep(0.1)
    assert abs(packet.read4ByteTxRx(port, 1, PRESENT_POSITION)[0] - held) <= 1  # it stopped
    assert packet.write1ByteTxRx(port, 1, BUS_WATCHDOG, 0)[:2] == (COMM_SUCCESS, 0)
    assert packet.write4ByteTxRx(port, 1, GOAL_POSITION, 2048)[:2] == (COMM_SUCCESS, 0)


def test_the_dynamixel_driver_holds_moves_and_reports_through_the_emulated_chain(
    tmp_path: Path,
) -> None:
    """The real driver path, on the emulated bus: connect holds the arm where it is,
    commands move it, faults become DriverErrors or reported error bits, and the bus
    watchdog is armed so a dead host stops the servos."""
    import numpy as np

    from dammrl_core.arm.driver import DriveCommand, DriveFault, DriverError, driver_plugin
    from dammrl_core.arm.dynamixel.calibration import Calibration, save_calibration

    plugin = driver_plugin("dynamixel")

    chain = ServoChain(IDS)  # first-order servos: they follow their goals
    calibration = Calibration(offsets_rad=(0.1, 0, 0, 0, 0, -0.2), directions=(1, -1, 1, 1, 1, 1),
                              button_id=None)  # fmt: skip
    save_calibration(calibration, tmp_path / "arm.json")
    path = tmp_path / "ttyROBOT"
    settings = plugin.settings(port=str(path), calibration_file=tmp_path / "arm.json")
    with ServoBusEmulator(chain, path) as emulator:
        driver = plugin.create(settings)
        with driver:
            start = driver.read_state().q_rad
            target = start + np.array([0.2, -0.1, 0.05, 0.0, 0.1, -0.05])
            zeros, gains = np.zeros(6), np.full(6, 100.0)
            command = DriveCommand(target, zeros, zeros, gains, zeros, np.full(6, 10.0))
            until = time.monotonic() + 0.4
            while time.monotonic() < until:  # a control loop: the watchdog (0.1 s) stays fed
                driver.write_command(command)
                time.sleep(0.01)
            state = driver.read_state()
            np.testing.assert_allclose(state.q_rad, target, atol=2 / 651.9)  # 2 ticks
            assert state.faults == ()
            with emulator.lock:
                assert all(s.table[BUS_WATCHDOG] == 5 for s in chain.servos.values())
                chain.overload(4)
            fault = DriveFault(3, "servo 4: overload", restartable=True)
            assert driver.read_state().faults == (fault,)
            with emulator.lock:
                chain.faults.missing = {2}
            with pytest.raises(DriverError, match="servo 2 missing from the sync read"):
                driver.read_state()
            with emulator.lock:
                chain.faults.missing = set()
    with pytest.raises(DriverError, match="cannot open"):
        plugin.create(plugin.settings(port=str(tmp_path / "nothing"))).connect()
    with pytest.raises(Exception, match=r"unknown arm driver \(DAMMRL_ARM_DRIVER\) 'kuka'"):
        driver_plugin("kuka")
