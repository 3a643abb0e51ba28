"""Load never stalls the arm's loop.

Found under load: the sim froze (no state for seconds, every episode a stale hold)
because its log writes blocked on a stderr pipe that was read too slowly. A service now
logs through a bounded queue and a writer thread (``services/common/logs.py``).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from schemas import RobotState
from services.common.logs import DroppingQueueHandler
from tests.busutil import Observer, client_settings, free_port, wait_for


def test_a_full_log_queue_drops_and_counts_instead_of_waiting() -> None:
    records: queue.Queue[logging.LogRecord] = queue.Queue(3)
    handler = DroppingQueueHandler(records)
    logger = logging.getLogger("test.dropping")
    logger.addHandler(handler)
    logger.propagate = False
    started = time.monotonic()
    for n in range(10):
        logger.warning("record %d", n)
    assert time.monotonic() - started < 0.5 and records.qsize() == 3 and handler.dropped == 7
    while not records.empty():
        records.get_nowait()
    logger.warning("after")
    said = [records.get_nowait().getMessage() for _ in range(records.qsize())]
    assert said == ["7 log records dropped: stderr did not keep up", "after"]


@pytest.mark.slow
def test_the_sim_keeps_its_period_when_nobody_reads_its_log() -> None:
    """A stray peer floods the sim with bad commands (each rejection may be logged) while
    the sim's stderr is a pipe nobody reads: its 64 KiB fill within seconds."""
    port = free_port()
    observer = Observer(port)
    env = os.environ | {"DAMMRL_BUS_CONNECT": json.dumps([f"tcp/127.0.0.1:{port}"])}
    sim = subprocess.Popen([sys.executable, "-m", "services.sim"], env=env,
                           stderr=subprocess.PIPE)  # fmt: skip
    try:
        wait_for(lambda: len(observer.of(RobotState)) > 10, 30, "the sim's states")
        with zenoh.open(_zenoh_config(port)) as session:
            publisher = session.declare_publisher("dammrl/robot/command")
            until = time.monotonic() + 12
            while time.monotonic() < until:
                for _ in range(50):
                    publisher.put(b"\x81\xa1x\x01")  # not a JointCommand: rejected, logged
                time.sleep(0.005)
        stamps = np.array([m.header.stamp_ns for m in observer.of(RobotState)]) * 1e-9
        assert time.time() - stamps[-1] < 0.5, "the sim stopped publishing"
        assert np.max(np.diff(stamps)) < 0.25
    finally:
        sim.kill()
        sim.wait()
        observer.close()


def _zenoh_config(port: int) -> zenoh.Config:
    from services.common.bus import zenoh_config

    return zenoh_config(client_settings(port))
