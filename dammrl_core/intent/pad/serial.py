"""Frames from the pressure sensor's serial port, surviving a device that comes and goes.

One reader serves the intent service, ``dammrl sensor monitor|calibrate`` and the
benchmark: it opens the port (again with exponential back-off after it disappears),
waits at most ``poll_s`` for bytes, and returns the valid frames with their arrival time
and how many frames were lost before each (from the sequence numbers).
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass

import serial

from dammrl_core.intent.pad.protocol import BAUD_RATE, Frame, FrameParser, frames_lost

log = logging.getLogger("dammrl.intent")

FIRST_BACKOFF_S = 0.5


@dataclass(frozen=True)
class Arrival:
    t_s: float  # time.monotonic() when the frame was read off the port
    frame: Frame
    lost_frames: int | None = 0  # missing just before it; None: the first since opening


class SerialSensor:
    def __init__(
        self,
        device: str,
        baud_rate: int = BAUD_RATE,
        reconnect_max_s: float = 5.0,
        poll_s: float = 0.005,
    ) -> None:
        self.device = device
        self.baud_rate = baud_rate
        self.reconnect_max_s = reconnect_max_s
        self.poll_s = poll_s
        self.parser = FrameParser()
        self.port: serial.Serial | None = None
        self.last_frame_s = 0.0
        self.last_error = ""
        self._last_seq: int | None = None  # None: nothing received since the port opened
        self._retry_at, self._backoff_s = 0.0, FIRST_BACKOFF_S

    @property
    def connected(self) -> bool:
        return self.port is not None

    def silent_for(self) -> float:
        """Seconds since the last valid frame (or since the port was opened)."""
        return time.monotonic() - self.last_frame_s

    def read(self) -> list[Arrival]:
        """The frames that arrived within ``poll_s`` (sleeps that long while disconnected)."""
        port = self._open()
        if port is None:
            time.sleep(self.poll_s)
            return []
        try:
            data = port.read(port.in_waiting or 1)
        except (serial.SerialException, OSError) as exc:
            self.last_error = str(exc)
            log.warning("sensor lost (%s): reconnecting", exc)
            self.close()
            return []
        now = time.monotonic()
        frames = self.parser.feed(data)
        if frames:
            self.last_frame_s = now
        return [self._arrival(now, frame) for frame in frames]

    def _arrival(self, t_s: float, frame: Frame) -> Arrival:
        lost = frames_lost(self._last_seq, frame.seq)
        self._last_seq = frame.seq
        return Arrival(t_s, frame, lost)

    def close(self) -> None:
        if self.port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self.port.close()
        self.port = None
        self._last_seq = None  # whatever comes next may be another device, or a restarted one

    def __enter__(self) -> SerialSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _open(self) -> serial.Serial | None:
        if self.port is not None:
            return self.port
        now = time.monotonic()
        if now < self._retry_at:
            return None
        try:
            self.port = serial.Serial(self.device, self.baud_rate, timeout=self.poll_s)
        except (serial.SerialException, OSError) as exc:
            self.last_error = str(exc)
            self._retry_at = now + self._backoff_s
            log.warning(
                "cannot open %s (%s); next try in %.1f s", self.device, exc, self._backoff_s
            )
            self._backoff_s = min(self._backoff_s * 2, self.reconnect_max_s)
            return None
        log.info("sensor connected on %s", self.device)
        self._backoff_s, self.last_frame_s, self.last_error = FIRST_BACKOFF_S, now, ""
        return self.port
