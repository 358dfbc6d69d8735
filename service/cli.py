"""The `gmt` console command: one entry point for data, training, evaluation, serving and clients.

`gmt` works with whatever is installed. Each command is registered from the module beside the code it drives;
a command whose extra is not installed is registered as a stub that says which extra to install, so the entry
point imports only typer and the light option definitions, never torch. Heavy imports happen inside commands.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from importlib import import_module
from typing import Any

import typer
from typer.core import TyperCommand, TyperGroup

from gmt.common.cli_support import fail
from gmt.common.extras import MissingExtra, missing


@dataclass(frozen=True)
class Entry:
    """One command (or group of commands) of `gmt`, imported only when it is run or its own help is asked for.

    Attributes:
        name: Its name on the command line.
        target: "module:attribute" of the command function, or of a typer group (attribute `app`).
        help: The line `gmt --help` shows (the command's docstring starts with it; a test checks).
        extra: The extra it needs at all (None: the base install), checked before its module is imported;
            without it the command says which extra to install. Sub-commands with needs of their own check
            them when run (`gmt.common.cli_support.needs`).
    """

    name: str
    target: str
    help: str
    extra: str | None = None

    def load(self) -> TyperCommand | TyperGroup:
        """The click command: the real one, or a stub naming the missing extra."""
        gone = missing(self.extra) if self.extra else []
        if gone:
            return _stub(self, MissingExtra(self.extra or "", f"gmt {self.name}", gone))
        module, _, attr = self.target.partition(":")
        obj = getattr(import_module(module), attr)
        if not isinstance(obj, typer.Typer):
            obj = _single(self.name, obj)
        return typer.main.get_command(obj)


def _single(name: str, fn: Callable[..., Any]) -> typer.Typer:
    one = typer.Typer(add_completion=False)
    one.command(name)(fn)
    return one


def _stub(entry: Entry, error: MissingExtra) -> TyperCommand:
    def stub() -> None:
        fail(error)

    return TyperCommand(
        entry.name,
        callback=stub,
        help=f"{entry.help} (Not installed: needs the `{entry.extra}` extra.)",
        context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
    )


COMMANDS = (
    Entry(
        "data",
        "gmt.datagen.cli:app",
        "Offline datasets: behaviour agents, collection, statistics and goal relabelling.",
    ),
    Entry(
        "train",
        "gmt.model.cli:train_command",
        "Train a Goal-Masked Transformer and write a checkpoint directory (safetensors + gmt.json).",
    ),
    Entry(
        "eval",
        "gmt.model.cli:eval_command",
        "Hold every goal, switch every ordered pair mid-episode, cycle goals every 300/200/100 steps.",
    ),
    Entry(
        "replay",
        "gmt.model.cli:replay_command",
        "Replay recorded sessions against a checkpoint: how far its actions are from the recorded ones.",
    ),
    Entry(
        "serve",
        "gmt.service.serve_cli:serve_command",
        "Serve every checkpoint under checkpoints/ over REST (OpenAPI at /docs) and gRPC.",
        "serve",
    ),
    Entry(
        "cluster",
        "gmt.cluster.supervisor:app",
        "The scale-out topology on loopback: Redis with Sentinel, two gmt serve replicas and nginx.",
        "serve",
    ),
    Entry(
        "run",
        "gmt.client.cli:run_command",
        "Drive an agent remotely: send observations, apply actions, report each goal segment.",
    ),
    Entry(
        "models",
        "gmt.client.models:app",
        "Model versions of a running server: list, load, promote, drain, unload.",
    ),
    Entry(
        "bench",
        "gmt.bench.cli:bench_command",
        "Engine, serving and training figures as JSON, every one beside the naive baseline of the same run.",
        "serve",
    ),
)


class _Lazy(TyperCommand):
    """Stands for an entry in `gmt --help`; the real command is imported when it is run."""

    def __init__(self, entry: Entry) -> None:
        super().__init__(entry.name, help=entry.help, short_help=entry.help)
        self.entry = entry

    @cached_property
    def real(self) -> TyperCommand | TyperGroup:
        return self.entry.load()

    def make_context(
        self, info_name: str | None, args: list[str], parent: typer.Context | None = None, **kw: Any
    ):
        return self.real.make_context(info_name, args, parent=parent, **kw)

    def invoke(self, ctx: typer.Context) -> Any:
        return self.real.invoke(ctx)


class LazyGroup(TyperGroup):
    """`gmt`: the commands declared here plus every `COMMANDS` entry, each imported only when used."""

    def list_commands(self, ctx: typer.Context) -> list[str]:
        return [*super().list_commands(ctx), *(e.name for e in COMMANDS)]

    def get_command(self, ctx: typer.Context, cmd_name: str) -> TyperCommand | TyperGroup | None:
        entry = next((e for e in COMMANDS if e.name == cmd_name), None)
        return _Lazy(entry) if entry else super().get_command(ctx, cmd_name)


app = typer.Typer(
    name="gmt",
    cls=LazyGroup,
    help="Train Goal-Masked Transformers on offline trajectories and serve them as controllable policies.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def _root() -> None:
    """Train Goal-Masked Transformers on offline trajectories and serve them as controllable policies."""


@app.command()
def version() -> None:
    """Print the versions of gmt and its main dependencies, and which extras are installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as v

    from gmt.common.extras import extras

    for pkg in ("gmt-service", "torch", "gymnasium", "mujoco", "fastapi", "grpcio"):
        try:
            typer.echo(f"{pkg} {v(pkg)}")
        except PackageNotFoundError:
            typer.echo(f"{pkg} not installed")
    for extra in extras():
        gone = missing(extra)
        typer.echo(f"extra {extra}: " + (f"missing {', '.join(gone)}" if gone else "installed"))


# A path that is missing, of the wrong kind, taken or not readable: what the user typed, not a bug.
PATH_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError, PermissionError)


def main() -> None:
    """Console-script entry point.

    The user's input is not a bug: a checkpoint that cannot be loaded (missing files, bad metadata, a pickle), a
    path that does not exist or is of the wrong kind, an environment id Gymnasium does not know end the command
    with `error: ...` and status 1 instead of a traceback. Anything else is a bug and shows its traceback.
    """
    try:
        app()
    except Exception as e:
        if not _users_error(e):
            raise
        if isinstance(e, OSError) and e.strerror and e.filename:
            typer.echo(f"error: {e.filename}: {e.strerror}", err=True)
        else:
            typer.echo(f"error: {e}", err=True)
        raise SystemExit(1) from None


def _users_error(e: Exception) -> bool:
    # These modules are loaded only by the commands that can raise their errors.
    checkpoint, gym_error = sys.modules.get("gmt.model.checkpoint"), sys.modules.get("gymnasium.error")
    return (
        isinstance(e, PATH_ERRORS)
        or (checkpoint is not None and isinstance(e, checkpoint.CheckpointError))
        or (gym_error is not None and isinstance(e, gym_error.Error))
    )


if __name__ == "__main__":
    main()
