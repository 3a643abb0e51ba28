"""``dammrl status`` and ``dammrl echo``: look at a running stack from any machine."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import zenoh

from dammrl.core.errors import DammrlError
from schemas import DecodeError, Health, decode, type_of
from services.common.bus import zenoh_config
from services.common.config import BusSettings


def status(settings: BusSettings, listen_s: float = 2.5) -> str:
    """A table of the services alive on the bus with their health and publish rates."""
    ns = settings.namespace
    with zenoh.open(zenoh_config(settings)) as session:
        health = session.declare_subscriber(f"{ns}/health/*")
        time.sleep(0.3)  # let the connection settle before asking
        alive = sorted(
            str(r.ok.key_expr).rsplit("/", 1)[-1]
            for r in session.liveliness().get(f"{ns}/alive/*", timeout=1.0)
            if r.ok is not None
        )
        reports: dict[str, Health] = {}
        deadline = time.monotonic() + listen_s
        while time.monotonic() < deadline:
            sample = health.try_recv()
            if sample is None:
                time.sleep(0.02)
                continue
            try:
                report = decode(Health, sample.payload.to_bytes())
            except DecodeError:
                continue
            reports[report.service] = report
    return _status_table(alive, reports)


def _status_table(alive: list[str], reports: dict[str, Health]) -> str:
    if not alive and not reports:
        return "no service alive on this namespace (is the stack up, are the endpoints right?)"
    lines = [f"{'service':12s} {'alive':6s} {'state':8s} {'rejected':>8s}  rates / detail"]
    for name in sorted(set(alive) | set(reports)):
        report = reports.get(name)
        if report is None:
            lines.append(f"{name:12s} {'yes':6s} {'?':8s} {'?':>8s}  no health report yet")
            continue
        rates = ", ".join(
            f"{k.split('/', 1)[-1]} {v:.0f} Hz" for k, v in report.rates_hz.items() if v
        )
        rejected = sum(report.rejected.values())
        detail = "; ".join(filter(None, [rates, report.detail]))
        is_alive = "yes" if name in alive else "NO"
        lines.append(f"{name:12s} {is_alive:6s} {report.state:8s} {rejected:8d}  {detail}")
        for where, count in report.rejected.items():
            lines.append(f"{'':12s} {'':6s} {'':8s} {count:8d}  rejected on {where}")
    return "\n".join(lines)


def echo(
    settings: BusSettings,
    topic: str,
    hz: bool = False,
    count: int | None = None,
    duration_s: float | None = None,
    out: Callable[[str], None] = print,
) -> int:
    """Print the decoded messages on ``<namespace>/<topic>`` (or their rate with ``hz``)."""
    key_expr = f"{settings.namespace}/{topic.strip('/')}"
    if type_of(settings.namespace, key_expr.replace("*", "x")) is None and "*" not in topic:
        raise DammrlError(f"unknown topic {topic!r}: see `dammrl schemas` for the topics")
    seen, window, window_start = 0, 0, time.monotonic()
    end = None if duration_s is None else time.monotonic() + duration_s
    with zenoh.open(zenoh_config(settings)) as session:
        subscriber = session.declare_subscriber(key_expr)
        while (count is None or seen < count) and (end is None or time.monotonic() < end):
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
