"""The recorder node: everything under the namespace, to MCAP, until a signal.

The Zenoh callback only enqueues (key, bytes, receipt time, publishing session); the loop
writes, in slices of at most ``WRITE_SLICE_S`` so that it also closes chunks by age
(``chunk_s``), rotates files and reports Health under any load. ``finish()`` runs on
SIGINT/SIGTERM (in a ``finally``). After a ``kill -9`` the file is readable up to its
last chunk, at most about ``chunk_s`` old (``dammrl recording repair`` completes it).

Once an episode's result (and the arm's state it was decided from) is written, the file
is synced and an ``EpisodeRecorded`` says so (``episodes.EpisodeLedger``): a session
stops its stack only after that; a finished file's ``dammrl.episodes`` metadata lists
the episodes it saw begin without their result.

A write error (a full disk) never stops the robot session: one error line, Health
"degraded" with the reason, the file left readable up to its last chunk, the messages
received meanwhile counted as not recorded, and a new file tried every ``retry_s``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import zenoh

from dammrl_core.errors import DammrlError
from schemas import EpisodeRecorded
from services.common.bus import Bus
from services.common.entry import run_service
from services.recorder.config import RecorderSettings
from services.recorder.core import McapRecorder, complete_mcap
from services.recorder.episodes import METADATA as EPISODES_METADATA
from services.recorder.episodes import EpisodeLedger

log = logging.getLogger("dammrl.recorder")

WRITE_SLICE_S = 0.1
"""The longest the loop writes before it looks at the clock again [s]."""

MAX_QUEUED_BYTES = 256 << 20
"""The writer's backlog in payload bytes beyond which new messages are dropped (counted)."""

Received = tuple[str, bytes, int, str]  # key, payload, receipt time [ns], Zenoh session id


class RecorderNode:
    def __init__(self, settings: RecorderSettings, bus: Bus) -> None:
        self.settings = settings
        self.bus = bus
        self.inbox: queue.Queue[Received] = queue.Queue(2_000_000)
        self.dropped = 0  # inbox overflow
        self.queued_bytes = 0  # payload bytes waiting to be written (approximate)
        self.not_recorded = 0  # received while no file could be written
        self.problem = ""  # why nothing is recorded ("" while recording)
        self.retry_at = 0.0
        self.files: list[Path] = []
        self.took_over = ""  # what this recorder found of a predecessor's cut file
        self.recorder: McapRecorder | None = None
        self.episodes = EpisodeLedger(bus.namespace)  # what a session waits to hear of
        self.acks = bus.publisher(EpisodeRecorded)
        self._try_open(startup=True)
        self._subscriber = bus.session.declare_subscriber(f"{bus.namespace}/**", self._enqueue)

    def _enqueue(self, sample: zenoh.Sample) -> None:
        key_expr = str(sample.key_expr)
        if not self.bus.admission.admit(key_expr, len(sample.payload)):
            return  # too large or too fast for its key: counted in Health, never queued
        source = sample.source_info  # set only by publishers that declare it
        session = "" if source is None else str(source.source_id.zid)
        if self.queued_bytes > MAX_QUEUED_BYTES:
            self.dropped += 1  # the writer is far behind: memory stays bounded
            return
        payload = sample.payload.to_bytes()
        try:
            self.inbox.put_nowait((key_expr, payload, time.time_ns(), session))
            self.queued_bytes += len(payload)
        except queue.Full:
            self.dropped += 1

    def run(self, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                self._write_pending(timeout_s=0.1)
                self._keep_up()
                self._acknowledge()
                self._report()
            self._write_pending(timeout_s=0.0)  # what arrived before the signal
            self._acknowledge()
        finally:
            self._close()

    def _write_pending(self, timeout_s: float) -> None:
        """Write what is queued, for at most ``WRITE_SLICE_S`` (``timeout_s``: the
        longest to wait for a first message; 0: drain without waiting)."""
        deadline = time.monotonic() + WRITE_SLICE_S
        try:
            item = self.inbox.get(timeout=timeout_s) if timeout_s else self.inbox.get_nowait()
            while True:
                self._write(item)
                if timeout_s and time.monotonic() > deadline:
                    return
                item = self.inbox.get_nowait()
        except queue.Empty:
            return

    def _write(self, item: Received) -> None:
        self.queued_bytes -= len(item[1])
        if self.recorder is None:
            self.not_recorded += 1
            return
        try:
            self.recorder.record(*item)
            self.episodes.written(item[0], item[1], time.monotonic())
        except OSError as exc:
            self._degrade(exc)
            self.not_recorded += 1

    def _keep_up(self) -> None:
        """Close an old chunk, rotate the file when due, or retry after a write error."""
        r, s = self.recorder, self.settings
        if r is None:
            if time.monotonic() >= self.retry_at:
                self._try_open()
            return
        try:
            if r.flush_due(time.time_ns(), s.chunk_s):
                r.flush()
                self.episodes.flushed()
            if self._rotation_due(r):
                self._finish(r)
                self._try_open()
        except OSError as exc:
            self._degrade(exc)

    def _rotation_due(self, r: McapRecorder) -> bool:
        s = self.settings
        too_big = s.max_bytes is not None and r.bytes_written() >= s.max_bytes
        started = r.first_ns or time.time_ns()
        too_long = (
            s.max_duration_s is not None and time.time_ns() - started >= s.max_duration_s * 1e9
        )
        return too_big or too_long

    def _report(self) -> None:
        if self.recorder is None:
            self.bus.report_health("degraded", self._detail())
        else:
            self.bus.report_health(detail=self._detail())

    def _detail(self) -> str:
        lost = self.not_recorded + self.dropped
        suffix = f"; {lost} messages not recorded" if lost else ""
        if self.recorder is None:
            return self.problem + suffix
        r = self.recorder
        total = sum(r.loss.messages.values()) + sum(r.invalid.values())
        after = f" ({self.took_over})" if self.took_over else ""
        return f"{total} messages in {r.path.name}{after}{suffix}"

    def _degrade(self, exc: OSError) -> None:
        """Leave the file being written (readable up to its last chunk) after an error."""
        assert self.recorder is not None
        self.episodes.write_failed(f"{self.recorder.path.name}: {_reason(exc)}")
        self.recorder.abandon()
        path, self.recorder = self.recorder.path, None
        self._pause(f"cannot write {path}: {_reason(exc)}")

    def _pause(self, problem: str) -> None:
        """Say once, in the log and in Health, why nothing is recorded; retry later."""
        if not self.problem:
            self.problem = f"not recording since {datetime.now(UTC):%H:%M:%S} UTC: {problem}"
            log.error("%s; a new file is tried every %g s", self.problem, self.settings.retry_s)
            self.bus.report_health("degraded", self._detail(), force=True)
        self.retry_at = time.monotonic() + self.settings.retry_s

    def _try_open(self, startup: bool = False) -> None:
        """Start a new file. At start-up a path that cannot be created is a bad setting
        (DammrlError); any other failure pauses the recording until a retry succeeds."""
        metadata = {"mode": self.settings.mode, "settings": self.settings.model_dump_json()}
        if self.settings.study:
            metadata["study"] = self.settings.study
        try:
            path = self._next_path()
            try:
                recorder = McapRecorder(
                    path, self.bus.namespace, metadata, self.settings.chunk_bytes
                )
            except OSError as exc:  # the disk is (still) full: that empty start is no file
                with contextlib.suppress(OSError):
                    path.unlink()
                self._pause(f"cannot write {path}: {_reason(exc)}")
                return
        except DammrlError as exc:
            if startup:
                raise
            self._pause(str(exc))
            return
        self.recorder = recorder
        self.files.append(path)
        if self.problem:
            log.warning("recording again, to %s (%d messages were not recorded)",
                        path, self.not_recorded)  # fmt: skip
            self.problem = ""
        log.info("recording to %s", path)

    def _next_path(self) -> Path:
        """The next file: ``out`` itself, then ``<stem>-001.mcap``, ... (a folder: one
        timestamped file each); never a file that exists (a restarted recorder's
        predecessor, cut by its death, is kept for repair)."""
        out = self.settings.out
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            if out.suffix != ".mcap":
                out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DammrlError(f"cannot create {out if out.suffix != '.mcap' else out.parent}: "
                              f"{exc}") from exc  # fmt: skip
        if out.suffix != ".mcap":
            return out / f"session-{datetime.now(UTC):%Y%m%d-%H%M%S-%f}.mcap"
        candidates = [out, *(out.with_name(f"{out.stem}-{n:03d}.mcap") for n in range(1, 10_000))]
        for path in candidates:
            if not path.exists():
                self._note_cut(path, candidates)
                return path
        raise DammrlError(f"{out}: 10,000 files of that name exist already")

    def _note_cut(self, path: Path, candidates: list[Path]) -> None:
        """Say in Health when the file before ``path`` was cut (no MCAP footer): this
        recorder took over after one that died."""
        index = candidates.index(path)
        if self.files or index == 0 or complete_mcap(candidates[index - 1]):
            return
        self.took_over = f"after a restart: {candidates[index - 1].name} was cut"
        log.warning("recording %s; the previous recorder's %s was cut (dammrl recording "
                    "repair completes it)", path.name, candidates[index - 1].name)  # fmt: skip

    def _acknowledge(self) -> None:
        """Say which episodes are on disk (synced first): a session stops its stack only
        once its last episode is (``EpisodeLedger``)."""
        recorder = self.recorder
        if recorder is None:
            return  # nothing reaches the disk now: nothing to promise
        acks = self.episodes.due(time.monotonic())
        if not acks:
            return
        try:
            recorder.sync()
        except OSError as exc:
            self._degrade(exc)
            self.episodes.not_acknowledged([ack.episode for ack in acks])  # said later
            return
        self.episodes.flushed()
        for ack in acks:
            if not ack.complete:
                log.warning("episode %d recorded without %s", ack.episode, ack.missing)
            self.acks.send(EpisodeRecorded(header=self.acks.stamp(), file=recorder.path.name,
                                           **dataclasses.asdict(ack)))  # fmt: skip

    def _finish(self, recorder: McapRecorder) -> None:
        recorder.writer.add_metadata(EPISODES_METADATA, self.episodes.metadata())
        recorder.finish()
        self.episodes.flushed()
        self.recorder = None
        log.info("finished %s", recorder.path)

    def _close(self) -> None:
        """Finish the file at the end (a write error leaves it cut, readable)."""
        if self.recorder is not None:
            try:
                self._finish(self.recorder)
            except OSError as exc:
                self._degrade(exc)


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def main(argv: Sequence[str] | None = None) -> int:
    """Recorder service: everything on the bus to MCAP."""
    return run_service(
        "recorder",
        "Recorder service: everything on the bus to MCAP (zstd chunks).",
        "DAMMRL_RECORDER_* (OUT, MAX_BYTES, MAX_DURATION_S, CHUNK_BYTES, CHUNK_S, RETRY_S, MODE)",
        lambda bus, args: RecorderNode(_settings(args), bus),
        argv,
        _add_out_argument,
    )


def _add_out_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, help="a .mcap file or a directory (default sessions/)")


def _settings(args: argparse.Namespace) -> RecorderSettings:
    return RecorderSettings(out=args.out) if args.out else RecorderSettings()
