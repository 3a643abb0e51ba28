"""What one message's Python costs in a loop that waits between messages: the sim's
RobotState built and encoded back to back (hot), and after the waits a 100 Hz loop has
between two states (one 10 ms sleep; 10 ms of the 0.2 ms sleeps of a time-critical
service's inbox polling; 10 ms of spinning). On a shared machine (or a VM) the processor's
caches and predictors go cold in the gap, and the same work costs several times its hot
cost: the bus's round trip pays that at each of its Python legs (``bench_bus.py``).

    python benchmarks/idle_gap.py [--messages 300]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from dammrl.stack.runner import ReachRunner
from schemas import Header, encode
from services.common import convert


def spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=300)
    args = parser.parse_args()
    runner = ReachRunner()
    state = runner.sim.reset(runner.start_posture(runner.sample(0).start), (0.45, 0.0))

    def message() -> bytes:
        header = Header(stamp_ns=time.time_ns(), seq=1, source="sim")
        return encode(convert.state_message(header, state, 1, False, state.q, 1))

    gaps: tuple[tuple[str, Callable[[], object]], ...] = (
        ("back to back (hot)", lambda: None),
        ("after one 0.2 ms sleep", lambda: time.sleep(0.0002)),
        ("after one 10 ms sleep", lambda: time.sleep(0.01)),
        ("after 10 ms of 0.2 ms sleeps", lambda: [time.sleep(0.0002) for _ in range(35)]),
        ("after 10 ms of spinning", lambda: spin(0.01)),
    )
    print(f"a RobotState built and encoded, {args.messages} times each [µs]:")
    for label, gap in gaps:
        spent = []
        for _ in range(args.messages):
            gap()
            start = time.perf_counter()
            message()
            spent.append(time.perf_counter() - start)
        p50, p99 = np.percentile(np.array(spent) * 1e6, [50, 99])
        print(f"    {label:30s}: p50 {p50:6.1f}  p99 {p99:6.1f}")


if __name__ == "__main__":
    main()
