"""Prometheus metrics per app: request counts and latency histograms by route template.

Labels use the route's path template (``/ipfs/{cid}``), never the raw path, and the method
only when it is one of HTTP's own (any other token counts as ``other``: HTTP/1.1 lets a client
send any token as a method), so that label cardinality stays bounded whatever clients send.
"""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest

from services.common.disk import DiskReserve

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

HTTP_METHODS = frozenset(
    {"GET", "HEAD", "POST", "PUT", "DELETE", "CONNECT", "OPTIONS", "TRACE", "PATCH"}
)


class ServiceMetrics:
    """The metrics registry of one service; services add their own collectors to ``registry``."""

    def __init__(self, service: str) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "robocloud_http_requests",
            "HTTP requests served, by route template and status.",
            ["service", "method", "route", "status"],
            registry=self.registry,
        )
        self.latency = Histogram(
            "robocloud_http_request_duration_seconds",
            "Time to serve a request, until the response headers are sent.",
            ["service", "method", "route"],
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10),
        )
        self.service = service

    def watch_disk(self, reserve: DiskReserve) -> None:
        """Free space on the data directory's disk, read at each scrape, beside the reserve
        that uploads may not take: an operator alerts on the first nearing the second, before
        robots get 507s."""
        free = Gauge(
            "robocloud_disk_free_bytes",
            "Free space on the disk of the service's data directory.",
            ["service"],
            registry=self.registry,
        )
        free.labels(self.service).set_function(reserve.free_bytes)
        reserve_gauge = Gauge(
            "robocloud_disk_reserve_bytes",
            "Free space that uploads, records and ingests may not take (0: no reserve).",
            ["service"],
            registry=self.registry,
        )
        reserve_gauge.labels(self.service).set(reserve.reserve_bytes)

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        method = method if method in HTTP_METHODS else "other"
        self.requests.labels(self.service, method, route, str(status)).inc()
        self.latency.labels(self.service, method, route).observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)
