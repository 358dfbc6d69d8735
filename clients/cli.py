"""`gmt run`: step a local Gymnasium environment with a policy served over REST or gRPC.

Heavy imports (gymnasium, grpc, matplotlib) stay inside the command so `gmt --help` is fast. Needs only the base
install; MuJoCo environments and the plots of `--out` need the `run` extra, Atari games `atari`, MP4s `video`.
"""

from __future__ import annotations

from typing import Any

import typer

from gmt.client.base import DEFAULT_RETRIES, DEFAULT_TIMEOUT_S
from gmt.client.runner import RunConfig
from gmt.common.cli_support import dataclass_flags, field_docs, with_flags
from gmt.common.extras import MissingExtra

# Options from the configuration they fill (`RunConfig`) and the clients' defaults; goal and schedule are parsed.
RUN_FLAGS = dataclass_flags(
    RunConfig,
    skip=("goal", "schedule", "random_schedule", "transport"),
    names={"env_id": ("--env",), "live_port": ("--port",)},
)


@with_flags(RUN_FLAGS)
def run_command(
    server: str = typer.Option("http://localhost:8000", envvar="GMT_SERVER", help="REST base URL."),
    grpc: str = typer.Option(
        None,
        "--grpc",
        help="host:port of the gRPC server (port 50051 when left out); when given, gRPC is used.",
    ),
    stream: bool = typer.Option(
        False, help="With --grpc: act and set_goal over the bidirectional Control stream."
    ),
    goal: str = typer.Option(str(RunConfig.goal), help=field_docs(RunConfig)["goal"]),
    schedule: str = typer.Option(
        "", help='Goal changes GOAL@STEP, comma-separated, e.g. "2@500,1@800" or "high@500".'
    ),
    random_schedule: str = typer.Option(
        "",
        help="LO:HI: a random first goal, then another random goal every LO..HI steps (from the episode's seed), "
        'e.g. "50:300"; instead of --goal and --schedule.',
    ),
    timeout: float = typer.Option(DEFAULT_TIMEOUT_S, help="Seconds per request."),
    retries: int = typer.Option(
        DEFAULT_RETRIES,
        min=0,
        help="Retries after a refused connection, unavailable or aborted (acts carry their step: never applied twice).",
    ),
    token: str = typer.Option(None, envvar="GMT_TOKEN", help="Bearer token, if the server requires one."),
    **flags: Any,
) -> None:
    """Drive an agent remotely: send observations, apply actions, report each goal segment."""
    import gymnasium as gym

    from gmt.client.errors import ConnectionFailed, ServiceError
    from gmt.client.runner import StatusLine, parse_every, parse_goal, parse_schedule, run
    from gmt.common.envs import SpaceMismatch

    if flags["video"] and flags["out"] is None:
        raise typer.BadParameter("--video needs --out DIR for the MP4 files", param_hint="--video")
    if stream and not grpc:
        raise typer.BadParameter(
            "--stream is the gRPC Control stream: give --grpc HOST:PORT too", param_hint="--stream"
        )
    if not timeout > 0:
        raise typer.BadParameter(
            f"must be a positive number of seconds, got {timeout}", param_hint="--timeout"
        )
    try:
        sched = parse_schedule(schedule)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--schedule") from None
    try:
        every = parse_every(random_schedule)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--random-schedule") from None
    transport = f"grpc{' stream' if stream else ''} {grpc}" if grpc else f"rest {server}"
    try:
        cfg = RunConfig(
            **flags, goal=parse_goal(goal), schedule=sched, random_schedule=every, transport=transport
        )
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    if grpc:
        from gmt.client.grpc import GrpcClient

        client = GrpcClient(grpc, timeout_s=timeout, retries=retries, token=token, stream=stream)
    else:
        from gmt.client.rest import RestClient

        client = RestClient(server, timeout_s=timeout, retries=retries, token=token)
    try:
        with client:
            run(client, cfg, echo=typer.echo, status=StatusLine())
    except ConnectionFailed as e:  # one line: the address tried and what to check
        hint = (
            "--grpc HOST:PORT is its gRPC address (gmt serve --grpc-port, default 50051)"
            if grpc
            else "--server URL is its REST address (gmt serve --rest-port, default 8000)"
        )
        typer.echo(f"error: {e}; check that the server is running and that {hint}", err=True)
        raise typer.Exit(1) from None
    except (SpaceMismatch, ServiceError, MissingExtra, KeyError, ValueError, gym.error.Error) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        typer.echo(f"error: {msg}", err=True)
        raise typer.Exit(1) from None
