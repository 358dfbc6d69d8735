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


# A discrete model's goals "differ" in an action mode when the lowest and the highest goal's action distributions
# on the same training states are at least this far apart (total variation, mean over states).
GOAL_SPREAD_MIN = 0.02


@torch.inference_mode()
def goal_spread(
    model: GMT, sampler: WindowSampler, n_goals: int, batches: int = 20, batch_size: int = 64, seed: int = 0
) -> dict[str, float]:
    """How much a discrete model's goals change its actions, per action mode.

    The same training windows are scored with every step's goal set to the lowest goal and to the highest; per
    action mode (`gmt.model.sampling`: argmax, expert, sample) the action distributions of the two are compared
    by their total-variation distance, averaged over the valid steps. 0: the goals choose the same actions
    (e.g. argmax and expert on CartPole, whose two actions leave expert one); 1: entirely different ones.

    Returns:
        {mode: mean total-variation distance}.
    """
    from gmt.model.sampling import EXPERT_QUANTILE

    was_training = model.training
    model.eval()
    gen = torch.Generator().manual_seed(seed)
    sums = {"argmax": 0.0, "expert": 0.0, "sample": 0.0}
    count = 0
    for _ in range(batches):
        w = sampler.sample(batch_size, gen)
        probs = []
        for g in (0, n_goals - 1):
            goals = torch.full_like(w.goals, g)
            logits, _ = model(goals, w.states, w.actions, w.timesteps, w.valid)  # [B, K, n]
            z = logits.double()[w.valid]  # [N, n]
            thr = torch.quantile(z, EXPERT_QUANTILE, dim=1, keepdim=True)
            probs.append(
                {
                    "argmax": torch.nn.functional.one_hot(z.argmax(1), z.shape[1]).double(),
                    "expert": torch.softmax(z.masked_fill(z < thr, -torch.inf), dim=1),
                    "sample": torch.softmax(z, dim=1),
                }
            )
        for mode in sums:
            sums[mode] += float(0.5 * (probs[0][mode] - probs[1][mode]).abs().sum(1).sum())
        count += int(w.valid.sum())
    model.train(was_training)
    return {mode: s / max(count, 1) for mode, s in sums.items()}


def mode_for_goals(spread: dict[str, float], chosen: str | None) -> tuple[str | None, str | None]:
    """The default action mode a discrete model should serve with, and a one-line note, from `goal_spread`.

    Where the mode in force (`chosen`, else expert) leaves the goals' actions the same but `sample` does not, an
    unchosen default becomes `sample`; a chosen one stays, with a warning.
    """
    mode = chosen or "expert"
    if spread[mode] >= GOAL_SPREAD_MIN:
        return chosen, None
    said = f"the goals change the {mode} action distribution by {spread[mode]:.3f} (total variation)"
    if chosen is None and spread["sample"] >= GOAL_SPREAD_MIN:
        return "sample", f"{said}, sample's by {spread['sample']:.3f}: sessions default to sample"
    return chosen, (
        f"warning: {said} (sample {spread['sample']:.3f}): the goals may not control the statistic in {mode} mode"
    )
