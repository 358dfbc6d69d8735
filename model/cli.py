"""`gmt train`, `gmt eval` and `gmt replay`: train a GMT on a Minari dataset, evaluate a checkpoint's goal switching,
replay served sessions' recordings against a checkpoint."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path
from typing import Any

import typer

from gmt.common.cli_support import dataclass_flags, needs, pick, with_flags
from gmt.model.config import GMTConfig, TrainConfig

# The options of `gmt train` are the fields of the configurations it fills: defaults and help cannot drift.
TRAIN_FLAGS = dataclass_flags(
    TrainConfig, skip=("extra",), names={"warmup_steps": ("--warmup-steps", "--warmup")}
)
MODEL_FLAGS = dataclass_flags(GMTConfig, skip=("obs_shape", "act_dim", "discrete_actions", "n_goals"))


@needs("train", "gmt train")
@with_flags(TRAIN_FLAGS, MODEL_FLAGS)
def train_command(
    dataset: str = typer.Option(..., help="Minari dataset id (e.g. gmt/halfcheetah/mixed-v0) or directory."),
    out: Path = typer.Option(..., help="Checkpoint directory to write (e.g. checkpoints/halfcheetah-gmt)."),
    labels: Path = typer.Option(
        None, help="Goal labels from `gmt data relabel` instead of relabelling here."
    ),
    resume: bool = typer.Option(True, help="Continue from OUT/_resume when present."),
    **flags: Any,
) -> None:
    """Train a Goal-Masked Transformer and write a checkpoint directory (safetensors + gmt.json)."""
    from gmt.model.checkpoint import Goal
    from gmt.model.data.minari_io import load_dataset
    from gmt.model.data.relabel import GoalTable, relabel
    from gmt.model.data.served import step_labels, switch_count
    from gmt.model.data.statistics import chosen_statistic, per_trajectory
    from gmt.model.train import train

    _check_train_flags(flags, out)
    if labels is not None and not labels.is_file():
        raise typer.BadParameter(f"{labels} is not a file", param_hint="--labels")
    ds = load_dataset(dataset)
    served = step_labels(ds) if labels is None else None
    if (
        served is not None
    ):  # served sessions (`gmt data import-sessions`): per-step labels from their timelines
        per_step, table = served
        goals = [Goal(**g) for g in table]
        n_switches, n_eps = switch_count(per_step)
        typer.echo(
            f"{len(ds.episodes)} episodes with per-step goal labels ({n_switches} goal switches in {n_eps} "
            f"episodes), k = {len(goals)} goals: " + ", ".join(f"{g.name}={g.mean:.2f}" for g in goals)
        )
        stat = ds.goal_labels.get("statistic") or flags["statistic"] or chosen_statistic(ds, typer.echo)
        tc = TrainConfig(**{**pick(flags, TRAIN_FLAGS), "statistic": stat, "k": len(goals)})
        command = "gmt train " + " ".join(shlex.quote(a) for a in sys.argv[2:])
        ckpt = train(
            ds,
            per_step,
            goals,
            out,
            tc,
            pick(flags, MODEL_FLAGS),
            resume=resume,
            extra_meta={"goal_labels": ds.goal_labels, "command": command},
        )
        _finished(ckpt, out)
        return
    if labels is not None:
        rel = GoalTable.load(labels)
        if len(rel.labels) != len(ds.episodes):
            raise typer.BadParameter(
                f"{labels} labels {len(rel.labels)} episodes, the dataset has {len(ds.episodes)}"
            )
    else:
        stat, k, seed = flags["statistic"] or chosen_statistic(ds, typer.echo), flags["k"], flags["seed"]
        try:
            values = per_trajectory(stat, ds)
        except KeyError as e:  # MissingInfoError: the data lacks what the statistic reads
            raise typer.BadParameter(str(e), param_hint="--statistic") from None
        rel = relabel(values, statistic=stat, k=k, seed=seed)
    goals = [Goal(**g.__dict__) for g in rel.goals]
    typer.echo(
        f"{len(ds.episodes)} episodes, k = {len(goals)} goals: "
        + ", ".join(f"{g.name}={g.mean:.2f}" for g in goals)
    )
    tc = TrainConfig(**{**pick(flags, TRAIN_FLAGS), "statistic": rel.statistic, "k": len(goals)})
    overrides = pick(flags, MODEL_FLAGS)
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
    _finished(ckpt, out)


def _check_train_flags(flags: dict[str, Any], out: Path) -> None:
    """Every training and model flag, checked before the dataset loads (which can take minutes).

    Raises:
        typer.BadParameter: naming the first flag that cannot work.
    """
    import torch

    from gmt.common.statistics import get_statistic

    try:
        TrainConfig(**pick(flags, TRAIN_FLAGS))
        GMTConfig((1,), 1, False, 2, **pick(flags, MODEL_FLAGS))  # the spaces and goals: placeholders
        if flags["statistic"] is not None:
            get_statistic(flags["statistic"])
    except (ValueError, KeyError) as e:
        raise typer.BadParameter(str(e.args[0]) if e.args else str(e)) from None
    if flags["k"] is not None and flags["k"] < 2:
        raise typer.BadParameter(f"k must be >= 2 goals, got {flags['k']} (leave it out: silhouette picks k)")
    if flags["device"] == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("--device cuda, but torch sees no CUDA GPU here (use auto or cpu)")
    if out.exists() and not out.is_dir():
        raise typer.BadParameter(f"{out} is a file, not a checkpoint directory", param_hint="--out")


def _finished(ckpt, out: Path) -> None:
    """Report the run (`_trained`); a `torchrun` worker then ends at once (`exit_worker`: its gloo threads must not
    outlive the interpreter's shutdown)."""
    from gmt.model.distributed import exit_worker, launched_by_torchrun

    _trained(ckpt, out)
    if launched_by_torchrun():
        exit_worker()


def _trained(ckpt, out: Path) -> None:
    if ckpt is None:  # a torchrun process other than rank 0: rank 0 wrote the checkpoint
        return
    info = ckpt.meta["training"]
    note = (ckpt.meta.get("goal_spread") or {}).get("note")
    if note:
        typer.echo(note, err=note.startswith("warning"))
    typer.echo(
        f"wrote {out} ({info['wall_time_s']} s, {info['steps_per_s']} steps/s, final loss {info['final']['loss']:.4f})"
    )
    stale = [n for n in STALE_AFTER_TRAINING if (out / n).exists()]
    if stale:  # written for the weights this run replaced
        typer.echo(
            f"note: {', '.join(stale)} in {out} describe the previous weights: run gmt eval {out} again, and "
            "update PROVENANCE.md",
            err=True,
        )


STALE_AFTER_TRAINING = ("eval.json", "eval.md", "eval.png", "PROVENANCE.md")


@needs("eval", "gmt eval")
def eval_command(
    checkpoint: Path = typer.Argument(..., help="Checkpoint directory."),
    seeds: int = typer.Option(15, min=1, help="Seeds 0..N-1 per condition."),
    first_seed: int = typer.Option(
        0,
        min=0,
        help="Seeds first_seed..first_seed+N-1 instead (unseen seeds, e.g. to choose an inference setting).",
    ),
    steps: int = typer.Option(1000, min=1, help="Episode length."),
    json_out: Path = typer.Option(None, "--json", help="Write the JSON result here."),
    markdown_out: Path = typer.Option(None, "--markdown", help="Write the Markdown table here."),
    plot: Path = typer.Option(None, help="Write the figure (PNG) here."),
    threads: int = typer.Option(2, min=1, help="torch threads."),
    action_mode: str = typer.Option(
        None,
        help="mean or sample (continuous), argmax/sample/expert (discrete); default: the model's default.",
    ),
    switch_relabel_steps: int = typer.Option(
        None,
        help="Steps of context a goal change relabels with the new goal (0: none); default: the model's "
        "(its gmt.json `switch_relabel_steps`).",
    ),
    precision: str = typer.Option(
        "fp32",
        help="fp32 (exact, the default) or bf16: the native step's block products in bfloat16, as "
        "`GMT_PRECISION=bf16` serves them (a CPU with AVX-512 BF16).",
    ),
) -> None:
    """Hold every goal, switch every ordered pair mid-episode, cycle goals every 300/200/100 steps.

    A checkpoint whose statistic sums (`return`, any sum(...)) gets the paper's game protocol instead (`gmt.model.evaluate_return`):
    hold every goal, switch at step 300 between the low, middle and high goals, against the expected return.
    A Decision Transformer (`--conditioning return` at training) plays the same protocol steered by
    returns-to-go (`gmt.model.evaluate_dt`).
    """
    import torch

    from gmt.common.statistics import is_sum
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.engine import PolicyEngine
    from gmt.model.evaluate import evaluate

    for flag, path in (("--json", json_out), ("--markdown", markdown_out), ("--plot", plot)):
        if path is not None and path.is_dir():  # found before the evaluation runs, not after
            raise typer.BadParameter(f"{path} is a directory; name the file to write", param_hint=flag)
    if precision not in ("fp32", "bf16"):
        raise typer.BadParameter(f"must be fp32 or bf16, got {precision!r}", param_hint="--precision")
    torch.set_num_threads(threads)
    ckpt = load_checkpoint(checkpoint)
    dt = ckpt.config.conditioning == "return"
    if precision != "fp32" and (dt or is_sum(ckpt.statistic)):
        raise typer.BadParameter(
            "bf16 is evaluated with the goal protocol (a mean statistic); this checkpoint uses another one",
            param_hint="--precision",
        )
    seed_list = list(range(first_seed, first_seed + seeds))
    modes = ("mean",) if dt else PolicyEngine(ckpt).action_modes
    if action_mode is not None and action_mode not in modes:
        raise typer.BadParameter(
            f"{action_mode!r} is not one of this model's modes {modes}", param_hint="--action-mode"
        )
    if dt:
        from gmt.model.eval_plot import plot_eval
        from gmt.model.evaluate_dt import evaluate_dt

        result = evaluate_dt(ckpt, seeds=seed_list, steps=steps)
    elif is_sum(ckpt.statistic):  # e.g. `return`: goals of whole episodes
        from gmt.model.evaluate_return import evaluate_returns, plot_returns

        result = evaluate_returns(ckpt, seeds=seed_list, steps=steps, action_mode=action_mode)
        plot_eval = plot_returns
    else:
        from gmt.model.eval_plot import plot_eval

        if switch_relabel_steps is not None and not 0 <= switch_relabel_steps <= ckpt.config.history_steps:
            raise typer.BadParameter(
                f"must be 0 to the model's history of {ckpt.config.history_steps} steps",
                param_hint="--switch-relabel-steps",
            )
        result = evaluate(
            ckpt,
            seeds=seed_list,
            steps=steps,
            action_mode=action_mode,
            switch_relabel_steps=switch_relabel_steps,
            precision=precision,
        )
    table = result.markdown()
    typer.echo(table)
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    if markdown_out:
        markdown_out.parent.mkdir(parents=True, exist_ok=True)
        markdown_out.write_text(table + "\n")
    if plot:
        plot_eval(result, plot)
        typer.echo(f"plot: {plot}")


@needs("eval", "gmt replay")
def replay_command(
    recordings: list[Path] = typer.Argument(
        ...,
        help="Recordings (<session_id>.json or .npz) or directories of them (e.g. gmt serve's --record-dir).",
    ),
    checkpoint: Path = typer.Option(..., help="The checkpoint to replay them against."),
    plot: Path = typer.Option(None, help="Write a figure (PNG) of the per-step differences here."),
    json_out: Path = typer.Option(None, "--json", help="Write the JSON result (per step and summary) here."),
    action_mode: str = typer.Option(None, help="Override the recorded action mode."),
    seed: int = typer.Option(None, help="Override each recording's sampler seed."),
    window: int = typer.Option(25, min=1, help="Steps measured on each side of a goal change."),
    threads: int = typer.Option(1, min=1, help="torch threads."),
) -> None:
    """Replay recorded sessions against a checkpoint: how far its actions are from the recorded ones.

    Every recorded episode's observations and goal timeline are fed to the checkpoint in lockstep through the
    engine; the difference is reported per step and around each goal change (0 against the recording's own
    checkpoint with its seed and action mode).
    """
    import torch

    from gmt.common.recording import RecordingError, find_recordings, read_recording
    from gmt.model.checkpoint import load_checkpoint
    from gmt.model.replay import ReplayError, plot_replay, replay

    torch.set_num_threads(threads)
    try:
        recs = [read_recording(p) for p in find_recordings(recordings)]
    except (FileNotFoundError, RecordingError) as e:
        raise typer.BadParameter(str(e), param_hint="RECORDING") from None
    ckpt = load_checkpoint(checkpoint)
    try:
        result = replay(
            recs,
            ckpt,
            action_mode=action_mode,
            seed=seed,
            window=window,
            fingerprint=ckpt.fingerprint,
        )
    except (ReplayError, ValueError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    typer.echo(result.text())
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(result.to_dict()) + "\n")
        typer.echo(f"wrote {json_out}")
    if plot:
        typer.echo(f"plot: {plot_replay(result, plot)}")
