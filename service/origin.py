"""Host allow-list and Origin check: what keeps a browser from using a keyless server.

Without API keys the server trusts every request, which is safe only because `serve` then
binds to loopback. A web page can still make the user's browser talk to loopback:

* DNS rebinding: a page on attacker.example makes its own name resolve to 127.0.0.1 and
  then reads the API as same-origin. Its requests carry `Host: attacker.example`, so a
  keyless server answers only Host names that are loopback (any port) or listed in
  LIGHTFIELD_ALLOWED_HOSTS: 400 `host_not_allowed` otherwise.
* Cross-site requests: any page can POST a form to http://127.0.0.1:8000/jobs (no CORS
  preflight for a form). State-changing methods (POST, PUT, PATCH, DELETE) whose `Origin`
  is neither the server's own (scheme://Host of the request) nor listed in
  LIGHTFIELD_ALLOWED_ORIGINS are refused with 403 `origin_not_allowed`; so are those a
  browser marks `Sec-Fetch-Site: cross-site`. Requests without these headers (curl,
  scripts, the Python client) are not from a browser page and pass.

With API keys a page has no credential to abuse, so neither check applies, except the Host
allow-list when LIGHTFIELD_ALLOWED_HOSTS is set explicitly.
"""
from __future__ import annotations

from starlette.types import ASGIApp, Receive, Scope, Send

from service.auth import is_loopback
from service.errors import error_response

STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def host_name(host: str) -> str:
    """'Example.com:8000' -> 'example.com'; '[::1]:8000' -> '::1'."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:].split("]", 1)[0]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


class OriginGuard:
    def __init__(self, app: ASGIApp, keyless: bool, allowed_hosts: tuple[str, ...] = (),
                 allowed_origins: tuple[str, ...] = ()):
        self.app = app
        self.check_host = keyless or bool(allowed_hosts)
        self.check_origin = keyless
        self.allowed_hosts = frozenset(host_name(h) for h in allowed_hosts)
        self.allowed_origins = frozenset(o.rstrip("/").lower() for o in allowed_origins)

    def host_allowed(self, host: str) -> bool:
        name = host_name(host)
        return name in self.allowed_hosts or (not self.allowed_hosts or self.check_origin) and is_loopback(name)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket" and (self.check_host or self.check_origin):
            await self._websocket(scope, receive, send)
            return
        if scope["type"] != "http" or not (self.check_host or self.check_origin):
            await self.app(scope, receive, send)
            return
        headers = {k.lower(): v.decode("latin-1") for k, v in scope.get("headers") or ()}
        host = headers.get(b"host")
        refusal = None
        if self.check_host and host is not None and not self.host_allowed(host):
            refusal = error_response(
                400,
                "host_not_allowed",
                f"Host {host[:100]!r} is not served here (set LIGHTFIELD_ALLOWED_HOSTS to add names)",
            )
        elif self.check_origin and scope["method"] in STATE_CHANGING:
            origin = headers.get(b"origin")
            own = f"{scope.get('scheme', 'http')}://{host}".lower() if host else None
            if origin is not None and origin.rstrip("/").lower() not in self.allowed_origins | {own}:
                refusal = error_response(403, "origin_not_allowed",
                                         f"cross-origin {scope['method']} from {origin[:100]!r} refused "
                                         "(set LIGHTFIELD_ALLOWED_ORIGINS or LIGHTFIELD_API_KEYS)")
            elif origin is None and headers.get(b"sec-fetch-site") == "cross-site":
                refusal = error_response(403, "origin_not_allowed", f"cross-site {scope['method']} refused")
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        await self.app(scope, receive, send)

    async def _websocket(self, scope: Scope, receive: Receive, send: Send) -> None:
        """A WebSocket handshake sends frames like a POST (any page may open one, no preflight):
        the same Host and Origin rules, refused by closing with 1008 (policy violation)."""
        headers = {k.lower(): v.decode("latin-1") for k, v in scope.get("headers") or ()}
        host, origin = headers.get(b"host"), headers.get(b"origin")
        scheme = "https" if scope.get("scheme") == "wss" else "http"
        own = f"{scheme}://{host}".lower() if host else None
        refused = (self.check_host and host is not None and not self.host_allowed(host)) or (
            self.check_origin and origin is not None and origin.rstrip("/").lower() not in self.allowed_origins | {own})
        if refused:
            message = await receive()
            if message["type"] == "websocket.connect":
                await send({"type": "websocket.close", "code": 1008, "reason": "origin_not_allowed"})
            return
        await self.app(scope, receive, send)
