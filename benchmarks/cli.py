"""`gmt bench`: the command (registered in `gmt.service.cli`; needs the `serve` extra)."""

from __future__ import annotations

from pathlib import Path

import typer


def bench_command(
    checkpoint: Path = typer.Option(
        None, help="Checkpoint to serve (default: a random-weight window model of the default size)."
    ),
    sections: str = typer.Option(
        "engine,serving,training,alternatives",
        help="Comma-separated: engine, serving, store, records, cluster, soak, console, failover, training, "
        "alternatives.",
    ),
    seconds: float = typer.Option(8.0, help="Load duration per serving measurement point."),
    sessions: str = typer.Option("1,16,64,256", help="Concurrent sessions per serving measurement point."),
    out: Path = typer.Option(None, help="Also write the JSON here."),
    markdown: Path = typer.Option(None, help="Also write the tables (as in docs/performance.md) here."),
) -> None:
    """Engine, serving and training figures as JSON, every one beside the naive baseline of the same run.

    The `serve` extra runs it; the `bench` extra adds the alternatives (Ray Serve, Hugging Face's Decision
    Transformer), which are skipped with a note when missing.
    """
    import json

    from gmt.bench.report import to_markdown
    from gmt.bench.run import run

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
