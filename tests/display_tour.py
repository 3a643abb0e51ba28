"""A real session (the service stack, the emulated pad pressed by the simulated
patient, in real time) shown on the participant's page in headless Chromium, with a
therapist at the console who visits every screen: a decision cue, the arm moving, an
outcome, a takeover, a pause, an emergency stop mid-reach (released, the trial run again),
the comfort question (answered by touch), a rest, the end. The page logs each screen it
shows with its own clock (a MutationObserver installed before the page's own script).
tests/test_session_display.py checks what the tour saw; benchmarks/display_screenshots.py
keeps its screenshots for the docs."""

from __future__ import annotations

import base64
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dammrl.cli.session import open_display
from dammrl.people.console import COMMANDS
from dammrl.people.session import SessionRunner, SetUp
from tests.browser import Browser
from tests.busutil import free_port, start_patient, wait_for
from tests.sessionutil import Typist

PROTOCOL = """\
format: 1
name: tour
version: "1"
blocks:
  - {name: first, trials: 2, seed: 7100100, rest_s: 5,
     condition: {policy: fixed, model: [2, 1]},
     instructions: Two reaches. The arm moves on once it is near each waypoint.}
  - {name: second, trials: 1, seed: 7100200, condition: {policy: fixed, model: [2, 1]},
     instructions: One more reach.}
"""
SCREENS = ("cue", "moving", "outcome", "rest", "comfort", "stopped", "taken", "end")
"""The screens the issue asks to see, each once at least (and in the docs)."""
LOG_SCREENS = """
window.__screens = [];
new MutationObserver(() => {
  const body = document.body, title = document.getElementById('title');
  if (!body || !title) return;
  const last = window.__screens[window.__screens.length - 1];
  const arrows = document.getElementById('arrows');
  const seen = {t: performance.timeOrigin + performance.now(), kind: body.dataset.kind,
                title: title.textContent, place: document.getElementById('place').textContent,
                arrows: getComputedStyle(arrows).display !== 'none' ? arrows.innerText : '',
                words_px: document.getElementById('words').getBoundingClientRect().height,
                background: getComputedStyle(body).backgroundColor};
  if (!last || last.kind !== seen.kind || last.title !== seen.title) window.__screens.push(seen);
}).observe(document, {subtree: true, childList: true, characterData: true,
                      attributes: true, attributeFilter: ['data-kind']});
"""
PICTURED = {"cue": "Decide now"}
"""The title a kind's picture must show (the cue also says "Your turn again")."""
PICTURED_S = 1.5
"""A screen's picture is the last frame painted in its first 1.5 s (a rest's countdown
then shows most of its time)."""
CLICK_FOUR = """(() => { const b = [...document.querySelectorAll('#answers button')]
    .find(b => b.innerText.trim().startsWith('4 ')); if (b) { b.click(); return true; }
    return false; })()"""


@dataclass
class Tour:
    """What the tour saw: the page's screens in order, the screenshots, what the session
    said at the console, its exit code and its folder."""

    screens: list[dict[str, Any]] = field(default_factory=list)
    shots: dict[str, Path] = field(default_factory=dict)
    said: list[str] = field(default_factory=list)
    code: int | None = None
    folder: Path | None = None
    facts: dict[str, Any] = field(default_factory=dict)  # the page's arrows, counter, ...
    error: str = ""  # what went wrong on the browser's side


def tour(work: Path, shots: Path, timeout_s: float = 480.0) -> Tour:
    """Run the session under ``work`` (the emulated pad pressed by the simulated patient),
    screenshots into ``shots``; what was seen."""
    shots.mkdir(parents=True, exist_ok=True)
    (work / "tour.yaml").write_text(PROTOCOL)
    typist = Typist([("is not counted", "release"), ("released", "a the arm is free")],
                    every={"press Enter": ""})  # fmt: skip
    link, bus = work / "ttyPAD", free_port()
    patient = start_patient(link, bus, human_model=1)
    display = open_display("127.0.0.1", free_port(), "pad")
    setup = SetUp(mode="semi-virtual", intent="pad", pad_port=str(link), bus_port=bus,
                  operator="T1")  # fmt: skip
    runner = SessionRunner(work / "sessions", "P001", work / "tour.yaml", setup,
                           say=typist.say, wait_for_operator=True, display=display,
                           comfort_timeout_s=60, console=typist.stream)  # fmt: skip
    seen = Tour(said=typist.said)
    browser = Browser("about:blank")
    try:
        browser.before_each_page(LOG_SCREENS)
        browser.open(display.url.replace("localhost", "127.0.0.1"))
        running = threading.Event()
        running.set()
        deadline = time.monotonic() + timeout_s

        def visit() -> None:
            try:
                _visit(browser, typist, seen, shots, running, deadline)
            except Exception as exc:  # the session must not wait on a dead visitor
                seen.error = f"the visitor failed: {exc!r}"
                typist.close()

        visitor = threading.Thread(target=visit)
        visitor.start()
        try:
            seen.code = runner.run()  # the stack takes signals: the main thread's
        finally:
            running.clear()
            visitor.join(30)
        seen.screens = list(browser.evaluate("window.__screens") or [])
        seen.folder = work / "sessions" / "P001" / "ses-01"
    finally:
        typist.close()
        browser.close()
        display.close()
        patient.terminate()
        patient.wait(10)
    return seen


def _visit(browser: Browser, typist: Typist, seen: Tour, shots: Path,
           running: threading.Event, deadline: float) -> None:  # fmt: skip
    """Act on each screen as it comes: shoot it the first time, then what the therapist
    or the participant does there; past ``deadline`` the console ends (so does the
    session). The second reach is paused, resumed and then stopped."""
    typed: dict[str, int] = {}  # each line typed: how much the session had said then

    def once(line: str) -> None:
        if line not in typed:
            typed[line] = len(typist.said)
            typist.type(line)

    def again_if_refused() -> None:
        """A line the session refused ("type it again once the reach runs": the page can
        show a reach a moment before the console acts on it) is typed again, as a
        therapist would."""
        for line, said in list(typed.items()):
            refusal = f"console: {COMMANDS.get(line.split()[0])} refused"
            if any(refusal in words for words in typist.said[said:]):
                del typed[line]

    frames = Frames(browser)
    while running.is_set():
        if time.monotonic() > deadline:
            typist.close()
            return
        frames.take()
        again_if_refused()
        kind = str(browser.evaluate("document.body && document.body.dataset.kind") or "")
        frames.shoot(list(browser.evaluate("window.__screens") or []), seen, shots)
        if kind == "comfort" and "comfort" in seen.shots:
            browser.evaluate(CLICK_FOUR)  # every question is answered (once pictured)
        steps = ("t the patient is tired", "g", "p a sip of water", "r", "x the arm slipped")
        step = next((line for line in steps if line not in typed), None)
        if step == steps[0] and kind in ("cue", "moving"):
            once(step)  # take the decisions over ...
        elif step == "g" and "taken" in seen.shots:
            once(step)  # ... and give them back
        elif step == steps[2] and kind == "outcome":
            typed["outcome"] = len(typist.said)  # the next reach: paused, resumed, stopped
        elif (
            (step == steps[2] and "outcome" in typed and kind in ("cue", "moving"))
            or (step == "r" and "paused" in seen.shots)
            or (step == steps[4] and kind in ("cue", "moving"))
        ):
            once(step)
        time.sleep(0.05)
    # the last screen painted (under load the page may take a while to get it)
    ended = "document.body && document.body.dataset.kind === 'end'"
    wait_for(lambda: bool(browser.evaluate(ended)), 15, "the end screen")
    time.sleep(0.5)
    frames.take()
    frames.shoot(list(browser.evaluate("window.__screens") or []), seen, shots, last=True)
    kind = str(browser.evaluate("document.body.dataset.kind"))
    if kind not in seen.shots:  # still now (the session is over): a plain screenshot
        seen.shots[kind] = shots / f"display_{kind}.png"
        browser.screenshot(seen.shots[kind])
        seen.facts[kind] = (browser.evaluate("window.__screens") or [{}])[-1]


class Frames:
    """The page's painted frames (Chromium's screencast, each with its paint time) and,
    for each screen in the page's own log, the first picture painted while it showed:
    a screen that lasts half a second is caught as surely as a long one."""

    def __init__(self, browser: Browser) -> None:
        self.browser = browser
        self.frames: list[tuple[float, str]] = []  # (paint time [ms since epoch], PNG base64)
        loaded = "document.readyState === 'complete' && !!document.body.dataset.kind"
        wait_for(lambda: bool(browser.evaluate(loaded)), 60, "the page loaded")
        browser.call("Page.startScreencast", format="png", everyNthFrame=1)

    def take(self) -> None:
        """Every frame painted since the last look (each acknowledged, or none come)."""
        while (frame := self.browser.event("Page.screencastFrame", 0.0)) is not None:
            self.browser.call("Page.screencastFrameAck", sessionId=frame["sessionId"])
            self.frames.append((1000 * float(frame["metadata"]["timestamp"]), frame["data"]))
        self.frames = self.frames[-120:]

    def shoot(self, screens: list[dict[str, Any]], seen: Tour, shots: Path,
              last: bool = False) -> None:  # fmt: skip
        """A picture of each screen kind not yet pictured, from the frames painted while
        it showed (the last screen too when ``last``: nothing follows it)."""
        ends = [s["t"] for s in screens[1:]] + [float("inf") if last else -1.0]
        for screen, end in zip(screens, ends, strict=True):
            kind = screen["kind"]
            if (
                not kind
                or kind in seen.shots
                or PICTURED.get(kind, screen["title"]) != screen["title"]
            ):
                continue
            if end < 0 and time.time() * 1000 - screen["t"] > 500:
                self._still(screen, len(screens), seen, shots)  # showing, painted once
                continue
            until = min(end, screen["t"] + 1000 * PICTURED_S)
            painted = [data for t, data in self.frames if screen["t"] <= t < until]
            if painted:  # the last: a still screen paints once, a moving scene on and on
                seen.shots[kind] = shots / f"display_{kind}.png"
                seen.shots[kind].write_bytes(base64.b64decode(painted[-1]))
                seen.facts[kind] = screen

    def _still(self, screen: dict[str, Any], count: int, seen: Tour, shots: Path) -> None:
        """A picture of the screen showing now, kept if no other came meanwhile."""
        png = self.browser.screenshot()
        if self.browser.evaluate("window.__screens.length") == count:
            seen.shots[screen["kind"]] = shots / f"display_{screen['kind']}.png"
            seen.shots[screen["kind"]].write_bytes(png)
            seen.facts[screen["kind"]] = screen
