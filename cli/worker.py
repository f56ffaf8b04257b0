"""`lightfield worker`: a Celery worker for the distributed mode (needs LIGHTFIELD_BROKER_URL)."""
from __future__ import annotations

HELP = "run a job worker against LIGHTFIELD_BROKER_URL (distributed mode)"


def add_arguments(p) -> None:
    p.add_argument("--name", default="worker", help="worker node name (name@hostname)")
    p.add_argument("--log-level", default="INFO")


def run(args) -> int:
    import os
    import sys

    from jobs.settings import JobSettings, SettingsError
    from service.processes import worker_command

    try:
        settings = JobSettings.from_env()
    except SettingsError as exc:
        print(f"lightfield worker: {exc}", file=sys.stderr)
        return 2
    if not settings.broker_url:
        print("lightfield worker: set LIGHTFIELD_BROKER_URL=redis://... (the API's Redis)", file=sys.stderr)
        return 2
    cmd = worker_command(args.name, loglevel=args.log_level)
    os.execv(cmd[0], cmd)  # replace this process: signals go straight to Celery
    return 0  # not reached
