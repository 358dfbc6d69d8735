"""A goal change that relabels the context (`PolicyEngine.set_goal` with `switch_relabel_steps`)."""

import json

import numpy as np
import pytest

from gmt.model.checkpoint import CheckpointError, load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint


@pytest.fixture(scope="module")
def window_ckpt():
    return tiny_checkpoint(attention="window", context_length=4, n_layer=2)


def _play(engine, ctx, obs):
    return [np.asarray(engine.act([ctx], [o])[0]) for o in obs]


@pytest.mark.parametrize("native", [None, False])
def test_a_switch_relabels_the_last_steps_and_acts_as_an_adopted_relabelled_context(window_ckpt, native):
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(14, 17)).astype(np.float32)
    eng = PolicyEngine(window_ckpt, native=native, switch_relabel_steps=3)
    plain = PolicyEngine(window_ckpt, native=native)
    ctx, pctx = eng.new_context(0), plain.new_context(0)
    _play(eng, ctx, obs[:8])
    _play(plain, pctx, obs[:8])
    before = ctx.to_stored()

    assert eng.set_goal(ctx, 2) == 3
    assert plain.set_goal(pctx, 2) == 0
    after = ctx.to_stored()
    assert list(after.goals[-3:]) == [2, 2, 2] and list(after.goals[:-3]) == list(before.goals[:-3])
    assert list(after.blend_to[-3:]) == [2, 2, 2] and not after.blend_w[-3:].any()

    # The same context built by hand (old goals, the last three relabelled) and adopted by another engine: the
    # relabelled session's rebuilt cache must answer exactly as that one does.
    by_hand = before
    by_hand.goals = before.goals.copy()
    by_hand.goals[-3:] = 2
    by_hand.blend_to = before.blend_to.copy()
    by_hand.blend_to[-3:] = 2
    by_hand.goal, by_hand.blend_from, by_hand.version = 2, 2, after.version
    twin = PolicyEngine(window_ckpt, native=native)
    adopted = twin.from_stored(by_hand)
    got, want = _play(eng, ctx, obs[8:]), _play(twin, adopted, obs[8:])
    np.testing.assert_array_equal(np.stack(got), np.stack(want))
    # ... and not as the context that kept its old goals.
    unrelabelled = _play(plain, pctx, obs[8:])
    assert not np.array_equal(np.stack(got), np.stack(unrelabelled))


def test_only_a_change_at_once_relabels(window_ckpt):
    eng = PolicyEngine(window_ckpt, switch_relabel_steps=7)  # the whole history (2 layers x 3 + 1)
    obs = np.random.default_rng(4).normal(size=(6, 17)).astype(np.float32)
    ctx = eng.new_context(0)
    assert eng.set_goal(ctx, 1) == 0  # nothing to relabel at step 0
    _play(eng, ctx, obs)
    assert eng.set_goal(ctx, 1) == 0  # the same goal
    assert eng.set_goal(ctx, 2, blend_steps=3) == 0  # a blend keeps the context as given
    assert list(ctx.to_stored().goals) == [1] * 6
    assert eng.set_goal(ctx, 0) == 6  # at most the steps held
    assert list(ctx.to_stored().goals) == [0] * 6


def test_the_setting_travels_in_the_checkpoint(tmp_path):
    tiny_checkpoint(tmp_path / "r", attention="window", switch_relabel_steps=5)
    ckpt = load_checkpoint(tmp_path / "r")
    assert ckpt.switch_relabel_steps == 5 and PolicyEngine(ckpt).switch_relabel_steps == 5
    assert PolicyEngine(ckpt, switch_relabel_steps=0).switch_relabel_steps == 0
    meta = json.loads((tmp_path / "r" / "gmt.json").read_text())
    for bad in (-1, 10_000, 2.5, True):
        (tmp_path / "r" / "gmt.json").write_text(json.dumps({**meta, "switch_relabel_steps": bad}))
        with pytest.raises(CheckpointError, match="switch_relabel_steps must be a whole number"):
            load_checkpoint(tmp_path / "r")
    with pytest.raises(ValueError, match="switch_relabel_steps must be 0 to"):
        PolicyEngine(ckpt, switch_relabel_steps=10_000)
