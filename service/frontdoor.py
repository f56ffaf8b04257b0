"""The listening socket, served by a thread of its own: `/healthz` answered outside the event loop.

Under a saturating load the event loop runs turns that resume dozens of requests; anything it
answers, even from memory, waits for the current turn (100-400 ms at 100 clients on 2 cores).
A liveness probe must not: so the loop does not accept connections itself. `FrontDoor`'s
thread accepts them and peeks (MSG_PEEK: nothing is consumed) at each one's first bytes:

* a connection whose next request is exactly one plain `GET /healthz HTTP/1.1` is answered by
  the thread, from memory (the route's body, service.routes.health), and stays with it while
  it keeps asking that;
* any other connection is handed, untouched, to the event loop (`loop.connect_accepted_socket`
  with uvicorn's protocol), which then serves it as if it had accepted it (keep-alive, limits,
  the header deadline of service.server).

Connections that send no complete request line within the header timeout are closed here, as
the protocol would. `FrontDoorServer` is uvicorn's Server with this front door in place of
`loop.create_server`.
"""
from __future__ import annotations

import asyncio
import heapq
import logging
import os
import selectors
import socket
import sys
import threading
import time
from typing import Callable

import uvicorn

log = logging.getLogger("lightfield.service")
HEALTH_PREFIX = b"GET /healthz HTTP/1.1\r\n"
PEEK_BYTES = 16 * 1024
RECHECK_S = 0.01  # a request that arrived in pieces is looked at again after this


def classify(data: bytes) -> str:
    """'health' (exactly one complete plain GET /healthz), 'wait' (could still become one), or
    'other' (hand it to the event loop)."""
    if not (data.startswith(HEALTH_PREFIX) or HEALTH_PREFIX.startswith(data)):
        return "other"
    end = data.find(b"\r\n\r\n")
    if end < 0:
        return "wait" if len(data) < PEEK_BYTES else "other"
    if end + 4 != len(data):  # a body or a pipelined request follows: the protocol handles it
        return "other"
    headers = data.lower()
    if b"\r\ncontent-length:" in headers or b"\r\ntransfer-encoding:" in headers or b"\r\nexpect:" in headers:
        return "other"
    return "health"


def health_response(status: int, body: bytes, close: bool) -> bytes:
    reason = b"OK" if status == 200 else b"Service Unavailable"
    extra = (b"" if status == 200 else b"retry-after: 5\r\n") + (b"connection: close\r\n" if close else b"")
    return (b"HTTP/1.1 %d %s\r\ncontent-type: application/json\r\ncontent-length: %d\r\n%s\r\n%s"
            % (status, reason, len(body), extra, body))


class FrontDoor:
    def __init__(self, listener: socket.socket, loop: asyncio.AbstractEventLoop, protocol_factory: Callable,
                 probe: Callable[[], tuple[int, bytes]] | None, header_timeout_s: float, keep_alive_s: float):
        self.listener, self.loop, self.protocol_factory, self.probe = listener, loop, protocol_factory, probe
        self.header_timeout_s, self.keep_alive_s = header_timeout_s, keep_alive_s
        self.listener.setblocking(False)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="front-door", daemon=True)
        self._selector = selectors.DefaultSelector()
        self._deadlines: dict[socket.socket, float] = {}
        self._rechecks: list[tuple[float, int, socket.socket]] = []
        self.answered = 0  # health requests answered here (tests)
        self.handed_off = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._thread.join(timeout=5)
        for conn in list(self._deadlines):
            self._close(conn)
        for s in (self.listener, self._wake_r, self._wake_w):
            s.close()

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        _raise_priority()
        sel = self._selector
        sel.register(self.listener, selectors.EVENT_READ, "accept")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        while not self._stop.is_set():
            try:
                self._turn(sel)
            except Exception:  # never let the front door die
                log.exception("front door: unexpected error")
                time.sleep(0.05)

    def _turn(self, sel: selectors.BaseSelector) -> None:
        now = time.monotonic()
        wait = 1.0
        if self._deadlines:
            wait = min(wait, max(0.0, min(self._deadlines.values()) - now))
        if self._rechecks:
            wait = min(wait, max(0.0, self._rechecks[0][0] - now))
        for key, _ in sel.select(wait):
            if key.data == "accept":
                self._accept()
            elif key.data == "wake":
                try:
                    self._wake_r.recv(64)
                except OSError:
                    pass
            else:
                self._readable(key.fileobj)
        now = time.monotonic()
        while self._rechecks and self._rechecks[0][0] <= now:
            _, _, conn = heapq.heappop(self._rechecks)
            if conn in self._deadlines and conn.fileno() >= 0:
                sel.register(conn, selectors.EVENT_READ, "conn")
        for conn, deadline in list(self._deadlines.items()):
            if deadline <= now:  # no complete request in time (or an idle kept-alive probe connection)
                self._close(conn)

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. EMFILE: try again on the next turn
                log.warning("front door: accept failed: %s", exc)
                return
            conn.setblocking(False)
            self._deadlines[conn] = time.monotonic() + self.header_timeout_s
            self._selector.register(conn, selectors.EVENT_READ, "conn")

    def _readable(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(PEEK_BYTES, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(conn)
            return
        if not data:
            self._close(conn)
            return
        verdict = classify(data) if self.probe is not None else "other"
        if verdict == "health":
            self._answer(conn, data)
        elif verdict == "wait":  # part of a request: look again shortly, not in a busy loop
            self._selector.unregister(conn)
            heapq.heappush(self._rechecks, (time.monotonic() + RECHECK_S, id(conn), conn))
        else:
            self._hand_off(conn)

    def _answer(self, conn: socket.socket, request: bytes) -> None:
        try:
            conn.recv(len(request))  # consume exactly the request peeked
            status, body = self.probe()
            close = b"\r\nconnection: close\r\n" in request.lower()
            conn.sendall(health_response(status, body, close))  # a few hundred bytes: fits the send buffer
        except OSError:
            self._close(conn)
            return
        self.answered += 1
        if close:
            self._close(conn)
        else:
            self._deadlines[conn] = time.monotonic() + self.keep_alive_s

    def _hand_off(self, conn: socket.socket) -> None:
        self._selector.unregister(conn)
        del self._deadlines[conn]
        self.handed_off += 1
        try:
            self.loop.call_soon_threadsafe(self._adopt, conn)
        except RuntimeError:  # the loop is closed: shutting down
            conn.close()

    def _adopt(self, conn: socket.socket) -> None:  # on the event loop
        async def adopt() -> None:
            try:
                await self.loop.connect_accepted_socket(self.protocol_factory, sock=conn)
            except Exception:
                log.warning("front door: handing a connection to the event loop failed", exc_info=True)
                conn.close()

        self.loop.create_task(adopt())

    def _close(self, conn: socket.socket) -> None:
        self._deadlines.pop(conn, None)
        try:
            self._selector.unregister(conn)
        except (KeyError, ValueError):
            pass
        try:
            conn.close()
        except OSError:
            pass


FRONT_DOOR_NICE = -5


def _raise_priority() -> None:
    """Ask the scheduler to prefer this thread (it needs microseconds per probe, and a probe
    must not queue behind the request threads when the cores are contended). Needs the right
    to lower a nice value (root, CAP_SYS_NICE); without it the thread keeps the process's."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), FRONT_DOOR_NICE)
    except (OSError, AttributeError):
        pass


def bind(host: str, port: int, backlog: int) -> socket.socket:
    """A listening TCP socket on host:port (IPv4 or IPv6 from the host's form)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    if host == "localhost":
        host = "127.0.0.1"
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, port))
    sock.listen(backlog)
    return sock


class FrontDoorServer(uvicorn.Server):
    """uvicorn's Server whose connections are accepted by a FrontDoor thread (module docstring)."""

    def __init__(self, config: uvicorn.Config, health_probe: Callable[[], tuple[int, bytes]] | None):
        super().__init__(config)
        self.health_probe = health_probe
        self.front_door: FrontDoor | None = None

    async def startup(self, sockets=None) -> None:
        await self.lifespan.startup()
        if self.lifespan.should_exit:
            sys.exit(3)  # uvicorn's STARTUP_FAILURE
        config = self.config

        def create_protocol(_loop=None) -> asyncio.Protocol:
            return config.http_protocol_class(config=config, server_state=self.server_state,
                                              app_state=self.lifespan.state, _loop=_loop)

        try:
            listener = bind(config.host, config.port, config.backlog)
        except OSError as exc:
            log.error("%s", exc)
            await self.lifespan.shutdown()
            sys.exit(3)
        self.servers = []
        self.front_door = FrontDoor(listener, asyncio.get_running_loop(), create_protocol, self.health_probe,
                                    float(getattr(config, "lightfield_header_timeout_s", 10.0)),
                                    float(config.timeout_keep_alive))
        # the interpreter lock changes hands every 1 ms instead of 5: the front door waits less
        # for it when the request threads keep the interpreter busy
        sys.setswitchinterval(0.001)
        self.front_door.start()
        host, port = listener.getsockname()[:2]
        log.info("lightfield API on http://%s:%d (health answered by the front door thread)", host, port)
        self.started = True

    async def shutdown(self, sockets=None) -> None:
        if self.front_door is not None:
            self.front_door.stop()  # no new connections; health connections closed
        await super().shutdown(sockets)
