"""The `gmt` console command: one entry point for data, training, evaluation, serving and clients.

Sub-command groups live beside the code they drive and are registered here. Heavy imports (torch, gymnasium)
happen inside commands so that `gmt --help` stays fast.
"""

from __future__ import annotations

from pathlib import Path

import typer

from model.data.cli import app as data_app

app = typer.Typer(
    name="gmt",
    help="Train Goal-Masked Transformers on offline trajectories and serve them as controllable policies.",
    no_args_is_help=True,
    add_completion=False,
)
app.add_typer(data_app, name="data")


@app.callback()
def _root() -> None:
    """Train Goal-Masked Transformers on offline trajectories and serve them as controllable policies."""


@app.command()
def version() -> None:
    """Print the versions of gmt and its main dependencies."""
    from importlib.metadata import version as v

    for pkg in ("gmt-service", "torch", "gymnasium", "mujoco", "fastapi", "grpcio"):
        typer.echo(f"{pkg} {v(pkg)}")


def _register() -> None:
    """Attach the command groups that live beside their code."""
    from model.cli import eval_command, train_command
    from model.data.cli import app as data_app

    app.add_typer(data_app, name="data")
    app.command("train")(train_command)
    app.command("eval")(eval_command)

    from service.serve_cli import serve_command

    app.command("serve")(serve_command)

    from service.cluster import app as cluster_app

    app.add_typer(cluster_app, name="cluster")

    from clients.cli import run_command

    app.command("run")(run_command)
    app.command("bench")(bench_command)


def bench_command(
    checkpoint: Path = typer.Option(
        None, help="Checkpoint to serve (default: a random-weight window model of the default size)."
    ),
    sections: str = typer.Option(
        "engine,serving,training,alternatives",
        help="Comma-separated: engine, serving, training, alternatives.",
    ),
    seconds: float = typer.Option(8.0, help="Load duration per serving measurement point."),
    sessions: str = typer.Option("1,16,64,256", help="Concurrent sessions per serving measurement point."),
    out: Path = typer.Option(None, help="Also write the JSON here."),
    markdown: Path = typer.Option(None, help="Also write the tables (as in docs/performance.md) here."),
) -> None:
    """Engine, serving and training figures as JSON, every one beside the naive baseline of the same run."""
    import json

    from service.bench import run, to_markdown

    result = run(
        checkpoint,
        tuple(x.strip() for x in sections.split(",") if x.strip()),
        seconds,
        tuple(int(x) for x in sessions.split(",")),
    )
    text = json.dumps(result, indent=2)
    typer.echo(text)
    if out:
        out.write_text(text + "\n")
    if markdown:
        markdown.write_text(to_markdown(result) + "\n")


_register()


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
