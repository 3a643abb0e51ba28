"""The bus's design choices, each undone alone, to measure what it costs (``bench_bus.py``).

A variant patches the one choice in the process it runs in (the benchmark's sim and every
service it starts), so the rest of the stack is the one that ships:

* ``as built``: nothing changed (a waiting loop looks at its rings every 0.2 ms in the
  time-critical services, every 1 ms in the others);
* ``doorbell (before)``: a waiting loop sleeps on a doorbell that every message rings (a
  Python callback per message, run by zenoh-python's callback thread);
* ``doorbell in Zenoh's thread``: the same rung from Zenoh's receiving thread (one thread
  hand-over less per message, but Zenoh's thread waits for the GIL);
* ``1 ms polling``: every service looks at its rings every millisecond;
* ``0.1 ms polling``: the time-critical services look at theirs every 0.1 ms;
* ``5 ms GIL hand-over``: Python's default switch interval instead of the time-critical
  services' 0.2 ms;
* ``loop thread SCHED_FIFO``: the sim's and the controller's loop thread (not Zenoh's)
  under the kernel's real-time FIFO policy (needs root or CAP_SYS_NICE), ahead of every
  ordinary process, other stacks' nice -10 services included;
* ``Zenoh's threads at the default priority``: the time-critical services raise the loop
  thread's priority (and their session's) after Zenoh's threads have started, so those
  stay at the default (as built, they inherit nice -10: a flood's decryption and routing
  then competes with the loop at its own priority);
* ``loop threads on their own cores``: the sim's loop thread on the first core, the
  controller's on the last (that thread only: Zenoh's are started before), so neither
  migrates and each keeps its core's caches between states;
* ``no rate limits``: no per-link ingress downsampling in any session;
* ``every state answered``: the controller answers each waiting state, not only the
  newest;
* ``no rehearsal``: the sim and the controller do not rehearse the next state's work
  while they wait for it (``Bus.rehearse``).

With ``DAMMRL_BENCH_TICKS`` set to a file, the controller service also times each tick
it answers, from taking the state to sending its command, by what the tick did, and
writes them there as it exits (``bench_bus.py --ticks``).

    python benchmarks/bus_variants.py VARIANT SERVICE   # a service under a variant
"""

from __future__ import annotations

import atexit
import json
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from schemas import RobotState
from services.common import bus as bus_module
from services.common import runtime
from services.common.bus import Bus
from services.common.security import ROLES


def _doorbell(indirect: bool) -> Callable[[], None]:
    """Before: each subscription also rings a doorbell (a Python callback per message, in
    zenoh-python's callback thread or, not ``indirect``, in Zenoh's receiving thread) that
    a waiting loop sleeps on."""

    def patch() -> None:
        subscribe_key = Bus.subscribe_key

        def subscribe_with_doorbell(self: Bus, key_expr: str) -> None:
            subscribe_key(self, key_expr)
            doorbell = self.__dict__.setdefault("doorbell", threading.Event())
            handler = zenoh.handlers.Callback(lambda _: doorbell.set(), indirect=indirect)
            self.__dict__.setdefault("doorbells", []).append(
                self.session.declare_subscriber(key_expr, handler)
            )

        def wait(self: Bus, timeout_s: float | None) -> None:
            doorbell = self.__dict__.setdefault("doorbell", threading.Event())
            doorbell.wait(timeout_s)
            doorbell.clear()  # a ring is looked at next: nothing that rang is missed

        Bus.subscribe_key = subscribe_with_doorbell  # type: ignore[method-assign]
        Bus._wait = wait  # type: ignore[method-assign]

    return patch


def _polling_every(poll_s: float) -> Callable[[], None]:
    def patch() -> None:
        bus_module.CRITICAL_POLL_S = bus_module.POLL_S = poll_s

    return patch


def _critical_polling_every(poll_s: float) -> Callable[[], None]:
    def patch() -> None:
        bus_module.CRITICAL_POLL_S = poll_s

    return patch


def _fifo_loop_thread() -> None:
    """The time-critical services' loop thread (that thread only: Zenoh's are started
    before) under the kernel's real-time FIFO policy, ahead of every ordinary process."""
    enter = Bus.__enter__

    def enter_fifo(self: Bus) -> Bus:
        bus = enter(self)
        if self.service in runtime.TIME_CRITICAL:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        return bus

    Bus.__enter__ = enter_fifo  # type: ignore[method-assign]


def _zenoh_threads_at_default_priority() -> None:
    """The time-critical services raise their loop thread's priority after Zenoh's threads
    have started (they stay at the default), not before (they inherit it)."""
    from services.common import entry

    def later(critical: bool) -> str:
        return "priority raised for the loop thread only, after Zenoh's start"

    entry.prioritise = later  # type: ignore[attr-defined]
    enter = Bus.__enter__

    def enter_then_raise(self: Bus) -> Bus:
        bus = enter(self)
        if self.settings.realtime and self.service in runtime.TIME_CRITICAL:
            runtime.prioritise(True)  # this thread (the loop's) and its session
        return bus

    Bus.__enter__ = enter_then_raise  # type: ignore[method-assign]


def _loop_threads_pinned() -> None:
    """The sim's loop thread on the first core, the controller's on the last."""
    enter = Bus.__enter__
    cores = sorted(os.sched_getaffinity(0))

    def enter_pinned(self: Bus) -> Bus:
        bus = enter(self)
        if self.service in runtime.TIME_CRITICAL:
            os.sched_setaffinity(0, {cores[-1] if self.service == "controller" else cores[0]})
        return bus

    Bus.__enter__ = enter_pinned  # type: ignore[method-assign]


def _default_switch_interval() -> None:
    runtime.CRITICAL_SWITCH_INTERVAL_S = 0.005


def _no_rate_limits() -> None:
    bus_module.UNLIMITED_ROLES = tuple(ROLES)


def _no_rehearsal() -> None:
    Bus.rehearse = lambda self, due_s, work: None  # type: ignore[method-assign]


def _every_state_answered() -> None:
    from services.controller.node import ControllerNode

    def dispatch_all(self: ControllerNode, messages: list[object]) -> None:
        for message in messages:
            if isinstance(message, RobotState):
                self._on_state(message)
            else:
                self._dispatch_other(message)  # type: ignore[arg-type]

    ControllerNode._dispatch_all = dispatch_all  # type: ignore[method-assign,assignment]


VARIANTS: dict[str, Callable[[], None]] = {
    "as built": lambda: None,
    "doorbell (before)": _doorbell(indirect=True),
    "doorbell in Zenoh's thread": _doorbell(indirect=False),
    "1 ms polling": _polling_every(0.001),
    "0.1 ms polling": _critical_polling_every(0.0001),
    "5 ms GIL hand-over": _default_switch_interval,
    "loop thread SCHED_FIFO": _fifo_loop_thread,
    "Zenoh's threads at the default priority": _zenoh_threads_at_default_priority,
    "loop threads on their own cores": _loop_threads_pinned,
    "no rate limits": _no_rate_limits,
    "every state answered": _every_state_answered,
    "no rehearsal": _no_rehearsal,
}


TICKS_ENV = "DAMMRL_BENCH_TICKS"
TICK_KINDS = ("quiet", "planned a step (its IK)", "asked for a decision", "started a step")


def time_ticks(path: Path) -> None:
    """Time the controller's answer to each state, from taking the state (``_on_state``)
    to sending its command, and note what the tick did besides (an IK solve, a decision
    request, a step started); written to ``path`` at exit as [kind, seconds] pairs."""
    from services.controller.node import ControllerNode

    ticks: list[tuple[str, float]] = []
    atexit.register(lambda: path.write_text(json.dumps(ticks)))
    init, on_state = ControllerNode.__init__, ControllerNode._on_state
    seen: dict[str, float] = {}  # what the tick running did, and when its command went

    def watch(owner: Any, name: str, what: str) -> None:
        call = getattr(owner, name)

        def watched(*args: Any) -> Any:
            result = call(*args)
            seen.setdefault(what, time.perf_counter())  # the command: built, encoded, put
            return result

        setattr(owner, name, watched)

    def init_watched(self: ControllerNode, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        watch(self.commands, "send", "command")
        watch(self.ik, "solve", TICK_KINDS[1])
        watch(self.asks, "send", TICK_KINDS[2])
        watch(self.steps, "send", TICK_KINDS[3])

    def on_state_timed(self: ControllerNode, message: RobotState, answer: bool = True) -> None:
        seen.clear()
        start = time.perf_counter()
        on_state(self, message, answer)
        if answer and "command" in seen:
            kind = next((k for k in TICK_KINDS[1:] if k in seen), TICK_KINDS[0])
            ticks.append((kind, seen["command"] - start))

    ControllerNode.__init__ = init_watched  # type: ignore[method-assign]
    ControllerNode._on_state = on_state_timed  # type: ignore[method-assign]


def apply(variant: str) -> None:
    """Undo one design choice in this process (see the module's docstring)."""
    VARIANTS[variant]()


def main() -> int:
    variant, service = sys.argv[1], sys.argv[2]
    apply(variant)
    if service == "controller" and os.environ.get(TICKS_ENV):
        time_ticks(Path(os.environ[TICKS_ENV]))
    module = __import__(f"services.{service}.node", fromlist=["main"])
    return int(module.main([]))


if __name__ == "__main__":
    raise SystemExit(main())
