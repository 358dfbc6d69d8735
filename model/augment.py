"""Image augmentation for training on frames: one random shift and small rotation per sequence.

A shifted crop (DrQ's pad-and-crop, here with sub-pixel shifts) and a rotation of a few degrees make the CNN
less sensitive to where exactly things sit in the frame. Every step of a sequence gets the same transform, so
the motion between its frames (the ball's flight) is kept. Borders repeat the edge pixels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def augment_frames(
    states: torch.Tensor, max_shift: float, max_degrees: float, gen: torch.Generator | None = None
) -> torch.Tensor:
    """Shift and rotate each sequence of frames by one random transform.

    Args:
        states: [B, T, C, H, W] frames (uint8 or float, 0..255).
        max_shift: Largest shift in pixels along each axis (uniform in [-max_shift, max_shift]).
        max_degrees: Largest rotation in degrees (uniform in [-max_degrees, max_degrees]).
        gen: Random generator (the training generator, so runs stay reproducible).

    Returns:
        float32 [B, T, C, H, W] frames on the same 0..255 scale.
    """
    B, T, C, H, W = states.shape
    x = states.float().reshape(B, T * C, H, W)  # one transform per sequence: its steps' frames as channels
    shift = (torch.rand(B, 2, generator=gen) * 2 - 1) * max_shift  # [B, 2] pixels (x, y)
    angle = (torch.rand(B, generator=gen) * 2 - 1) * math.radians(max_degrees)  # [B]
    cos, sin = torch.cos(angle), torch.sin(angle)
    # Normalised coordinates span 2 over W (or H) pixels: a shift of s pixels is 2 s / W.
    tx, ty = shift[:, 0] * 2 / W, shift[:, 1] * 2 / H
    theta = torch.stack(
        [torch.stack([cos, -sin, tx], dim=-1), torch.stack([sin, cos, ty], dim=-1)], dim=1
    )  # [B, 2, 3]: output pixel -> where it is read in the input
    grid = F.affine_grid(theta.to(x.device), [B, T * C, H, W], align_corners=False)  # [B, H, W, 2]
    y = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return y.reshape(B, T, C, H, W)  # [B, T, C, H, W]
