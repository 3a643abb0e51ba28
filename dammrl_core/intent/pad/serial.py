"""Frames from the pressure sensor's serial port, surviving a device that comes and goes.

One reader serves the intent service, ``dammrl sensor monitor|calibrate`` and the
benchmark: it opens the port (again with exponential back-off after it disappears),
waits at most ``poll_s`` for bytes, and returns the valid frames with their arrival time,
the time each sample was taken (on this host's clock, from the pad's own count) and how
many frames were lost before each (from the sequence numbers).

A busy host delivers a serial port's bytes late and in bursts (the kernel hands them to
the reader from a worker thread that competes for the processor: on a 2-core machine
beside two CPU hogs, seconds late). The pad's count says when each sample was taken, so a
press is timed and decoded as the person made it however late its frames arrive; only a
lost frame breaks a press. And the port is read on a thread of its own (``PortPump``):
while that worker waits, a read or a poll of the port does not return at its timeout but
waits for the worker, in the kernel (``n_tty_poll`` flushes the port's pending input
first): on the calling thread, the intent service's whole loop (its Health, the
operator's takeover) froze for as long, up to 60 s beside two CPU hogs.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass

import serial

from dammrl_core.intent.pad.protocol import (
    BAUD_RATE,
    SAMPLE_RATE_HZ,
    SEQ_MODULO,
    Frame,
    FrameParser,
    frames_lost,
)

log = logging.getLogger("dammrl.intent")

FIRST_BACKOFF_S = 0.5
PUMP_WAIT_S = 0.1
"""The longest the port's thread waits in one read (a close wakes it at once)."""


MAX_CLOCK_DRIFT = 1e-3
"""How fast the pad's clock may run slow against this host's [s/s] (a crystal's is ~1e-4)."""


@dataclass(frozen=True)
class Arrival:
    t_s: float  # time.monotonic() when the frame was read off the port
    frame: Frame
    lost_frames: int | None  # missing just before it; None: the first since opening
    sampled_s: float  # when the pad took it, on time.monotonic()'s clock (PadClock)


class PadClock:
    """When each sample was taken, on this host's monotonic clock: the pad's count times
    its period, plus the offset of the least delayed arrival seen (the others came later
    than their sample by a delivery delay). The offset may grow by ``MAX_CLOCK_DRIFT`` per
    second, so a pad whose clock runs slow is followed; the times never run backwards."""

    def __init__(self, period_s: float = 1.0 / SAMPLE_RATE_HZ) -> None:
        self.period_s = period_s
        self.reset()

    def reset(self) -> None:
        """A new device, or the same one again: nothing known of its clock."""
        self._seq: int | None = None
        self._count = 0
        self._offset_s = self._offset_at_s = self._last_s = 0.0

    def sampled_at(self, seq: int, arrival_s: float) -> float:
        """The time the sample ``seq`` arriving at ``arrival_s`` was taken [s]."""
        if self._seq is None:
            self._offset_s, self._offset_at_s, self._last_s = arrival_s, arrival_s, -math.inf
        else:
            self._count += (seq - self._seq) % SEQ_MODULO
        self._seq = seq
        device_s = self._count * self.period_s
        drifted = self._offset_s + MAX_CLOCK_DRIFT * (arrival_s - self._offset_at_s)
        self._offset_s, self._offset_at_s = min(drifted, arrival_s - device_s), arrival_s
        self._last_s = max(self._last_s, device_s + self._offset_s)
        return self._last_s


class PortPump:
    """A serial port read on a thread of its own: every chunk of bytes with the time it was
    read off the port, or the error that ended the reading, into ``chunks``. The thread
    owns the port: it closes it as it ends, so a port closed while the kernel holds a read
    is never reused under it."""

    def __init__(self, port: serial.Serial) -> None:
        self.port = port
        self.chunks: queue.SimpleQueue[tuple[float, bytes] | Exception] = queue.SimpleQueue()
        self._stopping = threading.Event()
        threading.Thread(target=self._pump, name="serial-port", daemon=True).start()

    def stop(self) -> None:
        """End the reading (at once, unless the kernel holds the read; the port is closed
        when it ends)."""
        self._stopping.set()
        with contextlib.suppress(Exception):  # a port already gone
            self.port.cancel_read()

    def _pump(self) -> None:
        port = self.port
        try:
            while not self._stopping.is_set():
                data = port.read(port.in_waiting or 1)
                if data:
                    self.chunks.put((time.monotonic(), data))
        except Exception as exc:  # any end of the reading reaches the reader, which reopens
            if not self._stopping.is_set():
                self.chunks.put(exc)
        finally:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()


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
        self.pump: PortPump | None = None
        self.last_frame_s = 0.0
        self.last_error = ""
        self._last_seq: int | None = None  # None: nothing received since the port opened
        self.clock = PadClock()
        self._retry_at, self._backoff_s = 0.0, FIRST_BACKOFF_S

    @property
    def connected(self) -> bool:
        return self.pump is not None

    def silent_for(self) -> float:
        """Seconds since the last valid frame (or since the port was opened)."""
        return time.monotonic() - self.last_frame_s

    def read(self) -> list[Arrival]:
        """The frames that arrived within ``poll_s`` (sleeps that long while disconnected)."""
        pump = self._open()
        if pump is None:
            time.sleep(self.poll_s)
            return []
        arrivals: list[Arrival] = []
        with contextlib.suppress(queue.Empty):
            chunk = pump.chunks.get(timeout=self.poll_s)
            while True:
                if isinstance(chunk, Exception):
                    self.last_error = str(chunk)
                    log.warning("sensor lost (%s): reconnecting", chunk)
                    self.close()
                    return arrivals
                t_s, data = chunk
                frames = self.parser.feed(data)
                if frames:
                    self.last_frame_s = t_s
                arrivals += [self._arrival(t_s, frame) for frame in frames]
                chunk = pump.chunks.get_nowait()
        return arrivals

    def _arrival(self, t_s: float, frame: Frame) -> Arrival:
        lost = frames_lost(self._last_seq, frame.seq)
        self._last_seq = frame.seq
        return Arrival(t_s, frame, lost, self.clock.sampled_at(frame.seq, t_s))

    def close(self) -> None:
        if self.pump is not None:
            self.pump.stop()
        self.pump = None
        self._last_seq = None  # whatever comes next may be another device, or a restarted one
        self.clock.reset()

    def __enter__(self) -> SerialSensor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _open(self) -> PortPump | None:
        if self.pump is not None:
            return self.pump
        now = time.monotonic()
        if now < self._retry_at:
            return None
        try:
            port = serial.Serial(self.device, self.baud_rate, timeout=PUMP_WAIT_S)
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
        self.pump = PortPump(port)
        return self.pump
