"""A virtual pressure sensor on a pseudo-terminal: the semi-virtual path without hardware.

It opens a pty pair, links the slave side to a path (e.g. /tmp/ttySENSOR) that any
serial client (pyserial, the intent service) opens like a real port, and writes frames
of the wire protocol at the sensor's rate from a press script, with ADC noise, and on
demand drop-outs, corrupted bytes and glitches (valid frames with a wrong reading).
Presses can also be added while it runs (:meth:`SensorEmulator.press`,
:meth:`SensorEmulator.hold`): from the keyboard or from a simulated patient
(``services/intent/patient.py``).
"""

from __future__ import annotations

import os
import threading
import time
import tty
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl_core.intent.pad.calibration import DEFAULT_CALIBRATION, NOISE_RAW
from dammrl_core.intent.pad.decoder import Calibration
from dammrl_core.intent.pad.protocol import RAW_MAX, SAMPLE_RATE_HZ, encode_frame


@dataclass(frozen=True)
class Press:
    start_s: float  # from the start of the script
    duration_s: float
    level: float  # 0 rest .. 1 firm (normalised)


def press_level(presses: Sequence[Press], t_s: float, ramp_s: float = 0.05) -> float:
    """Normalised pressure of a press script at ``t_s`` (trapezoid presses)."""
    level = 0.0
    for p in presses:
        rise = min(t_s - p.start_s, p.start_s + p.duration_s - t_s) / ramp_s
        level = max(level, p.level * min(max(rise, 0.0), 1.0))
    return level


class SensorEmulator:
    """Writes frames into a pty until stopped (a context manager)."""

    def __init__(
        self,
        link: Path,
        presses: Sequence[Press],
        calibration: Calibration = DEFAULT_CALIBRATION,
        noise_raw: float = NOISE_RAW,
        seed: int = 0,
        loop_s: float | None = None,
        rate_hz: float = SAMPLE_RATE_HZ,
        record_write_times: bool = False,
    ) -> None:
        self.link = Path(link)
        self.presses = list(presses)
        self.calibration = calibration
        self.noise_raw = noise_raw
        self.loop_s = loop_s
        self.rate_hz = rate_hz
        self.live: list[Press] = []  # presses added while running, on the emulator's clock
        self.held_level = 0.0  # a press held until released (keyboard)
        self.write_times: dict[int, float] | None = {} if record_write_times else None
        """When each frame (by absolute sequence number) was written (benchmarks)."""
        self.rng = np.random.default_rng(seed)
        self.silent = threading.Event()  # set: a drop-out, nothing is sent
        self.corrupt_next = 0  # frames still to corrupt
        self._glitch: tuple[int, int] = (0, 0)  # (frames still to glitch, their raw reading)
        self.sent = 0
        self._stop = threading.Event()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes as they are
        if self.link.is_symlink() or self.link.exists():
            self.link.unlink()
        self.link.symlink_to(os.ttyname(self._slave))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._start = time.monotonic()

    def __enter__(self) -> SensorEmulator:
        self._start = time.monotonic()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.link.unlink(missing_ok=True)
        for fd in (self._master, self._slave):
            os.close(fd)

    @property
    def clock_s(self) -> float:
        """Seconds since the emulator started (the time of its next frame)."""
        return time.monotonic() - self._start

    def press(self, level: float, duration_s: float, delay_s: float = 0.0) -> None:
        """Add one press starting ``delay_s`` from now."""
        now = self.clock_s
        recent = [p for p in self.live if p.start_s + p.duration_s > now - 1.0]
        self.live = [*recent, Press(now + delay_s, duration_s, level)]  # one atomic swap

    def hold(self, level: float) -> None:
        """Press at ``level`` until :meth:`hold` is called again (0 releases)."""
        self.held_level = level

    def glitch(self, raw: int, frames: int) -> None:
        """Send ``raw`` in the next ``frames`` valid frames (a spike, or a drop to 0)."""
        self._glitch = (frames, min(max(raw, 0), RAW_MAX))

    def inject(self, data: bytes) -> None:
        """Write arbitrary bytes into the line (garbage, cut or overlong frames)."""
        os.write(self._master, data)

    def level_at(self, script_t_s: float, t_s: float) -> float:
        scripted = press_level(self.presses, script_t_s)
        return max(scripted, press_level(self.live, t_s), self.held_level)

    def raw_of(self, level: float) -> int:
        """The ADC reading of a normalised pressure, with noise."""
        c = self.calibration
        raw = c.rest_raw + level * (c.firm_raw - c.rest_raw) + self.rng.normal(0, self.noise_raw)
        return int(min(max(raw, 0), RAW_MAX))

    def _reading(self, level: float) -> int:
        """The raw reading of the next frame: the pad's, or a glitch's."""
        left, raw = self._glitch
        if left <= 0:
            return self.raw_of(level)
        self._glitch = (left - 1, raw)
        return raw

    def _run(self) -> None:
        period, seq = 1.0 / self.rate_hz, 0
        while not self._stop.is_set():
            t = seq * period
            script_t = t % self.loop_s if self.loop_s else t
            frame = encode_frame(seq, self._reading(self.level_at(script_t, t)))
            if self.corrupt_next > 0:
                self.corrupt_next -= 1
                frame = frame[:4] + b"\x07" + frame[5:]  # one bad byte: the checksum fails
            if not self.silent.is_set():
                os.write(self._master, frame)
                if self.write_times is not None:
                    self.write_times[seq] = time.monotonic()
                self.sent += 1
            seq += 1
            delay = self._start + seq * period - time.monotonic()
            if delay > 0:  # behind schedule: the next frames go out back to back
                time.sleep(delay)
