"""A container's health check: ``python -m services.common.healthcheck SERVICE``.

Healthy means SERVICE is alive on the bus (its liveliness token) and its own latest Health
report names a working state. The check reads the service's bus settings from the same
environment (DAMMRL_BUS_*, the mounted credentials) and joins as a read-only Zenoh
*client* with the ``observer`` certificate at the service's own LISTEN endpoint on loopback:
the bus's access control accepts a service's token and Health only from that service's
own link (a client of the sim would hear the others' through the sim, and drop them), and
a client links to that one endpoint, so a check every few seconds adds no peer to the
stack's mesh. A service is checked only if it listens on a fixed port.

Exit status as Docker reads it: 0 healthy, 1 not (also for unusable settings); one line
on stdout says why (``docker inspect`` keeps it).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Sequence

import zenoh
from pydantic import ValidationError

from dammrl_core.errors import ConfigurationError, DammrlError
from dammrl_core.settings import error_line
from schemas import DecodeError, Health, decode, key
from services.common.bus import tool_session
from services.common.config import BusSettings
from services.common.security import OBSERVER

HEALTHY_STATES = ("ok", "holding")
"""Working states. "holding" is the arm's safe wait (gravity compensation until the
controller's first command; the controller waiting for the policy and the human): a sim
that waits for a controller that waits for a healthy sim would otherwise never start.
"degraded" (a fallback policy, an unplugged sensor, a recorder that cannot write) is not."""
WILDCARD_HOSTS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}


def probe_settings(settings: BusSettings) -> BusSettings:
    """The check's own session: a client with the observer role (read only), at the
    service's listening endpoints on loopback."""
    if not settings.listen or any(e.endswith(":0") for e in settings.listen):
        raise ConfigurationError(
            f"the service listens on no fixed endpoint (DAMMRL_BUS_LISTEN={settings.listen}): "
            'give it one, e.g. ["tls/0.0.0.0:7447"], to check it'
        )
    connect = [_on_loopback(e) for e in settings.listen]
    return settings.model_copy(
        update={"mode": "client", "listen": [], "connect": connect, "role": OBSERVER}
    )


def _on_loopback(endpoint: str) -> str:
    """``tls/0.0.0.0:7447`` -> ``tls/127.0.0.1:7447``: a listening endpoint, reached from
    inside the same container."""
    scheme, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    return f"{scheme}/{WILDCARD_HOSTS.get(host, host)}:{port}"


def check(settings: BusSettings, service: str, timeout_s: float) -> str | None:
    """Why ``service`` is not healthy, or None when it is (waits up to ``timeout_s``)."""
    probe = probe_settings(settings)
    deadline = time.monotonic() + timeout_s
    try:
        with tool_session(probe) as session:
            reports = session.declare_subscriber(key(probe.namespace, Health, service))
            alive = f"{probe.namespace}/alive/{service}"
            if not any(r.ok is not None for r in session.liveliness().get(alive, timeout=1.0)):
                return f"{service} is not alive on the bus at {probe.connect}"
            report = _next_report(reports, deadline)
    except zenoh.ZError as exc:
        return f"cannot join the bus at {probe.connect}: {error_line(exc)}"
    if report is None:
        return f"{service} is alive but sent no Health in {timeout_s:g} s"
    if report.state not in HEALTHY_STATES:
        return f"{service} reports {report.state}: {report.detail}"
    return None


def _next_report(
    reports: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]], deadline: float
) -> Health | None:
    """The first well-formed Health before ``deadline`` (a service reports every second)."""
    while time.monotonic() < deadline:
        sample = reports.try_recv()
        if sample is None:
            time.sleep(0.05)
            continue
        with contextlib.suppress(DecodeError):
            return decode(Health, sample.payload.to_bytes())
    return None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m services.common.healthcheck",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog="Bus settings come from DAMMRL_BUS_* as for the service itself. "
        "Exit status: 0 healthy, 1 not.",
    )
    parser.add_argument("service", help="the service's name on the bus, e.g. sim")
    parser.add_argument(
        "--timeout", type=float, default=5.0, metavar="S", help="longest wait for a Health [s]"
    )
    args = parser.parse_args(argv)
    try:
        problem = check(BusSettings(), args.service, args.timeout)
    except (ValidationError, DammrlError) as exc:
        problem = f"cannot check: {error_line(exc)}"
    print(problem or f"{args.service} is healthy")
    return 0 if problem is None else 1


if __name__ == "__main__":
    sys.exit(main())
