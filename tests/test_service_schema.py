"""schemathesis (an OpenAPI fuzzer) against the real server: requests generated from
/openapi.json, for every operation, must never get a 5xx, and every answer must conform to
the schema (status code documented, content type, headers, body schema).

Runs against the session stack (real uvicorn + Redis + a worker), with a bounded number of
examples per operation (derandomised, so CI sees the same requests every run). Half of the
/lightfield requests name the finished job instead of a random id, so the 200 paths are
fuzzed too. To bound the run's time, exact-quality maps are capped at 64 rows (their cost is
the benchmark's business: bench/service_load.py); fast maps keep every generated size.
"""
from __future__ import annotations

import pytest

from conftest import TENANTS

pytestmark = pytest.mark.slow

EXAMPLES_PER_OPERATION = 15
EXACT_MAX_HEIGHT = 64


EXPORTS = ("/gltf", "/usdz", "/sequence")  # always exact evaluations


def _bounded(case) -> None:
    """Cap the cost of exact evaluations (see module docstring)."""
    query = case.query or {}
    exports = case.operation.path.endswith(EXPORTS) or query.get("format") == "ktx2"
    if isinstance(query.get("frames"), int):
        query["frames"] = min(query["frames"], 4)
    if query.get("quality") == "exact" or exports:
        if isinstance(query.get("height"), int):
            query["height"] = min(query["height"], EXACT_MAX_HEIGHT)
        if isinstance(query.get("size"), int):
            query["size"] = min(query["size"], EXACT_MAX_HEIGHT // 2)
    body = case.body if isinstance(case.body, dict) else None
    if body and body.get("quality", "fast") == "exact" and isinstance(body.get("height"), int):
        body["height"] = min(body["height"], EXACT_MAX_HEIGHT)


def _requests_served(stack) -> float:
    import httpx

    text = httpx.get(stack.base_url + "/metrics", timeout=30).text
    return sum(float(line.split()[-1]) for line in text.splitlines()
               if line.startswith("lightfield_http_requests_total{"))


def test_fuzzed_requests_get_no_5xx_and_conforming_answers(service_stack, finished_job):
    import schemathesis
    from hypothesis import HealthCheck, given, settings, strategies as st
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        response_headers_conformance,
        response_schema_conformance,
        status_code_conformance,
    )

    checks = [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
              response_schema_conformance]
    headers = {"Authorization": f"Bearer {TENANTS['alice']}"}
    schema = schemathesis.openapi.from_url(service_stack.base_url + "/openapi.json", headers=headers, timeout=30)
    failures: dict[str, str] = {}
    operations = 0
    served_before = _requests_served(service_stack)
    for result in schema.get_all_operations():
        operation = result.ok()
        operations += 1
        uses_job = operation.path.startswith("/lightfield/") and operation.method.upper() != "DELETE"

        @given(case=operation.as_strategy(), own_job=st.booleans())
        @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck))
        def run(case, own_job):
            if uses_job and own_job:
                case.path_parameters["job_id"] = finished_job
            _bounded(case)
            case.call_and_validate(base_url=service_stack.base_url, headers=headers, checks=checks, timeout=120)

        try:
            run()
        except Exception as exc:  # collect every operation's first failure, then report them all
            failures[f"{operation.method.upper()} {operation.path}"] = f"{type(exc).__name__}: {exc}"[:3000]
    assert operations >= 12
    assert _requests_served(service_stack) - served_before >= 5 * operations  # it did fuzz
    assert not failures, "\n\n".join(f"{k}:\n{v}" for k, v in failures.items())
    assert "Traceback" not in service_stack.log("api")
