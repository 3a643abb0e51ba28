"""One logging format for every service: time, service, level, message.

A service never waits for its log: records go through a bounded queue to a writer
thread, so a slow or full stderr (a pipe nobody reads, a slow terminal, a stalled
``ssh``) cannot stall the arm's loop; if the queue fills, records are dropped and
counted, and the count is logged once the writer catches up.
"""

from __future__ import annotations

import atexit
import logging
import logging.handlers
import os
import queue
import time

QUEUE_SIZE = 10_000
"""Records waiting for stderr before new ones are dropped."""


class DroppingQueueHandler(logging.handlers.QueueHandler):
    """A ``QueueHandler`` that drops (and counts) records when the queue is full."""

    def __init__(self, records: queue.Queue[logging.LogRecord]) -> None:
        super().__init__(records)
        self.records = records
        self.dropped = 0

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            if self.dropped and self.records.empty():
                self.records.put_nowait(_dropped_record(record, self.dropped))
                self.dropped = 0
            self.records.put_nowait(record)
        except queue.Full:
            self.dropped += 1


def _dropped_record(like: logging.LogRecord, dropped: int) -> logging.LogRecord:
    return logging.LogRecord(
        like.name, logging.WARNING, __file__, 0,
        "%d log records dropped: stderr did not keep up", (dropped,), None,
    )  # fmt: skip


def _drain(records: queue.Queue[logging.LogRecord], within_s: float = 1.0) -> None:
    """At exit, give the writer a moment to write what is queued (never forever: a
    blocked stderr must not keep a stopped service alive)."""
    deadline = time.monotonic() + within_s
    while not records.empty() and time.monotonic() < deadline:
        time.sleep(0.01)


def setup_logging(service: str) -> logging.Logger:
    """Log to stderr at ``DAMMRL_LOG_LEVEL`` (default INFO), through a writer thread."""
    level = os.environ.get("DAMMRL_LOG_LEVEL", "INFO").upper()
    writer = logging.StreamHandler()
    writer.setFormatter(logging.Formatter(f"%(asctime)s {service} %(levelname)s %(message)s"))
    records: queue.Queue[logging.LogRecord] = queue.Queue(QUEUE_SIZE)
    listener = logging.handlers.QueueListener(records, writer)
    listener.start()  # a daemon thread
    atexit.register(_drain, records)
    handler = DroppingQueueHandler(records)
    # the queue carries the message alone (the writer adds time, service and level):
    # basicConfig would otherwise give it its own "LEVEL:name:" format, printed twice
    handler.setFormatter(logging.Formatter("%(message)s"))
    logging.basicConfig(
        level=level if level in logging.getLevelNamesMapping() else "INFO",
        handlers=[handler],
        force=True,
    )
    return logging.getLogger(f"dammrl.{service}")
