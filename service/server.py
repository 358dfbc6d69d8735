"""One process, one asyncio loop: the core, uvicorn (REST) and grpc.aio (gRPC), with graceful shutdown."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import gc
import logging
import signal
import socket
import time

import uvicorn

from gmt.service.core import Core
from gmt.service.grpc.server import GrpcServer
from gmt.service.limits import connection_caps
from gmt.service.memory import freeze_startup_heap
from gmt.service.rest.app import create_app
from gmt.service.rest.protocol import ConnectionGuard, GuardedHttpProtocol
from gmt.service.settings import Settings

log = logging.getLogger("gmt.server")


class _Uvicorn(uvicorn.Server):
    """uvicorn that leaves signals to us and says when it listens."""

    def __init__(self, config: uvicorn.Config) -> None:
        super().__init__(config)
        self.listening = asyncio.Event()

    def capture_signals(self):
        return contextlib.nullcontext()

    async def startup(self, sockets=None) -> None:
        await super().startup(sockets=sockets)
        self.listening.set()


class PortUnavailable(OSError):
    """A port `gmt serve` was told to listen on cannot be bound (in use, not allowed, or no such interface).

    Attributes:
        transport: "REST" or "gRPC".
        host: The interface.
        port: The port.
        reason: Why, as the system says it (e.g. "Address already in use").
        port_at_fault: Whether another port would do (in use, or privileged), rather than another host.
    """

    def __init__(self, transport: str, host: str, port: int, reason: str, port_at_fault: bool = True) -> None:
        address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        super().__init__(f"cannot listen for {transport} on {address}: {reason}")
        self.transport, self.host, self.port, self.reason = transport, host, port, reason
        self.port_at_fault = port_at_fault


def _bound(host: str, port: int, transport: str) -> socket.socket:
    """A TCP socket bound to (host, port), not listening yet.

    Raises:
        PortUnavailable: the port cannot be bound.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = None
    try:
        # IPPROTO_TCP given: asyncio sets TCP_NODELAY only then
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
    except OSError as e:
        if sock is not None:
            sock.close()
        at_fault = e.errno in (errno.EADDRINUSE, errno.EACCES)
        raise PortUnavailable(transport, host, port, e.strerror or str(e), at_fault) from None
    return sock


def _bind(host: str, port: int) -> socket.socket:
    sock = _bound(host, port, "REST")
    sock.listen(2048)
    sock.set_inheritable(True)
    return sock


def _check_port(host: str, port: int, transport: str) -> None:
    """Raise `PortUnavailable` now if `port` cannot be bound (gRPC binds it later, after the models load)."""
    if port:
        _bound(host, port, transport).close()


class Server:
    """Both transports over one core.

    Args:
        settings: Server settings.
        core: A core to serve (default: built from settings, with the Redis store they name); the REST lifespan
            starts it, `stop` closes it.
    """

    def __init__(self, settings: Settings, core: Core | None = None) -> None:
        self.settings = settings
        if core is None:
            store = None
            if settings.redis_url:  # built here with every store setting (Core builds one from the URL alone)
                from gmt.service.redis_store import store_for

                store = store_for(settings, time.time)
            core = Core(settings, store=store)
        self.core = core
        self.rest_port = 0
        self.grpc_port = 0
        self._grpc: GrpcServer | None = None
        self._uvicorn: _Uvicorn | None = None
        self._uvicorn_task: asyncio.Task | None = None

    async def start(self, freeze_heap: bool = False) -> None:
        """Listen for REST (its lifespan loads the models), then for gRPC; the bound ports are in `rest_port`
        and `grpc_port`.

        Args:
            freeze_heap: Once the models are loaded, hide every object alive then from the garbage collector and
                collect young objects less often (`memory.freeze_startup_heap`): for a process that only serves,
                as `gmt serve` is.
        """
        s = self.settings
        store = self.core.store
        if store is not None and not self.core.started and hasattr(store, "ping"):
            try:  # Core checks only a store it built: fail now if Redis is unreachable
                await store.ping()
            except BaseException:
                await self.core.close()
                raise
        try:
            sock = _bind(s.host, s.rest_port)
            try:
                _check_port(s.host, s.grpc_port, "gRPC")  # before the models load, not after
            except PortUnavailable:
                sock.close()
                raise
        except PortUnavailable:
            await self.core.close()
            raise
        self.rest_port = sock.getsockname()[1]
        caps = connection_caps(s)
        guard = ConnectionGuard(
            caps.rest,
            s.header_timeout_s,
            s.body_timeout_s,
            s.replica_id,
            self.core.metrics,
            body_min_rate=s.body_min_rate,
            per_peer=caps.rest_per_peer,
        )
        config = uvicorn.Config(
            create_app(s, self.core),
            http=functools.partial(GuardedHttpProtocol, guard=guard),  # read deadlines, connection cap
            ws="none",
            log_config=None,
            access_log=False,
            lifespan="on",
            timeout_graceful_shutdown=max(int(s.shutdown_grace_s), 1),
            timeout_keep_alive=int(s.keep_alive_s),
        )
        self._uvicorn = _Uvicorn(config)
        self._uvicorn_task = asyncio.create_task(self._uvicorn.serve(sockets=[sock]), name="uvicorn")
        listening = asyncio.create_task(self._uvicorn.listening.wait())
        await asyncio.wait({listening, self._uvicorn_task}, return_when=asyncio.FIRST_COMPLETED)
        if not self._uvicorn.listening.is_set():
            listening.cancel()
            sock.close()
            await self.core.close()
            raise RuntimeError("REST server failed to start (see the log above)")
        try:
            try:
                self._grpc = GrpcServer(self.core, s.host, s.grpc_port)
            except (RuntimeError, OSError):  # grpcio's "Failed to bind to address": taken since the check
                raise PortUnavailable("gRPC", s.host, s.grpc_port, "gRPC could not bind it") from None
            self.grpc_port = self._grpc.port
            await self._grpc.start()
        except BaseException:
            self._uvicorn.should_exit = True
            await self._uvicorn_task
            await self.core.close()
            raise
        frozen = freeze_startup_heap() if freeze_heap else None
        log.info(
            "serving",
            extra={
                "rest": f"http://{s.host}:{self.rest_port}",
                "grpc": f"{s.host}:{self.grpc_port}",
                "rest_port": self.rest_port,
                "grpc_port": self.grpc_port,
                "replica_id": s.replica_id,
                "models": sorted(self.core.registry.models),
                "ready": self.core.ready,
                "auth": bool(s.keys),
                "keys": sorted(s.keys),  # their names: a token is never logged
                "admin_auth": "admin token"
                if s.admin_token
                else "auth token"
                if s.token
                else "this machine only",
                "session_store": "redis" if s.redis_url else "memory",
                "model_state": self.core.model_state.where,
                "recording": str(s.record_dir) if s.record_dir is not None else "off (no --record-dir)",
                "record_share": s.record_share,
                "descriptors": caps.descriptors,
                "rest_max_connections": caps.rest,
                "grpc_max_connections": caps.grpc,
                "gc_frozen_objects": frozen,
                "gc_young_threshold": gc.get_threshold()[0],
            },
        )

    async def stop(self) -> None:
        """Stop taking work, let in-flight calls finish (up to the grace period), then close the core."""
        log.info("shutting down", extra={"grace_s": self.settings.shutdown_grace_s})
        self.core.closing = True
        self.core.events.close()  # event streams end now: uvicorn waits for open requests
        if self._uvicorn is not None:
            self._uvicorn.should_exit = True
        waits = [self._uvicorn_task] if self._uvicorn_task is not None else []
        if self._grpc is not None:
            waits.append(self._grpc.stop(self.settings.shutdown_grace_s))
        await asyncio.gather(*waits)
        await self.core.close()
        log.info("stopped")


async def serve(settings: Settings) -> None:
    """Run until SIGINT or SIGTERM, then shut down gracefully."""
    server = Server(settings)
    await server.start(freeze_heap=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        await stop.wait()
    finally:
        await server.stop()
