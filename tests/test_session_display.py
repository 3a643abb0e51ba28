"""A real session on the participant's page in headless Chromium: every screen appears
(the decision cue with its arrows and the trial counter, the arm moving, each outcome held
for its set time, a takeover, a pause, the stop screen, the comfort question, a rest, the
end); and an open page reconnects by itself when the session is killed (``kill -9``, its
stack with it) and started again, during the comfort question and during the rest, which
the resumed session completes."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.browser import CHROMIUM, Browser
from tests.busutil import free_port, wait_for
from tests.display_tour import CLICK_FOUR, LOG_SCREENS, SCREENS, tour

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(CHROMIUM is None, reason="no chromium (apt-get install chromium)"),
]
OUTCOME_S = 2.0  # the session's default


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_every_screen_of_a_real_session_appears_on_the_page(tmp_path: Path) -> None:
    seen = tour(tmp_path, tmp_path / "shots")
    kinds = [s["kind"] for s in seen.screens]
    print("the page showed:", " ".join(kinds))  # in full when it fails (pytest cuts asserts)
    print("the session said:", *seen.said, sep="\n  ")
    assert not seen.error and seen.code == 0, (seen.error, seen.said[-10:])
    assert set(SCREENS) <= set(kinds), (kinds, seen.said)
    # each outcome stays its set time (the next reach, or the block's comfort, after it),
    # less the jitter between the result's and the next goal's way to the page (under load)
    held = [b["t"] - a["t"] for a, b in zip(seen.screens, seen.screens[1:], strict=False)
            if a["kind"] == "outcome" and b["kind"] != "stopped"]  # fmt: skip
    around = [(a["kind"], a["title"], round(b["t"] - a["t"]), b["kind"], b["title"])
              for a, b in zip(seen.screens, seen.screens[1:], strict=False)
              if a["kind"] == "outcome"]  # fmt: skip
    print(f"figure: outcomes held {sorted(round(h) for h in held)} ms (set {OUTCOME_S:g} s)")
    assert held and min(held) >= 1000 * OUTCOME_S - 300, around
    cue = seen.facts["cue"]
    assert "FORWARD" in cue["arrows"] and "Press firmly" in cue["arrows"]
    assert "BACK" in cue["arrows"] and "Press lightly" in cue["arrows"]
    assert cue["words_px"] >= 400  # of 800: the words take half the page and more
    places = {s["place"] for s in seen.screens if s["kind"] == "cue"}
    assert {"Trial 1 of 2 · Block 1 of 2", "Trial 1 of 1 · Block 2 of 2"} <= places
    assert seen.facts["stopped"]["background"] == "rgb(176, 0, 0)"  # the whole page red
    assert seen.facts["taken"]["arrows"] == ""  # nothing to choose while taken over
    assert seen.folder is not None
    trials = _lines(seen.folder / "trials.jsonl")
    stopped = [t for t in trials if t.get("stopped")]
    assert stopped and stopped[0]["repeat"] and stopped[0]["trial"] == 2
    assert sorted(t["trial"] for t in trials if not t.get("repeat")) == [1, 2, 3]
    comfort = [e for e in _lines(seen.folder / "events.jsonl") if e["what"] == "comfort"]
    assert next((e["block"], e["rating"]) for e in comfort) == ("first", 4)


PROTOCOL = """\
format: 1
name: kills
version: "1"
blocks:
  - {name: one, trials: 1, seed: 7100100, rest_s: 20, condition: {policy: fixed, model: [2, 1]}}
  - {name: two, trials: 1, seed: 7100200, condition: {policy: fixed, model: [2, 1]}}
"""


def _start(tmp_path: Path, bus: int, display: int) -> subprocess.Popen[bytes]:
    log = open(tmp_path / "runner.log", "ab")  # noqa: SIM115  (the child writes it)
    return subprocess.Popen(
        [sys.executable, "-m", "dammrl", "session", "run", "--participant", "P001",
         "--protocol", str(tmp_path / "kills.yaml"), "--root", str(tmp_path / "sessions"),
         "--lockstep", "--bus-port", str(bus), "--display-host", "127.0.0.1",
         "--display-port", str(display), "--comfort-timeout", "120"],
        stdin=subprocess.DEVNULL, stdout=log, stderr=log,
    )  # fmt: skip


def _kill(runner: subprocess.Popen[bytes]) -> None:
    runner.send_signal(signal.SIGKILL)
    runner.wait(10)


def _events(tmp_path: Path) -> list[dict[str, Any]]:
    path = tmp_path / "sessions" / "P001" / "ses-01" / "events.jsonl"
    return _lines(path) if path.exists() else []


def _said(tmp_path: Path) -> str:
    return (tmp_path / "runner.log").read_text(errors="replace")


def _reconnected(tmp_path: Path, connected: Any, run: int) -> float:
    """Seconds from the ``run``-th display being up to the open page connected to it."""
    wait_for(lambda: _said(tmp_path).count("participant display: open") >= run, 60,
             f"display {run} up")  # fmt: skip
    up = time.monotonic()
    wait_for(connected, 30, f"the page connected to display {run}")
    took = time.monotonic() - up
    print(f"figure: the open page reconnected {took:.2f} s after display {run} was up")
    return took


def test_a_page_reconnects_after_kills_during_the_comfort_question_and_the_rest(
    tmp_path: Path,
) -> None:
    (tmp_path / "kills.yaml").write_text(PROTOCOL)
    bus, port = free_port(), free_port()
    runner = _start(tmp_path, bus, port)
    browser = Browser("about:blank")
    try:
        browser.before_each_page(LOG_SCREENS)
        wait_for(lambda: "participant display: open" in _said(tmp_path), 60, "the display")
        browser.open(f"http://127.0.0.1:{port}/")

        def kind() -> str:
            return str(browser.evaluate("document.body && document.body.dataset.kind"))

        def connected() -> bool:
            return browser.evaluate("document.body && document.body.dataset.connected") == "true"

        wait_for(lambda: kind() == "comfort", 240, "the comfort question after block one")
        _kill(runner)  # mid-question: the session, its display and its stack go at once
        wait_for(lambda: not connected(), 10, "the page noticing")
        assert not [e for e in _events(tmp_path) if e["what"] == "comfort"]
        runner = _start(tmp_path, bus, port)
        assert _reconnected(tmp_path, connected, 2) < 5.0  # seconds after the display is up
        wait_for(lambda: kind() == "comfort", 60, "the interrupted question asked again")
        wait_for(lambda: bool(browser.evaluate(CLICK_FOUR)), 15, "the answers")
        wait_for(lambda: kind() == "rest", 30, "the rest")
        time.sleep(3)
        _kill(runner)  # mid-rest
        wait_for(lambda: not connected(), 10, "the page noticing")
        runner = _start(tmp_path, bus, port)
        assert _reconnected(tmp_path, connected, 3) < 5.0
        wait_for(lambda: kind() == "rest", 30, "what was left of the rest")
        assert runner.wait(300) == 0, _said(tmp_path)[-2000:]
        events = _events(tmp_path)
        comfort = [e for e in events if e["what"] == "comfort"]
        assert [(e["block"], e["rating"]) for e in comfort][:1] == [("one", 4)]
        rests = [e for e in events if e["what"] == "rest"]
        assert len(rests) == 2 and rests[1]["resumed"] and rests[1]["seconds"] < 20
        assert [e["what"] for e in events].count("rest-end") == 1
        assert events[-1]["what"] == "end"
        said = _said(tmp_path)
        assert said.count("participant page: connected (1)") >= 3  # the console says it
    finally:
        if runner.poll() is None:
            _kill(runner)
        browser.close()
