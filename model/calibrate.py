"""Action-noise calibration: the per-goal spread of the behaviour actions around the network's prediction.

The network regresses the action *mean* (MSE, paper section 2.2). The behaviour policies that made the data
acted stochastically, and the goal statistics (e.g. a goal's mean x-velocity) were measured under that noise:
on HalfCheetah a deterministic rollout of the mean runs about 20% faster than the same policy with its Gaussian
noise. To reproduce a goal's statistic, continuous-action sessions can sample `mean + std[goal] * N(0, 1)`,
where `std[goal]` is the root-mean-square residual of the dataset's actions around the network's prediction,
measured here per goal and action dimension.
"""

from __future__ import annotations

import numpy as np
import torch

from gmt.model.gmt import GMT
from gmt.model.tokens import WindowSampler


@torch.inference_mode()
def action_noise(
    model: GMT, sampler: WindowSampler, n_goals: int, batches: int = 200, batch_size: int = 64, seed: int = 0
) -> np.ndarray:
    """Per-goal, per-dimension RMS residual of the dataset actions around the network's (fp32) prediction.

    Windows are drawn with a fixed seed and carry their true, unmasked goals, as at inference.

    Args:
        model: A continuous-action GMT.
        sampler: Windows of the training dataset (model-space actions).
        n_goals: Number of goals.
        batches: Batches of windows to score.
        batch_size: Windows per batch.
        seed: Seed of the window draw.

    Returns:
        [n_goals, act_dim] float32 standard deviations in model space ([-1, 1] actions).

    Raises:
        ValueError: the model has discrete actions, or a goal never appears in the drawn windows.
    """
    if model.cfg.discrete_actions:
        raise ValueError("action noise applies to continuous actions only")
    was_training = model.training
    model.eval()
    gen = torch.Generator().manual_seed(seed)
    sq = torch.zeros(n_goals, model.cfg.act_dim, dtype=torch.float64)
    count = torch.zeros(n_goals, dtype=torch.float64)
    for _ in range(batches):
        w = sampler.sample(batch_size, gen)
        pred, _ = model(*w.model_inputs())  # [B, K, A]
        res = (w.actions - pred).double()[w.valid]  # [n_valid, A]
        g = w.goals[w.valid]  # [n_valid]
        sq.index_add_(0, g, res * res)
        count.index_add_(0, g, torch.ones_like(g, dtype=torch.float64))
    model.train(was_training)
    if (count == 0).any():
        missing = torch.nonzero(count == 0).flatten().tolist()
        raise ValueError(f"goals {missing} never appeared in {batches} batches; raise `batches`")
    return torch.sqrt(sq / count[:, None]).float().numpy()
