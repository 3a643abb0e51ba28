"""``dammrl status`` and ``dammrl echo``: look at a running stack from any machine."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

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


LOOK_AGAIN_S = 1.0
"""A client alone this long looks again for the stack's settings (a run started since)."""


@dataclass
class _Heard:
    """What ``echo`` heard so far (it may listen on several sessions in turn)."""

    seen: int = 0
    window: int = 0
    window_start: float = field(default_factory=time.monotonic)


def echo(
    settings: BusSettings,
    topic: str,
    hz: bool = False,
    count: int | None = None,
    duration_s: float | None = None,
    out: Callable[[str], None] = print,
    say: Callable[[str], None] | None = None,
    found_later: Callable[[], BusSettings] | None = None,
) -> int:
    """Print the decoded messages on ``<namespace>/<topic>`` (or their rate with ``hz``)
    until ``count``, ``duration_s``, Ctrl-C or a closed pipe; how many arrived. ``say``
    hears within seconds if no stack let the session in. ``found_later``: the settings
    looked up again while no stack answers (a `dammrl up` started after this, or started
    again, speaks TLS with credentials of its own): echo then listens to that run."""
    key_expr = f"{settings.namespace}/{topic.strip('/')}"
    if type_of(settings.namespace, key_expr.replace("*", "x")) is None and "*" not in topic:
        raise DammrlError(f"unknown topic {topic!r}: see `dammrl schemas` for the topics")
    heard = _Heard()
    end = None if duration_s is None else time.monotonic() + duration_s
    with stopping_on_signals() as stop:
        while True:
            with tool_session(settings, say) as session:
                listen = _Listen(session.declare_subscriber(key_expr), hz, out,
                                 settings.namespace, key_expr)  # fmt: skip
                moved = partial(_moved, session, settings, found_later)
                again = listen.until(heard, stop, count, end, moved)
            if again is None:
                return heard.seen
            if say is not None:
                say(f"dammrl: a run answers at {', '.join(again.connect)} now: listening to it")
            settings = again


def _moved(session: Any, settings: BusSettings,
           found_later: Callable[[], BusSettings] | None) -> BusSettings | None:  # fmt: skip
    """Other settings to listen with, when nothing answers these and a run is found."""
    if found_later is None or linked(session):
        return None
    now = found_later()
    return now if now != settings else None


@dataclass
class _Listen:
    subscriber: Any
    hz: bool
    out: Callable[[str], None]
    namespace: str
    key_expr: str

    def until(self, heard: _Heard, stop: Any, count: int | None, end: float | None,
              moved: Callable[[], BusSettings | None]) -> BusSettings | None:  # fmt: skip
        """Print what comes until done (None) or other settings are due (them)."""
        look_again = time.monotonic() + LOOK_AGAIN_S
        while not stop.is_set() and (count is None or heard.seen < count):
            now = time.monotonic()
            if end is not None and now >= end:
                break
            if now >= look_again:
                look_again = now + LOOK_AGAIN_S
                if (settings := moved()) is not None:
                    return settings
            sample = self.subscriber.try_recv()
            if self.hz and now - heard.window_start >= 1.0:
                self.out(f"{self.key_expr}: {heard.window / (now - heard.window_start):.1f} Hz")
                heard.window, heard.window_start = 0, now
            if sample is None:
                time.sleep(0.005)
                continue
            heard.seen += 1
            heard.window += 1
            if not self.hz:
                self.out(_render(self.namespace, str(sample.key_expr), sample.payload.to_bytes()))
        return None


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
