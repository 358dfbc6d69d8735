"""`gmt run`: step a local Gymnasium environment with a policy served over REST or gRPC.

Heavy imports (gymnasium, grpc, matplotlib) stay inside the command so `gmt --help` is fast.
"""

from __future__ import annotations

from pathlib import Path

import typer


def run_command(
    env: str = typer.Option(
        None, help="Gymnasium id to step locally, e.g. HalfCheetah-v5 (default: the model's)."
    ),
    server: str = typer.Option("http://localhost:8000", help="REST base URL."),
    grpc: str = typer.Option(None, "--grpc", help="host:port of the gRPC server; when given, gRPC is used."),
    stream: bool = typer.Option(
        False, help="With --grpc: act and set_goal over the bidirectional Control stream."
    ),
    model: str = typer.Option(None, help="Model name (default: the server's only model for --env)."),
    goal: str = typer.Option("0", help="Goal at step 0: an id (0 = lowest statistic) or a name."),
    schedule: str = typer.Option(
        "", help='Goal changes GOAL@STEP, comma-separated, e.g. "2@500,1@800" or "high@500".'
    ),
    episodes: int = typer.Option(1, min=1, help="Episodes; episode i uses seed + i."),
    seed: int = typer.Option(0, help="Seed of the first episode."),
    steps: int = typer.Option(1000, min=1, help="Steps per episode (the environment's time limit)."),
    out: Path = typer.Option(None, help="Write episode-<i>.json/.csv traces and .png plots here."),
    video: bool = typer.Option(
        False, help="Also record episode-<i>.mp4 into --out (MuJoCo renders offscreen)."
    ),
    timeout: float = typer.Option(10.0, help="Seconds per request."),
    retries: int = typer.Option(
        3,
        min=0,
        help="Retries after a refused connection, unavailable or aborted (acts carry their step: never applied twice).",
    ),
    token: str = typer.Option(None, envvar="GMT_TOKEN", help="Bearer token, if the server requires one."),
) -> None:
    """Drive an agent remotely: send observations, apply actions, report each goal segment."""
    import gymnasium as gym

    from clients.envs import SpaceMismatch
    from clients.errors import ServiceError
    from clients.runner import RunConfig, StatusLine, parse_goal, parse_schedule, run

    if video and out is None:
        raise typer.BadParameter("--video needs --out DIR for the MP4 files", param_hint="--video")
    try:
        sched = parse_schedule(schedule)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--schedule") from None
    if grpc:
        from clients.grpc import GrpcClient

        client = GrpcClient(grpc, timeout_s=timeout, retries=retries, token=token, stream=stream)
        transport = f"grpc{' stream' if stream else ''} {grpc}"
    else:
        from clients.rest import RestClient

        client = RestClient(server, timeout_s=timeout, retries=retries, token=token)
        transport = f"rest {server}"
    cfg = RunConfig(
        env_id=env,
        model=model,
        goal=parse_goal(goal),
        schedule=sched,
        episodes=episodes,
        seed=seed,
        steps=steps,
        out=out,
        video=video,
        transport=transport,
    )
    try:
        with client:
            run(client, cfg, echo=typer.echo, status=StatusLine())
    except (SpaceMismatch, ServiceError, KeyError, ValueError, gym.error.Error) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        typer.echo(f"error: {msg}", err=True)
        raise typer.Exit(1) from None
