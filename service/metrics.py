"""Prometheus metrics: request counts/latencies (middleware) and job/queue gauges (read from
Redis at scrape time, so every API replica reports the same shared numbers)."""
from __future__ import annotations

import logging
import time

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from starlette.types import ASGIApp, Receive, Scope, Send

from jobs.queue import QUEUE
from jobs.store import JobStore

log = logging.getLogger("lightfield.service")
# label values come from a fixed set: a client inventing methods must not grow /metrics
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class JobCollector:
    def __init__(self, store: JobStore):
        self.store = store

    def collect(self):
        states = GaugeMetricFamily("lightfield_jobs", "Jobs by state (all tenants)", labels=["state"])
        depth = GaugeMetricFamily("lightfield_queue_depth", "Messages waiting in the job queue")
        try:
            for state, n in self.store.state_counts().items():
                states.add_metric([state], n)
            depth.add_metric([], self.store.client.llen(QUEUE))
        except Exception:  # a scrape must not fail because Redis blinked
            log.warning("metrics: Redis unavailable", exc_info=True)
        yield states
        yield depth


class Metrics:
    def __init__(self, store: JobStore):
        self.registry = CollectorRegistry()
        self.requests = Counter("lightfield_http_requests", "HTTP requests", ["method", "route", "status"],
                                registry=self.registry)
        self.latency = Histogram("lightfield_http_request_seconds", "HTTP request latency", ["method", "route"],
                                 registry=self.registry,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30))
        self.field_calls = Counter("lightfield_field_evaluations", "Field calls answering queued env maps (batches)",
                                   ["quality"], registry=self.registry)
        self.field_maps = Counter("lightfield_field_maps", "Env maps answered by field calls", ["quality"],
                                  registry=self.registry)
        self.export_maps = Counter("lightfield_export_maps", "Env maps evaluated for exports (sequences, large maps, "
                                   "probes) on a field's export copy", ["quality"], registry=self.registry)
        self.exports_cancelled = Counter("lightfield_exports_cancelled", "Exports stopped because their client left",
                                         registry=self.registry)
        self.registry.register(JobCollector(store))

    def observe_batch(self, requests) -> None:
        """One FieldBatcher evaluation: maps per call show how much batching saves."""
        by_quality: dict[str, int] = {}
        for r in requests:
            by_quality[r.quality] = by_quality.get(r.quality, 0) + 1
        for quality, n in by_quality.items():
            self.field_calls.labels(quality).inc()
            self.field_maps.labels(quality).inc(n)


class MetricsMiddleware:
    """Pure ASGI middleware (no BaseHTTPMiddleware: it would buffer SSE streams)."""

    def __init__(self, app: ASGIApp, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = {"code": 500}

        async def send_wrapper(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            # route templates, never raw paths: job ids would explode the label cardinality
            name = getattr(route, "path", "unmatched")
            method = scope["method"] if scope["method"] in KNOWN_METHODS else "other"
            self.metrics.requests.labels(method, name, str(status["code"])).inc()
            self.metrics.latency.labels(method, name).observe(time.perf_counter() - start)
