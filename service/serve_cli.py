"""`gmt serve`: REST and gRPC in one process. Its options are the fields of `gmt.service.settings.Settings` but the
tuning knobs (`settings.TUNING`, environment only); a flag that is given overrides the `GMT_*` environment variable,
one that is not leaves it (or the default)."""

from __future__ import annotations

from typing import Any

import typer

from gmt.common.cli_support import settings_flags, with_flags
from gmt.service.settings import TUNING, Settings

SERVE_FLAGS = settings_flags(
    Settings,
    skip=TUNING,
    shown={"replica_id": "hostname:pid"},
    names={"checkpoints": ("--checkpoints", "-c"), "idle_timeout_s": ("--idle-timeout", "--idle-timeout-s")},
)


@with_flags(SERVE_FLAGS)
def serve_command(**flags: Any) -> None:
    """Serve every checkpoint under checkpoints/ over REST (OpenAPI at /docs) and gRPC."""
    import asyncio

    from pydantic import ValidationError

    from gmt.service import logs
    from gmt.service.errors import Unavailable
    from gmt.service.server import PortUnavailable, serve

    try:
        settings = Settings(**{k: v for k, v in flags.items() if v is not None and v != [] and v != ()})
    except ValidationError as e:  # each problem by its setting; not the input, which may hold a password
        problems = [
            f"{'.'.join(map(str, err['loc'])) or 'settings'}: {err['msg']}"
            for err in e.errors(include_url=False, include_input=False)
        ]
        raise typer.BadParameter("; ".join(problems)) from None
    from gmt.model.engine import resolve_device

    if settings.device != "cpu":
        try:
            resolve_device(settings.device)
        except ValueError as e:  # e.g. cuda on a machine without a GPU: say so before loading anything
            raise typer.BadParameter(str(e), param_hint="--device") from None
    if settings.precision == "bf16" and not settings.naive:
        from gmt.model import native

        if resolve_device(settings.device) != "cpu":
            raise typer.BadParameter(
                f"bf16 runs in the CPU's native step; --device {settings.device} runs the torch step on a GPU",
                param_hint="--precision",
            )
        if not native.has_bf16():
            raise typer.BadParameter(
                "bf16 needs the native step built with AVX-512 BF16 (this CPU or compiler has none, or GMT_NATIVE=0)",
                param_hint="--precision",
            )
    logs.configure(settings.log_format, settings.log_level)
    try:
        if settings.event_loop == "uvloop":
            import uvloop

            uvloop.run(serve(settings))
        else:
            asyncio.run(serve(settings))
    except Unavailable as e:  # the session store did not answer at startup
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    except PortUnavailable as e:
        typer.echo(f"error: {e}", err=True)
        typer.echo(_port_hint(e.transport) if e.port_at_fault else _HOST_HINT, err=True)
        raise typer.Exit(1) from None


_HOST_HINT = (
    "check the interface to listen on: gmt serve --host ADDRESS or GMT_HOST=ADDRESS (default 127.0.0.1)"
)


def _port_hint(transport: str) -> str:
    """How to choose another port for `transport` ("REST" or "gRPC"): the flag, the variable, the make variable."""
    name = "rest" if transport == "REST" else "grpc"
    return (
        f"choose another {transport} port: gmt serve --{name}-port PORT, GMT_{name.upper()}_PORT=PORT, "
        f"or make serve {name.upper()}_PORT=PORT"
    )
