"""How late a serial port's frames reach their reader on a busy PC, and how well the pad's
own clock times them anyway (figures, not pass/fail).

The emulated pad writes 100 frames/s into a pseudo-terminal at the priority of the
hardware it stands in for; ``SerialSensor`` reads them as the intent service does. Per
frame: the delivery delay (read minus written) and the timing error of ``PadClock`` (the
sample's time it gives minus when it was written). Three loads in one run: quiet; beside
two CPU hogs; beside two CPU hogs and a virtual stack (`dammrl up`) running reaches. The
kernel hands a tty's bytes to its reader from a worker thread of its own, at normal
priority: beside the hogs and the stack that worker can wait seconds.

    PYTHONPATH=. python benchmarks/serial_delivery.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np

from benchmarks.bench_sensor import free_port
from benchmarks.cpu_hogs import hogs
from dammrl.devices.emulators.pad import SensorEmulator
from dammrl_core.intent.pad.serial import SerialSensor
from services.common.runtime import prioritise


@contextmanager
def virtual_stack() -> Iterator[None]:
    """`dammrl up` running reaches on a port of its own, its output discarded."""
    command = [sys.executable, "-m", "dammrl", "up", "--episodes", "50", "--bus-port",
               str(free_port())]  # fmt: skip
    stack = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(8.0)  # its services up and reaching
        yield
    finally:
        stack.terminate()
        stack.wait(30)


def measure(seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """(delivery delay, timing error) [s] of every frame read over ``seconds``."""
    delays, errors = [], []
    with tempfile.TemporaryDirectory() as folder:
        link = Path(folder) / "ttyPAD"
        prioritise(True)  # the emulator's writer thread inherits it: the pad's own processor
        with SensorEmulator(link, [], record_write_times=True) as pad:
            os.setpriority(os.PRIO_PROCESS, 0, 0)  # this thread reads, as the intent service
            with SerialSensor(str(link)) as sensor:
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    for arrival in sensor.read():
                        written = (pad.write_times or {}).get(arrival.frame.seq)
                        if written is not None:
                            delays.append(arrival.t_s - written)
                            errors.append(arrival.sampled_s - written)
    return np.array(delays), np.array(errors)


def row(name: str, delays: np.ndarray, errors: np.ndarray) -> str:
    d = np.percentile(delays, [50, 99, 100]) * 1e3
    e = np.percentile(np.abs(errors), [50, 99, 100]) * 1e3
    return (f"| {name} | {len(delays)} | {d[0]:.1f} / {d[1]:.1f} / {d[2]:.1f} | "
            f"{e[0]:.1f} / {e[1]:.1f} / {e[2]:.1f} |")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    print(f"{os.cpu_count()} cores; {args.seconds:g} s per load; 100 frames/s\n")
    print("| load | frames | delivery delay p50 / p99 / max [ms] "
          "| pad-clock timing error p50 / p99 / max [ms] |")  # fmt: skip
    print("|---|---|---|---|")
    loads = {"quiet": 0, "two CPU hogs": 2, "two CPU hogs and a running virtual stack": 2}
    for name, count in loads.items():
        with ExitStack() as load:
            load.enter_context(hogs(count))
            if "stack" in name:
                load.enter_context(virtual_stack())
            print(row(name, *measure(args.seconds)), flush=True)


if __name__ == "__main__":
    main()
