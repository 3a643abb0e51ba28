"""Dynamixel Protocol 2.0 framing on the device side: instruction packets parsed from a
byte stream, status packets built. CRC-16 and byte stuffing are the official
dynamixel-sdk's own functions, so the emulated servos and the host cannot disagree.

Packet: FF FF FD 00 | ID | LEN_L LEN_H | INSTRUCTION | (ERROR) PARAMS... | CRC_L CRC_H,
LEN counting everything after itself; FF FF FD inside the payload is sent as FF FF FD FD.
"""

from __future__ import annotations

from dataclasses import dataclass

from dynamixel_sdk import INST_STATUS, Protocol2PacketHandler

HEADER = bytes([0xFF, 0xFF, 0xFD, 0x00])
BROADCAST_ID = 0xFE
MAX_PACKET = 1024
_SDK = Protocol2PacketHandler()


@dataclass(frozen=True)
class Instruction:
    servo_id: int
    instruction: int
    params: bytes


@dataclass(frozen=True)
class CorruptPacket:
    """A complete packet whose CRC does not match (the device answers nothing)."""

    servo_id: int


def crc16(data: bytes | list[int]) -> int:
    return int(_SDK.updateCRC(0, list(data), len(data)))


def status_packet(servo_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet (stuffed, with its CRC)."""
    length = len(params) + 4  # instruction, error, CRC
    packet = [*HEADER, servo_id, length & 0xFF, length >> 8, INST_STATUS, error, *params, 0, 0]
    packet = _SDK.addStuffing(packet)
    crc = crc16(packet[:-2])
    packet[-2:] = [crc & 0xFF, crc >> 8]
    return bytes(packet)


def instruction_packet(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction packet as a host sends it (for tests and fault injection)."""
    length = len(params) + 3  # instruction, CRC
    packet = [*HEADER, servo_id, length & 0xFF, length >> 8, instruction, *params, 0, 0]
    packet = _SDK.addStuffing(packet)
    crc = crc16(packet[:-2])
    packet[-2:] = [crc & 0xFF, crc >> 8]
    return bytes(packet)


class PacketReader:
    """Accumulates bytes from the bus; returns each complete packet once it has arrived.
    Noise before a header is skipped; an impossible length drops the header."""

    def __init__(self) -> None:
        self.buffer = bytearray()

    def feed(self, data: bytes) -> list[Instruction | CorruptPacket]:
        self.buffer += data
        packets: list[Instruction | CorruptPacket] = []
        while True:
            start = self.buffer.find(HEADER[:3])
            if start < 0:
                del self.buffer[: max(0, len(self.buffer) - 2)]  # keep a split header
                return packets
            del self.buffer[:start]
            if len(self.buffer) < 7:
                return packets
            length = self.buffer[5] | self.buffer[6] << 8
            if not 3 <= length <= MAX_PACKET or self.buffer[3] != 0x00:
                del self.buffer[:3]  # not a packet: look for the next header
                continue
            if len(self.buffer) < 7 + length:
                return packets
            raw = list(self.buffer[: 7 + length])
            del self.buffer[: 7 + length]
            packets.append(_parse(raw))

    def pending(self) -> int:
        return len(self.buffer)


def _parse(raw: list[int]) -> Instruction | CorruptPacket:
    servo_id = raw[4]
    if crc16(raw[:-2]) != (raw[-2] | raw[-1] << 8):
        return CorruptPacket(servo_id)
    packet = _SDK.removeStuffing(raw)
    length = packet[5] | packet[6] << 8
    return Instruction(servo_id, packet[7], bytes(packet[8 : 8 + length - 3]))
