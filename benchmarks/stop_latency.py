"""A stop from the operator, command to every arm holding (prints figures).

Against a running ``dammrl up`` (``--mode real``: the robot service on the emulated
Dynamixel arm; ``--mode virtual``: the sim), quiet and again beside two CPU hogs
(``yes > /dev/null`` twice), each trial:

* ``dammrl stop --connect ...`` started as a program: the time from its start until
  every arm's Health says "stopped" (seen by this benchmark's own session), and until the
  program has exited;
* the stop console (``dammrl stop --console``, its session opened once): the time from
  Enter (one key) until every arm says "stopped";
* ``dammrl status`` started as a program, to its exit (it waits for every service's
  Health, up to its own bound);
* the baselines, in the same run: ``python -c "import zenoh"`` (the bus library's start-up
  alone) and ``python -c "from dammrl.cli import parser; parser()"`` (the whole CLI's
  start-up, which a stop paid before it had a parser of its own).

Between trials the stop is released and the arm holds again. Figures: median, 90th
percentile and worst [s], and each median as a ratio to ``import zenoh``'s.

    PYTHONPATH=. python benchmarks/stop_latency.py [--trials 10] [--mode real|virtual]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zenoh

from dammrl.stack.stop import ARM_SERVICES, StopConsole
from schemas import DecodeError, Health, decode
from services.common.bus import zenoh_config
from services.common.config import BusSettings
from services.common.security import run_credentials
from tests.busutil import Lines, free_port

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cpu_hogs import hogs

WAIT_S = 60.0  # a stop not confirmed within this is a failed trial


class Arms:
    """Every arm's Health as this benchmark's own session sees it."""

    def __init__(self, settings: BusSettings) -> None:
        self.session = zenoh.open(zenoh_config(settings))
        self.states: dict[str, tuple[str, float]] = {}  # service -> (state, since)
        self.lock = threading.Lock()
        self.session.declare_subscriber(f"{settings.namespace}/health/*", self._on_health)

    def _on_health(self, sample: zenoh.Sample) -> None:
        try:
            health = decode(Health, sample.payload.to_bytes())
        except DecodeError:
            return
        if health.service in ARM_SERVICES:
            with self.lock:
                if self.states.get(health.service, ("",))[0] != health.state:
                    self.states[health.service] = (health.state, time.monotonic())

    def wait(self, stopped: bool, after: float) -> float:
        """When every arm last changed to (or away from) "stopped", once all have, after
        ``after`` (monotonic) [s]; nan after WAIT_S."""
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            with self.lock:
                states = dict(self.states)
            if states and all((s == "stopped") == stopped and t >= after
                              for s, t in states.values()):  # fmt: skip
                return max(t for _, t in states.values())
            time.sleep(0.001)
        return float("nan")


@contextmanager
def stack(mode: str, port: int) -> Iterator[None]:
    """``dammrl up`` in ``mode`` (open-ended), until every service is alive."""
    folder = Path(tempfile.mkdtemp(prefix="stop-"))
    command = [sys.executable, "-m", "dammrl", "up", "--mode", mode, "--bus-port", str(port)]
    if mode == "real":
        command += ["--robot-port", str(folder / "ttyARM"), "--emulate-robot"]
    quiet = os.environ | {"DAMMRL_LOG_LEVEL": "ERROR"}
    launcher = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True, env=quiet)  # fmt: skip
    assert launcher.stderr is not None
    try:
        Lines(launcher.stderr).wait_for("all services alive", 120)
        yield
    finally:
        launcher.terminate()
        launcher.wait(30)


def timed_program(command: list[str]) -> float:
    """Wall time of a program from its start to its exit [s]."""
    started = time.monotonic()
    subprocess.run(command, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.monotonic() - started


def release(operator: StopConsole, arms: Arms) -> None:
    """Release the stop; wait until every arm holds again (not "stopped")."""
    now = time.monotonic()
    operator.send(engaged=False, timeout_s=5.0)
    arms.wait(stopped=False, after=now - 10.0)


def program_stop(endpoint: str, arms: Arms) -> tuple[float, float]:
    """``dammrl stop`` as a program: (start to every arm stopped, start to exit) [s]."""
    started = time.monotonic()
    stop = subprocess.Popen([sys.executable, "-m", "dammrl", "stop", "--connect", endpoint],
                            stdout=subprocess.DEVNULL)  # fmt: skip
    held = arms.wait(stopped=True, after=started)
    stop.wait(WAIT_S)
    return held - started, time.monotonic() - started


def console_stop(console: subprocess.Popen[str], arms: Arms) -> float:
    """Enter in the stop console: to every arm stopped [s]."""
    assert console.stdin is not None
    started = time.monotonic()
    console.stdin.write("\n")
    console.stdin.flush()
    return arms.wait(stopped=True, after=started) - started


def console_release(console: subprocess.Popen[str], arms: Arms) -> None:
    assert console.stdin is not None
    now = time.monotonic()
    console.stdin.write("release\n")
    console.stdin.flush()
    arms.wait(stopped=False, after=now)


def condition(name: str, trials: int, endpoint: str, arms: Arms, operator: StopConsole) -> None:
    figures: dict[str, list[float]] = {
        'python -c "import zenoh" (baseline)': [],
        "the whole CLI's start-up (before)": [],
        "dammrl stop: start to every arm stopped": [],
        "dammrl stop: start to exit": [],
        "stop console: Enter to every arm stopped": [],
        "dammrl status: start to exit": [],
    }
    rows = list(figures.values())
    console = subprocess.Popen(
        [sys.executable, "-m", "dammrl", "stop", "--console", "--connect", endpoint],
        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    time.sleep(5.0)  # the console's session is open
    whole_cli = "from dammrl.cli import parser; parser()"
    for _ in range(trials):
        rows[0].append(timed_program([sys.executable, "-c", "import zenoh"]))
        rows[1].append(timed_program([sys.executable, "-c", whole_cli]))
        release(operator, arms)
        held, ended = program_stop(endpoint, arms)
        rows[2].append(held)
        rows[3].append(ended)
        release(operator, arms)
        rows[4].append(console_stop(console, arms))
        console_release(console, arms)
        rows[5].append(timed_program([sys.executable, "-m", "dammrl", "status", "--connect",
                                      endpoint]))  # fmt: skip
    assert console.stdin is not None
    console.stdin.close()
    console.wait(30)
    report(name, figures)


def report(name: str, figures: dict[str, list[float]]) -> None:
    base = float(np.median(next(iter(figures.values()))))
    load = os.getloadavg()[0]
    print(f"{name} (load average {load:.1f}, {len(next(iter(figures.values())))} trials)")
    for what, values in figures.items():
        row = np.array(values)
        failed = int(np.isnan(row).sum())
        p50, p90, worst = np.nanpercentile(row, [50, 90, 100])
        print(f"  {what:44s} median {p50:6.3f} s  p90 {p90:6.3f} s  worst {worst:6.3f} s  "
              f"x{p50 / base:5.1f} of import zenoh" + (f"  ({failed} not confirmed)"
                                                      if failed else ""))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--mode", choices=["real", "virtual"], default="real")
    args = parser.parse_args()
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with stack(args.mode, port):
        settings = BusSettings(connect=[f"tls/127.0.0.1:{port}"], credentials=run_credentials(port))
        arms, operator = Arms(settings), StopConsole(settings)
        for name, count in (("quiet", 0), ("beside two CPU hogs", 2)):
            with hogs(count):
                condition(f"{args.mode} mode, {name}", args.trials, endpoint, arms, operator)
        release(operator, arms)
        operator.close()


if __name__ == "__main__":
    main()
