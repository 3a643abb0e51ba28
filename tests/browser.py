"""Headless Chromium (Debian's package) driven over the Chrome DevTools Protocol: open a
page, wait, screenshot. Playwright and Puppeteer download their own browser (which fails
here); CDP over one WebSocket needs nothing but ``websockets``."""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

from tests.busutil import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class Browser:
    """One headless Chromium showing ``url`` (software WebGL)."""

    def __init__(self, url: str, width: int = 1280, height: int = 800, webgl: bool = False
                 ) -> None:  # fmt: skip
        """``webgl``: software WebGL (SwiftShader: a core's worth of CPU, for a 3D page such
        as viser's); without it the page draws on the CPU directly (the participant
        display's 2D canvas: SwiftShader would make each of its frames cost tens of ms)."""
        assert CHROMIUM is not None, "chromium is not installed (apt-get install chromium)"
        self.port = free_port()
        self.profile = tempfile.mkdtemp(prefix="dammrl-chromium-")
        graphics = (["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
                    if webgl else ["--disable-gpu"])  # fmt: skip
        self.process = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", *graphics,
             f"--remote-debugging-port={self.port}", f"--user-data-dir={self.profile}",
             f"--window-size={width},{height}", "--hide-scrollbars",
             # the page's timers as in a visible tab (a participant's screen is one)
             "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
             "--disable-backgrounding-occluded-windows", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        self.ws = connect(self._page_socket(), max_size=None, open_timeout=10)
        self.next_id = 0
        self.events: list[dict[str, Any]] = []
        self.call("Page.enable")
        # the page's viewport exactly: headless Chromium's window keeps some for itself
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                  deviceScaleFactor=1, mobile=False)  # fmt: skip

    def _page_socket(self) -> str:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json") as answer:
                    pages = [p for p in json.load(answer) if p.get("type") == "page"]
                if pages:
                    return str(pages[0]["webSocketDebuggerUrl"])
            except OSError:
                pass
            time.sleep(0.1)
        raise AssertionError("chromium did not open its DevTools port")

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self.next_id += 1
        ident = self.next_id
        self.ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=30))
            if reply.get("id") == ident:
                if "error" in reply:
                    raise AssertionError(f"{method}: {reply['error']}")
                return dict(reply.get("result", {}))
            if "method" in reply:
                self.events.append(reply)

    def event(self, method: str, timeout_s: float) -> dict[str, Any] | None:
        """The next event ``method`` (events come once a domain is enabled)."""
        deadline = time.monotonic() + timeout_s
        while True:
            for i, message in enumerate(self.events):
                if message["method"] == method:
                    return dict(self.events.pop(i)["params"])
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                self.events.append(json.loads(self.ws.recv(timeout=left)))
            except TimeoutError:
                return None

    def open(self, url: str) -> None:
        """Go to ``url`` (the scripts added before run in it from its first line)."""
        self.call("Page.navigate", url=url)

    def before_each_page(self, script: str) -> None:
        """Run ``script`` in every page this browser loads, before the page's own."""
        self.call("Page.addScriptToEvaluateOnNewDocument", source=script)

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result.get("result", {}).get("value")

    def screenshot(self, path: Path | None = None) -> bytes:
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            path.write_bytes(png)
        return png

    def close(self) -> None:
        self.ws.close()
        self.process.terminate()
        self.process.wait(10)
        shutil.rmtree(self.profile, ignore_errors=True)
