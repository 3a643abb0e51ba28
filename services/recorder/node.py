"""The recorder node: everything under the namespace, to MCAP, until a signal.

The Zenoh callback only enqueues (key, bytes, receipt time); the loop writes. Files rotate
by size or duration; ``finish()`` runs on SIGINT/SIGTERM (in a ``finally``). After a
``kill -9`` the file is readable up to its last complete chunk (``dammrl recording repair``).
"""

from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import zenoh

from dammrl.core.errors import DammrlError
from services.common.bus import Bus
from services.common.entry import run_service
from services.recorder.config import RecorderSettings
from services.recorder.core import McapRecorder

log = logging.getLogger("dammrl.recorder")


class RecorderNode:
    def __init__(self, settings: RecorderSettings, bus: Bus) -> None:
        self.settings = settings
        self.bus = bus
        self.inbox: queue.Queue[tuple[str, bytes, int]] = queue.Queue(2_000_000)
        self.dropped = 0
        self.files: list[Path] = []
        self.recorder = self._open()
        self._subscriber = bus.session.declare_subscriber(f"{bus.namespace}/**", self._enqueue)

    def _enqueue(self, sample: zenoh.Sample) -> None:
        try:
            self.inbox.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
        except queue.Full:
            self.dropped += 1

    def run(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                self._write_pending(timeout_s=0.1)
                self._rotate_if_due()
                total = sum(self.recorder.loss.messages.values())
                self.bus.report_health(detail=f"{total} messages in {self.recorder.path.name}")
            self._write_pending(timeout_s=0.0)  # what arrived before the signal
        finally:
            self.recorder.finish()
            log.info("finished %s", self.recorder.path)

    def _write_pending(self, timeout_s: float) -> None:
        try:
            item = self.inbox.get(timeout=timeout_s) if timeout_s else self.inbox.get_nowait()
        except queue.Empty:
            return
        while True:
            self.recorder.record(*item)
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                return

    def _rotate_if_due(self) -> None:
        s, r = self.settings, self.recorder
        too_big = s.max_bytes is not None and r.bytes_written() >= s.max_bytes
        started = r.first_ns or time.time_ns()
        too_long = (
            s.max_duration_s is not None and time.time_ns() - started >= s.max_duration_s * 1e9
        )
        if too_big or too_long:
            r.finish()
            self.recorder = self._open()

    def _open(self) -> McapRecorder:
        out = self.settings.out
        if out.suffix == ".mcap":
            path = (
                out if not self.files else out.with_name(f"{out.stem}-{len(self.files):03d}.mcap")
            )
        else:
            path = out / f"session-{datetime.now(UTC):%Y%m%d-%H%M%S-%f}.mcap"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DammrlError(f"cannot create {path.parent}: {exc}") from exc
        self.files.append(path)
        log.info("recording to %s", path)
        metadata = {"mode": self.settings.mode, "settings": self.settings.model_dump_json()}
        return McapRecorder(path, self.bus.namespace, metadata, self.settings.chunk_bytes)


def main(argv: Sequence[str] | None = None) -> int:
    """Recorder service: everything on the bus to MCAP."""
    return run_service(
        "recorder",
        "Recorder service: everything on the bus to MCAP (zstd chunks).",
        "DAMMRL_RECORDER_* (OUT, MAX_BYTES, MAX_DURATION_S, CHUNK_BYTES, MODE)",
        lambda bus, args: RecorderNode(_settings(args), bus),
        argv,
        _add_out_argument,
    )


def _add_out_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, help="a .mcap file or a directory (default sessions/)")


def _settings(args: argparse.Namespace) -> RecorderSettings:
    return RecorderSettings(out=args.out) if args.out else RecorderSettings()
