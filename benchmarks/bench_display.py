"""The participant display's state-to-frame latency, in a real browser (headless
Chromium over the DevTools protocol, software WebGL on this machine), beside bare viser
moving one box in the same page and the same run.

    PYTHONPATH=. python benchmarks/bench_display.py [--moves 40]

For each move: the wall time a RobotState is fed to the display (dammrl: forward
kinematics, 8 shapes updated) or a box is moved (bare viser: one node), and the time of
the first screencast frame (Page.screencastFrame's own timestamp) whose pixels show it.
Also: the CPU cost of ``feed`` per state (no browser).
"""

from __future__ import annotations

import argparse
import base64
import io
import statistics
import time

import numpy as np
from PIL import Image

from dammrl.display import ParticipantDisplay
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import Header, RobotState, TaskGoal
from tests.browser import Browser
from tests.busutil import free_port

HEADER = Header(stamp_ns=1, seq=0, source="sim")
POSES = ((0.0, 0.3, 0.0, 0.8, 0.0, 0.0), (0.9, 0.1, 0.0, 0.4, 0.0, 0.0))
VIEW = (slice(60, 600), slice(0, 880))


def _state(q: tuple[float, ...]) -> RobotState:
    return RobotState.model_construct(episode=1, q_rad=q)


def _image(frame: dict[str, object]) -> np.ndarray:
    png = base64.b64decode(str(frame["data"]))
    return np.asarray(Image.open(io.BytesIO(png)).convert("L")).astype(int)[VIEW]


def _latency(browser: Browser, change: object, before: np.ndarray) -> tuple[float, np.ndarray]:
    """Seconds from ``change()`` to the first frame that differs from ``before``."""
    while (old := browser.event("Page.screencastFrame", 0.05)) is not None:  # drain
        browser.call("Page.screencastFrameAck", sessionId=old["sessionId"])  # or none come
    fed = time.time()
    change()  # type: ignore[operator]
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        frame = browser.event("Page.screencastFrame", 1.0)
        if frame is None:
            continue
        browser.call("Page.screencastFrameAck", sessionId=frame["sessionId"])
        image = _image(frame)
        if np.count_nonzero(np.abs(image - before) > 40) > 200:
            return float(frame["metadata"]["timestamp"]) - fed, image  # type: ignore[index]
    raise RuntimeError("no frame showed the change within 10 s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--moves", type=int, default=40)
    args = parser.parse_args()
    display = ParticipantDisplay(RobotSettings().load(), TaskSettings(), "127.0.0.1",
                                 free_port())  # fmt: skip
    display.feed(TaskGoal(header=HEADER, episode=1, seed=0, start_m=(0.3, 0.0, 0.0),
                          goal_m=(0.45, 0.08, -0.25), q_start_rad=POSES[0]))  # fmt: skip
    box = display.server.scene.add_box("/bench_box", (40, 220, 40), (0.1, 0.1, 0.1),
                                       position=(0.3, 0.3, 0.0))  # fmt: skip
    browser = Browser(f"http://127.0.0.1:{display.port}/")
    try:
        time.sleep(8)  # the page loads and draws
        browser.call("Page.startScreencast", format="png", everyNthFrame=1)
        first = browser.event("Page.screencastFrame", 10)
        assert first is not None, "no screencast frame"
        browser.call("Page.screencastFrameAck", sessionId=first["sessionId"])
        image = _image(first)
        dammrl_s, viser_s = [], []
        for move in range(args.moves):
            pose = POSES[(move + 1) % 2]
            latency, image = _latency(browser, lambda p=pose: display.feed(_state(p)), image)
            dammrl_s.append(latency)
            time.sleep(1 / 15)  # the display's own rate limit (30 Hz) never drops a move
            where = (0.3, 0.3 if move % 2 else -0.3, 0.0)
            latency, image = _latency(browser, lambda w=where: setattr(box, "position", w),
                                      image)  # fmt: skip
            viser_s.append(latency)
        browser.call("Page.stopScreencast")
    finally:
        browser.close()
    feeds = []
    for _ in range(500):
        display._drawn_s = 0.0  # measure the drawing, not the rate limit
        started = time.perf_counter()
        display.feed(_state(POSES[len(feeds) % 2]))
        feeds.append(time.perf_counter() - started)
    display.close()
    _report("dammrl: RobotState -> arm drawn", dammrl_s)
    _report("bare viser: one box moved (baseline)", viser_s)
    ratio = statistics.median(dammrl_s) / statistics.median(viser_s)
    print(f"ratio of medians dammrl / bare viser: {ratio:.2f}")
    print(
        f"feed() per state, CPU: median {statistics.median(feeds) * 1e3:.2f} ms, "
        f"p99 {np.percentile(feeds, 99) * 1e3:.2f} ms"
    )


def _report(name: str, seconds: list[float]) -> None:
    ms = np.array(seconds) * 1e3
    print(
        f"{name}: n {len(ms)}, p50 {np.percentile(ms, 50):.0f} ms, "
        f"p90 {np.percentile(ms, 90):.0f} ms, max {ms.max():.0f} ms"
    )


if __name__ == "__main__":
    main()
