"""The arm's state stream under floods from the stack's own roles (prints figures).

``dammrl up`` (secured, its own credentials) runs ordinary episodes while this process
floods the bus with each role's own certificate, as an adversary holding one would:

* ``none``: no flood (the baseline of the same run);
* ``10MB``: the review's attack, twenty 10 MB payloads on ``intent`` and
  ``sensor/sample`` from the intent role;
* ``at-limits``: payloads of each key's size limit on every key, each from the role that
  may publish it, at each key's rate limit (all that the limits let through);
* ``1kHz``: payloads of each key's size limit on every key, each from the role that may
  publish it, at 1 kHz per key (or the key's rate limit when lower): the review's flood;
* ``denied``: the same from a role that may publish none of those keys (the access
  control refuses them at the hub);
* ``unbounded``: the same as ``at-limits`` as fast as one process sends them (most of it
  dropped by the receivers' Zenoh, after it was read and decrypted).

Per flood: the worst and p99 gap between robot states as a tool session receives them,
gaps over 0.1 s, episodes that ended in a stale hold, and the processor time each
process of the stack took (the services, the launcher's hub, the flooder) per second of
the run. ``--hogs N`` runs N busy programs beside (another workload on the lab's PC).
``--checkout DIR`` (repeatable) runs the same floods against another checkout of dammrl
(e.g. the commit before a change) in the same run, for a before/after; ``--rounds``
repeats the whole, checkouts interleaved.

    PYTHONPATH=. python benchmarks/flood.py [--episodes 3] [--hogs 2] [--checkout /tmp/before]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from zenoh.handlers import RingChannel

from schemas import TOPICS, DecodeError, EpisodeResult, RobotState, decode, key
from schemas.keys import LIMITS
from services.common.bus import zenoh_config
from services.common.config import BusSettings
from services.common.security import OBSERVER, roles_publishing, run_credentials
from tests.busutil import free_port

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bus_variants import VARIANTS

FLOODS = ("none", "10MB", "at-limits", "1kHz", "denied", "unbounded")
REVIEW_RATE_HZ = 1000.0  # the review's flood: ~1 kHz per key
UNLIMITED_HZ = 10_000.0  # "at each key's rate limit" for a key with none (as the limit was)
HOG = "while True: pass"  # another program on the lab's PC, at the default priority
TOPICS_FLOODED = [t if t != "health/*" else "health/sim" for t in TOPICS]


def _session(port: int, role: str) -> zenoh.Session:
    settings = BusSettings(connect=[f"tls/127.0.0.1:{port}"], credentials=run_credentials(port),
                           role=role)  # fmt: skip
    return zenoh.open(zenoh_config(settings, role))


class Watch:
    """A tool session timing robot states and collecting episode results; its rings are
    filled by Zenoh without Python and drained every millisecond (what a service does)."""

    def __init__(self, port: int) -> None:
        self.session = _session(port, "observer")
        self.arrivals: list[float] = []
        self.stamps: list[float] = []  # when the sim published each state (its clock)
        self.results: list[EpisodeResult] = []
        self._states = self.session.declare_subscriber(key("dammrl", RobotState), RingChannel(256))
        self._results = self.session.declare_subscriber(
            key("dammrl", EpisodeResult), RingChannel(64)
        )
        self.stop = threading.Event()
        self._thread = threading.Thread(target=self._drain, daemon=True)
        self._thread.start()

    def _drain(self) -> None:
        while not self.stop.wait(0.001):
            while (sample := self._states.try_recv()) is not None:
                self._state(sample.payload.to_bytes())
            while (sample := self._results.try_recv()) is not None:
                self._result(sample.payload.to_bytes())

    def _state(self, payload: bytes) -> None:
        with contextlib.suppress(DecodeError):  # the flood's own payloads on robot/state
            state = decode(RobotState, payload)
            if state.header.source == "sim":
                self.arrivals.append(time.monotonic())
                self.stamps.append(state.header.stamp_ns * 1e-9)

    def _result(self, payload: bytes) -> None:
        with contextlib.suppress(DecodeError):  # the flood's own payloads on task/result
            result = decode(EpisodeResult, payload)
            if result.header.source == "controller":
                self.results.append(result)

    def close(self) -> None:
        self.stop.set()
        self._thread.join(2)
        self.session.close()  # type: ignore[no-untyped-call]


def _flood(port: int, kind: str, stop: Any, count: Any, nice: int) -> None:
    """Flood until ``stop``; ``count`` (a shared integer) holds the messages sent."""
    with contextlib.suppress(PermissionError):  # an adversary's flood at its own priority
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    if kind == "none":
        return
    if kind == "10MB":
        with _session(port, "intent") as session:
            for n in range(20):
                topic = ("intent", "sensor/sample")[n % 2]
                session.put(f"dammrl/{topic}", os.urandom(10_000_000))
                count.value += 1
                if stop.wait(0.25):
                    return
        return
    sessions: dict[str, zenoh.Session] = {}
    publishers = []
    for topic in TOPICS_FLOODED:
        role = _denied_role(topic) if kind == "denied" else roles_publishing(topic)[0]
        session = sessions.get(role) or sessions.setdefault(role, _session(port, role))
        limits = LIMITS["health/*" if topic.startswith("health/") else topic]
        limit = limits.max_rate_hz or UNLIMITED_HZ  # a key with no rate rule: as fast as it goes
        rate = limit if kind in ("at-limits", "unbounded") else REVIEW_RATE_HZ
        publisher = session.declare_publisher(f"dammrl/{topic}")
        publishers.append((publisher, os.urandom(limits.max_bytes), min(rate, limit)))
    try:
        if kind == "unbounded":
            while not stop.is_set():
                for publisher, payload, _ in publishers:
                    publisher.put(payload)
                count.value += len(publishers)
        else:  # each key at its rate: what the limits let through, or the review's 1 kHz
            _paced(publishers, stop, count)
    finally:
        for session in sessions.values():
            session.close()  # type: ignore[no-untyped-call]


def _denied_role(topic: str) -> str:
    """A role that may not publish ``topic``: the access control refuses its flood."""
    return OBSERVER if OBSERVER not in roles_publishing(topic) else "recorder"


def _paced(publishers: list[tuple[Any, bytes, float]], stop: Any, count: Any) -> None:
    start, sent = time.monotonic(), [0] * len(publishers)
    while not stop.is_set():
        elapsed = time.monotonic() - start
        for n, (publisher, payload, rate) in enumerate(publishers):
            while sent[n] < elapsed * rate:
                publisher.put(payload)
                sent[n] += 1
        count.value = sum(sent)
        time.sleep(0.001)


CLOCK_HZ = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """Processor time a process took so far (user + system) [s]; 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / CLOCK_HZ


def _processes(launcher: int, flooder: int) -> dict[str, int]:
    """The stack's processes by name (the launcher is the services' hub) and the flooder."""
    named = {"hub (launcher)": launcher, "flooder": flooder}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            command = (stat.parent / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        module = next((c.decode() for c in command if c.startswith(b"services.")), None)
        if parent == launcher and module is not None:
            named[module.removeprefix("services.")] = int(stat.parent.name)
    return named


def _run(source: Path, kind: str, episodes: int, nice: int = 0, variant: str | None = None
         ) -> dict[str, object]:  # fmt: skip
    port = free_port()
    env = os.environ | {"PYTHONPATH": str(source)}
    if variant is not None:  # every process of the stack under it (variant_site)
        site = Path(__file__).resolve().parent / "variant_site"
        env |= {"PYTHONPATH": f"{site}:{source}", "DAMMRL_BENCH_VARIANT": variant}
    launcher = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "up", "--episodes", str(episodes), "--model", "2,1",
         "--bus-port", str(port)],
        cwd=source, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert launcher.stderr is not None
    while "all services alive" not in launcher.stderr.readline():
        if launcher.poll() is not None:
            raise SystemExit(f"dammrl up in {source} failed")
    drain = threading.Thread(target=lambda: launcher.stderr and launcher.stderr.read(), daemon=True)
    drain.start()  # the services log to the same pipe: it must never fill
    watch = Watch(port)
    time.sleep(2.0)  # the first episode under way
    context = multiprocessing.get_context("spawn")
    stop = context.Event()  # the flood in a process of its own, as an adversary's is
    count = context.Value("q", 0)
    flooder = context.Process(target=_flood, args=(port, kind, stop, count, nice), daemon=True)
    flooder.start()
    assert flooder.pid is not None
    processes = _processes(launcher.pid, flooder.pid)
    first = {name: _cpu_s(pid) for name, pid in processes.items()}
    last, started = dict(first), time.monotonic()
    while launcher.poll() is None and time.monotonic() - started < 120 * episodes:
        for name, pid in processes.items():  # the last look before each exits
            last[name] = _cpu_s(pid) or last[name]
        time.sleep(0.5)
    elapsed = time.monotonic() - started
    cores = {name: round((last[name] - first[name]) / elapsed, 2) for name in processes}
    flooded = count.value / elapsed
    stop.set()
    flooder.join(10)
    flooder.kill()
    watch.close()
    gaps = np.diff(watch.arrivals) if len(watch.arrivals) > 1 else np.zeros(1)
    published = np.diff(np.unique(watch.stamps)) if len(watch.stamps) > 1 else np.zeros(1)
    return {
        "worst publication gap [s]": float(published.max()),
        "states": len(watch.arrivals),
        "distinct": len(np.unique(watch.stamps)),
        "worst gap [s]": float(gaps.max()),
        "p99 gap [ms]": float(np.percentile(gaps, 99) * 1000),
        "gaps > 0.1 s": int(np.sum(gaps > 0.1)),
        "stale holds": sum("stale" in r.reason or "stalled" in r.reason for r in watch.results),
        "episodes": len(watch.results),
        "reasons": sorted({r.reason for r in watch.results if not r.success}),  # type: ignore[dict-item]
        "cores used": cores,
        "flood [msg/s]": round(flooded),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--checkout", type=Path, action="append", default=[],
                        help="another checkout of dammrl to measure beside this one")  # fmt: skip
    parser.add_argument("--floods", nargs="*", choices=FLOODS, help="default: all")
    parser.add_argument("--hogs", type=int, default=0, help="busy programs beside the runs")
    parser.add_argument("--rounds", type=int, default=1, help="everything this often")
    parser.add_argument("--flooder-nice", type=int, default=0,
                        help="the flooder's niceness (-10: the time-critical services' own, "
                             "so that it floods at its rate on a busy machine)")  # fmt: skip
    parser.add_argument("--variants", nargs="*", choices=list(VARIANTS), default=["as built"],
                        help="this checkout under each of bench_bus's variants")  # fmt: skip
    parser.add_argument("--json", type=Path, help="append each run's figures here (lines)")
    args = parser.parse_args()
    here = Path(__file__).resolve().parents[1]
    runs = [(checkout, "as built") for checkout in args.checkout]
    runs += [(here, variant) for variant in args.variants]
    hogs = [subprocess.Popen([sys.executable, "-c", HOG]) for _ in range(args.hogs)]
    try:
        for _ in range(args.rounds):
            for kind in args.floods or FLOODS:
                for source, variant in runs:
                    figures = _run(source.resolve(), kind, args.episodes, args.flooder_nice,
                                   None if variant == "as built" else variant)  # fmt: skip
                    _report(source, kind, args, {"variant": variant, **figures})
    finally:
        for hog in hogs:
            hog.kill()


def _report(source: Path, kind: str, args: argparse.Namespace, figures: dict[str, Any]) -> None:
    shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float | int) else f"{k} {v}"
                      for k, v in figures.items())  # fmt: skip
    print(f"flood {kind:9s} {source.name:12s} hogs {args.hogs} {shown}", flush=True)
    if args.json is not None:
        with args.json.open("a") as out:
            row = {
                "flood": kind,
                "checkout": str(source),
                "hogs": args.hogs,
                "flooder nice": args.flooder_nice,
                **figures,
            }
            out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
