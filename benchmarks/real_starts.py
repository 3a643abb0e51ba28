"""Real-mode starts beside two CPU hogs: crashes and unprompted stops (prints figures).

N times: ``dammrl up --mode real --robot-port PORT --emulate-robot --episodes 1`` (the
robot service on the emulated Dynamixel arm: connect, torque on, soft start, homing, one
reach), with two ``yes > /dev/null`` running throughout and no fault injected. Each start
is classed by what the launcher and the services said:

* crash: a service exited unexpectedly, or any Python traceback;
* overspeed: the arm stopped itself on a joint's speed (no fault was injected, so any is
  unprompted); other stop: on any other reason (a limit, a drive's fault);
* done: exit 0 and one episode's result (its outcome is the controller's business: a
  stale hold on a starved PC is counted apart, not as a failure of the arm).

Printed: one line per start (its exit code, outcome and time; a start that did not end
done names the log it kept of every service's words), then the counts, with the
machine's load average (other work on the PC comes on top of the two hogs).

    PYTHONPATH=. python benchmarks/real_starts.py [--starts 30] [--hogs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from tests.busutil import Lines, free_port

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cpu_hogs import hogs

TIMEOUT_S = 240.0  # a start that has not ended by then is counted as hung


def start(index: int) -> tuple[str, str]:
    """One real-mode start: its class and a line saying what happened."""
    folder = Path(tempfile.mkdtemp(prefix="real-start-"))
    command = [sys.executable, "-m", "dammrl", "up", "--mode", "real", "--robot-port",
               str(folder / "ttyARM"), "--emulate-robot", "--episodes", "1", "--json",
               "--bus-port", str(free_port()), "--seed", str(7_000_000 + index)]  # fmt: skip
    began = time.monotonic()
    launcher = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)  # fmt: skip
    assert launcher.stderr is not None and launcher.stdout is not None
    lines = Lines(launcher.stderr)
    ended = f"no end after {TIMEOUT_S:.0f} s"
    while time.monotonic() - began < TIMEOUT_S:
        if launcher.poll() is not None:
            ended = f"exit {launcher.returncode}"
            break
        if any("robot stopped" in line for line in list(lines.lines)):
            ended = "stopped"  # it holds until someone acts: nothing more will happen
            break
        time.sleep(0.2)
    if launcher.poll() is None:
        launcher.terminate()  # the launcher stops its services
        launcher.wait(60)
    out = launcher.stdout.read()
    time.sleep(0.5)  # the last lines of stderr
    said = "".join(lines.lines)
    took = time.monotonic() - began
    results = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    outcome = results[0]["outcome"] if results else "none"
    line = f"{ended}, episode {outcome}, {took:.0f} s"
    (folder / "stderr.log").write_text(said)  # what every service said, kept to read
    kept = f" (log: {folder / 'stderr.log'})"
    if "Traceback" in said or "exited unexpectedly" in said:
        return "crash", f"{line}: {_first(said, ('Traceback', 'exited unexpectedly'))}{kept}"
    if "rad/s beyond its limit" in said:
        return "overspeed", f"{line}: {_first(said, ('rad/s beyond',))}{kept}"
    if "robot stopped" in said:
        return "other stop", f"{line}: {_first(said, ('robot stopped',))}{kept}"
    if ended != "exit 0" or not results:
        return ("failed" if ended.startswith("exit") else "hung",
                f"{line}: {said[-300:]!r}{kept}")  # fmt: skip
    return "done", line


def _first(text: str, marks: tuple[str, ...]) -> str:
    return next((ln.strip() for ln in text.splitlines() if any(m in ln for m in marks)), "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=30)
    parser.add_argument("--hogs", type=int, default=2)
    args = parser.parse_args()
    counts: Counter[str] = Counter()
    loads = []
    with hogs(args.hogs):
        for index in range(args.starts):
            kind, line = start(index)
            counts[kind] += 1
            loads.append(os.getloadavg()[0])
            print(f"start {index + 1:2d}: {kind:10s} {line}", flush=True)
    print(f"{args.starts} real-mode starts beside {args.hogs} CPU hogs (load average "
          f"{min(loads):.0f}-{max(loads):.0f}): " + ", ".join(
              f"{counts[k]} {k}" for k in ("done", "crash", "overspeed", "other stop",
                                           "failed", "hung")))  # fmt: skip


if __name__ == "__main__":
    main()
