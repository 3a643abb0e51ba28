"""What the viewer's subprotocol gate costs: messages from `FoxgloveServer.log` to a
WebSocket client, straight from the SDK's server (the baseline, same run) and through the
gate on the public port (what every client gets), with each subprotocol name.

    python benchmarks/viewer_gate.py [--messages 3000]

Prints the one-way latency (log call to the client's receipt, same machine) p50/p99 and
the throughput of a burst, and the ratios gate/direct.
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time

from websockets.sync.client import connect

from dammrl.views.viewer import FoxgloveServer
from dammrl_core.robot import RobotDescription
from tests.busutil import free_port

TOPIC = "/dammrl/error"


def _subscribe(ws) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        frame = ws.recv(timeout=1)
        if isinstance(frame, str) and json.loads(frame)["op"] == "advertise":
            channel = next(c for c in json.loads(frame)["channels"] if c["topic"] == TOPIC)
            ws.send(
                json.dumps(
                    {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel["id"]}]}
                )
            )
            time.sleep(0.3)
            return
    raise RuntimeError("no advertise")


def measure(server: FoxgloveServer, port: int, subprotocol: str, messages: int) -> dict[str, float]:
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol], max_size=None) as ws:
        _subscribe(ws)
        latencies = []
        for k in range(200):  # one at a time: latency
            sent = time.perf_counter_ns()
            server.log(TOPIC, {"timestamp": {"sec": 0, "nsec": k}, "x": 0.0, "y": 0.0, "z": 0.0,
                               "norm": float(sent)}, time.time_ns())  # fmt: skip
            while not isinstance(ws.recv(timeout=2), bytes):
                pass
            latencies.append((time.perf_counter_ns() - sent) / 1e3)
        got, last = 0, 0.0

        def receive() -> None:
            """Count the burst's messages until it is all in or 2 s pass without one (the
            server drops what a slow client cannot take): the time of the last counts."""
            nonlocal got, last
            while got < messages:
                try:
                    frame = ws.recv(timeout=2)
                except TimeoutError:
                    return
                if isinstance(frame, bytes):
                    got, last = got + 1, time.perf_counter()

        reader = threading.Thread(target=receive)
        reader.start()
        started = time.perf_counter()
        for k in range(messages):  # a burst: throughput
            server.log(TOPIC, {"timestamp": {"sec": 1, "nsec": k}, "x": 0.0, "y": 0.0, "z": 0.0,
                               "norm": 0.0}, time.time_ns())  # fmt: skip
        reader.join(30)
        elapsed = max(last - started, 1e-9)
    latencies.sort()
    return {"p50_us": statistics.median(latencies),
            "p99_us": latencies[int(0.99 * len(latencies))],
            "msg_per_s": got / elapsed, "delivered": got / messages}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=3000)
    args = parser.parse_args()
    server = FoxgloveServer(RobotDescription.from_urdf(), "127.0.0.1", free_port())
    try:
        rows = {
            "direct (SDK port), foxglove.sdk.v1": measure(
                server, int(server.server.port), "foxglove.sdk.v1", args.messages),
            "gate, foxglove.sdk.v1": measure(server, server.port, "foxglove.sdk.v1",
                                             args.messages),
            "gate, foxglove.websocket.v1": measure(server, server.port, "foxglove.websocket.v1",
                                                   args.messages),
        }  # fmt: skip
    finally:
        server.stop()
    base = rows["direct (SDK port), foxglove.sdk.v1"]
    print(f"{'path':40s} {'p50 us':>8s} {'p99 us':>8s} {'msg/s':>9s} {'got':>5s} "
          f"{'x p50':>6s} {'x rate':>6s}")  # fmt: skip
    for name, row in rows.items():
        print(
            f"{name:40s} {row['p50_us']:8.0f} {row['p99_us']:8.0f} {row['msg_per_s']:9.0f} "
            f"{row['delivered']:5.0%} "
            f"{row['p50_us'] / base['p50_us']:6.2f} {row['msg_per_s'] / base['msg_per_s']:6.2f}"
        )


if __name__ == "__main__":
    main()
