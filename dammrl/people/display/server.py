"""The page's server: ``page.html`` over HTTP and one WebSocket per open page, on one port.

The server keeps the latest message of each channel (``hello``, ``screen``, ``arm``,
``marks``) and sends a page all of them when it connects, so a page that reconnects (after
the network, the page or this server restarted) shows the present at once; afterwards
every change goes to every page from one sender thread (a bus callback never waits on a
slow page, and of a burst of arm states only the newest is sent). Each page says it is
alive every second and the server beats every second: either side notices a silent
other within a few seconds (a page then reconnects by itself; the console says so).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from importlib import resources
from typing import Any

from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.sync.server import Server, ServerConnection, serve

from dammrl_core.errors import ConfigurationError

TEMPLATE = resources.files("dammrl.people.display").joinpath("page.html").read_bytes()
VERSION = hashlib.sha256(TEMPLATE).hexdigest()[:12]
"""A page of another version reloads itself when it reconnects (an upgraded dammrl)."""
PAGE = TEMPLATE.replace(b"%VERSION%", VERSION.encode())
ALIVE_S = 6.0
"""A page that said nothing for this long (it pings every second) is no longer counted as
connected [s]; a page that closes says so at once."""
BEAT_S = 1.0
MAX_INCOMING = 4096  # a page sends pings and ratings, nothing larger
SEND_TIMEOUT_S = 2
"""A page that takes nothing for this long (a frozen tab, a cut network) is dropped:
it never holds up the other pages [s]."""

OnMessage = Callable[[dict[str, Any]], None]


class PageServer:
    """Serves the page on ``host:port`` from threads of its own until ``close``."""

    def __init__(self, host: str, port: int, on_message: OnMessage) -> None:
        self.on_message = on_message
        self.latest: dict[str, str] = {}  # channel -> its latest message (JSON)
        self.dirty: list[str] = []  # channels changed since the sender last sent
        self.pages: dict[ServerConnection, float] = {}  # page -> when it last spoke
        self.changed = threading.Condition()
        self.sending = threading.Lock()  # a connection takes one send at a time
        self.closing = False
        logging.getLogger("websockets").setLevel(logging.CRITICAL)  # a dropped page is normal
        try:
            self.server: Server = serve(self._page, host, port, process_request=self._http,
                                        max_size=MAX_INCOMING, compression=None,
                                        ping_interval=None)  # fmt: skip
        except (OSError, OverflowError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            raise ConfigurationError(
                f"the participant display cannot listen on {host}:{port} "
                f"({why}): give another --display-port"
            ) from exc
        self.port: int = self.server.socket.getsockname()[1]
        for target in (self.server.serve_forever, self._send_loop):
            threading.Thread(target=target, daemon=True).start()

    def publish(self, channel: str, message: dict[str, Any]) -> None:
        """The latest ``message`` of ``channel``, to every page (now) and to every page
        that connects later."""
        text = json.dumps(message, separators=(",", ":"))
        with self.changed:
            self.latest[channel] = text
            if channel not in self.dirty:
                self.dirty.append(channel)
            self.changed.notify()

    def connected(self) -> int:
        """Pages that spoke within the last ALIVE_S."""
        now = time.monotonic()
        with self.changed:
            return sum(now - seen < ALIVE_S for seen in self.pages.values())

    def close(self) -> None:
        with self.changed:
            self.closing = True
            self.changed.notify()
        self.server.shutdown()

    # ---- HTTP and the pages ------------------------------------------------------------
    def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        if request.path == "/ws":
            return None  # the page's WebSocket
        if request.path.split("?")[0] in ("/", "/index.html"):
            headers = Headers({"Content-Type": "text/html; charset=utf-8",
                               "Content-Length": str(len(PAGE)),
                               "Cache-Control": "no-store"})  # fmt: skip
            return Response(200, "OK", headers, PAGE)
        return connection.respond(404, "not found\n")

    def _page(self, page: ServerConnection) -> None:
        """One open page: everything it missed, then its pings and answers."""
        with contextlib.suppress(OSError):
            page.socket.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO,
                                   struct.pack("ll", SEND_TIMEOUT_S, 0))  # fmt: skip
        with self.changed:
            self.pages[page] = time.monotonic()
            snapshot = list(self.latest.values())
        for text in snapshot:
            self._send(page, text)
        with contextlib.suppress(ConnectionClosed):
            for raw in page:
                with self.changed:
                    self.pages[page] = time.monotonic()
                message = _parsed(raw)
                if message is not None and message.get("t") != "ping":
                    self.on_message(message)
        with self.changed:
            self.pages.pop(page, None)

    def _send_loop(self) -> None:
        """Send what changed to every page as it changes, and a beat every BEAT_S."""
        while True:
            with self.changed:
                if not self.dirty and not self.closing:
                    self.changed.wait(BEAT_S)
                if self.closing:
                    return
                texts = [self.latest[c] for c in self.dirty] or ['{"t":"beat"}']
                self.dirty.clear()
                pages = list(self.pages)
            for page in pages:
                for text in texts:
                    self._send(page, text)

    def _send(self, page: ServerConnection, text: str) -> None:
        with self.sending, contextlib.suppress(ConnectionClosed, OSError):
            page.send(text)


def _parsed(raw: str | bytes) -> dict[str, Any] | None:
    """A page's message (a JSON object), or None for anything else."""
    try:
        message = json.loads(raw)
    except (ValueError, RecursionError):  # not JSON, or nested past the parser's depth
        return None
    return message if isinstance(message, dict) else None
