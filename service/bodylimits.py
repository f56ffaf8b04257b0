"""Request bodies: bounded in size (every body but the multipart upload) and in time (all).

* Size: a JSON (or any non-multipart) body over `max_json_bytes` is refused with 413
  `too_large` from its Content-Length before a byte is read, or as soon as the bytes received
  pass the limit (chunked bodies). Multipart uploads are bounded part by part while they
  stream (service.upload). A million-query batch is refused in milliseconds instead of being
  parsed on the event loop for seconds.
* Time: a body must keep arriving — at most `body_idle_s` between two chunks, and after
  `body_grace_s` at least `body_min_rate` bytes/s on average — or the request is answered
  408 `body_timeout`. A body dripped one byte every two seconds is cut off after the grace
  time instead of holding a connection for hours; a 200 MB upload at 4 KB/s is still fine.

A response that starts before the body was fully received (an early 4xx) carries
`Connection: close`: otherwise the server would keep reading the rest of a refused body on
a keep-alive connection.
"""
from __future__ import annotations

import asyncio

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.config import HttpTimeouts
from service.errors import error_response

MULTIPART = b"multipart/form-data"


class BodyLimits:
    def __init__(self, app: ASGIApp, max_json_bytes: int, timeouts: HttpTimeouts):
        self.app = app
        self.max_json_bytes = max_json_bytes
        self.timeouts = timeouts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or ())
        limit = None if headers.get(b"content-type", b"").lower().startswith(MULTIPART) else self.max_json_bytes
        length = headers.get(b"content-length", b"")
        if limit is not None and length.isdigit() and int(length) > limit:
            response = error_response(413, "too_large", f"request body of {int(length)} bytes exceeds the limit of "
                                      f"{limit} bytes", {"Connection": "close"})
            await response(scope, receive, send)
            return
        guard = _BodyGuard(receive, limit, self.timeouts)
        # HTTP/1.1: no Content-Length and no Transfer-Encoding means no body (most GETs)
        guard.done = length in (b"", b"0") and b"transfer-encoding" not in headers

        async def send_closing(message: Message) -> None:
            if message["type"] == "http.response.start" and not guard.done:
                message = {**message, "headers": [*message.get("headers", []), (b"connection", b"close")]}
            await send(message)

        await self.app(scope, guard.receive, send_closing)


class _BodyGuard:
    """Wraps `receive` while the body is incomplete; afterwards (disconnect polling by
    streaming responses) it passes `receive` through untouched."""

    def __init__(self, receive: Receive, limit: int | None, timeouts: HttpTimeouts):
        self._receive = receive
        self.limit = limit
        self.timeouts = timeouts
        self.received = 0
        self.done = False
        self._start: float | None = None

    async def receive(self) -> Message:
        if self.done:
            return await self._receive()
        loop = asyncio.get_running_loop()
        now = loop.time()
        if self._start is None:
            self._start = now
        t = self.timeouts
        rate_deadline = self._start + t.body_grace_s + self.received / t.body_min_rate
        wait = min(t.body_idle_s, rate_deadline - now)
        if wait <= 0:
            raise self._timeout()
        try:
            message = await asyncio.wait_for(self._receive(), wait)
        except asyncio.TimeoutError:
            raise self._timeout() from None
        if message["type"] == "http.request":
            self.received += len(message.get("body", b""))
            if not message.get("more_body", False):
                self.done = True
            if self.limit is not None and self.received > self.limit:
                raise HTTPException(413, f"request body exceeds the limit of {self.limit} bytes")
        else:  # http.disconnect
            self.done = True
        return message

    def _timeout(self) -> HTTPException:
        t = self.timeouts
        return HTTPException(408, f"request body too slow: {self.received} bytes received; a body must not pause for "
                                  f"more than {t.body_idle_s:g} s and must average {t.body_min_rate:g} bytes/s "
                                  f"after {t.body_grace_s:g} s", headers={"Connection": "close"})
