"""Prometheus metrics at ``/metrics``: HTTP traffic, jobs by state, job durations, queue depth,
requests refused by quotas and rate limits (``cmc_rate_limited_total{limit}``).

Job numbers are read from the database (and the broker) when scraped, so every API replica
reports the same truth whichever process ran the jobs. Each app has its own registry.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from starlette.types import ASGIApp, Receive, Scope, Send

from service.db.scenes import SceneStore
from service.jobs import JobQueue

log = logging.getLogger("cmc.api")
JOB_BUCKETS = (30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400, 28800)


class _JobCollector:
    def __init__(self, store: SceneStore, queue: JobQueue):
        self.store, self.queue = store, queue

    def collect(self) -> Iterator[Metric]:
        jobs = GaugeMetricFamily("cmc_jobs", "Scenes by job status", labels=["status"])
        for status, n in self.store.count_by_status().items():
            jobs.add_metric([status], n)
        yield jobs
        durations = HistogramMetricFamily(
            "cmc_job_duration_seconds", "Seconds from upload to the end of the job", labels=["status"]
        )
        by_status: dict[str, list[float]] = {}
        for status, d in self.store.finished_durations():
            by_status.setdefault(status, []).append(d)
        for status, ds in sorted(by_status.items()):
            buckets = [(str(b), sum(d <= b for d in ds)) for b in JOB_BUCKETS] + [("+Inf", len(ds))]
            durations.add_metric([status], buckets, sum(ds))
        yield durations
        depth = GaugeMetricFamily("cmc_queue_depth", "Jobs waiting in each queue", labels=["queue"])
        try:
            for q, n in self.queue.depth().items():
                depth.add_metric([q], n)
        except Exception:
            log.warning("queue depth unavailable", exc_info=True)
        yield depth


class Metrics:
    def __init__(self, store: SceneStore, queue: JobQueue):
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "cmc_http_requests_total", "HTTP requests", ["method", "route", "status"], registry=self.registry
        )
        self.latency = Histogram(
            "cmc_http_request_duration_seconds",
            "HTTP request duration",
            ["method", "route"],
            buckets=(0.01, 0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 1, 2, 5, 10),
            registry=self.registry,
        )
        self.rate_limited = Counter(
            "cmc_rate_limited", "Requests refused with 429 by a quota or rate limit", ["limit"], registry=self.registry
        )
        for limit in ("concurrent_jobs", "jobs_per_day", "renders_per_second"):  # zeros from the start
            self.rate_limited.labels(limit)
        self.registry.register(_JobCollector(store, queue))

    def export(self) -> bytes:
        return generate_latest(self.registry)


class MetricsMiddleware:
    """Counts requests and their durations by route template (not by raw path)."""

    def __init__(self, app: ASGIApp, metrics: Metrics):
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0, status = time.perf_counter(), [500]

        async def send_status(message: dict) -> None:
            if message["type"] == "http.response.start":
                status[0] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", "unmatched")
            self.metrics.requests.labels(scope["method"], route, str(status[0])).inc()
            self.metrics.latency.labels(scope["method"], route).observe(time.perf_counter() - t0)
