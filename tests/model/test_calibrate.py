"""Action-noise calibration measures each goal's spread of dataset actions around the network's prediction."""

import numpy as np
import pytest
import torch

from gmt.model.calibrate import action_noise
from gmt.model.fixtures import tiny_checkpoint
from gmt.model.tokens import WindowSampler


def _zero_action_head(model):
    with torch.no_grad():
        model.action_head.weight.zero_()
        model.action_head.bias.zero_()


def test_action_noise_is_the_per_goal_rms_residual():
    ckpt = tiny_checkpoint(context_length=4, n_goals=2)
    _zero_action_head(ckpt.model)  # prediction tanh(0) = 0: residuals are the actions themselves
    rng = np.random.default_rng(0)
    states, actions, goals = [], [], []
    for i in range(20):
        g = i % 2
        states.append(rng.normal(size=(50, 17)).astype(np.float32))
        a = rng.normal(0, 0.1, (50, 6)) if g == 0 else rng.uniform(-1, 1, (50, 6))
        actions.append(a.astype(np.float32))
        goals.append(g)
    sampler = WindowSampler(states, actions, goals, K=4)
    std = action_noise(ckpt.model, sampler, n_goals=2, batches=60, batch_size=32)
    assert std.shape == (2, 6) and std.dtype == np.float32
    by_goal = [np.concatenate([a for a, g in zip(actions, goals, strict=True) if g == k]) for k in (0, 1)]
    want = [np.sqrt(np.mean(a**2, axis=0)) for a in by_goal]
    np.testing.assert_allclose(std[0], want[0], rtol=0.1)
    np.testing.assert_allclose(std[1], want[1], rtol=0.1)
    assert (std[1] > 4 * std[0]).all()


def test_missing_goal_and_discrete_models_are_refused():
    ckpt = tiny_checkpoint(context_length=4, n_goals=3)
    rng = np.random.default_rng(0)
    sampler = WindowSampler(
        [rng.normal(size=(30, 17)).astype(np.float32)], [np.zeros((30, 6), np.float32)], [0], K=4
    )
    with pytest.raises(ValueError, match=r"goals \[1, 2\] never appeared"):
        action_noise(ckpt.model, sampler, n_goals=3, batches=2)
    cartpole = tiny_checkpoint(env_id="CartPole-v1", context_length=4)
    with pytest.raises(ValueError, match="continuous actions only"):
        action_noise(cartpole.model, sampler, n_goals=3, batches=1)


def test_a_mode_in_which_the_goals_act_alike_gives_way_to_sample():
    from gmt.model.calibrate import mode_for_goals

    alike = {"argmax": 0.004, "expert": 0.004, "sample": 0.3}
    mode, note = mode_for_goals(alike, None)
    assert mode == "sample" and "sessions default to sample" in note
    mode, note = mode_for_goals(alike, "argmax")  # chosen by the user: kept, with a warning
    assert mode == "argmax" and note.startswith("warning") and "argmax" in note
    assert mode_for_goals({"argmax": 0.2, "expert": 0.2, "sample": 0.3}, None) == (None, None)
    mode, note = mode_for_goals({"argmax": 0.0, "expert": 0.0, "sample": 0.001}, None)
    assert mode is None and note.startswith("warning")
