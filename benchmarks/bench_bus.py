"""Bus benchmarks, in one run on this machine (figures, not pass/fail):

(a) state -> command round trip through the real controller: the sim node runs in a
    process of its own (instrumented, at the sim service's priority), policy / intent /
    controller as their services; from a RobotState's publication to the moment the sim
    holds the JointCommand answering it (taken as it arrives, decoded and checked), over
    ``--seconds`` of running reaches (the stack's start-up is left out and said apart);
    the states of the running reaches the controller answered (commands per state), the
    periods the physics stepped on the answer to their own state, and the states it
    superseded; on a plain tcp bus and on a secured one (mutual TLS + access control);
(b) the floor of this machine, run just before each (a): a bare Zenoh ping-pong between
    two processes at the same rate and payload size (the transport without the services'
    work), and once a raw UDP ping-pong;
(c) the cost of each of the bus's design choices (``bus_variants.py``): each undone alone,
    measured as (a) beside its own bare Zenoh run;
(d) the virtual stack's real-time factor and missed deadlines;
(e) with ``--ticks``, which states make the p99: the controller's time from taking a
    state to sending its command, by what the tick did besides (nothing, an IK solve for
    the next step, a decision request, a step started), and the kinds of its 1 % slowest.

    PYTHONPATH=. python benchmarks/bench_bus.py [--seconds 15] [--variants ...] [--hogs 2]
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
from typing import Any

import numpy as np
import zenoh
from bus_variants import TICK_KINDS, TICKS_ENV, VARIANTS, apply  # beside this script

from dammrl.study.inference import median_interval
from dammrl_core.robot import RobotSettings
from dammrl_core.sim.settings import SimSettings
from dammrl_core.task import TaskSettings
from schemas import JointCommand, RobotState
from services.common.bus import Bus, zenoh_config
from services.common.certificates import create_credentials
from services.common.config import BusSettings
from services.common.runtime import prioritise
from services.sim.node import SimNode

PAYLOAD_BYTES = 420  # about one msgpack RobotState
STARTUP_LIMIT_S = 120.0  # the stack's first answer, on a loaded machine
SECURED = "as built, mutual TLS + ACL"
HOG = "while True: pass"  # another program on the lab's PC, at the default priority
ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def percentiles(samples_s: list[float] | np.ndarray) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    if len(ms) == 0:
        return {"p50": float("nan"), "p99": float("nan"), "p99.9": float("nan"), "n": 0}
    p50, p99, p999 = np.percentile(ms, [50, 99, 99.9])
    return {"p50": float(p50), "p99": float(p99), "p99.9": float(p999), "n": len(ms)}


LEGS = (
    "the sim builds and sends the state",
    "to the command's stamp (transport, the controller's wake and decode, its tick)",
    "to the sim holding it (the controller builds and sends it, transport, the sim's wake "
    "and decode)",
)
"""A round trip's three legs, each from the sim's own view (one machine, one clock)."""


class TimedSim(SimNode):
    """The sim node, noting each state it publishes (and when its put returned) and each
    command it takes (its own stamp, the controller's clock being this machine's)."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.published: list[tuple[int, int]] = []  # (stamp_ns, episode)
        self.sent_ns: dict[int, int] = {}  # state stamp_ns: when its put returned
        # (answered state's stamp_ns, the command's stamp_ns, taken at ns)
        self.answers: list[tuple[int, int, int]] = []
        self.first_answer_s: float | None = None
        send = self.state_publisher.send

        def timed_send(message: RobotState) -> RobotState:
            sent = send(message)
            self.sent_ns[message.header.stamp_ns] = time.time_ns()
            return sent

        self.state_publisher.send = timed_send  # type: ignore[method-assign]

    def _publish_state(self) -> None:
        super()._publish_state()
        self.published.append((self.last_stamp_ns, self.episode))

    def _take_command(self, message: JointCommand) -> None:
        if self.first_answer_s is None:
            self.first_answer_s = time.monotonic()
        self.answers.append((message.state_stamp_ns, message.header.stamp_ns,
                             self.bus.arrival_ns))  # fmt: skip
        super()._take_command(message)


def _stack_figures(sim: TimedSim, started_s: float) -> dict[str, Any]:
    """Round trips and answered states over the running reaches: per episode, from its
    first answered state to its last (between reaches nobody is asked to answer)."""
    taken: dict[int, int] = {}  # the first command answering each state
    legs_of: dict[int, tuple[int, int, int]] = {}  # its round trip's legs (LEGS) [ns]
    for state, command, arrival in sim.answers:
        if state not in taken:
            taken[state] = arrival
            sent = sim.sent_ns.get(state, state)
            legs_of[state] = (sent - state, command - sent, arrival - command)
    trips, legs, states, answered = [], [], 0, 0
    for episode in {e for _, e in sim.published if e > 0}:
        stamps = [s for s, e in sim.published if e == episode]
        hits = [i for i, s in enumerate(stamps) if s in taken]
        if not hits:
            continue
        window = stamps[hits[0] : hits[-1] + 1]
        states += len(window)
        answered += sum(s in taken for s in window)
        trips += [(taken[s] - s) * 1e-9 for s in window if s in taken]
        legs += [legs_of[s] for s in window if s in taken]
    assert sim.first_answer_s is not None
    spans = np.array(legs).reshape(-1, len(LEGS)) * 1e-9
    return {
        "round trip [ms]": percentiles(trips),
        "legs [ms]": {leg: percentiles(spans[:, k]) for k, leg in enumerate(LEGS)},
        "states": states,
        "commands per state": answered / max(states, 1),
        "periods on their own answer": sim.answered_periods / max(sim.commanded_periods, 1),
        "start-up [s]": sim.first_answer_s - started_s,
    }


def _spawn_service(name: str, variant: str, env: dict[str, str]) -> subprocess.Popen[bytes]:
    command = [sys.executable, str(ROOT / "benchmarks" / "bus_variants.py"), variant, name]
    return subprocess.Popen(command, env=os.environ | env, cwd=ROOT)


def stack_round_trip(
    seconds: float, rate_hz: float, variant: str, credentials: Path | None, ticks: bool = False
) -> dict[str, Any]:
    """Run the stack under ``variant`` for ``seconds`` of running reaches (this process is
    the sim); its figures (``ticks``: the controller's ticks timed, see ``--ticks``)."""
    with tempfile.TemporaryDirectory() as folder:
        timed = Path(folder) / "ticks.json" if ticks else None
        figures = _stack_round_trip(seconds, rate_hz, variant, credentials, timed)
        if timed is not None:
            figures["ticks"] = json.loads(timed.read_text()) if timed.exists() else []
    return figures


def _stack_round_trip(
    seconds: float, rate_hz: float, variant: str, credentials: Path | None, ticks: Path | None
) -> dict[str, Any]:
    apply(variant)
    port = free_port()
    endpoint = f"{'tcp' if credentials is None else 'tls'}/127.0.0.1:{port}"
    env = {"DAMMRL_BUS_CONNECT": json.dumps([endpoint]), "DAMMRL_LOG_LEVEL": "WARNING",
           "DAMMRL_TASK_EPISODE_TIMEOUT_S": "1000", "PYTHONPATH": str(ROOT)}  # fmt: skip
    if credentials is not None:
        env["DAMMRL_BUS_CREDENTIALS"] = str(credentials)
    settings = BusSettings(listen=[endpoint], credentials=credentials)
    prioritise(True)  # as the sim service does
    timed = {} if ticks is None else {TICKS_ENV: str(ticks)}
    children = [_spawn_service(name, variant, env | (timed if name == "controller" else {}))
                for name in ("policy", "intent", "controller")]  # fmt: skip
    stop = threading.Event()
    try:
        with Bus(settings, "sim") as bus:
            sim = TimedSim(SimSettings(state_rate_hz=rate_hz), TaskSettings(), RobotSettings(), bus)
            started = time.monotonic()
            window: list[tuple[float, int, int]] = []  # (wall, ticks, missed) at its ends
            threading.Thread(target=_stop_after, args=(sim, seconds, started, stop, window),
                             daemon=True).start()  # fmt: skip
            sim.run(stop)
            window.append((time.monotonic(), sim.pacer.ticks, sim.pacer.missed))
    finally:
        for child in children:
            child.terminate()
        for child in children:
            try:
                child.wait(20)  # a loaded machine: the services' own grace is 5 s
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
    figures = _stack_figures(sim, started)
    (t0, ticks0, missed0), (t1, ticks1, missed1) = window[0], window[-1]
    figures["real-time factor"] = (ticks1 - ticks0) * sim.pacer.period_s / (t1 - t0)
    figures["missed deadlines"] = (missed1 - missed0) / max(ticks1 - ticks0, 1)
    return figures


def _stop_after(
    sim: TimedSim,
    seconds: float,
    started: float,
    stop: threading.Event,
    window: list[tuple[float, int, int]],
) -> None:
    """Stop ``seconds`` after the stack's first answer (or when it never came)."""
    while sim.first_answer_s is None and time.monotonic() - started < STARTUP_LIMIT_S:
        time.sleep(0.05)
    window.append((time.monotonic(), sim.pacer.ticks, sim.pacer.missed))
    time.sleep(seconds if sim.first_answer_s is not None else 0)
    stop.set()


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
        echo = spawn.Process(target=_zenoh_echo, args=(endpoint, seconds + STARTUP_LIMIT_S))
        echo.start()
        payload, samples, period = bytes(PAYLOAD_BYTES), [], 1.0 / rate_hz
        deadline = time.monotonic() + STARTUP_LIMIT_S
        while time.monotonic() < deadline:  # the spawned interpreter imports and connects
            arrived.clear()
            ping.put(payload)
            if arrived.wait(0.5):
                break
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


def _one(args: argparse.Namespace) -> None:
    """A child run: one variant of the stack, its figures as one JSON line."""
    if args.one == SECURED:
        with tempfile.TemporaryDirectory() as folder:
            create_credentials(Path(folder) / "bus")
            figures = stack_round_trip(args.seconds, args.rate, "as built", Path(folder) / "bus",
                                       args.ticks)  # fmt: skip
    else:
        figures = stack_round_trip(args.seconds, args.rate, args.one, None, args.ticks)
    print(json.dumps(figures), flush=True)


def run_variant(
    variant: str, seconds: float, rate_hz: float, ticks: bool = False
) -> dict[str, Any]:
    """One variant in a process of its own (its patches stay there), beside a bare Zenoh
    ping-pong run just before it."""
    bare = percentiles(zenoh_round_trip(seconds, rate_hz))
    command = [sys.executable, __file__, "--one", variant, "--seconds", str(seconds),
               "--rate", str(rate_hz), *(["--ticks"] if ticks else [])]  # fmt: skip
    out = subprocess.run(command, cwd=ROOT, env=os.environ | {"PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, timeout=seconds + 300)  # fmt: skip
    lines = [line for line in out.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise SystemExit(f"{variant}: no figures\n{out.stderr[-3000:]}")
    figures: dict[str, Any] = json.loads(lines[-1])
    figures["bare Zenoh [ms]"] = bare
    return figures


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """A variant's figures over its rounds: medians of the per-round percentiles and of
    the per-round ratio to the bare Zenoh run just before (with the median's
    distribution-free 95 % interval, the rounds as units: unbounded with fewer than 6
    rounds); answered states pooled."""
    ratios = [r["round trip [ms]"]["p99"] / r["bare Zenoh [ms]"]["p99"] for r in runs]
    interval = median_interval(np.array(ratios))
    states = sum(r["states"] for r in runs)
    answered = sum(r["commands per state"] * r["states"] for r in runs)
    return {
        "round trip p50 [ms]": float(np.median([r["round trip [ms]"]["p50"] for r in runs])),
        "round trip p99 [ms]": float(np.median([r["round trip [ms]"]["p99"] for r in runs])),
        "bare Zenoh p50 [ms]": float(np.median([r["bare Zenoh [ms]"]["p50"] for r in runs])),
        "bare Zenoh p99 [ms]": float(np.median([r["bare Zenoh [ms]"]["p99"] for r in runs])),
        "p99 / bare p99": float(np.median(ratios)),
        "p99 / bare p99, range": (min(ratios), max(ratios)),
        "p99 / bare p99, 95 % interval": (interval.low, interval.high),
        "p99 / bare p99, rounds": ratios,
        "commands per state": answered / max(states, 1),
        "states": states,
        "periods on their own answer": float(
            np.mean([r["periods on their own answer"] for r in runs])
        ),
        "start-up [s]": float(np.median([r["start-up [s]"] for r in runs])),
        "real-time factor": float(np.median([r["real-time factor"] for r in runs])),
        "legs p50 / p99 [ms]": {
            leg: [float(np.median([r["legs [ms]"][leg][p] for r in runs])) for p in ("p50", "p99")]
            for leg in LEGS
        },
        "rounds": len(runs),
        "ticks": tick_figures([tuple(t) for r in runs for t in r.get("ticks", [])]),
    }


def tick_figures(ticks: list[tuple[str, float]]) -> dict[str, dict[str, float]]:
    """Per kind of tick: how many, their p50 / p90 / p99 [µs] from taking the state to
    sending the command, and how many of them are among the 1 % slowest of all (``all``:
    every tick)."""
    if not ticks:
        return {}
    seconds = np.array([s for _, s in ticks])
    slowest = seconds >= np.quantile(seconds, 0.99)
    figures = {}
    for kind in ("all", *TICK_KINDS):
        mine = np.array([kind in ("all", k) for k, _ in ticks])
        if mine.any():
            p50, p90, p99 = np.quantile(seconds[mine], [0.5, 0.9, 0.99]) * 1e6
            figures[kind] = {"ticks": int(mine.sum()), "p50": p50, "p90": p90, "p99": p99,
                             "among the 1 % slowest": int((mine & slowest).sum())}  # fmt: skip
    return figures


def row(variant: str, f: dict[str, Any]) -> str:
    low, high = f["p99 / bare p99, range"]
    return (
        f"| {variant} | {f['round trip p50 [ms]']:.2f} / {f['round trip p99 [ms]']:.2f} | "
        f"{f['bare Zenoh p50 [ms]']:.2f} / {f['bare Zenoh p99 [ms]']:.2f} | "
        f"{f['p99 / bare p99']:.2f} ({low:.2f}-{high:.2f}) | {f['commands per state']:.4f} | "
        f"{f['periods on their own answer']:.4f} | {f['states']} | {f['start-up [s]']:.1f} | "
        f"{f['real-time factor']:.3f} |"
    )


HEADER = (
    "| variant | round trip p50 / p99 [ms] | bare Zenoh p50 / p99 [ms] | p99 / bare p99 "
    "(range) | commands per state | periods on their own answer | states | start-up [s] | "
    "real-time factor |\n|---|---|---|---|---|---|---|---|---|"
)


TICKS_HEADER = (
    "| the tick | ticks | p50 / p90 / p99 [µs] | among the 1 % slowest |\n|---|---|---|---|"
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0, help="of running reaches")
    parser.add_argument("--rate", type=float, default=SimSettings().state_rate_hz)
    parser.add_argument("--variants", nargs="*", choices=[*VARIANTS, SECURED],
                        default=["as built", SECURED])  # fmt: skip
    parser.add_argument("--all", action="store_true", help="every variant (c)")
    parser.add_argument("--rounds", type=int, default=2, help="each variant this often")
    parser.add_argument("--hogs", type=int, default=0, help="CPU hogs beside the runs")
    parser.add_argument("--ticks", action="store_true",
                        help="time the controller's ticks by kind (e)")  # fmt: skip
    parser.add_argument("--json", type=Path, help="write the figures here too")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:
        _one(args)
        return
    variants = [*VARIANTS, SECURED] if args.all else args.variants
    hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(args.hogs)]
    runs: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
    try:
        udp = percentiles(udp_round_trip(args.seconds, args.rate))
        for _ in range(args.rounds):  # interleaved: the machine's load changes
            for variant in variants:
                runs[variant].append(run_variant(variant, args.seconds, args.rate, args.ticks))
    finally:
        for hog in hogs:
            hog.kill()
    results = {variant: summary(r) for variant, r in runs.items()}
    print(f"state rate {args.rate:.0f} Hz, {args.seconds:.0f} s of running reaches per run, "
          f"{args.rounds} rounds, {args.hogs} CPU hogs beside; raw UDP ping-pong p50 "
          f"{udp['p50']:.2f} ms / p99 {udp['p99']:.2f} ms")  # fmt: skip
    print(HEADER)
    for variant, figures in results.items():
        print(row(variant, figures))
    for variant, figures in results.items():
        legs = "; ".join(f"{leg}: {p50:.2f} / {p99:.2f}"
                         for leg, (p50, p99) in figures["legs p50 / p99 [ms]"].items())  # fmt: skip
        print(f"{variant}, the round trip's legs p50 / p99 [ms]: {legs}")
    for variant, figures in results.items():
        if figures["ticks"]:
            print(f"\n{variant}, the controller from taking a state to sending its command:")
            print(TICKS_HEADER)
            for kind, f in figures["ticks"].items():
                print(f"| {kind} | {f['ticks']} | {f['p50']:.0f} / {f['p90']:.0f} / "
                      f"{f['p99']:.0f} | {f['among the 1 % slowest']} |")  # fmt: skip
    if args.json is not None:
        lean = {
            v: [{k: f for k, f in r.items() if k != "ticks"} for r in rs] for v, rs in runs.items()
        }  # the ticks themselves: only their figures
        args.json.write_text(json.dumps({"udp [ms]": udp, "variants": results, "runs": lean},
                                        indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
