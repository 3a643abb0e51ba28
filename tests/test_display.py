"""The participant display in a real browser (headless Chromium): the words fill at least
half of the page and grow with the larger-text setting, nothing on it is a control but the
comfort answers, the arm, the goal and the subgoal's admission sphere are drawn and the arm
moves with the state, the comfort rating works by touch, and an open page reconnects by
itself when the display restarts under it (tests/test_session_display.py runs a whole
session on it)."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dammrl.people.display import ParticipantDisplay, Place, inputs_for
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import DecisionRequest, Header, RobotState, StepEvent, TaskGoal
from tests.browser import CHROMIUM, Browser
from tests.busutil import free_port, wait_for

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no chromium (apt-get install chromium)"),
]
HEADER = Header(stamp_ns=1, seq=0, source="controller")
Q_A = (0.0, 0.3, 0.0, 0.8, 0.0, 0.0)
Q_B = (0.9, 0.1, 0.0, 0.4, 0.0, 0.0)
MID_REACH = (0.35, 0.45, 0.0, 0.9, 0.0, 0.2)


def _display(port: int, large: bool = False) -> ParticipantDisplay:
    return ParticipantDisplay(RobotSettings().load(), TaskSettings(), "127.0.0.1", port,
                              inputs_for("pad"), large)  # fmt: skip


def _reach(display: ParticipantDisplay, q: tuple[float, ...] = MID_REACH) -> None:
    """A reach under way: its goal, the arm at ``q``, a subgoal, a decision asked."""
    tip = ArmModel(RobotSettings().load()).ee_position(np.array(q))
    goal = (tip[0] + 0.12, tip[1] + 0.04, TaskSettings().table_top_z_m)
    display.expect_run({1: Place(3, 5, 2, 3)}, "pad")
    display.feed(TaskGoal(header=HEADER, episode=1, seed=0, start_m=tuple(tip), goal_m=goal,
                          q_start_rad=q))  # fmt: skip
    display.feed(RobotState.model_construct(episode=1, q_rad=q))
    subgoal = tip + 0.25 * (np.array(goal) - tip)
    display.feed(StepEvent.model_construct(subgoal_m=tuple(subgoal), radius_m=0.004))
    display.feed(DecisionRequest.model_construct(episode=1, request=1))


@pytest.fixture
def page() -> Iterator[tuple[ParticipantDisplay, Browser]]:
    display = _display(free_port())
    browser: Browser | None = None
    try:
        browser = Browser(display.url.replace("localhost", "127.0.0.1"))
        yield display, browser
    finally:
        if browser is not None:
            browser.close()
        display.close()


def _kind(browser: Browser) -> str:
    return str(browser.evaluate("document.body.dataset.kind"))


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_the_words_fill_half_the_page_in_large_type_and_nothing_is_a_control(
    page: tuple[ParticipantDisplay, Browser],
) -> None:
    display, browser = page
    _reach(display)
    wait_for(lambda: _kind(browser) == "cue", 30, "the decision cue")
    words = browser.evaluate("document.getElementById('words').getBoundingClientRect().height")
    title = browser.evaluate(
        "parseFloat(getComputedStyle(document.getElementById('title')).fontSize)"
    )
    assert words >= 0.5 * 800 and title >= 80  # px on a 1280 x 800 screen
    arrows = browser.evaluate("document.getElementById('arrows').innerText")
    assert "FORWARD" in arrows and "Press firmly" in arrows and "Press lightly" in arrows
    assert browser.evaluate("document.getElementById('place').innerText") == (
        "Trial 3 of 5 · Block 2 of 3")  # fmt: skip
    controls = "document.querySelectorAll('button, input, select, textarea, a').length"
    assert browser.evaluate(controls) == 0  # no settings, no engineering controls
    larger = _display(free_port(), large=True)
    try:
        browser.open(larger.url.replace("localhost", "127.0.0.1"))
        wait_for(lambda: _kind(browser) == "welcome", 30, "the larger page")
        wait_for(lambda: "large" in str(browser.evaluate("document.body.className")), 10, "large")
        big = browser.evaluate(
            "parseFloat(getComputedStyle(document.getElementById('title')).fontSize)"
        )
        high = browser.evaluate("document.getElementById('words').getBoundingClientRect().height")
        assert big >= 1.25 * title and high > words
    finally:
        larger.close()


def test_the_arm_the_goal_and_the_subgoals_sphere_are_drawn_and_the_arm_moves(
    page: tuple[ParticipantDisplay, Browser], tmp_path: Path
) -> None:
    display, browser = page
    _reach(display)
    wait_for(lambda: _kind(browser) == "cue", 30, "the reach on the page")
    top = int(browser.evaluate("document.getElementById('view').getBoundingClientRect().top"))
    time.sleep(0.5)

    def scene() -> np.ndarray:
        return _pixels(browser.screenshot(tmp_path / "scene.png"))[top:]

    image = scene()
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    assert int(((r > 200) & (g < 60) & (b < 60)).sum()) > 150  # the red button and its pin
    sphere = (b > 200) & (r < 80) & (g > 110) & (g < 180)
    assert int(sphere.sum()) > 100  # a 4 mm sphere drawn large enough to see
    arm = (abs(r - 205) < 12) & (abs(g - 210) < 12) & (abs(b - 220) < 12)
    before = arm.copy()
    assert int(before.sum()) > 3000
    time.sleep(1 / 20)  # states are drawn at most 30 a second
    display.feed(RobotState.model_construct(episode=1, q_rad=Q_B))

    def moved() -> bool:
        now = scene()
        after = (abs(now[..., 0] - 205) < 12) & (abs(now[..., 1] - 210) < 12)
        return int((after ^ before).sum()) > 2000

    wait_for(moved, 15, "the arm moved on the page")


def test_the_comfort_rating_by_touch(page: tuple[ParticipantDisplay, Browser]) -> None:
    display, browser = page
    wait_for(lambda: _kind(browser) == "welcome", 30, "the page")
    answer: list[tuple[int, float] | None] = []
    asking = threading.Thread(target=lambda: answer.append(display.ask_comfort(30)))
    asking.start()
    wait_for(lambda: _kind(browser) == "comfort", 15, "the question")
    click_four = """(() => { const b = [...document.querySelectorAll('#answers button')]
        .find(b => b.innerText.trim().startsWith('4 ')); if (b) { b.click(); return true; }
        return false; })()"""
    wait_for(lambda: bool(browser.evaluate(click_four)), 15, "the answers")
    asking.join(15)
    assert answer and answer[0] is not None and answer[0][0] == 4
    wait_for(lambda: _kind(browser) == "thanks", 10, "the thanks")
    assert browser.evaluate("document.querySelectorAll('button').length") == 0


def test_an_open_page_reconnects_by_itself_when_the_display_restarts(
    page: tuple[ParticipantDisplay, Browser],
) -> None:
    display, browser = page
    _reach(display)
    wait_for(lambda: _kind(browser) == "cue", 30, "the page")
    wait_for(lambda: display.pages() == 1, 10, "the page counted as connected")
    port = display.port
    display.close()
    wait_for(lambda: browser.evaluate("document.body.dataset.connected") == "false", 10,
             "the page noticing its server went")  # fmt: skip
    again = _display(port)
    try:
        again.say("Back again", "The display restarted.")
        started = time.monotonic()
        wait_for(lambda: browser.evaluate("document.getElementById('title').innerText")
                 == "Back again", 15, "the page reconnected")  # fmt: skip
        took = time.monotonic() - started
        print(f"figure: the open page showed the restarted display's words after {took:.2f} s")
        assert took < 5
        wait_for(lambda: again.pages() == 1, 5, "the restarted display counting the page")
    finally:
        again.close()
