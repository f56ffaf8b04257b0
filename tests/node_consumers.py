"""The Node consumers of tests/node (three.js, the Khronos glTF validator), installed once per
session by `npm ci` from the project's own package.json + package-lock.json into
tests/node/node_modules (gitignored). Skipped, with the reason, only when npm is absent or the
npm registry cannot be reached; any other install failure fails the tests."""
from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
from pathlib import Path

import pytest

NODE_DIR = Path(__file__).parent / "node"
STAMP = NODE_DIR / "node_modules" / ".lightfield-lock-sha256"
INSTALL_TIMEOUT_S = 300


def _lock_sha() -> str:
    return hashlib.sha256((NODE_DIR / "package-lock.json").read_bytes()).hexdigest()


def _registry_reachable() -> bool:
    try:
        return subprocess.run(["npm", "ping"], cwd=NODE_DIR, capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def ensure_installed() -> Path:
    """npm ci unless node_modules already matches the lock file; returns the package dir."""
    if not shutil.which("node") or not shutil.which("npm"):
        pytest.skip("node/npm are not installed (apt-get install nodejs npm)")
    if STAMP.is_file() and STAMP.read_text().strip() == _lock_sha():
        return NODE_DIR
    cmd = ["npm", "ci", "--no-audit", "--no-fund", "--prefer-offline"]
    try:
        proc = subprocess.run(cmd, cwd=NODE_DIR, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc = None
    if proc is None or proc.returncode != 0:
        if not _registry_reachable():
            pytest.skip(
                "the npm registry is unreachable, so tests/node's consumers (three.js, gltf-validator) cannot be "
                "installed"
            )
        pytest.fail(f"`{' '.join(cmd)}` in {NODE_DIR} failed:\n{(proc.stderr if proc else 'timed out')[-3000:]}")
    STAMP.write_text(_lock_sha())
    return NODE_DIR


def run_consumer(command: str, path: Path, timeout_s: float = 120) -> dict:
    """`node tests/node/consumers.mjs COMMAND PATH` -> its JSON answer (the last line of stdout)."""
    proc = subprocess.run(["node", "consumers.mjs", command, str(Path(path).resolve())], cwd=NODE_DIR,
                          capture_output=True, text=True, timeout=timeout_s)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="session")
def node_consumers():
    """The installed tests/node package; use `run_consumer`."""
    return ensure_installed()
