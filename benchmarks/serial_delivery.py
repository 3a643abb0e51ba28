"""How late a serial port's frames reach their reader on a busy PC, and how well the pad's
own clock times them anyway (figures, not pass/fail).

The emulated pad writes 100 frames/s into a pseudo-terminal at the priority of the
hardware it stands in for; ``SerialSensor`` reads them at normal priority, as the intent
service does. Per frame: the delivery delay (read minus when the pad's schedule sent it: a
writer the kernel blocks counts as late) and the timing error of ``PadClock`` (the
sample's time it gives minus that schedule). Three loads in one run: quiet; beside two
CPU hogs; beside two CPU hogs and a semi-virtual stack (`dammrl up --mode semi-virtual`
with its own emulated pad and simulated patient) running reaches. The kernel hands a
tty's bytes to its reader from a worker thread of its own, at normal priority: beside the
hogs and the stack that worker can wait seconds.

    PYTHONPATH=. python benchmarks/serial_delivery.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np

from benchmarks.cpu_hogs import hogs
from dammrl.devices.emulators.pad import SensorEmulator
from dammrl_core.intent.pad.serial import SerialSensor
from services.common.runtime import prioritise
from tests.busutil import Observer, free_port, start_patient, start_service

RATE_HZ = 100.0


@contextmanager
def semi_virtual_stack(folder: Path) -> Iterator[None]:
    """The semi-virtual services reaching (as `tests/test_semi_virtual.py` starts them: the
    sim, policy, intent service on an emulated pad of their own, controller, recorder) with
    a simulated patient pressing that pad; this process listens for them."""
    port, pad = free_port(), folder / "ttySTACK"
    hub = Observer(port)
    services = [
        start_patient(pad, port, human_model=2),
        start_service("recorder", port, DAMMRL_RECORDER_OUT=str(folder / "load.mcap")),
        start_service("sim", port),
        start_service("policy", port),
        start_service("intent", port, DAMMRL_INTENT_SOURCE="pad", DAMMRL_PAD_PORT=str(pad)),
        start_service("controller", port, DAMMRL_TASK_EPISODES="50"),
    ]
    try:
        time.sleep(10.0)  # up and reaching
        yield
    finally:
        for process in services:
            process.terminate()
        for process in services:
            process.wait(30)
        hub.close()


def measure(seconds: float, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(delivery delay, timing error) [s] of every frame read over ``seconds``."""
    delays, errors = [], []
    prioritise(True)  # the emulator's writer thread inherits it: the pad's own processor
    with SensorEmulator(folder / "ttyPAD", [], rate_hz=RATE_HZ) as pad:
        os.setpriority(os.PRIO_PROCESS, 0, 0)  # this thread reads, as the intent service
        start = time.monotonic() - pad.clock_s  # the pad's schedule: frame n at n / rate
        with SerialSensor(str(folder / "ttyPAD")) as sensor:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                for arrival in sensor.read():
                    sent = start + arrival.frame.seq / RATE_HZ  # under 65,536 frames: no wrap
                    delays.append(arrival.t_s - sent)
                    errors.append(arrival.sampled_s - sent)
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
    print(f"{os.cpu_count()} cores; {args.seconds:g} s per load; {RATE_HZ:g} frames/s\n")
    print("| load | frames | delivery delay p50 / p99 / max [ms] "
          "| pad-clock timing error p50 / p99 / max [ms] |")  # fmt: skip
    print("|---|---|---|---|")
    loads = {"quiet": 0, "two CPU hogs": 2, "two CPU hogs and a semi-virtual stack": 2}
    for name, count in loads.items():
        with tempfile.TemporaryDirectory() as folder, ExitStack() as load:
            load.enter_context(hogs(count))
            if "stack" in name:
                load.enter_context(semi_virtual_stack(Path(folder)))
            print(row(name, *measure(args.seconds, Path(folder))), flush=True)


if __name__ == "__main__":
    main()
