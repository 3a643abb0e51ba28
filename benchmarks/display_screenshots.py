"""The participant display's screenshots in the docs (docs/guide/display_*.png), taken in
headless Chromium (Debian's package, software WebGL) as the display tests take theirs.

    PYTHONPATH=. python benchmarks/display_screenshots.py [--out docs/guide]

Two screens: mid-reach with a decision asked (the arm, the goal button, the subgoal with
its admission sphere, "Decide now"), and the comfort question after a block. Chromium's
notice about software WebGL is hidden: a browser with a GPU shows none.
"""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np

from dammrl.display import ParticipantDisplay
from dammrl_core.dynamics import ArmModel
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import DecisionRequest, Header, RobotState, StepEvent, TaskGoal
from tests.browser import Browser
from tests.busutil import free_port, wait_for

HEADER = Header(stamp_ns=1, seq=0, source="controller")
MID_REACH = (0.35, 0.45, 0.0, 0.9, 0.0, 0.2)  # rad: the arm part-way to the goal
HIDE_NOTICES = """document.querySelectorAll('.mantine-Notification-root, [class*=otification]')
    .forEach(n => n.style.display = 'none')"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs/guide"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    robot, task = RobotSettings().load(), TaskSettings()
    display = ParticipantDisplay(robot, task, "127.0.0.1",
                                 free_port(), decide_with="Press firmly to go forward, "
                                 "lightly to go back.")  # fmt: skip
    browser = Browser(f"http://127.0.0.1:{display.port}/")
    try:
        tip = ArmModel(robot).ee_position(np.array(MID_REACH))
        goal = (tip[0] + 0.12, tip[1] + 0.04, task.table_top_z_m)
        display.feed(TaskGoal(header=HEADER, episode=1, seed=0, start_m=tuple(tip),
                              goal_m=goal, q_start_rad=MID_REACH))  # fmt: skip
        display.feed(RobotState.model_construct(episode=1, q_rad=MID_REACH))
        subgoal = tip + 0.25 * (np.array(goal) - tip)
        display.feed(StepEvent.model_construct(subgoal_m=tuple(subgoal), radius_m=0.02))
        display.feed(DecisionRequest.model_construct(episode=1, request=4))
        _shoot(browser, "Decide now", args.out / "display_decide.png")
        asking = threading.Thread(target=display.ask_comfort, args=(30,), daemon=True)
        asking.start()
        _shoot(browser, "Touch one answer", args.out / "display_comfort.png")
    finally:
        browser.close()
        display.close()


def _shoot(browser: Browser, words: str, path: Path) -> None:
    """A screenshot once ``words`` show and the scene has had time to draw."""
    wait_for(lambda: words in str(browser.evaluate("document.body.innerText")), 60, words)
    time.sleep(6)  # software WebGL draws the scene slowly
    browser.evaluate(HIDE_NOTICES)
    time.sleep(0.5)
    browser.screenshot(path)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
