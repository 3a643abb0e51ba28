"""Stale holds and state gaps of the real-time stack under load (prints figures).

``dammrl up --record`` runs N episodes while a second process floods an unrelated key
under the namespace (which the recorder, subscribed to everything, must write) at a
given rate, with ``DAMMRL_BUS_REALTIME`` off and on, and again beside two busy programs
(another workload on the lab's PC). Per configuration: episodes that ended as a stale
hold, the worst gap between consecutive robot states as the sim stamped them (its own
delay) and as the recorder received them, and the states lost on the way (by sequence
number).

    PYTHONPATH=. python benchmarks/load_holds.py [--episodes 20] [--flood-hz 10000]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import zenoh
from mcap.reader import make_reader

from services.common.bus import zenoh_config
from tests.busutil import client_settings, free_port

CONFIGS = {  # name: (CPU hogs, DAMMRL_BUS_REALTIME); the recorder and the flood always
    "recorder + flood, realtime off": (0, "false"),
    "recorder + flood, realtime on": (0, "true"),
    "+ 2 CPU hogs, realtime off": (2, "false"),
    "+ 2 CPU hogs, realtime on": (2, "true"),
}
HOG = "while True: pass"  # another program on the lab's PC, at the default priority


def _flood(port: int, rate_hz: float, stop: threading.Event, sent: list[int]) -> None:
    """Publish ``rate_hz`` 100-byte messages per second on ``dammrl/flood`` (batched)."""
    with zenoh.open(zenoh_config(client_settings(port))) as session:
        publisher = session.declare_publisher("dammrl/flood")
        payload, batch, started = bytes(100), max(1, int(rate_hz / 100)), time.monotonic()
        while not stop.is_set():
            for _ in range(batch):
                publisher.put(payload)
            sent[0] += batch
            delay = started + sent[0] / rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)


def _states(recording: Path) -> tuple[int, float, float]:
    """Robot states lost on the way to the recorder (by the sim's sequence numbers), the
    worst gap between consecutive states as the sim stamped them (the sim's own delay) and
    the worst gap between the states the recorder received [s]."""
    rows = []
    with recording.open("rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages():
            if channel.topic.endswith("robot/state"):
                seq = msgpack.unpackb(message.data)["header"]["seq"]
                rows.append((seq, message.publish_time, message.log_time))
    seq, stamps, receipts = (np.array(column) for column in zip(*sorted(rows), strict=True))
    consecutive = np.diff(seq) == 1
    lost = int(seq[-1] - seq[0] + 1 - len(seq))
    sim_gap = float(np.max(np.diff(stamps)[consecutive])) * 1e-9
    return lost, sim_gap, float(np.max(np.diff(np.sort(receipts)))) * 1e-9


def run(name: str, hogs: int, realtime: str, episodes: int, rate_hz: float) -> str:
    port = free_port()
    folder = Path(tempfile.mkdtemp(prefix="load-"))
    command = [sys.executable, "-m", "dammrl", "up", "--insecure", "--json", "--model", "2,1",
               "--episodes", str(episodes), "--seed", "7000200", "--bus-port", str(port),
               "--record", str(folder / "run.mcap")]  # fmt: skip
    env = os.environ | {"DAMMRL_LOG_LEVEL": "WARNING", "DAMMRL_BUS_REALTIME": realtime}
    stop, sent = threading.Event(), [0]
    launcher = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=env)  # fmt: skip
    flooder = threading.Thread(target=_flood, args=(port, rate_hz, stop, sent), daemon=True)
    time.sleep(8)  # the stack is up
    flooder.start()
    busy = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(hogs)]
    started = time.monotonic()
    try:
        out, err = launcher.communicate(timeout=60 + 60 * episodes)
    finally:
        stop.set()
        for hog in busy:
            hog.kill()
    results = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    holds = sum(r["outcome"] == "hold" for r in results)
    lost, sim_gap, received_gap = _states(folder / "run.mcap")
    rate = sent[0] / (time.monotonic() - started)
    if launcher.returncode != 0:
        print(err[-2000:], file=sys.stderr)
    return (f"{name:30s} episodes {len(results):3d}  stale holds {holds:3d}  worst state gap: "
            f"sim {sim_gap * 1e3:4.0f} ms, received {received_gap * 1e3:4.0f} ms  states lost "
            f"{lost:4d}  flood {rate:6.0f} msg/s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--flood-hz", type=float, default=10_000)
    args = parser.parse_args()
    for name, (hogs, realtime) in CONFIGS.items():
        print(run(name, hogs, realtime, args.episodes, args.flood_hz), flush=True)


if __name__ == "__main__":
    main()
