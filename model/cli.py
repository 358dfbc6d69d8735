"""`gmt train` and `gmt eval`: train a GMT on a Minari dataset, evaluate a checkpoint's goal switching."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

import typer


def train_command(
    dataset: str = typer.Option(..., help="Minari dataset id (e.g. gmt/halfcheetah/mixed-v0) or directory."),
    out: Path = typer.Option(..., help="Checkpoint directory to write (e.g. checkpoints/halfcheetah-gmt)."),
    statistic: str = typer.Option("mean_x_velocity", help="Per-trajectory statistic the goals cluster."),
    k: int = typer.Option(None, help="Number of goals (default: chosen by silhouette score)."),
    labels: Path = typer.Option(
        None, help="Goal labels from `gmt data relabel` instead of relabelling here."
    ),
    steps: int = typer.Option(20000, help="Optimiser steps."),
    batch_size: int = typer.Option(64, help="Windows per batch."),
    lr: float = typer.Option(6e-4, help="Peak learning rate."),
    warmup: int = typer.Option(1000, help="Warmup steps."),
    masking: str = typer.Option("token", help="Goal masking: token, trajectory or none."),
    mask_prob: float = typer.Option(0.5, help="Masking probability p."),
    context_length: int = typer.Option(20, help="K, timesteps in the context."),
    n_layer: int = typer.Option(3, help="Transformer blocks."),
    n_embd: int = typer.Option(128, help="Embedding width."),
    n_head: int = typer.Option(1, help="Attention heads."),
    attention: str = typer.Option(
        "full",
        help="full (the paper's K-step windows) or window (banded attention, exact KV-cached serving).",
    ),
    sequence_length: int = typer.Option(
        0, help="Timesteps per training sequence (0 = K for full attention, 2K for window attention)."
    ),
    seed: int = typer.Option(0, help="Seed of weights, sampling and masks (and of k's sampling)."),
    threads: int = typer.Option(
        2, help="torch threads (match the free cores: oversubscription is 3x slower)."
    ),
    bf16: bool = typer.Option(True, help="bfloat16 autocast for matrix products (2x faster on AMX CPUs)."),
    save_every: int = typer.Option(2000, help="Steps between resumable states."),
    resume: bool = typer.Option(True, help="Continue from OUT/_resume when present."),
) -> None:
    """Train a Goal-Masked Transformer and write a checkpoint directory (safetensors + gmt.json)."""
    from model.checkpoint import Goal
    from model.config import TrainConfig
    from model.data.minari_io import load_dataset
    from model.data.relabel import GoalTable, relabel
    from model.data.statistics import per_trajectory
    from model.train import train

    ds = load_dataset(dataset)
    if labels is not None:
        rel = GoalTable.load(labels)
        if len(rel.labels) != len(ds.episodes):
            raise typer.BadParameter(
                f"{labels} labels {len(rel.labels)} episodes, the dataset has {len(ds.episodes)}"
            )
    else:
        rel = relabel(per_trajectory(statistic, ds), statistic=statistic, k=k, seed=seed)
    goals = [Goal(**g.__dict__) for g in rel.goals]
    typer.echo(
        f"{len(ds.episodes)} episodes, k = {len(goals)} goals: "
        + ", ".join(f"{g.name}={g.mean:.2f}" for g in goals)
    )
    tc = TrainConfig(
        steps=steps,
        batch_size=batch_size,
        lr=lr,
        warmup_steps=warmup,
        masking=masking,
        mask_prob=mask_prob,
        seed=seed,
        threads=threads,
        bf16=bf16,
        save_every=save_every,
        statistic=rel.statistic,
        k=len(goals),
        sequence_length=sequence_length,
    )
    overrides = {
        "context_length": context_length,
        "n_layer": n_layer,
        "n_embd": n_embd,
        "n_head": n_head,
        "attention": attention,
    }
    command = "gmt train " + " ".join(shlex.quote(a) for a in sys.argv[2:])
    ckpt = train(
        ds,
        list(rel.labels),
        goals,
        out,
        tc,
        overrides,
        resume=resume,
        extra_meta={
            "relabel": {k_: v for k_, v in rel.to_dict().items() if k_ != "labels"},
            "command": command,
        },
    )
    info = ckpt.meta["training"]
    typer.echo(
        f"wrote {out} ({info['wall_time_s']} s, {info['steps_per_s']} steps/s, final loss {info['final']['loss']:.4f})"
    )


def eval_command(
    checkpoint: Path = typer.Argument(..., help="Checkpoint directory."),
    seeds: int = typer.Option(15, help="Seeds 0..N-1 per condition."),
    steps: int = typer.Option(1000, help="Episode length."),
    json_out: Path = typer.Option(None, "--json", help="Write the JSON result here."),
    markdown_out: Path = typer.Option(None, "--markdown", help="Write the Markdown table here."),
    plot: Path = typer.Option(None, help="Write the figure (PNG) here."),
    threads: int = typer.Option(2, help="torch threads."),
    action_mode: str = typer.Option(
        None,
        help="mean or sample (continuous), argmax/sample/expert (discrete); default: the model's default.",
    ),
) -> None:
    """Hold every goal, switch every ordered pair mid-episode, cycle goals every 300/200/100 steps."""
    import torch

    from model.checkpoint import load_checkpoint
    from model.engine import PolicyEngine
    from model.evaluate import evaluate

    torch.set_num_threads(threads)
    ckpt = load_checkpoint(checkpoint)
    modes = PolicyEngine(ckpt).action_modes
    if action_mode is not None and action_mode not in modes:
        raise typer.BadParameter(
            f"{action_mode!r} is not one of this model's modes {modes}", param_hint="--action-mode"
        )
    result = evaluate(ckpt, seeds=seeds, steps=steps, action_mode=action_mode)
    table = result.markdown()
    typer.echo(table)
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    if markdown_out:
        markdown_out.write_text(table + "\n")
    if plot:
        from model.eval_plot import plot_eval

        plot_eval(result, plot)
        typer.echo(f"plot: {plot}")
