"""Connection caps derived from the process's file-descriptor limit (docs/reliability.md, "Slowloris")."""

from __future__ import annotations

import resource
from dataclasses import dataclass

from gmt.service.settings import Settings

FD_RESERVE = 128  # the process's own descriptors (~25), the Redis pool (64), files, and a margin
UNLIMITED_FDS = 1 << 20  # what an RLIM_INFINITY soft limit counts as


def descriptor_limit() -> int:
    """The soft RLIMIT_NOFILE of this process."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return UNLIMITED_FDS if soft == resource.RLIM_INFINITY else soft


@dataclass(frozen=True)
class ConnectionCaps:
    """Open connections allowed per transport.

    Attributes:
        rest: REST connections (past it the oldest one without a request in progress is closed).
        grpc: gRPC connections (past it gRPC closes the new one).
        descriptors: The descriptor limit they were derived from.
        rest_per_peer: REST connections one client address may hold while the server is full.
    """

    rest: int
    grpc: int
    descriptors: int
    rest_per_peer: int = 0


def connection_caps(settings: Settings, descriptors: int | None = None) -> ConnectionCaps:
    """The caps of `settings`; each one left at 0 gets half of the descriptors above `FD_RESERVE` (at least 16),
    so that neither transport can take the descriptors the other, Redis and the process itself need."""
    fds = descriptor_limit() if descriptors is None else descriptors
    auto = max(16, (fds - FD_RESERVE) // 2)
    rest = settings.rest_max_connections or auto
    return ConnectionCaps(
        rest=rest,
        grpc=settings.grpc_max_connections or auto,
        descriptors=fds,
        rest_per_peer=settings.rest_max_connections_per_peer or max(1, rest // 2),
    )
