"""The participant display's server without a browser: a page that connects gets the
present at once, a page's garbage or a late answer changes nothing, the page counts as
connected while it speaks, and a port that cannot be used is one line."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import pytest
from websockets.sync.client import connect

from dammrl.people.display import ParticipantDisplay, inputs_for
from dammrl_core.errors import ConfigurationError
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from tests.busutil import free_port, wait_for


@pytest.fixture
def display() -> Iterator[ParticipantDisplay]:
    shown = ParticipantDisplay(RobotSettings().load(), TaskSettings(), "127.0.0.1", free_port(),
                               inputs_for("pad"))  # fmt: skip
    try:
        yield shown
    finally:
        shown.close()


def _channels(page: object, wanted: set[str]) -> dict[str, dict[str, object]]:
    """The messages a page receives until it has one of each ``wanted`` channel."""
    got: dict[str, dict[str, object]] = {}
    while not wanted <= set(got):
        message = json.loads(page.recv(timeout=10))  # type: ignore[attr-defined]
        got[message["t"]] = message
    return got


def test_a_page_that_connects_gets_the_present_screen_and_scene_at_once(
    display: ParticipantDisplay,
) -> None:
    display.say("Back again", "The display restarted.")
    with connect(f"ws://127.0.0.1:{display.port}/ws") as page:
        got = _channels(page, {"hello", "screen", "arm", "marks"})
    assert got["screen"]["title"] == "Back again"
    assert got["hello"]["stage"]["camera"] and got["arm"]["shapes"]


def test_garbage_and_late_answers_from_a_page_change_nothing(display: ParticipantDisplay) -> None:
    answer: list[tuple[int, float] | None] = []
    asking = threading.Thread(target=lambda: answer.append(display.ask_comfort(10)))
    with connect(f"ws://127.0.0.1:{display.port}/ws") as page:
        asking.start()
        wait_for(lambda: display.screens.question == 1, 10, "the question")
        for junk in (
            "not json",
            "[1, 2]",
            json.dumps({"t": "rating", "question": 1, "value": 9}),
            json.dumps({"t": "rating", "question": 0, "value": 3}),  # an older one
            json.dumps({"t": "rating", "question": "1", "value": 3}),
            json.dumps({"t": "rating", "question": 1, "value": True}),
            "[" * 1500 + "]" * 1500,  # nested deeper than the parser goes
        ):  # fmt: skip
            page.send(junk)
        time.sleep(0.5)
        assert asking.is_alive()  # none of them answered
        assert display.pages() == 1  # and the page still counts (its handler went on)
        page.send(json.dumps({"t": "rating", "question": 1, "value": 2}))
        asking.join(10)
    assert answer and answer[0] is not None and answer[0][0] == 2


def test_a_page_counts_as_connected_while_it_speaks_and_not_once_it_closes(
    display: ParticipantDisplay,
) -> None:
    assert display.pages() == 0
    with connect(f"ws://127.0.0.1:{display.port}/ws") as page:
        page.send(json.dumps({"t": "ping"}))
        wait_for(lambda: display.pages() == 1, 5, "the page counted")
    wait_for(lambda: display.pages() == 0, 5, "the closed page no longer counted")


def test_a_port_in_use_is_one_line_naming_the_setting(display: ParticipantDisplay) -> None:
    with pytest.raises(ConfigurationError, match=r"cannot listen on 127\.0\.0\.1:.*--display-port"):
        ParticipantDisplay(RobotSettings().load(), TaskSettings(), "127.0.0.1", display.port)
