"""The arm's state stream under floods from the stack's own roles (prints figures).

``dammrl up`` (secured, its own credentials) runs ordinary episodes while this process
floods the bus with each role's own certificate, as an adversary holding one would:

* ``none``: no flood (the baseline of the same run);
* ``10MB``: the review's attack, twenty 10 MB payloads on ``intent`` and
  ``sensor/sample`` from the intent role;
* ``at-limits``: payloads of each key's size limit on every key, each from the role that
  may publish it, at each key's rate limit (all that the limits let through);
* ``unbounded``: the same as fast as one process sends them (most of it dropped by the
  receivers' Zenoh, after it was read and decrypted).

Per flood: the worst and p99 gap between robot states as a tool session receives them,
gaps over 0.1 s, and episodes that ended in a stale hold. ``--checkout DIR`` (repeatable)
runs the same floods against another checkout of dammrl (e.g. the commit before the
limits) in the same run, for a before/after.

    PYTHONPATH=. python benchmarks/flood.py [--episodes 3] [--checkout /tmp/before]
"""

from __future__ import annotations

import argparse
import contextlib
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
from services.common.security import roles_publishing, run_credentials
from tests.busutil import free_port

FLOODS = ("none", "10MB", "at-limits", "unbounded")
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


def _flood(port: int, kind: str, stop: Any) -> None:
    if kind == "none":
        return
    if kind == "10MB":
        with _session(port, "intent") as session:
            for n in range(20):
                topic = ("intent", "sensor/sample")[n % 2]
                session.put(f"dammrl/{topic}", os.urandom(10_000_000))
                if stop.wait(0.25):
                    return
        return
    sessions: dict[str, zenoh.Session] = {}
    publishers = []
    for topic in TOPICS_FLOODED:
        role = roles_publishing(topic)[0]
        session = sessions.get(role) or sessions.setdefault(role, _session(port, role))
        limits = LIMITS["health/*" if topic.startswith("health/") else topic]
        publisher = session.declare_publisher(f"dammrl/{topic}")
        publishers.append((publisher, os.urandom(limits.max_bytes), limits.max_rate_hz))
    try:
        if kind == "unbounded":
            while not stop.is_set():
                for publisher, payload, _ in publishers:
                    publisher.put(payload)
        else:  # each key at its rate limit: what the limits let through
            _paced(publishers, stop)
    finally:
        for session in sessions.values():
            session.close()  # type: ignore[no-untyped-call]


def _paced(publishers: list[tuple[Any, bytes, float]], stop: Any) -> None:
    start, sent = time.monotonic(), [0] * len(publishers)
    while not stop.is_set():
        elapsed = time.monotonic() - start
        for n, (publisher, payload, rate) in enumerate(publishers):
            while sent[n] < elapsed * rate:
                publisher.put(payload)
                sent[n] += 1
        time.sleep(0.001)


def _run(source: Path, kind: str, episodes: int) -> dict[str, object]:
    port = free_port()
    env = os.environ | {"PYTHONPATH": str(source)}
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
    flooder = context.Process(target=_flood, args=(port, kind, stop), daemon=True)
    flooder.start()
    launcher.wait(120 * episodes)
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
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--checkout", type=Path, action="append", default=[],
                        help="another checkout of dammrl to measure beside this one")  # fmt: skip
    parser.add_argument("--floods", nargs="*", choices=FLOODS, help="default: all")
    args = parser.parse_args()
    sources = [*args.checkout, Path(__file__).resolve().parents[1]]
    for kind in args.floods or FLOODS:
        for source in sources:
            figures = _run(source.resolve(), kind, args.episodes)
            shown = ", ".join(f"{k} {v:.3g}" if isinstance(v, float | int) else f"{k} {v}"
                              for k, v in figures.items())  # fmt: skip
            print(f"flood {kind:8s} {source.name:12s} {shown}", flush=True)


if __name__ == "__main__":
    main()
