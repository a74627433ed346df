"""Prometheus metrics of the API (``GET /metrics``)."""

from __future__ import annotations

import logging

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily

log = logging.getLogger("dancegraph.api")

REGISTRY = CollectorRegistry(auto_describe=True)

HTTP_REQUESTS = Counter(
    "dancegraph_http_requests_total",
    "HTTP requests by route and status",
    ["method", "route", "status"],
    registry=REGISTRY,
)
HTTP_LATENCY = Histogram(
    "dancegraph_http_request_seconds",
    "HTTP request latency by route",
    ["method", "route"],
    registry=REGISTRY,
    buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
)
JOBS_CREATED = Counter(
    "dancegraph_jobs_created_total", "jobs accepted by the API", registry=REGISTRY
)
UPLOAD_BYTES = Counter("dancegraph_upload_bytes_total", "audio bytes accepted", registry=REGISTRY)


class JobStatusCollector:
    """Jobs per status, read from the database at scrape time (queue depth without a side channel)."""

    def __init__(self):
        self.database_url: str | None = None

    def collect(self):
        family = GaugeMetricFamily("dancegraph_jobs", "jobs per status", labels=["status"])
        if self.database_url is not None:
            try:
                from sqlalchemy import func, select

                from services.db import session_scope
                from services.models import JOB_STATUSES, Job

                with session_scope(self.database_url) as session:
                    counts = dict(
                        session.execute(select(Job.status, func.count()).group_by(Job.status)).all()
                    )
                for status in JOB_STATUSES:
                    family.add_metric([status], float(counts.get(status, 0)))
            except Exception as exc:  # a scrape must not fail because the database is away
                log.warning("job metrics unavailable: %s", exc)
        yield family


JOB_STATUS = JobStatusCollector()
REGISTRY.register(JOB_STATUS)


def render() -> bytes:
    return generate_latest(REGISTRY)
