"""What one message's Python costs in a loop that waits between messages, back to back
(hot) and after the waits a 100 Hz loop has between two states (one 10 ms sleep; 10 ms
of the 0.2 ms sleeps of a time-critical service's inbox polling; 10 ms of spinning), and
why: after a sleep and then 1 ms of spinning (were it the processor's clock coming back
up, this would be hot again), and after a sleep and the same work once (were it the
caches, this would be). The works: the sim's RobotState built and encoded; the
controller's answer (the state decoded, converted, a quiet tick with the reference
moving, the JointCommand built and encoded); a trivial call. On a shared machine (or a VM)
the processor's caches go cold in the gap, and the same work costs several times its hot
cost: the bus's round trip pays that at each of its Python legs (``bench_bus.py``).

    python benchmarks/idle_gap.py [--messages 300]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Callable

import numpy as np

from dammrl.stack.runner import ReachRunner
from dammrl_core.policy import FixedPolicy
from schemas import Header, RobotState, decode, encode
from services.common import convert


def spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def sleeps(seconds: float, then: Callable[[], object] = lambda: None) -> Callable[[], object]:
    """A gap: sleep ``seconds``, then ``then()``."""

    def gap() -> None:
        time.sleep(seconds)
        then()

    return gap


def polls() -> None:
    """10 ms of a time-critical inbox's 0.2 ms sleeps."""
    for _ in range(35):
        time.sleep(0.0002)


def works() -> dict[str, Callable[[], object]]:
    """The works timed, each a function of nothing."""
    runner = ReachRunner()
    episode = runner.episode(3)
    loop = episode.loop()
    next(loop)  # the first tick: the reach starts, a decision is asked
    choice = FixedPolicy(runner.settings.models, 1, 1).choice
    state = loop.send(choice)  # the next ask: the first step's trigger has fired
    reach = episode.reach
    # ticked halfway through that step, with no decision due: a quiet tick, the reference
    # moving (sampled, its inverse dynamics), as most of the bus's quiet ticks are
    segment = reach.controller.segment
    state = dataclasses.replace(state, t_s=segment.t0_s + segment.duration_s / 2)

    def state_message() -> bytes:
        header = Header(stamp_ns=time.time_ns(), seq=1, source="sim")
        return encode(convert.state_message(header, state, 1, False, state.q, 1))

    payload = state_message()

    def answer() -> bytes:
        message = decode(RobotState, payload)
        tick = reach.tick(convert.robot_state(message))
        assert tick.command is not None
        header = Header(stamp_ns=time.time_ns(), seq=1, source="controller")
        return encode(convert.command_message(header, tick.command, 1, message.header.stamp_ns))

    return {
        "a RobotState built and encoded": state_message,
        "the controller's answer to a state": answer,
        "a trivial call": lambda: None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=300)
    args = parser.parse_args()
    for name, work in works().items():
        gaps: tuple[tuple[str, Callable[[], object]], ...] = (
            ("back to back (hot)", lambda: None),
            ("after one 0.2 ms sleep", sleeps(0.0002)),
            ("after one 10 ms sleep", sleeps(0.01)),
            ("after 10 ms of 0.2 ms sleeps", polls),
            ("after 10 ms of spinning", lambda: spin(0.01)),
            ("after a 10 ms sleep, 1 ms of spinning", sleeps(0.01, lambda: spin(0.001))),
            ("after a 10 ms sleep and the work once", sleeps(0.01, work)),
        )
        print(f"{name}, {args.messages} times each [µs]:")
        for label, gap in gaps:
            spent = []
            for _ in range(args.messages):
                gap()
                start = time.perf_counter()
                work()
                spent.append(time.perf_counter() - start)
            p50, p99 = np.percentile(np.array(spent) * 1e6, [50, 99])
            print(f"    {label:40s}: p50 {p50:6.1f}  p99 {p99:6.1f}")


if __name__ == "__main__":
    main()
