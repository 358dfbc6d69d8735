"""`gmt serve`: REST and gRPC in one process. Flags override `GMT_*` environment variables."""

from __future__ import annotations

from pathlib import Path

import typer


def serve_command(
    checkpoints: list[Path] = typer.Option(
        None,
        "--checkpoints",
        "-c",
        help="Checkpoint directory, or a folder of them (repeatable). Default: checkpoints/ [GMT_CHECKPOINTS]",
    ),
    host: str = typer.Option(None, help="Interface to bind. Default 127.0.0.1 [GMT_HOST]"),
    rest_port: int = typer.Option(None, help="REST port, 0 = any free port. Default 8000 [GMT_REST_PORT]"),
    grpc_port: int = typer.Option(None, help="gRPC port, 0 = any free port. Default 50051 [GMT_GRPC_PORT]"),
    max_sessions: int = typer.Option(None, help="Live sessions allowed. Default 1024 [GMT_MAX_SESSIONS]"),
    idle_timeout: float = typer.Option(
        None, help="Seconds before an unused session expires. Default 600 [GMT_IDLE_TIMEOUT_S]"
    ),
    batch_wait_ms: float = typer.Option(
        None, help="Longest wait for a batch to fill, in ms. Default 2 [GMT_BATCH_WAIT_MS]"
    ),
    max_batch: int = typer.Option(
        None, help="Most observations per forward pass. Default 64 [GMT_MAX_BATCH]"
    ),
    inference_threads: int = typer.Option(
        None, help="Forward-pass threads. Default 1 [GMT_INFERENCE_THREADS]"
    ),
    max_request_bytes: int = typer.Option(
        None, help="Largest REST body / gRPC message. Default 1 MiB [GMT_MAX_REQUEST_BYTES]"
    ),
    auth_token: str = typer.Option(
        None, help="Require 'Authorization: Bearer TOKEN' (health stays open). [GMT_AUTH_TOKEN]"
    ),
    redis_url: str = typer.Option(
        None,
        help="Keep sessions in Redis (shared by replicas), e.g. redis://localhost:6379/0 [GMT_REDIS_URL]",
    ),
    log_format: str = typer.Option(None, help="json or kv. Default json [GMT_LOG_FORMAT]"),
    log_level: str = typer.Option(None, help="Default INFO [GMT_LOG_LEVEL]"),
    replica_id: str = typer.Option(
        None,
        help="This replica's name, sent as X-Served-By (REST) / x-served-by (gRPC metadata) on every answer. "
        "Default hostname:pid [GMT_REPLICA_ID]",
    ),
    naive: bool = typer.Option(
        None,
        "--naive/--no-naive",
        help="Reference path: full recompute, one request at a time, no batching (exactness oracle and "
        "benchmark baseline). [GMT_NAIVE]",
    ),
) -> None:
    """Serve every checkpoint under checkpoints/ over REST (OpenAPI at /docs) and gRPC."""
    import asyncio

    from pydantic import ValidationError

    from service import logs
    from service.server import serve
    from service.settings import Settings

    given = {
        "checkpoints": checkpoints or None,
        "host": host,
        "rest_port": rest_port,
        "grpc_port": grpc_port,
        "max_sessions": max_sessions,
        "idle_timeout_s": idle_timeout,
        "batch_wait_ms": batch_wait_ms,
        "max_batch": max_batch,
        "inference_threads": inference_threads,
        "max_request_bytes": max_request_bytes,
        "auth_token": auth_token,
        "redis_url": redis_url,
        "log_format": log_format,
        "log_level": log_level,
        "naive": naive,
        "replica_id": replica_id,
    }
    try:
        settings = Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as e:
        raise typer.BadParameter(str(e)) from None
    logs.configure(settings.log_format, settings.log_level)
    if settings.event_loop == "uvloop":
        import uvloop

        uvloop.run(serve(settings))
    else:
        asyncio.run(serve(settings))
