"""The `gmt` console command: one entry point for data, training, evaluation, serving and clients.

Sub-command groups live beside the code they drive and are registered here. Heavy imports (torch, gymnasium)
happen inside commands so that `gmt --help` stays fast.
"""

from __future__ import annotations

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

    from clients.cli import run_command

    app.command("run")(run_command)


_register()


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
