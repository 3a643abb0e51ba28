"""Bus benchmarks, in one run on this machine (figures, not pass/fail):

(a) state -> command round trip through the real controller: the sim node runs in this
    process (instrumented), policy / intent / controller as their own processes; latency
    from a RobotState's publication to the arrival of the JointCommand answering it, on a
    plain tcp bus and on a secured one (mutual TLS + access control), side by side;
(b) the floor of this machine: a raw UDP ping-pong between two processes on loopback at
    the same rate and payload size, and the same ping-pong over bare Zenoh (the transport
    without the services' work);
(c) the virtual stack's real-time factor (simulated / wall time) and missed deadlines.

    python benchmarks/bench_bus.py [--seconds 30]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from dammrl_core.robot import RobotSettings
from dammrl_core.sim.settings import SimSettings
from dammrl_core.task import TaskSettings
from services.common.bus import Bus, zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.sim.node import SimNode

PAYLOAD_BYTES = 420  # about one msgpack RobotState


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def percentiles(samples_s: list[float] | np.ndarray) -> str:
    ms = np.asarray(samples_s) * 1e3
    p50, p99, p999 = np.percentile(ms, [50, 99, 99.9])
    return f"p50 {p50:6.3f} ms  p99 {p99:6.3f} ms  p99.9 {p999:6.3f} ms  (n={len(ms)})"


def bus_round_trip(
    seconds: float, rate_hz: float, credentials: Path | None = None
) -> tuple[SimNode, float]:
    """Run the stack for ``seconds``; return the instrumented sim node and wall time."""
    port = free_port()
    endpoint = f"{'tcp' if credentials is None else 'tls'}/127.0.0.1:{port}"
    env = {"DAMMRL_BUS_CONNECT": json.dumps([endpoint]), "DAMMRL_LOG_LEVEL": "WARNING",
           "DAMMRL_TASK_EPISODE_TIMEOUT_S": "1000"}  # fmt: skip
    if credentials is not None:
        env["DAMMRL_BUS_CREDENTIALS"] = str(credentials)
    children = [
        subprocess.Popen([sys.executable, "-m", f"services.{name}"], env=os.environ | env)
        for name in ("policy", "intent", "controller")
    ]
    stop = threading.Event()
    try:
        settings = SimSettings(state_rate_hz=rate_hz)
        with Bus(BusSettings(listen=[endpoint], credentials=credentials), "sim") as bus:
            node = SimNode(settings, TaskSettings(), RobotSettings(), bus)
            timer = threading.Timer(seconds, stop.set)
            timer.start()
            start = time.monotonic()
            node.run(stop)
            wall = time.monotonic() - start
    finally:
        for child in children:
            child.terminate()
            child.wait(10)
    return node, wall


def _echo_server(port_queue: multiprocessing.Queue, stop_after_s: float) -> None:  # type: ignore[type-arg]
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    server.settimeout(1.0)
    port_queue.put(server.getsockname()[1])
    end = time.monotonic() + stop_after_s
    while time.monotonic() < end:
        try:
            data, address = server.recvfrom(65536)
        except TimeoutError:
            continue
        server.sendto(data, address)


def udp_round_trip(seconds: float, rate_hz: float) -> list[float]:
    """Raw UDP ping-pong between two processes on loopback at ``rate_hz``."""
    ports: multiprocessing.Queue = multiprocessing.Queue()  # type: ignore[type-arg]
    server = multiprocessing.Process(target=_echo_server, args=(ports, seconds + 5))
    server.start()
    port = ports.get(timeout=10)
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(1.0)
    payload = bytes(PAYLOAD_BYTES)
    samples = []
    period = 1.0 / rate_hz
    next_t = time.monotonic()
    end = next_t + seconds
    while time.monotonic() < end:
        start = time.perf_counter()
        client.sendto(payload, ("127.0.0.1", port))
        client.recvfrom(65536)
        samples.append(time.perf_counter() - start)
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))
    server.terminate()
    return samples


def _zenoh_echo(endpoint: str, stop_after_s: float) -> None:
    """Echo every ping payload back as a pong, from the subscriber's handler channel."""
    settings = BusSettings(connect=[endpoint])
    with zenoh.open(zenoh_config(settings)) as session:
        pong = session.declare_publisher("bench/pong", express=True)
        pings = session.declare_subscriber("bench/ping")
        end = time.monotonic() + stop_after_s
        while time.monotonic() < end:
            sample = pings.try_recv()
            if sample is None:
                time.sleep(0.00005)
                continue
            pong.put(sample.payload)


def zenoh_round_trip(seconds: float, rate_hz: float) -> list[float]:
    """The same ping-pong over Zenoh (two processes, express publishers, raw bytes)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config(BusSettings(listen=[endpoint]))) as session:
        arrived = threading.Event()
        session.declare_subscriber("bench/pong", lambda sample: arrived.set())
        ping = session.declare_publisher("bench/ping", express=True)
        spawn = multiprocessing.get_context("spawn")  # never fork a process running Zenoh
        echo = spawn.Process(target=_zenoh_echo, args=(endpoint, seconds + 10))
        echo.start()
        time.sleep(3.0)  # the spawned interpreter imports and connects
        payload, samples, period = bytes(PAYLOAD_BYTES), [], 1.0 / rate_hz
        next_t = time.monotonic()
        end = next_t + seconds
        while time.monotonic() < end:
            arrived.clear()
            start = time.perf_counter()
            ping.put(payload)
            if arrived.wait(1.0):
                samples.append(time.perf_counter() - start)
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
        echo.terminate()
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=SimSettings().state_rate_hz)
    args = parser.parse_args()

    node, wall = bus_round_trip(args.seconds, args.rate)
    with tempfile.TemporaryDirectory() as folder:
        create_credentials(Path(folder) / "bus")
        secured, _ = bus_round_trip(args.seconds, args.rate, Path(folder) / "bus")
    udp = udp_round_trip(args.seconds, args.rate)
    bare = zenoh_round_trip(args.seconds, args.rate)
    trips = list(node.round_trips_s)[50:]  # skip the connection warm-up
    pacer = node.pacer
    simulated = pacer.ticks * pacer.period_s
    print(
        f"state rate {args.rate:.0f} Hz, {args.seconds:.0f} s each, UDP payload {PAYLOAD_BYTES} B"
    )
    print(f"(a) bus state->command round trip : {percentiles(trips)}")
    print(f"(a') the same, mutual TLS + ACL    : {percentiles(list(secured.round_trips_s)[50:])}")
    print(f"(b) raw UDP ping-pong (2 processes): {percentiles(udp)}")
    print(f"(b') bare Zenoh ping-pong (same)   : {percentiles(bare)}")
    p99_ratio = np.percentile(trips, 99) / np.percentile(udp, 99)
    bare_ratio = np.percentile(bare, 99) / np.percentile(udp, 99)
    print(f"    p99 / UDP p99: bus {p99_ratio:.1f}x, bare Zenoh {bare_ratio:.1f}x (goal 2x)")
    print(f"(c) real-time factor               : {simulated / wall:.3f}   (goal >= 0.99)")
    print(
        f"    missed control deadlines       : {pacer.missed} of {pacer.ticks} "
        f"({pacer.missed / max(pacer.ticks, 1):.2%})"
    )
    print(
        f"    messages per state             : {len(node.round_trips_s) / max(pacer.ticks, 1):.2f} "
        "commands received per state published"
    )


if __name__ == "__main__":
    main()
