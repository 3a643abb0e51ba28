"""The time-critical loops rehearse the next state's work while they wait for it
(``Bus.rehearse``): at the right time, once, never stopping the loop, and changing no
result."""

from __future__ import annotations

import logging
import time

import pytest

from dammrl_core.control.controller import Controller
from dammrl_core.control.settings import ControllerSettings
from dammrl_core.state import RobotState
from services.common.bus import REHEARSAL_LEAD_S, Bus
from services.common.config import BusSettings
from tests.test_results_unchanged import reaches


def test_a_rehearsal_runs_once_while_the_loop_waits_its_lead_before_the_state() -> None:
    bus = Bus(BusSettings(), "controller")  # no session: only the waiting is used
    ran: list[str] = []
    due = time.monotonic() + REHEARSAL_LEAD_S + 0.05
    bus.rehearse(due, lambda: ran.append("old"))
    bus.rehearse(due, lambda: ran.append("new"))  # a later call replaces it
    while time.monotonic() < due - REHEARSAL_LEAD_S - 0.001:
        bus._wait(0.001)
    assert ran == []  # not before its lead
    while time.monotonic() < due:
        bus._wait(0.001)
    assert ran == ["new"]
    bus._wait(0.001)
    assert ran == ["new"]  # once


def test_a_rehearsal_that_fails_is_logged_and_the_loop_goes_on_without_them(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus = Bus(BusSettings(), "controller")

    def broken() -> None:
        raise ValueError("a bug in a rehearsal")

    bus.rehearse(0.0, broken)
    with caplog.at_level(logging.ERROR):
        bus._wait(0.001)  # no exception reaches the loop
    assert "a rehearsal failed (the loop goes on without them)" in caplog.text
    ran: list[int] = []
    bus.rehearse(0.0, lambda: ran.append(1))
    bus._wait(0.001)
    assert ran == []


@pytest.mark.parametrize("feedforward", ["inverse_dynamics", "resolved_acceleration"])
def test_a_rehearsal_before_every_tick_changes_no_result(
    monkeypatch: pytest.MonkeyPatch, feedforward: str
) -> None:
    """The controller's rehearsal on the state about to be ticked, before every tick of
    whole reaches: the reaches hash the same, bit for bit."""
    settings = ControllerSettings(feedforward=feedforward)  # type: ignore[arg-type]
    plain = reaches(False, settings)
    tick = Controller.tick

    def rehearsed_tick(self: Controller, state: RobotState, early: object = None) -> object:
        self.rehearse(state)
        return tick(self, state, early)  # type: ignore[arg-type]

    monkeypatch.setattr(Controller, "tick", rehearsed_tick)
    assert reaches(False, settings) == plain
