"""The HTTP server: uvicorn with a bound on every wait a client can impose.

uvicorn bounds header size (h11_max_incomplete_event_size) and idle keep-alive connections,
but not the time a client takes to send its request line and headers: a slowloris client
that sends one header byte every few seconds holds a connection (and its memory) forever,
and one that starts a second request on a keep-alive connection cancels the keep-alive
timer. `GuardedH11Protocol` closes a connection whose next request has not finished its
headers `header_s` after the connection opened or the previous response ended. Request
bodies are bounded in size and time by service.bodylimits (an ASGI middleware, so the same
rules hold under any server); `max_connections` caps open connections (503 beyond).
"""
from __future__ import annotations

import asyncio
import logging

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.config import HttpTimeouts

log = logging.getLogger("lightfield.service")
HEALTH_PREFIX = b"GET /healthz HTTP/1.1\r\n"


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol plus a deadline on every request's headers."""

    def __init__(self, config, *args, **kwargs):
        super().__init__(config, *args, **kwargs)
        self.header_timeout_s = float(getattr(config, "lightfield_header_timeout_s", HttpTimeouts().header_s))
        self.health_probe = getattr(config, "lightfield_health_probe", None)  # () -> (status, body bytes)
        self._header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_header_timer()

    def data_received(self, data: bytes) -> None:
        if self._answer_health(data):
            return
        cycle = self.cycle
        super().data_received(data)
        # a request's headers are complete: it is the app's now; or the connection became a
        # WebSocket (uvicorn hands the transport to its WebSocket protocol, with no new cycle),
        # whose frames are no request headers: the deadline would cut a live session's stream
        if self.cycle is not cycle or self.transport.get_protocol() is not self:
            self._disarm_header_timer()

    def on_response_complete(self) -> None:
        cycle = self.cycle
        super().on_response_complete()
        if self.cycle is cycle and not self.transport.is_closing():  # waiting for the next request
            self._arm_header_timer()

    def connection_lost(self, exc) -> None:
        self._disarm_header_timer()
        super().connection_lost(exc)

    def _answer_health(self, data: bytes) -> bool:
        """Answer a plain `GET /healthz` on an idle connection right here, without an ASGI task:
        a liveness probe then waits for one turn of the event loop, not for the queue of
        requests the loop is busy with (100 clients asking for maps). The body is the route's
        (service.routes.health.health_answer); anything unusual goes the normal way."""
        probe = self.health_probe
        if probe is None or not data.startswith(HEALTH_PREFIX) or not data.endswith(b"\r\n\r\n"):
            return False
        if data.count(b"\r\n\r\n") != 1 or (self.cycle is not None and not self.cycle.response_complete):
            return False
        if self.conn.their_state is not h11.IDLE or self.conn.our_state is not h11.IDLE:
            return False
        status, body = probe()
        extra = b"" if status == 200 else b"retry-after: 5\r\n"
        self.transport.write(b"HTTP/1.1 %d %s\r\ncontent-type: application/json\r\ncontent-length: %d\r\n%s\r\n%s"
                             % (status, b"OK" if status == 200 else b"Service Unavailable", len(body), extra, body))
        self._arm_header_timer()  # waiting for the next request again
        return True

    def _arm_header_timer(self) -> None:
        self._disarm_header_timer()
        self._header_timer = self.loop.call_later(self.header_timeout_s, self._header_timeout)

    def _disarm_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_timeout(self) -> None:
        self._header_timer = None
        if not self.transport.is_closing():
            log.info("closing a connection from %s: no complete request headers within %g s",
                     self.client, self.header_timeout_s)
            self.transport.close()


def server_config(app, host: str, port: int, timeouts: HttpTimeouts, log_level: str = "info",
                  health_probe=None):
    """A uvicorn.Config for the API with the guarded protocol and the connection limits;
    `health_probe() -> (status, body)` answers plain GET /healthz in the protocol."""
    config = uvicorn.Config(app, host=host, port=port, log_level=log_level, http=GuardedH11Protocol,
                            timeout_keep_alive=timeouts.keep_alive_s,
                            limit_concurrency=timeouts.max_connections, timeout_graceful_shutdown=5,
                            h11_max_incomplete_event_size=16 * 1024)
    config.lightfield_header_timeout_s = timeouts.header_s
    config.lightfield_health_probe = health_probe
    return config
