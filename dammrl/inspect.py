"""``dammrl status`` and ``dammrl echo``: look at a running stack from any machine."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dammrl_core.errors import DammrlError
from schemas import DecodeError, Health, decode, type_of
from services.common.bus import linked, not_joined_line, tool_session
from services.common.config import BusSettings
from services.common.runtime import stopping_on_signals


@dataclass
class Roll:
    """What ``status`` heard: tokens alive (its own query and what the services see), the
    last Health of each service, and the services others saw go away (when, Unix time)."""

    alive: set[str] = field(default_factory=set)
    reports: dict[str, Health] = field(default_factory=dict)
    missing: dict[str, float] = field(default_factory=dict)

    def hear(self, report: Health) -> None:
        self.reports[report.service] = report
        self.alive |= set(report.peers)
        for name, when in report.missing.items():
            self.missing[name] = max(when, self.missing.get(name, 0.0))

    def names(self) -> set[str]:
        return self.alive | set(self.reports) | set(self.missing)


def status(settings: BusSettings, listen_s: float = 2.5) -> tuple[str, bool]:
    """A table of the services on the bus with their health and publish rates, and
    whether every service heard of is alive and reporting."""
    ns = settings.namespace
    roll = Roll()
    with tool_session(settings) as session:
        health = session.declare_subscriber(f"{ns}/health/*")
        time.sleep(0.3)  # let the connection settle before asking
        roll.alive |= {
            str(r.ok.key_expr).rsplit("/", 1)[-1]
            for r in session.liveliness().get(f"{ns}/alive/*", timeout=1.0)
            if r.ok is not None
        }
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline:
            sample = health.try_recv()
            if sample is None:
                time.sleep(0.02)
                continue
            with contextlib.suppress(DecodeError):
                roll.hear(decode(Health, sample.payload.to_bytes()))
        joined = linked(session)
    names = roll.names()
    if not names and not joined:
        return not_joined_line(settings), False
    for name in roll.alive:
        roll.missing.pop(name, None)  # back since (a restarted service)
    healthy = bool(names) and all(n in roll.alive and n in roll.reports for n in names)
    return _status_table(roll, listen_s), healthy


def _status_table(roll: Roll, listen_s: float) -> str:
    names = sorted(roll.names())
    if not names:
        return "no service alive on this namespace (is the stack up, are the endpoints right?)"
    lines = [f"{'service':12s} {'alive':6s} {'state':8s} {'rejected':>8s}  rates / detail"]
    for name in names:
        lines += _service_lines(name, roll, listen_s)
    return "\n".join(lines)


def _service_lines(name: str, roll: Roll, listen_s: float) -> list[str]:
    report = roll.reports.get(name)
    if name not in roll.alive and report is None:
        ago = time.time() - roll.missing[name]
        return [f"{name:12s} {'NO':6s} {'missing':8s} {'':>8s}  last seen {ago:.0f} s ago"]
    if report is None:
        silence = f"no health report in {listen_s:.1f} s (hung, or just started?)"
        return [f"{name:12s} {'yes':6s} {'silent':8s} {'?':>8s}  {silence}"]
    rates = ", ".join(f"{k.split('/', 1)[-1]} {v:.0f} Hz" for k, v in report.rates_hz.items() if v)
    rejected = sum(report.rejected.values())
    detail = "; ".join(filter(None, [rates, report.detail]))
    is_alive = "yes" if name in roll.alive else "NO"
    lines = [f"{name:12s} {is_alive:6s} {report.state:8s} {rejected:8d}  {detail}"]
    for where, count in report.rejected.items():
        lines.append(f"{'':12s} {'':6s} {'':8s} {count:8d}  rejected on {where}")
    return lines


def echo(
    settings: BusSettings,
    topic: str,
    hz: bool = False,
    count: int | None = None,
    duration_s: float | None = None,
    out: Callable[[str], None] = print,
    say: Callable[[str], None] | None = None,
) -> int:
    """Print the decoded messages on ``<namespace>/<topic>`` (or their rate with ``hz``)
    until ``count``, ``duration_s``, Ctrl-C or a closed pipe; how many arrived. ``say``
    hears within seconds if no stack let the session in."""
    key_expr = f"{settings.namespace}/{topic.strip('/')}"
    if type_of(settings.namespace, key_expr.replace("*", "x")) is None and "*" not in topic:
        raise DammrlError(f"unknown topic {topic!r}: see `dammrl schemas` for the topics")
    seen, window, window_start = 0, 0, time.monotonic()
    end = None if duration_s is None else time.monotonic() + duration_s
    with stopping_on_signals() as stop, tool_session(settings, say) as session:
        subscriber = session.declare_subscriber(key_expr)
        while not stop.is_set() and (count is None or seen < count):
            if end is not None and time.monotonic() >= end:
                break
            sample = subscriber.try_recv()
            now = time.monotonic()
            if hz and now - window_start >= 1.0:
                out(f"{key_expr}: {window / (now - window_start):.1f} Hz")
                window, window_start = 0, now
            if sample is None:
                time.sleep(0.005)
                continue
            seen += 1
            window += 1
            if not hz:
                out(_render(settings.namespace, str(sample.key_expr), sample.payload.to_bytes()))
    return seen


def _render(namespace: str, key_expr: str, payload: bytes) -> str:
    message_type = type_of(namespace, key_expr)
    if message_type is None:
        return json.dumps({"key": key_expr, "undecodable": payload.hex()})
    try:
        return json.dumps(
            {"key": key_expr, **decode(message_type, payload).model_dump(mode="json")}
        )
    except DecodeError as exc:
        return json.dumps({"key": key_expr, "invalid": str(exc)})
