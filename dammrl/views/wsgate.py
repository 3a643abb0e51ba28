"""One viewer port for both names of Foxglove's WebSocket protocol.

Foxglove's SDK server (what ``dammrl view`` runs) accepts only the subprotocol
``foxglove.sdk.v1``; clients built on ``@foxglove/ws-protocol`` — Lichtblick (the
open-source Foxglove Studio), older Foxglove releases, robotics web tools — offer
``foxglove.websocket.v1``. The two are the same protocol under two names (Foxglove's own
statement, foxglove/discussions 1131; Lichtblick PR 819 added the new name on that ground).
The gate listens on the public port, renames the offer in the HTTP upgrade request, renames
the answer back, and then relays bytes untouched in both directions: no frame is parsed,
so no message can be altered, and a client offering the current name passes unchanged.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading

CURRENT = b"foxglove.sdk.v1"
LEGACY = b"foxglove.websocket.v1"
HEADER = b"sec-websocket-protocol:"
MAX_HEAD_BYTES = 16 * 1024  # an upgrade request is far smaller; more is not a client
HANDSHAKE_S = 10.0
CHUNK = 64 * 1024


def rename_offer(head: bytes) -> tuple[bytes, bool]:
    """The upgrade request with a legacy-only offer renamed to the current protocol, and
    whether it was renamed."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        if line.lower().startswith(HEADER):
            offered = [p.strip() for p in line[len(HEADER) :].split(b",")]
            if LEGACY in offered and CURRENT not in offered:
                lines[i] = b"Sec-WebSocket-Protocol: " + CURRENT
                return b"\r\n".join(lines), True
    return head, False


def rename_answer(head: bytes) -> bytes:
    """The server's upgrade answer, its chosen protocol named as the legacy client asked."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        if line.lower().startswith(HEADER) and CURRENT in line:
            lines[i] = b"Sec-WebSocket-Protocol: " + LEGACY
    return b"\r\n".join(lines)


class SubprotocolGate:
    """A TCP listener on ``host:port`` in front of a WebSocket server on loopback
    ``upstream_port``; runs in a thread of its own until ``stop``."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self.renamed = 0  # connections whose legacy offer was renamed
        self._loop = asyncio.new_event_loop()
        self._server = self._loop.run_until_complete(
            asyncio.start_server(self._serve, host, port, limit=MAX_HEAD_BYTES)
        )
        self.port: int = self._server.sockets[0].getsockname()[1]
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True,
                                        name="viewer-gate")  # fmt: skip
        self._thread.start()

    async def _serve(
        self, client_in: asyncio.StreamReader, client_out: asyncio.StreamWriter
    ) -> None:
        try:
            head = await asyncio.wait_for(client_in.readuntil(b"\r\n\r\n"), HANDSHAKE_S)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, OSError):
            client_out.close()  # not an HTTP request within bounds: not a viewer
            return
        head, renamed = rename_offer(head)
        self.renamed += renamed
        try:
            server_in, server_out = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        except OSError:
            client_out.close()
            return
        server_out.write(head)
        try:
            answer = await asyncio.wait_for(server_in.readuntil(b"\r\n\r\n"), HANDSHAKE_S)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, OSError):
            client_out.close()
            server_out.close()
            return
        client_out.write(rename_answer(answer) if renamed else answer)
        await asyncio.gather(_relay(client_in, server_out), _relay(server_in, client_out))

    def stop(self) -> None:
        """Close the listener and every relayed connection."""

        async def close() -> None:
            self._server.close()
            for task in asyncio.all_tasks():
                if task is not asyncio.current_task():
                    task.cancel()

        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)


async def _relay(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    """Bytes from ``source`` to ``sink`` until either side closes."""
    try:
        while chunk := await source.read(CHUNK):
            sink.write(chunk)
            await sink.drain()
    except (OSError, asyncio.CancelledError):
        pass
    finally:
        sink.close()
