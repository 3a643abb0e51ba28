"""The participant display's latency from a bus event to the words on the page, beside
bare viser showing the same words from the same events, in one run, quiet and under load.

    PYTHONPATH=. python benchmarks/bench_display.py [--events 60] [--hogs 2]

One Zenoh bus (a router on loopback); a publisher alternates DecisionRequest and Intent
(the page's title turns "Decide now", then "Moving forward"). The participant display
takes them through its BusFeed (decode, its screens, its server, its WebSocket, its page);
bare viser (the baseline) takes them through a Zenoh subscriber that sets an HTML element
of viser's panel to the same words. Each page runs in its own headless Chromium (viser's
with software WebGL, as it needs; the display's draws on the CPU) with a MutationObserver
that stamps every change of the words with the page's clock (``performance.timeOrigin +
performance.now()``, the machine's wall clock, as the publisher's ``time.time()`` is).
Latency: the page's stamp minus the publisher's. Then the same again beside ``--hogs``
CPU hogs (``yes > /dev/null``). Also: the CPU cost of ``feed`` per message (no browser).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import viser
import zenoh

from dammrl.people.display import BusFeed, ParticipantDisplay, inputs_for
from dammrl_core.robot import RobotSettings
from dammrl_core.task import TaskSettings
from schemas import DecisionRequest, Header, Intent, TaskGoal, decode, encode, key
from services.common.bus import zenoh_config
from tests.browser import Browser
from tests.busutil import client_settings, free_port, listener_settings, wait_for

NAMESPACE = "dammrl"
TITLES = {DecisionRequest: "Decide now", Intent: "Moving forward"}
WATCH = """
window.__seen = [];
new MutationObserver(() => {
  const node = document.getElementById('%s');
  const text = node ? node.textContent.trim() : '';
  const last = window.__seen[window.__seen.length - 1];
  if (text && (!last || last.text !== text))
    window.__seen.push({t: performance.timeOrigin + performance.now(), text});
}).observe(document, {subtree: true, childList: true, characterData: true});
"""


def _messages(n: int) -> Iterator[DecisionRequest | Intent]:
    header = Header(stamp_ns=1, seq=0, source="controller")
    for k in range(n):
        if k % 2 == 0:
            yield DecisionRequest(header=header, episode=1, seed=0, request=k // 2 + 1,
                                  t_s=float(k), ee_pos_m=(0.4, 0.0, 0.0), goal_m=(0.5, 0, -0.2),
                                  primary_axis=0, human_model=1)  # fmt: skip
        else:
            yield Intent(header=header, episode=1, request=k // 2 + 1, u_h=1, human_model=1,
                         radius_m=0.01, confidence=1.0, source="pad", person=True,
                         decision_s=0.4)  # fmt: skip


class BareViser:
    """The baseline: viser's own page, one HTML element set from the bus."""

    def __init__(self, session: zenoh.Session) -> None:
        with contextlib.redirect_stdout(open(os.devnull, "w")):
            self.server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
        self.html = self.server.gui.add_html('<div id="bench">Welcome</div>')
        self.subscribers = [
            session.declare_subscriber(key(NAMESPACE, kind), self._take(kind)) for kind in TITLES
        ]

    def _take(self, kind: type) -> Any:
        def take(sample: zenoh.Sample) -> None:
            decode(kind, sample.payload.to_bytes())  # the same work as the display's feed
            self.html.content = f'<div id="bench">{TITLES[kind]}</div>'

        return take


def _run(
    events: int, browsers: dict[str, Browser], publisher: zenoh.Session
) -> dict[str, list[float]]:
    """Publish ``events`` alternating messages; each page's latency per event [ms]."""
    for browser in browsers.values():
        browser.evaluate("window.__seen = []")
    sent: list[tuple[float, str]] = []
    for message in _messages(events):
        time.sleep(0.5)  # each change shown before the next, as a person reads it
        title = TITLES[type(message)]
        sent.append((time.time() * 1e3, title))
        publisher.put(key(NAMESPACE, type(message)), encode(message))
    time.sleep(2.0)
    latencies: dict[str, list[float]] = {}
    for name, browser in browsers.items():
        seen = list(browser.evaluate("window.__seen") or [])
        latencies[name] = _match(sent, seen)
    return latencies


def _match(sent: list[tuple[float, str]], seen: list[dict[str, Any]]) -> list[float]:
    """For each event, the first change to its words after it was sent, if that came
    before the next event's words (an event whose words never showed is not counted) [ms]."""
    out = []
    for k, (at, title) in enumerate(sent):
        shown = next((s["t"] for s in seen if s["text"] == title and s["t"] >= at), None)
        if shown is None:
            continue
        if k + 1 < len(sent):
            after, following = sent[k + 1]
            later = [s["t"] for s in seen if s["text"] == following and s["t"] >= after]
            if later and shown > later[0]:
                continue  # its words never showed: the next event's came first
        out.append(shown - at)
    return out


def _report(label: str, latencies: dict[str, list[float]], events: int) -> None:
    load = os.getloadavg()[0]
    print(f"{label} (load average {load:.1f} on {os.cpu_count()} cores):")
    for name, ms in latencies.items():
        if not ms:
            print(f"  {name}: no event shown")
            continue
        a = np.array(ms)
        print(f"  {name}: n {len(a)} of {events}, p50 {np.percentile(a, 50):.1f} ms, "
              f"p90 {np.percentile(a, 90):.1f} ms, max {a.max():.1f} ms")  # fmt: skip
    ours, base = latencies.get("dammrl display", []), latencies.get("bare viser", [])
    if ours and base:
        print(f"  ratio of medians dammrl / bare viser: "
              f"{statistics.median(ours) / statistics.median(base):.2f}")  # fmt: skip


def _feed_cost(display: ParticipantDisplay) -> None:
    display.feed(TaskGoal(header=Header(stamp_ns=1, seq=0, source="controller"), episode=1,
                          seed=0, start_m=(0.3, 0, 0), goal_m=(0.5, 0, -0.2),
                          q_start_rad=(0, 1, 0, 1.6, 0, 0.3)))  # fmt: skip
    costs = []
    for message in _messages(400):
        started = time.perf_counter()
        display.feed(message)
        costs.append(time.perf_counter() - started)
    print(f"feed() per message, CPU: median {statistics.median(costs) * 1e3:.3f} ms, "
          f"p99 {np.percentile(costs, 99) * 1e3:.3f} ms")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--events", type=int, default=60)
    parser.add_argument("--hogs", type=int, default=2)
    args = parser.parse_args()
    port = free_port()
    hub = zenoh.open(zenoh_config(listener_settings(port, NAMESPACE, mode="router")))
    publisher = zenoh.open(zenoh_config(client_settings(port, NAMESPACE)))
    display = ParticipantDisplay(RobotSettings().load(), TaskSettings(), "127.0.0.1", free_port(),
                                 inputs_for("pad"))  # fmt: skip
    feed = BusFeed(display, NAMESPACE)
    feed.attach(hub)
    bare = BareViser(hub)
    browsers: dict[str, Browser] = {}
    hogs: list[subprocess.Popen[bytes]] = []
    try:
        browsers["dammrl display"] = Browser("about:blank")
        browsers["bare viser"] = Browser("about:blank", webgl=True)
        browsers["dammrl display"].before_each_page(WATCH % "title")
        browsers["bare viser"].before_each_page(WATCH % "bench")
        browsers["dammrl display"].open(display.url.replace("localhost", "127.0.0.1"))
        browsers["bare viser"].open(f"http://127.0.0.1:{bare.server.get_port()}/")
        for name, element in (("dammrl display", "title"), ("bare viser", "bench")):
            shown = f"(document.getElementById('{element}') || {{}}).textContent"
            wait_for(lambda b=browsers[name], s=shown: b.evaluate(s) == "Welcome", 120,
                     f"the {name}'s page")  # fmt: skip
        time.sleep(2)
        _report("quiet", _run(args.events, browsers, publisher), args.events)
        hogs = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(args.hogs)]
        time.sleep(2)
        _report(f"beside {args.hogs} CPU hogs", _run(args.events, browsers, publisher),
                args.events)  # fmt: skip
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
        for browser in browsers.values():
            browser.close()
        with contextlib.redirect_stdout(open(os.devnull, "w")):
            bare.server.stop()
    _feed_cost(display)
    display.close()
    publisher.close()
    hub.close()


if __name__ == "__main__":
    main()
