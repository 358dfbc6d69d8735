"""Random-weight models the kernel tests share."""

from __future__ import annotations

import torch

from gmt.model.config import GMTConfig
from gmt.model.gmt import GMT

# Everything but the width, the heads and the action kind.
SHAPE = dict(
    obs_shape=(11,), act_dim=5, n_goals=4, context_length=6, n_layer=2, max_timestep=30, attention="window"
)


def random_window_model(discrete: bool, n_head: int, n_embd: int) -> GMT:
    """A 2-layer `window` model (11-d observations, 5 actions, 4 goals, K = 6) with N(0, 0.3) weights, seed 0;
    its timestep table (30 rows) is shorter than the steps the tests take, so later timesteps clamp to its last
    row."""
    torch.manual_seed(0)
    cfg = GMTConfig(discrete_actions=discrete, n_head=n_head, n_embd=n_embd, **SHAPE)
    model = GMT(cfg).eval()
    for p in model.parameters():
        p.data.normal_(0.0, 0.3)
    return model
