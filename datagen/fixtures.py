"""Tiny random-weight behaviour snapshots for tests (the data lab's counterpart of `gmt.model.fixtures`)."""

from __future__ import annotations

from pathlib import Path

import torch

from gmt.datagen.behaviour import BehaviourMeta, save_behaviour


def random_behaviour(
    folder: str | Path,
    level: str,
    speed: float,
    seed: int,
    *,
    hidden_sizes: tuple[int, ...] = (8,),
    activation: str = "tanh",
    weight_scale: float = 0.1,
    bias_scale: float = 0.1,
    obs_mean: float = 0.0,
    obs_var: float = 1.0,
    command: float | None = None,
    train_step: int | None = None,
) -> Path:
    """A random-weight HalfCheetah behaviour snapshot in the exported format, at `folder/halfcheetah/level`.

    Args:
        folder: Behaviour root (the layout `gmt data collect --behaviour-dir` reads).
        level: Level name.
        speed: The snapshot's recorded mean speed (m/s).
        seed: Torch seed of the weights.
        hidden_sizes: Widths of the mean network's hidden layers.
        activation: "tanh" or "relu".
        weight_scale: Std of the weights.
        bias_scale: Std of the biases.
        obs_mean: Every entry of the observation normaliser's mean.
        obs_var: Every entry of its variance.
        command: When given, a commanded actor: it reads this command appended to its observation.
        train_step: Recorded training step.

    Returns:
        The snapshot's path stem.
    """
    torch.manual_seed(seed)
    n_in = 17 + (command is not None)
    meta = BehaviourMeta(
        "HalfCheetah-v5",
        level,
        list(hidden_sizes),
        activation,
        [obs_mean] * n_in,
        [obs_var] * n_in,
        mean_speed=speed,
        train_step=train_step,
        extra={} if command is None else {"command": command},
    )
    sizes = [n_in, *hidden_sizes, 6]
    state = {}
    for i in range(len(sizes) - 1):
        state[f"mean_net.{2 * i}.weight"] = weight_scale * torch.randn(sizes[i + 1], sizes[i])  # (out, in)
        state[f"mean_net.{2 * i}.bias"] = bias_scale * torch.randn(sizes[i + 1])
    state["log_std"] = torch.full((6,), -1.0)
    path = Path(folder) / "halfcheetah" / level
    save_behaviour(path, state, meta)
    return path
