"""Prometheus metrics of one app instance (own registry, so several apps can live in one process)."""

from __future__ import annotations

from typing import Literal, get_args

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector

RejectReason = Literal["queue_full", "overloaded", "deadline", "disconnect", "too_large", "bad_input", "not_ready"]

_LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)


class Metrics:
    """All metrics the service exports under the `crestereo_` prefix."""

    def __init__(self, max_batch_size: int) -> None:
        self.registry = CollectorRegistry()
        ProcessCollector(registry=self.registry)
        ns = "crestereo"
        self.requests = Counter(
            "requests",
            "POST /disparity answers by model and HTTP status.",
            ["model", "status"],
            namespace=ns,
            registry=self.registry,
        )
        self.latency = Histogram(
            "request_latency_seconds",
            "POST /disparity end-to-end time in the server.",
            ["model"],
            namespace=ns,
            registry=self.registry,
            buckets=_LATENCY_BUCKETS,
        )
        self.queue_wait = Histogram(
            "queue_wait_seconds",
            "Time from admission to the start of the request's batch.",
            ["model"],
            namespace=ns,
            registry=self.registry,
            buckets=_LATENCY_BUCKETS,
        )
        self.compute = Histogram(
            "compute_seconds",
            "Network time per batch.",
            ["model"],
            namespace=ns,
            registry=self.registry,
            buckets=_LATENCY_BUCKETS,
        )
        self.batch_size = Histogram(
            "batch_size",
            "Requests per computed batch.",
            ["model"],
            namespace=ns,
            registry=self.registry,
            buckets=tuple(range(1, max_batch_size + 1)),
        )
        self.queue_depth = Gauge(
            "queue_depth", "Requests admitted and not yet computing.", ["model"], namespace=ns, registry=self.registry
        )
        self.rejected = Counter(
            "rejected", "POST /disparity requests refused, by reason.", ["reason"], namespace=ns, registry=self.registry
        )
        for reason in get_args(RejectReason):
            self.rejected.labels(reason=reason)  # export every reason from the start, at 0
        self.delayed_errors = Counter(
            "client_errors_delayed",
            "4xx answers held back from clients past their error budget (CRESTEREO_CLIENT_ERROR_RATE).",
            namespace=ns,
            registry=self.registry,
        )

    def reject(self, reason: RejectReason) -> None:
        self.rejected.labels(reason=reason).inc()
