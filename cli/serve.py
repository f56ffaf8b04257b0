"""`lightfield serve`: run the HTTP API; with no LIGHTFIELD_BROKER_URL also its own Redis and worker."""
from __future__ import annotations

HELP = "run the REST API (embedded Redis + worker unless LIGHTFIELD_BROKER_URL is set)"


def add_arguments(p) -> None:
    p.add_argument("--host", default="127.0.0.1", help="bind address (non-loopback needs LIGHTFIELD_API_KEYS)")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def run(args) -> int:
    import logging
    import sys

    from jobs.settings import SettingsError
    from service.auth import AuthConfigError
    from service.config import ServiceSettings
    from service.embedded import serve
    from service.processes import LaunchError

    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        settings = ServiceSettings.from_env()
        return serve(args.host, args.port, settings, log_level=args.log_level)
    except (AuthConfigError, SettingsError, LaunchError) as exc:
        print(f"lightfield serve: {exc}", file=sys.stderr)
        return 2
