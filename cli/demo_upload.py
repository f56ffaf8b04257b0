"""What the demo sends to POST /jobs (or runs in-process with --no-service): one upload, shared
by the demo's simulated job (cli/demo.py) and its room scan (cli/demo_scan.py). Not a command."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Upload:
    """What a user sends to POST /jobs."""

    file: Path  # frame (PNG) or video (MP4)
    depth: Path | None  # .npz with an array `depth`
    params: dict  # JobParams as JSON
    name: str = "lightfield"  # --no-service: the artefact's directory under the output
