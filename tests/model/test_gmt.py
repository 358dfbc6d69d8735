"""The network is causal and goal-conditioned; masking masks what it claims at the rate it claims."""

import pytest
import torch

from gmt.model.config import GMTConfig
from gmt.model.gmt import GMT
from gmt.model.masking import mask_goals


def _cfg(**kw):
    return GMTConfig(
        obs_shape=(5,),
        act_dim=2,
        discrete_actions=False,
        n_goals=3,
        context_length=6,
        n_layer=2,
        n_head=2,
        n_embd=32,
        **kw,
    )


def _batch(B=2, T=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randint(0, 3, (B, T), generator=g),
        torch.randn(B, T, 5, generator=g),
        torch.rand(B, T, 2, generator=g) * 2 - 1,
        torch.arange(T).repeat(B, 1),
        torch.ones(B, T, dtype=torch.bool),
    )


def test_changing_a_later_token_leaves_earlier_outputs_unchanged():
    torch.manual_seed(0)
    model = GMT(_cfg()).eval()
    goals, states, actions, ts, valid = _batch()
    a0, g0 = model(goals, states, actions, ts, valid)
    states2, actions2, goals2 = states.clone(), actions.clone(), goals.clone()
    states2[:, 4] += 3.0  # state of step 4: affects action predictions from step 4 on
    actions2[:, 3] = -actions2[:, 3]  # action of step 3: affects outputs after a_3
    goals2[:, 5] = (goals2[:, 5] + 1) % 3
    a1, g1 = model(goals2, states2, actions2, ts, valid)
    assert torch.equal(a0[:, :3], a1[:, :3]) and torch.equal(g0[:, :3], g1[:, :3])
    assert not torch.allclose(a0[:, 4:], a1[:, 4:])


def test_action_at_step_t_does_not_see_its_own_action():
    torch.manual_seed(0)
    model = GMT(_cfg()).eval()
    goals, states, actions, ts, valid = _batch()
    a0, _ = model(goals, states, actions, ts, valid)
    actions2 = actions.clone()
    actions2[:, 2] = 0.0
    a1, g1 = model(goals, states, actions2, ts, valid)
    assert torch.equal(a0[:, :3], a1[:, :3])


def test_padding_is_invisible_to_real_tokens():
    torch.manual_seed(0)
    model = GMT(_cfg()).eval()
    goals, states, actions, ts, valid = _batch(B=1)
    valid[:, :2] = False
    a0, _ = model(goals, states, actions, ts, valid)
    states[:, :2] = 100.0
    goals[:, :2] = 0
    a1, _ = model(goals, states, actions, ts, valid)
    assert torch.allclose(a0[:, 2:], a1[:, 2:], atol=1e-6)
    assert torch.isfinite(a1).all()


def test_goal_token_conditions_the_action():
    torch.manual_seed(0)
    model = GMT(_cfg()).eval()
    goals, states, actions, ts, valid = _batch(B=1)
    a0, _ = model(goals, states, actions, ts, valid)
    a1, _ = model((goals + 1) % 3, states, actions, ts, valid)
    assert not torch.allclose(a0, a1)


def _masks(mode, p, B=4000, T=10):
    goals = torch.randint(0, 3, (B, T), generator=torch.Generator().manual_seed(1))
    valid = torch.ones(B, T, dtype=torch.bool)
    valid[: B // 2, :3] = False  # half the windows are left-padded by 3
    out = mask_goals(goals, valid, mode, p, mask_token=3, generator=torch.Generator().manual_seed(2))
    return goals, valid, out


def test_token_masking_rate_and_first_goal_kept():
    goals, valid, out = _masks("token", 0.5)
    masked = out == 3
    first = valid.int().argmax(1)
    assert not masked[torch.arange(len(out)), first].any()
    assert not masked[~valid].any()
    maskable = valid.clone()
    maskable[torch.arange(len(out)), first] = False
    rate = masked[maskable].float().mean().item()
    assert abs(rate - 0.5) < 0.01
    assert torch.equal(out[~masked], goals[~masked])
    per_window = masked.sum(1)[len(out) // 2 :]
    assert per_window.unique().numel() > 3  # independent per token, not all-or-nothing


def test_trajectory_masking_masks_whole_windows():
    _, valid, out = _masks("trajectory", 0.3)
    masked = out == 3
    maskable = valid.clone()
    maskable[torch.arange(len(out)), valid.int().argmax(1)] = False
    per_window = masked.sum(1)
    assert set(per_window.unique().tolist()) <= {0, 6, 9}  # all maskable tokens or none
    frac = (per_window > 0).float().mean().item()
    assert abs(frac - 0.3) < 0.03


def test_no_masking_is_identity():
    goals, _, out = _masks("none", 0.5)
    assert torch.equal(goals, out)


def test_window_attention_sees_exactly_the_last_K_timesteps():
    torch.manual_seed(0)
    K, T = 3, 8
    window = {"obs_shape": (5,), "act_dim": 2, "discrete_actions": False, "n_goals": 3, "context_length": K}
    model = GMT(
        GMTConfig(**window, n_layer=1, n_embd=32, attention="window")
    ).eval()  # one layer: span = K steps
    goals, states, actions, ts, valid = _batch(T=T)
    a0, _ = model(goals, states, actions, ts, valid)
    far, near = states.clone(), states.clone()
    far[:, T - 1 - K] += 5.0  # K steps before the last one: outside its span
    near[:, T - K] += 5.0  # the oldest step inside it
    a_far, _ = model(goals, far, actions, ts, valid)
    a_near, _ = model(goals, near, actions, ts, valid)
    assert torch.equal(a0[:, -1], a_far[:, -1])
    assert not torch.allclose(a0[:, -1], a_near[:, -1])
    assert model.cfg.history_steps == K  # one layer: receptive field n_layer * (K - 1) + 1
    assert GMTConfig(**window, n_layer=3, attention="window").history_steps == 3 * (K - 1) + 1


def test_a_one_row_timestep_table_makes_the_model_blind_to_the_clock():
    torch.manual_seed(0)
    goals, states, actions, ts, valid = _batch()
    blind, timed = GMT(_cfg(max_timestep=1)).eval(), GMT(_cfg()).eval()
    later = ts + 400  # the same window, 400 steps later in its episode
    assert torch.equal(
        blind(goals, states, actions, ts, valid)[0], blind(goals, states, actions, later, valid)[0]
    )
    assert not torch.allclose(
        timed(goals, states, actions, ts, valid)[0], timed(goals, states, actions, later, valid)[0]
    )
    with pytest.raises(ValueError, match="max_timestep"):
        _cfg(max_timestep=0)
