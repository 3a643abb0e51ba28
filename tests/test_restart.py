"""kill -9 and restart, by hand, each service of a running stack mid-episode.

What a lab does when a process dies: start it again (``python -m services.<name>``).
The stack must go on within ``RECOVERY_S`` of the restart: the reach resumes, or the
episode ends with a reason and the next one starts. Never a silent wait to the episode
timeout.
"""

from __future__ import annotations

import signal
import time

import pytest

from schemas import EpisodeResult, Health, Message, StepEvent
from tests.busutil import SERVICES, Observer, Stack, free_port, wait_for

pytestmark = pytest.mark.slow

RECOVERY_S = 20.0
"""Bound from the restart to the next step of a reach: the restarted process's start-up
(Python, MuJoCo, torch: up to ~6 s on a busy 2-core machine), the controller's re-sent
decision request (every 2 s) and, for the sim, the reset of the next episode."""


def _progress(messages: list[Message]) -> bool:
    """A step of a reach, or the end of an episode."""
    return any(isinstance(m, StepEvent | EpisodeResult) for m in messages)


def _taking_part(name: str, messages: list[Message]) -> bool:
    """The restarted service did its job (not only its health), and the stack stepped
    after that."""
    worked = [i for i, m in enumerate(messages) if m.header.source == name
              and not isinstance(m, Health)]  # fmt: skip
    return bool(worked) and _progress(messages[worked[0] :])


def _restart(stack: Stack, observer: Observer, name: str) -> float:
    """Kill ``name`` mid-reach, start it again; seconds until it takes part."""
    mark = len(observer.received)
    wait_for(lambda: _progress(observer.received[mark:]), 60, "a reach under way")
    stack.kill(name)
    time.sleep(0.5)  # a restart by hand is never instantaneous
    mark = len(observer.received)
    stack.restart(name)
    started = time.monotonic()
    wait_for(
        lambda: _taking_part(name, observer.received[mark:]),
        RECOVERY_S,
        f"the stack to go on with {name} restarted",
    )
    for result in observer.received[mark:]:
        if isinstance(result, EpisodeResult) and not result.success:
            assert result.reason, f"episode {result.episode} ended with no reason"
    return time.monotonic() - started


def test_each_service_killed_and_restarted_mid_episode_the_stack_goes_on() -> None:
    port = free_port()
    observer = Observer(port)
    stack = Stack(port, DAMMRL_TASK_EPISODES="100", DAMMRL_LOG_LEVEL="WARNING")
    try:
        recovered = {name: _restart(stack, observer, name) for name in SERVICES}
        assert all(stack.alive().values()), stack.alive()
        print("recovery after restart [s]:", {k: round(v, 1) for k, v in recovered.items()})
    finally:
        stack.stop()
        observer.close()


def _frozen(stack: Stack, observer: Observer, name: str) -> EpisodeResult:
    """Freeze ``name`` (SIGSTOP) for a second mid-reach, then let it go on; the episode
    it broke: the first result decided after the freeze began (on a busy PC the reach seen
    under way may have ended before, its result still on the way)."""
    mark = len(observer.received)
    wait_for(lambda: _progress(observer.received[mark:]), 60, "a reach under way")
    mark = len(observer.received)
    frozen_ns = time.time_ns()
    stack.processes[name].send_signal(signal.SIGSTOP)
    time.sleep(1.0)
    stack.processes[name].send_signal(signal.SIGCONT)

    def broken() -> list[EpisodeResult]:
        return [m for m in observer.received[mark:]
                if isinstance(m, EpisodeResult) and m.header.stamp_ns > frozen_ns]  # fmt: skip

    wait_for(lambda: bool(broken()), 30, "the broken episode's result")
    return broken()[0]


def test_a_hold_names_who_went_silent() -> None:
    """A frozen controller is reported as the controller's stall, a frozen sim as the sim
    alive but silent (never the one for the other)."""
    port = free_port()
    observer = Observer(port)
    stack = Stack(port, DAMMRL_TASK_EPISODES="100", DAMMRL_LOG_LEVEL="WARNING")
    try:
        controller = _frozen(stack, observer, "controller")
        assert "the controller itself stalled" in controller.reason, controller.reason
        sim = _frozen(stack, observer, "sim")
        assert "sim alive but silent" in sim.reason, sim.reason
    finally:
        stack.stop()
        observer.close()
