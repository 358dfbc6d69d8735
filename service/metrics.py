"""Prometheus metrics of one server (its own registry, so several servers can live in one process)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)

from gmt.service import keys

LATENCY_BUCKETS = (
    0.0005,
    0.001,
    0.002,
    0.003,
    0.005,
    0.0075,
    0.01,
    0.015,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
)
BATCH_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512)


class Metrics:
    """Request latency, batch sizes, forward time, sessions and errors."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self._children: dict = {}
        r = self.registry
        self.request_latency = Histogram(
            "gmt_request_duration_seconds",
            "Time to answer a request, by transport, method and outcome code.",
            ["transport", "method", "code"],
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.batch_size = Histogram(
            "gmt_batch_size",
            "Observations per forward pass, by model and version.",
            ["model", "version"],
            buckets=BATCH_BUCKETS,
            registry=r,
        )
        self.forward_latency = Histogram(
            "gmt_forward_duration_seconds",
            "Time of one batched forward pass, by model and version.",
            ["model", "version"],
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.in_flight = Gauge(
            "gmt_requests_in_flight",
            "Requests (and Control stream commands) received and not yet answered, by transport; scrapes of "
            "/metrics and event streams (GET /sessions/{id}/events) are not counted.",
            ["transport"],
            registry=r,
        )
        self.in_flight_rest, self.in_flight_grpc = (
            self.in_flight.labels("rest"),
            self.in_flight.labels("grpc"),
        )
        self.live_sessions = Gauge("gmt_live_sessions", "Live sessions in the session store.", registry=r)
        self.models_loaded = Gauge("gmt_models_loaded", "Models (names) this server answers for.", registry=r)
        self.versions_loaded = Gauge(
            "gmt_model_versions_loaded", "Model versions loaded (serving or draining).", registry=r
        )
        self.batch_queued = Gauge(
            "gmt_batch_queued",
            "Act requests waiting in a model version's micro-batcher for their forward pass, by model and version.",
            ["model", "version"],
            registry=r,
        )
        self.sessions_created = Counter(
            "gmt_sessions_created",
            "Sessions created, by model and version.",
            ["model", "version"],
            registry=r,
        )
        self.key_requests = Counter(
            "gmt_key_requests",
            "Requests (and Control stream commands) answered, by the key that made them (--auth-tokens, "
            "--auth-token: default, --admin-token: admin), transport and outcome code; none on a server without "
            "keys.",
            ["key", "transport", "code"],
            registry=r,
        )
        self.key_sessions_created = Counter(
            "gmt_key_sessions_created",
            "Sessions created, by the key that created them (their owner); none on a server without keys.",
            ["key"],
            registry=r,
        )
        self.sessions_expired = Counter(
            "gmt_sessions_expired", "Sessions removed by the idle timeout.", registry=r
        )
        self.rest_connections = Gauge("gmt_rest_connections", "Open REST connections.", registry=r)
        self.connections_closed = Counter(
            "gmt_connections_closed",
            "Connections (REST) and Control streams (gRPC) the server closed to protect itself, by transport and "
            "reason: header_timeout, body_timeout, body_rate (a body under GMT_BODY_MIN_RATE), evicted (a connection "
            "not being answered, closed for a new one past the cap), over_limit (a new connection past the cap, none could be evicted), "
            "write_timeout (a Control stream whose client took no answer).",
            ["transport", "reason"],
            registry=r,
        )

    def closed(self, transport: str, reason: str) -> None:
        """Count one connection or stream closed by the server (`gmt_connections_closed`)."""
        self._child(self.connections_closed, transport, reason).inc()

    def observe_request(self, transport: str, method: str, code: str, seconds: float) -> None:
        """Record one answered request (and its key's count, when an adapter identified its caller)."""
        self._child(self.request_latency, transport, method, code).observe(seconds)
        caller = keys.identified()
        if caller is not None:
            self._child(self.key_requests, caller.name, transport, code).inc()

    def created(self, model: str, version: str, owner: str) -> None:
        """Count one session created (by its owner's key too, when it has one)."""
        self._child(self.sessions_created, model, version).inc()
        if owner:
            self._child(self.key_sessions_created, owner).inc()

    def observe_batch(self, model: str, version: str, size: int, seconds: float) -> None:
        """Record one forward pass."""
        self._child(self.batch_size, model, version).observe(size)
        self._child(self.forward_latency, model, version).observe(seconds)

    def track_queue(self, model: str, version: str, queued: Callable[[], int]) -> None:
        """Report `queued()` as the version's `gmt_batch_queued`, read at each scrape."""
        self.batch_queued.labels(model, version).set_function(queued)

    def untrack_queue(self, model: str, version: str) -> None:
        """Stop reporting an unloaded version's queue (the gauge held its batcher)."""
        with contextlib.suppress(KeyError):
            self.batch_queued.remove(model, version)

    def _child(self, metric, *labels: str):
        """`metric.labels(*labels)`, looked up once (prometheus_client's lookup costs more than the observation)."""
        key = (id(metric), labels)
        child = self._children.get(key)
        if child is None:
            child = self._children[key] = metric.labels(*labels)
        return child

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its content type."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
