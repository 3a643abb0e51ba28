"""The bus layer with two real Zenoh sessions on loopback (explicit endpoints only)."""

from __future__ import annotations

import sys
import threading
import time

import msgpack
import numpy as np

from dammrl_core.robot import RobotSettings
from dammrl_core.sim.settings import SimSettings
from dammrl_core.state import JointCommand as CoreCommand
from dammrl_core.task import TaskSettings
from schemas import Header, Health, JointCommand, ModelChoice, RobotState, encode
from services.common import convert
from services.common.bus import Bus
from services.common.runtime import CRITICAL_SWITCH_INTERVAL_S
from services.sim.node import SimNode
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


def test_the_sim_takes_each_command_when_it_arrives_not_at_its_next_period() -> None:
    """The sim waits out its period looking at its inbox: a command answering a state is
    taken as it arrives, so the round trip it measures is the bus's and the answerer's
    (it looked only once a period: every round trip was the period less the step, ~19 ms
    here; two threads of one process on a loaded machine may take longer, but not always)."""
    port = free_port()
    settings = SimSettings(state_rate_hz=50.0)  # a 20 ms period
    switch = sys.getswitchinterval()
    sys.setswitchinterval(CRITICAL_SWITCH_INTERVAL_S)  # two services' loops in one process
    with Bus(listener_settings(port), "sim") as bus, Bus(client_settings(port), "controller") as c:
        c.subscribe(RobotState)
        node = SimNode(settings, TaskSettings(), RobotSettings(), bus)
        stop = threading.Event()
        loop = threading.Thread(target=node.run, args=(stop,), daemon=True)
        loop.start()
        commands, deadline = c.publisher(JointCommand), time.monotonic() + 30
        try:
            while len(node.round_trips_s) < 20 and time.monotonic() < deadline:
                if isinstance(state := c.receive(0.5), RobotState):
                    commands.send(_answer(commands.stamp(), state))
        finally:
            stop.set()
            loop.join(5)
            sys.setswitchinterval(switch)
    assert len(node.round_trips_s) >= 20
    # looked at only once a period, none could be shorter than the period less a step
    assert min(node.round_trips_s) < 0.5 / settings.state_rate_hz


def _answer(header: Header, state: RobotState) -> JointCommand:
    """Hold where the state says the arm is (what a controller at rest sends)."""
    zeros = np.zeros(6)
    q = np.array(state.q_rad)
    hold = CoreCommand(q_ref=q, dq_ref=zeros, tau_ff=zeros, kp=np.full(6, 20.0),
                       kd=np.full(6, 2.0))  # fmt: skip
    return convert.command_message(header, hold, state.episode, state.header.stamp_ns)
