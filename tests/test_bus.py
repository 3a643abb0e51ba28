"""The bus layer with two real Zenoh sessions on loopback (explicit endpoints only)."""

from __future__ import annotations

import time

import msgpack

from schemas import Header, Health, ModelChoice, RobotState, encode
from services.common.bus import Bus
from tests.busutil import client_settings, free_port, listener_settings
from tests.test_schemas import EXAMPLES

STATE = EXAMPLES[0]


def _choice(header: Header, i: int, j: int) -> ModelChoice:
    return ModelChoice(header=header, human_model=i, robot_model=j, radius_m=0.004,
                       steps_m=(0.03, 0.01, 0.01))  # fmt: skip


def _receive(bus: Bus, timeout_s: float = 3.0) -> object:
    return bus.receive(timeout_s)


def test_sessions_find_each_other_only_through_explicit_endpoints() -> None:
    port = free_port()
    with Bus(listener_settings(port), "a") as a, Bus(client_settings(port), "b") as b:
        b.subscribe(ModelChoice)
        time.sleep(0.5)
        publisher = a.publisher(ModelChoice)
        sent = publisher.send(_choice(publisher.stamp(), 2, 5))
        received = _receive(b)
        assert received == sent
        assert sent.header.source == "a" and sent.header.seq == 0
        assert publisher.send(_choice(publisher.stamp(), 2, 5)).header.seq == 1


def test_namespaces_keep_stacks_apart() -> None:
    port = free_port()
    with (
        Bus(listener_settings(port, "lab1"), "a") as a,
        Bus(client_settings(port, "lab2"), "b") as b,
    ):
        b.subscribe(ModelChoice)
        time.sleep(0.5)
        publisher = a.publisher(ModelChoice)
        publisher.send(_choice(publisher.stamp(), 1, 1))
        assert b.receive(0.5) is None


def test_malformed_input_is_rejected_counted_and_reported() -> None:
    port = free_port()
    with (
        Bus(listener_settings(port), "fuzzer") as fuzzer,
        Bus(client_settings(port), "victim") as victim,
    ):
        victim.subscribe(RobotState, Health)
        time.sleep(0.5)
        key = victim.key(RobotState)
        bad_state = msgpack.unpackb(encode(STATE))
        bad_state["q_rad"][0] = float("nan")
        for payload in (b"\x00\xff not msgpack", msgpack.packb([1, 2]), msgpack.packb(bad_state)):
            fuzzer.session.put(key, payload)
            time.sleep(0.01)  # slower than the key's rate limit on one link
        fuzzer.session.put(key, encode(STATE))  # one good message after the garbage
        assert _receive(victim) == STATE
        assert victim.rejected[key] == 3


def test_messages_from_an_unexpected_source_are_rejected() -> None:
    port = free_port()
    with (
        Bus(listener_settings(port), "impostor") as impostor,
        Bus(client_settings(port), "sim") as sim,
    ):
        sim.subscribe(ModelChoice)
        sim.expect(ModelChoice, "policy")
        time.sleep(0.5)
        publisher = impostor.publisher(ModelChoice)
        publisher.send(_choice(publisher.stamp(), 1, 1))
        assert sim.receive(0.5) is None
        assert sim.rejected[sim.key(ModelChoice)] == 1


def test_health_reports_rates_and_rejections() -> None:
    port = free_port()
    with (
        Bus(listener_settings(port), "watcher") as watcher,
        Bus(client_settings(port), "svc") as svc,
    ):
        watcher.subscribe_key("dammrl/health/*")
        time.sleep(0.5)
        svc.reject("dammrl/robot/command", "test")
        svc.report_health("holding", "because", force=True)
        report = watcher.receive(3.0)
        assert isinstance(report, Health)
        assert report.service == "svc" and report.state == "holding"
        assert report.rejected == {"dammrl/robot/command": 1}
