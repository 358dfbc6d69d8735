"""The batched engine: exact agreement with the training forward, rolling context, goals and blends."""

import dataclasses

import numpy as np
import pytest
import torch

from model.checkpoint import load_checkpoint
from model.engine import SAMPLE_STD_CAP, InvalidObservation, PolicyEngine
from model.fixtures import tiny_checkpoint
from model.tokens import WindowSampler


def _episode(rng, T, obs_dim=17, act_dim=6):
    return rng.normal(size=(T, obs_dim)).astype(np.float32), rng.uniform(-1, 1, (T, act_dim)).astype(
        np.float32
    )


def test_engine_action_is_bit_identical_to_training_forward():
    ckpt = tiny_checkpoint(context_length=5)
    engine = PolicyEngine(ckpt)
    rng = np.random.default_rng(0)
    raw_obs, actions = _episode(rng, 12)
    states = ckpt.obs_norm(raw_obs)
    sampler = WindowSampler([states], [actions], [2], K=5)
    # Engine: feed the episode step by step, forcing the dataset's actions into the context.
    ctx = engine.new_context(goal=2)
    engine_actions = []
    for t in range(12):
        engine.act([ctx], [raw_obs[t]])
        engine_actions.append(ctx.actions[-1].copy())
        ctx.actions[-1] = actions[t]
    # Training code: the window ending at each step, scored by the model's forward.
    for t in (0, 3, 4, 11):
        w = sampler.windows(torch.tensor([t]))
        with torch.inference_mode():
            pred, _ = ckpt.model(*w.model_inputs())
        assert np.array_equal(pred[0, -1].numpy(), engine_actions[t]), f"step {t} differs"


def test_batch_rows_are_independent_and_contexts_roll():
    engine = PolicyEngine(tiny_checkpoint(context_length=4))
    rng = np.random.default_rng(1)
    a, b = engine.new_context(0), engine.new_context(2)
    for _ in range(7):
        obs = rng.normal(size=(2, 17))
        both = engine.act([a, b], list(obs))
        assert all(np.all(np.abs(x) <= 1.0) for x in both)
    assert a.size == 4 and a.step == 7 and list(a.timesteps) == [3, 4, 5, 6]
    assert list(b.goals) == [2, 2, 2, 2]


def test_set_goal_changes_the_next_token_and_the_action():
    engine = PolicyEngine(tiny_checkpoint(context_length=5))
    rng = np.random.default_rng(2)
    obs = rng.normal(size=(6, 17))
    a, b = engine.new_context(0), engine.new_context(0)
    for t in range(5):
        engine.act([a, b], [obs[t], obs[t]])
    engine.set_goal(b, 2)
    out = engine.act([a, b], [obs[5], obs[5]])
    assert list(b.goals[-2:]) == [0, 2] and a.goals[-1] == 0
    assert not np.array_equal(out[0], out[1])


def test_blend_fades_the_goal_in():
    engine = PolicyEngine(tiny_checkpoint())
    ctx = engine.new_context(0)
    engine.act([ctx], [np.zeros(17)])
    engine.set_goal(ctx, 2, blend_steps=4)
    for _ in range(5):
        engine.act([ctx], [np.zeros(17)])
    assert list(ctx.blend_w) == [0.25, 0.5, 0.75, 1.0, 0.0]
    assert list(ctx.goals) == [0, 0, 0, 0, 2] and list(ctx.blend_to[:4]) == [2, 2, 2, 2]
    assert ctx.blend_remaining == 0 and ctx.goal == 2


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros(5), "has 5 values, expected 17"),
        (np.full(17, np.nan), "non-finite"),
        (["a"] * 17, "numeric"),
    ],
)
def test_bad_observation_is_refused_and_context_untouched(bad, message):
    engine = PolicyEngine(tiny_checkpoint())
    ctx = engine.new_context(1)
    engine.act([ctx], [np.ones(17)])
    before = (ctx.step, ctx.states.copy())
    with pytest.raises(InvalidObservation, match=message):
        engine.act([ctx], [bad])
    assert ctx.step == before[0] and np.array_equal(ctx.states, before[1])
    engine.act([ctx], [np.ones(17)])
    assert ctx.step == 2


def test_unknown_goal_is_refused():
    engine = PolicyEngine(tiny_checkpoint())
    with pytest.raises(ValueError, match="not a goal id"):
        engine.new_context(3)


def test_discrete_modes_pick_valid_actions(tmp_path):
    tiny_checkpoint(tmp_path / "c", env_id="CartPole-v1")
    engine = PolicyEngine(load_checkpoint(tmp_path / "c"))
    for mode in ("argmax", "sample", "expert"):
        ctx = engine.new_context(0, action_mode=mode, seed=0)
        acts = [engine.act([ctx], [np.zeros(4)])[0] for _ in range(6)]
        assert all(isinstance(a, int) and 0 <= a < 2 for a in acts)


def test_continuous_sample_mode_adds_the_goals_calibrated_noise():
    ckpt = tiny_checkpoint(context_length=5)
    assert PolicyEngine(ckpt).action_modes == ("mean",)  # uncalibrated: deterministic only
    with pytest.raises(ValueError, match="action_mode"):
        PolicyEngine(ckpt).new_context(0, "sample")
    ckpt.action_noise = np.array([[0.05] * 6, [0.07] * 6, [0.4] * 6], dtype=np.float32)
    engine = PolicyEngine(ckpt)
    assert engine.action_modes == ("sample", "mean") and engine.default_action_mode == "sample"
    obs = np.random.default_rng(1).normal(size=(3, 17)).astype(np.float32)
    for goal in (0, 2):
        a, b = engine.new_context(goal, seed=7), engine.new_context(goal, seed=7)
        noise = np.random.default_rng(7)
        for t in range(3):
            # The mean action for the same history: a deterministic copy of `a` (the engine replaces arrays).
            (m,) = engine.act([dataclasses.replace(a, action_mode="mean")], [obs[t]])
            (x,) = engine.act([a], [obs[t]])
            (y,) = engine.act([b], [obs[t]])
            std = min(ckpt.action_noise[goal][0], SAMPLE_STD_CAP)  # goal 2's 0.4 is capped
            want = np.clip(m + std * noise.standard_normal(6), -1, 1)
            np.testing.assert_allclose(x, want, atol=1e-6)
            assert np.array_equal(x, y)  # same seed, same actions
            np.testing.assert_allclose(a.actions[-1], x, atol=1e-6)  # the context holds the action taken
