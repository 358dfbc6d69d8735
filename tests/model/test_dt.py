"""The Decision Transformer baseline: return-to-go tokens, training targets and the switching protocol."""

import numpy as np
import pytest
import torch

from gmt.model.checkpoint import load_checkpoint
from gmt.model.config import GMTConfig, TrainConfig
from gmt.model.engine import PolicyEngine
from gmt.model.evaluate import protocol
from gmt.model.evaluate_dt import evaluate_dt, returns_to_go, target_returns
from gmt.model.fixtures import SyntheticDataset
from gmt.model.losses import gmt_loss
from gmt.model.tokens import WindowSampler
from gmt.model.train import build_sampler, train

SMALL = {
    "context_length": 4,
    "n_layer": 1,
    "n_head": 1,
    "n_embd": 32,
    "conditioning": "return",
    "return_scale": 10.0,
}


def _train(tmp_path, steps=300):
    ds = SyntheticDataset(n_episodes=12, length=40)
    tc = TrainConfig(steps=steps, batch_size=32, lr=3e-3, warmup_steps=10, log_every=50, save_every=10_000)
    return ds, train(ds, ds.labels, ds.goals, tmp_path / "dt", tc, SMALL, progress=False)


def test_windows_carry_the_returns_to_go_of_their_steps():
    states = [np.zeros((3, 2), np.float32), np.zeros((2, 2), np.float32)]
    actions = [np.zeros((3, 1), np.float32), np.zeros((2, 1), np.float32)]
    sampler = WindowSampler(
        states, actions, [0, 1], K=3, rewards=[np.array([1.0, 2.0, 3.0]), np.array([5.0, 7.0])]
    )
    w = sampler.windows(torch.tensor([2, 4]))  # last step of each episode
    assert w.rtg.tolist() == [[6.0, 5.0, 3.0], [0.0, 12.0, 7.0]]  # sums to each episode's end; padding 0
    assert w.valid.tolist() == [[True, True, True], [False, True, True]]


def test_a_decision_transformer_learns_to_read_the_return_to_go(tmp_path):
    ds, ckpt = _train(tmp_path)
    assert ckpt.config.conditioning == "return" and ckpt.action_noise is None
    returns = target_returns(load_checkpoint(tmp_path / "dt"))
    assert np.all(np.diff(returns) > 30)  # goal g earns about g + 1 per step over 40 steps
    sampler, _, _ = build_sampler(ds, ds.labels, ckpt.config)
    w = sampler.windows(torch.arange(0, sampler.n, 3))
    with torch.inference_mode():
        true_pred, gl = ckpt.model(w.rtg, w.states, w.actions, w.timesteps, w.valid)
        # The same windows told another goal's return: the actions must move away from the data's.
        wrong_pred, _ = ckpt.model(w.rtg + 40.0 * torch.where(w.goals < 2, 1.0, -2.0), w.states, w.actions,
                                   w.timesteps, w.valid)  # fmt: skip
    true_loss = gmt_loss(true_pred, gl, w.actions, w.goals, w.valid, False, alpha=0.0).action
    wrong_loss = gmt_loss(wrong_pred, gl, w.actions, w.goals, w.valid, False, alpha=0.0).action
    assert true_loss < 0.5 * wrong_loss, (true_loss, wrong_loss)


def test_the_engine_refuses_a_decision_transformer(tmp_path):
    _, ckpt = _train(tmp_path, steps=5)
    with pytest.raises(ValueError, match="Decision Transformer"):
        PolicyEngine(ckpt)


def test_a_switch_targets_the_new_goals_return_minus_what_was_received():
    targets = np.array([100.0, 400.0])
    cond = protocol(2, steps=10)[2]  # switch 0->1 at step 5
    assert cond.name == "switch 0->1"
    rewards = np.arange(10, dtype=np.float64)  # 0, 1, 2, ...
    assert returns_to_go(targets, cond.goal_at, rewards, 0) == 100.0
    assert returns_to_go(targets, cond.goal_at, rewards, 3) == 100.0 - (0 + 1 + 2)
    assert returns_to_go(targets, cond.goal_at, rewards, 5) == 400.0 - 10.0
    assert returns_to_go(targets, cond.goal_at, rewards, 7) == 400.0 - 21.0


def test_evaluate_dt_plays_the_protocol_in_a_real_environment(tmp_path):
    _, ckpt = _train(tmp_path, steps=5)
    res = evaluate_dt(ckpt, seeds=2, steps=40, progress=False)
    d = res.to_dict()
    assert [c["name"] for c in d["conditions"]] == [c.name for c in protocol(3, steps=40)]
    assert all(c["episodes"] == 2 for c in d["conditions"])
    hold = res.results[0]
    assert hold.signal.shape == (2, 40) and np.isfinite(hold.signal).all()  # HalfCheetah never terminates


def test_config_refuses_an_unknown_conditioning():
    with pytest.raises(ValueError, match="conditioning"):
        GMTConfig(obs_shape=(3,), act_dim=1, discrete_actions=False, n_goals=2, conditioning="reward")
