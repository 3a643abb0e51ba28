"""The bus's design choices, each undone alone, to measure what it costs (``bench_bus.py``).

A variant patches the one choice in the process it runs in (the benchmark's sim and every
service it starts), so the rest of the stack is the one that ships:

* ``as built``: nothing changed;
* ``1 ms polling``: no doorbell; a waiting loop looks at its rings every millisecond
  (no Python callback per message);
* ``doorbell in Zenoh's thread``: the doorbell rung from Zenoh's receiving thread instead
  of zenoh-python's callback thread (one thread hand-over less per message);
* ``5 ms GIL hand-over``: Python's default switch interval instead of the time-critical
  services' 0.2 ms;
* ``no rate limits``: no per-link ingress downsampling in any session;
* ``every state answered``: the controller answers each waiting state, not only the
  newest.

    python benchmarks/bus_variants.py VARIANT SERVICE   # a service under a variant
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import zenoh

from schemas import RobotState
from services.common import bus as bus_module
from services.common import runtime
from services.common.bus import Bus
from services.common.security import ROLES


def _polling() -> None:
    def wait(self: Bus, timeout_s: float | None) -> None:
        time.sleep(0.001 if timeout_s is None else min(timeout_s, 0.001))

    Bus._declare_doorbell = lambda self, key_expr: None  # type: ignore[method-assign]
    Bus._wait_for_doorbell = wait  # type: ignore[method-assign]


def _doorbell_in_zenoh_thread() -> None:
    def declare(self: Bus, key_expr: str) -> None:
        ring = zenoh.handlers.Callback(self._ring_doorbell, indirect=False)
        self._doorbells.append(self.session.declare_subscriber(key_expr, ring))

    Bus._declare_doorbell = declare  # type: ignore[method-assign]


def _default_switch_interval() -> None:
    runtime.CRITICAL_SWITCH_INTERVAL_S = 0.005


def _no_rate_limits() -> None:
    bus_module.UNLIMITED_ROLES = tuple(ROLES)


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
    "1 ms polling": _polling,
    "doorbell in Zenoh's thread": _doorbell_in_zenoh_thread,
    "5 ms GIL hand-over": _default_switch_interval,
    "no rate limits": _no_rate_limits,
    "every state answered": _every_state_answered,
}


def apply(variant: str) -> None:
    """Undo one design choice in this process (see the module's docstring)."""
    VARIANTS[variant]()


def main() -> int:
    variant, service = sys.argv[1], sys.argv[2]
    apply(variant)
    module = __import__(f"services.{service}.node", fromlist=["main"])
    return int(module.main([]))


if __name__ == "__main__":
    raise SystemExit(main())
