"""The participant display in a real browser (headless Chromium, software WebGL): the
arm and the goal are drawn, the arm moves with the state, the cue and the comfort
rating work by touch."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dammrl.display import ParticipantDisplay
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import DecisionRequest, EpisodeResult, Header, RobotState, StepEvent, TaskGoal
from tests.browser import CHROMIUM, Browser
from tests.busutil import free_port, wait_for

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no chromium (apt-get install chromium)"),
]
HEADER = Header(stamp_ns=1, seq=0, source="controller")
Q_A = (0.0, 0.3, 0.0, 0.8, 0.0, 0.0)
Q_B = (0.9, 0.1, 0.0, 0.4, 0.0, 0.0)
VIEW = (slice(60, 600), slice(0, 880))  # the 3D view (rows, columns): left of the panel


def _state(q: tuple[float, ...]) -> RobotState:
    return RobotState.model_construct(episode=1, q_rad=q)


def _pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)[VIEW]


def _red(image: np.ndarray) -> np.ndarray:
    """The goal: strongly red pixels."""
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    return (r > 150) & (g < 110) & (b < 110)


def _arm(image: np.ndarray) -> np.ndarray:
    """The arm: light, nearly grey, slightly blue pixels (the table is brown, the
    background dark)."""
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    return (b > 150) & (abs(r - g) < 25) & (b >= r - 5) & (b - r < 60)


@pytest.fixture
def page(tmp_path: Path) -> Iterator[tuple[ParticipantDisplay, Browser]]:
    display = ParticipantDisplay(RobotSettings().load(), TaskSettings(), host="127.0.0.1",
                                 port=free_port())  # fmt: skip
    browser: Browser | None = None
    try:
        display.feed(TaskGoal(header=HEADER, episode=1, seed=0, start_m=(0.3, 0.0, 0.0),
                              goal_m=(0.45, 0.08, -0.25), q_start_rad=Q_A))  # fmt: skip
        display.feed(_state(Q_A))
        browser = Browser(f"http://127.0.0.1:{display.port}/")
        yield display, browser
    finally:
        if browser is not None:
            browser.close()
        display.close()


def test_the_arm_and_the_goal_are_drawn_and_the_arm_moves_with_the_state(
    page: tuple[ParticipantDisplay, Browser], tmp_path: Path
) -> None:
    display, browser = page
    shots: list[np.ndarray] = []

    def drawn() -> bool:
        shots.append(_pixels(browser.screenshot(tmp_path / "a.png")))
        return int(_red(shots[-1]).sum()) > 30 and int(_arm(shots[-1]).sum()) > 2000

    wait_for(drawn, 60, "arm and goal on the page")
    before = _arm(shots[-1])
    time.sleep(1 / 20)  # the display redraws states at most 30 a second
    display.feed(_state(Q_B))

    def moved() -> bool:
        shots.append(_arm(_pixels(browser.screenshot(tmp_path / "b.png"))))
        return int((shots[-1] ^ before).sum()) > 1500

    wait_for(moved, 30, "arm moved on the page")
    after = shots[-1]
    rows, cols = np.nonzero(before)
    rows_b, cols_b = np.nonzero(after)
    shift = np.hypot(rows.mean() - rows_b.mean(), cols.mean() - cols_b.mean())
    assert shift > 10, shift  # the arm's pixels moved (the base joint turned 0.9 rad)


def test_the_cue_the_outcome_and_the_comfort_rating_by_touch(
    page: tuple[ParticipantDisplay, Browser], tmp_path: Path
) -> None:
    display, browser = page

    def text() -> str:
        return str(browser.evaluate("document.body.innerText"))

    wait_for(lambda: "Get ready" in text(), 60, "the reach's first words")
    display.feed(StepEvent.model_construct(subgoal_m=(0.4, 0.05, -0.1), radius_m=0.02))
    display.feed(DecisionRequest.model_construct(episode=1, request=1))
    wait_for(lambda: "Decide now" in text(), 10, "the decision cue")
    result = EpisodeResult.model_construct(success=True, t_total_s=12.3, outcome="success")
    display.feed(result)
    wait_for(lambda: "Well done" in text(), 10, "the outcome")

    answer: list[tuple[int, float] | None] = []
    asking = threading.Thread(target=lambda: answer.append(display.ask_comfort(30)))
    asking.start()
    click_four = """(() => { const b = [...document.querySelectorAll('button')]
        .find(b => b.innerText.trim().startsWith('4 ')); if (b) { b.click(); return true; }
        return false; })()"""
    wait_for(lambda: "Touch one answer" in text(), 15, "the rating's question")
    browser.screenshot(tmp_path / "comfort.png")
    wait_for(lambda: bool(browser.evaluate(click_four)), 15, "the rating's buttons")
    asking.join(15)
    assert answer and answer[0] is not None and answer[0][0] == 4
    wait_for(lambda: "Thank you" in text(), 10, "the thanks")
