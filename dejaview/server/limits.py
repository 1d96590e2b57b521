"""Limits on what a client may send: request body size, and messages per second.

The WebSocket message size is checked where messages are read
(``dejaview.server.websocket``); the WebSocket layer itself (uvicorn) cuts
off anything over ``ServerConfig.ws_max_size``.
"""

from __future__ import annotations

import json
import time


class BodyLimit:
    """ASGI middleware: HTTP request bodies over ``max_bytes`` get 413 before the app sees them.

    The body is read here (at most ``max_bytes`` of it are kept) and replayed to
    the app, so a chunked body without a Content-Length is limited too. A body
    up to 4x the limit is read to its end before the 413 goes out (a client
    still sending would otherwise see a connection reset); beyond that the
    connection is closed right after the 413.
    """

    def __init__(self, app, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes
        self.drain_bytes = 4 * max_bytes  # bodies up to this size are read to the end before a 413

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or ()).get(b"content-length")
        try:
            declared = int(declared) if declared is not None else None
        except ValueError:
            declared = None
        if declared is not None and declared > self.max_bytes:
            if declared <= self.drain_bytes:
                await self._drain(receive)
            return await self._refuse(send, declared)
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            size += len(message.get("body", b""))
            if size > self.max_bytes:
                if message.get("more_body", False):
                    await self._drain(receive, size)
                return await self._refuse(send, None)
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        replayed = False

        async def replay():
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _drain(self, receive, size: int = 0) -> None:
        """Read and drop the rest of a refused body (up to ``drain_bytes``), so the client, still
        sending, reads the 413 instead of a connection reset."""
        while size <= self.drain_bytes:
            message = await receive()
            if message["type"] != "http.request" or not message.get("more_body", False):
                return
            size += len(message.get("body", b""))

    async def _refuse(self, send, size):
        what = f"{size} bytes" if size is not None else "larger"
        body = json.dumps({"code": "message_too_large",
                           "message": f"request body is {what}, over the limit of {self.max_bytes} "
                                      f"bytes"}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode()),
                                (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})


class TokenBucket:
    """``rate`` messages per second on average, bursts of up to ``burst``."""

    def __init__(self, rate: float, burst: float | None = None, clock=time.monotonic):
        self.rate = rate
        self.burst = burst if burst is not None else 2 * rate
        self.tokens = self.burst
        self.clock = clock
        self.stamp = clock()

    def take(self) -> bool:
        """Spend one token; False when none is left (the message should be dropped)."""
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1:
            self.tokens -= 1
            return True
        return False
