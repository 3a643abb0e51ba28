"""The emulated sensor over a real pseudo-terminal, read with pyserial."""

from __future__ import annotations

import time
from pathlib import Path

import serial

from dammrl.devices.emulators.pad import DEFAULT_CALIBRATION, Press, SensorEmulator
from dammrl_core.intent.pad.decoder import PressDecoder
from dammrl_core.intent.pad.protocol import BAUD_RATE, SAMPLE_RATE_HZ, FrameParser
from dammrl_core.intent.pad.serial import Arrival, SerialSensor

SCRIPT = [Press(0.3, 0.25, 1.0), Press(1.0, 0.25, 0.35), Press(1.7, 0.8, 1.0)]


def _read(port: serial.Serial, seconds: float, parser: FrameParser) -> list[tuple[float, int]]:
    samples, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        for frame in parser.feed(port.read(port.in_waiting or 1)):
            samples.append((frame.seq / SAMPLE_RATE_HZ, frame.raw))
    return samples


def test_emulated_presses_decode_to_known_commands(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    with SensorEmulator(link, SCRIPT), serial.Serial(str(link), BAUD_RATE, timeout=0.05) as port:
        parser = FrameParser()
        samples = _read(port, 3.0, parser)
    decoder = PressDecoder(DEFAULT_CALIBRATION)
    decisions = [d for t, raw in samples if (d := decoder.update(t, raw)) is not None]
    assert [(d.u_h, d.human_model) for d in decisions] == [(1, 1), (-1, 1), (1, 2)]
    assert not parser.errors and len(samples) > 250


def test_corrupted_bytes_and_drop_outs_are_survived_and_counted(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    with (
        SensorEmulator(link, SCRIPT) as sensor,
        serial.Serial(str(link), BAUD_RATE, timeout=0.05) as port,
    ):
        parser = FrameParser()
        _read(port, 0.3, parser)
        sensor.corrupt_next = 5
        _read(port, 0.3, parser)
        sensor.silent.set()
        _read(port, 0.05, parser)  # what was already on its way
        quiet = _read(port, 0.3, parser)
        sensor.silent.clear()
        after = _read(port, 0.3, parser)
    assert parser.errors["checksum"] == 5
    assert quiet == [] and len(after) > 20


def test_a_glitch_is_that_many_valid_frames_of_that_reading(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    with (
        SensorEmulator(link, []) as sensor,
        serial.Serial(str(link), BAUD_RATE, timeout=0.05) as port,
    ):
        parser = FrameParser()
        _read(port, 0.2, parser)
        sensor.glitch(4095, 4)
        samples = _read(port, 0.3, parser)
    assert [raw for _, raw in samples].count(4095) == 4 and not parser.errors


def test_the_reader_counts_frames_lost_and_flags_the_first_after_opening(tmp_path: Path) -> None:
    link = tmp_path / "ttySENSOR"
    with SensorEmulator(link, []) as pad, SerialSensor(str(link)) as sensor:
        first = _arrivals(sensor, 0.2)
        pad.silent.set()
        _arrivals(sensor, 0.3)
        pad.silent.clear()
        after = _arrivals(sensor, 0.2)
    assert first[0].lost_frames is None and all(a.lost_frames == 0 for a in first[1:])
    assert 20 <= max(a.lost_frames or 0 for a in after) <= 40  # about 0.3 s at 100 Hz


def _arrivals(sensor: SerialSensor, seconds: float) -> list[Arrival]:
    arrivals, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        arrivals.extend(sensor.read())
    return arrivals
