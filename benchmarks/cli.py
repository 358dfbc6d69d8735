"""`gmt bench`: the command (registered in `gmt.service.cli`; needs the `serve` extra)."""

from __future__ import annotations

from pathlib import Path

import typer

SECTIONS = (
    "engine",
    "serving",
    "store",
    "batching",
    "stream",
    "store-ab",
    "store-ab-replicated",
    "records",
    "device",
    "cluster",
    "soak",
    "console",
    "failover",
    "training",
    "alternatives",
)


def bench_command(
    checkpoint: Path = typer.Option(
        None, help="Checkpoint to serve (default: a random-weight window model of the default size)."
    ),
    sections: str = typer.Option(
        "engine,serving,training,alternatives",
        help=f"Comma-separated: {', '.join(SECTIONS)}.",
    ),
    seconds: float = typer.Option(8.0, help="Load duration per serving measurement point."),
    sessions: str = typer.Option("1,16,64,256", help="Concurrent sessions per serving measurement point."),
    out: Path = typer.Option(None, help="Also write the JSON here."),
    markdown: Path = typer.Option(None, help="Also write the tables (as in docs/performance.md) here."),
    device: str = typer.Option(
        "auto", help="Where the device section serves: cpu, cuda, cuda:N or auto (a GPU when torch sees one)."
    ),
    replicas: str = typer.Option("1,2", help="Replica counts of the cluster section's deployments."),
    baseline: str = typer.Option(
        None,
        help="The commit the batching, stream and store-ab sections compare this checkout with (default: each's own).",
    ),
) -> None:
    """Engine, serving and training figures as JSON, every one beside the naive baseline of the same run.

    The `serve` extra runs it; the `bench` extra adds the alternatives (Ray Serve, Hugging Face's Decision
    Transformer), which are skipped with a note when missing.
    """
    import json

    from gmt.bench.report import to_markdown
    from gmt.bench.run import run

    chosen = tuple(x.strip() for x in sections.split(",") if x.strip())
    unknown = [x for x in chosen if x not in SECTIONS]
    if unknown or not chosen:
        raise typer.BadParameter(
            f"{unknown or 'none'}: choose among {', '.join(SECTIONS)}", param_hint="--sections"
        )
    try:
        counts = tuple(int(x) for x in sessions.split(","))
    except ValueError:
        counts = ()
    if not counts or min(counts) < 1:
        raise typer.BadParameter("give positive integers, e.g. 1,16,64", param_hint="--sessions")
    try:
        replica_counts = tuple(int(x) for x in replicas.split(","))
    except ValueError:
        replica_counts = ()
    if not replica_counts or min(replica_counts) < 1 or max(replica_counts) > 64:
        raise typer.BadParameter("give integers in 1..64, e.g. 1,2,4,8", param_hint="--replicas")
    if device != "auto":
        from gmt.model.engine import resolve_device

        try:
            resolve_device(device)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--device") from None
    if not seconds > 0:
        raise typer.BadParameter("must be positive", param_hint="--seconds")
    if checkpoint is not None and not checkpoint.is_dir():
        raise typer.BadParameter(f"{checkpoint} is not a checkpoint directory", param_hint="--checkpoint")
    result = run(checkpoint, chosen, seconds, counts, baseline, device=device, replicas=replica_counts)
    text = json.dumps(result, indent=2)
    typer.echo(text)
    if out:
        out.write_text(text + "\n")
    if markdown:
        markdown.write_text(to_markdown(result) + "\n")
