"""Goal masking (paper section 2.3): replace goal tokens by the learned [mask] token during training."""

from __future__ import annotations

import torch

from gmt.model.config import MaskingMode


def mask_goals(
    goals: torch.Tensor,
    valid: torch.Tensor,
    mode: MaskingMode,
    p: float,
    mask_token: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Return a copy of `goals` with goal tokens replaced by `mask_token`.

    The first real step of every window keeps its goal (the goal is always given to the model once).
    `token` masks every other goal token independently with probability p; `trajectory` masks all of a
    window's other goal tokens together with probability p; `none` masks nothing. Padding is never masked.

    Args:
        goals: [B, T] true goal ids.
        valid: [B, T] True for real steps (windows are left-padded).
        mode: Masking mode.
        p: Masking probability.
        mask_token: Id of the [mask] row.
        generator: Random generator, for reproducible masks.

    Returns:
        [B, T] goal ids with masked positions set to `mask_token`.
    """
    if mode == "none" or p <= 0.0:
        return goals.clone()
    B, T = goals.shape
    first = valid.int().argmax(dim=1)  # [B] index of the first real step
    maskable = valid.clone()
    maskable[torch.arange(B), first] = False  # [B, T]
    if mode == "token":
        draw = torch.rand(B, T, generator=generator) < p  # [B, T]
    elif mode == "trajectory":
        draw = (torch.rand(B, 1, generator=generator) < p).expand(B, T)  # [B, T]
    else:
        raise ValueError(f"unknown masking mode {mode!r}")
    return torch.where(maskable & draw, torch.full_like(goals, mask_token), goals)
