"""API keys -> tenants.

`LIGHTFIELD_API_KEYS` is either `tenant:key` pairs separated by commas, or a path to a file
with one pair per line (`#` comments allowed). Each key is one tenant. With no keys the
service is single-user: every request is tenant `local`, and `lightfield serve` refuses to
bind to anything but loopback (see `require_loopback`).
"""
from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
from dataclasses import dataclass
from pathlib import Path

from service.errors import Unauthorized

LOCAL_TENANT = "local"
_TENANT_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class AuthConfigError(ValueError):
    """LIGHTFIELD_API_KEYS is malformed, or the bind address is unsafe without keys."""


@dataclass(frozen=True)
class KeyRing:
    keys: tuple[tuple[str, str], ...]  # (tenant, key)

    @property
    def enabled(self) -> bool:
        return bool(self.keys)

    @classmethod
    def parse(cls, spec: str | None) -> "KeyRing":
        if not spec or not spec.strip():
            return cls(())
        text = spec
        candidate = Path(spec.strip())
        if ":" not in spec or candidate.is_file():
            if not candidate.is_file():
                raise AuthConfigError(f"LIGHTFIELD_API_KEYS: {spec!r} is neither tenant:key pairs nor a file")
            text = candidate.read_text()
        entries = [e.strip() for line in text.splitlines() for e in line.split(",")]
        keys = []
        for entry in entries:
            if not entry or entry.startswith("#"):
                continue
            tenant, sep, key = entry.partition(":")
            tenant, key = tenant.strip(), key.strip()
            if not sep or not _TENANT_RE.match(tenant) or len(key) < 8:
                raise AuthConfigError(
                    "LIGHTFIELD_API_KEYS entries must be tenant:key with tenant in [A-Za-z0-9_.-]{1,64} "
                    "and a key of at least 8 characters"
                )
            keys.append((tenant, key))
        if len({k for _, k in keys}) != len(keys):
            raise AuthConfigError("LIGHTFIELD_API_KEYS: the same key is given to two tenants")
        return cls(tuple(keys))

    def tenant_for(self, authorization: str | None) -> str:
        """Tenant of an `Authorization` header value; raises Unauthorized."""
        if not self.enabled:
            return LOCAL_TENANT
        scheme, _, token = (authorization or "").partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise Unauthorized()
        token = token.strip().encode()
        found = None
        for tenant, key in self.keys:  # compare against every key: timing reveals nothing
            if hmac.compare_digest(token, key.encode()):
                found = tenant
        if found is None:
            raise Unauthorized()
        return found


def tenant_hash(tenant: str) -> str:
    """Directory / index name of a tenant: never the (user-chosen) tenant string itself."""
    return hashlib.sha256(("lightfield-tenant:" + tenant).encode()).hexdigest()[:24]


def is_loopback(host: str) -> bool:
    if host in ("localhost", "localhost.localdomain"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def require_loopback(host: str, ring: KeyRing) -> None:
    if not ring.enabled and not is_loopback(host):
        raise AuthConfigError(
            f"refusing to bind to {host!r} without API keys: set LIGHTFIELD_API_KEYS "
            "(tenant:key,...) or bind to 127.0.0.1"
        )
