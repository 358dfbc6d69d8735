"""The batched engine: exact agreement with the training forward, the incremental path with the reference,
rolling history, goals, blends, per-item failures and adoption of a stored context."""

import numpy as np
import pytest
import torch

from gmt.model.checkpoint import CheckpointError, load_checkpoint
from gmt.model.engine import InvalidObservation, PolicyEngine, StepFailed
from gmt.model.fixtures import tiny_checkpoint
from gmt.model.sampling import SAMPLE_STD_CAP, normals
from gmt.model.tokens import WindowSampler


def _episode(rng, T, obs_dim=17, act_dim=6):
    return rng.normal(size=(T, obs_dim)).astype(np.float32), rng.uniform(-1, 1, (T, act_dim)).astype(
        np.float32
    )


@pytest.mark.parametrize("attention", ["full", "window"])
def test_engine_action_is_bit_identical_to_training_forward(attention):
    ckpt = tiny_checkpoint(context_length=5, attention=attention)
    engine = PolicyEngine(ckpt, incremental=False)
    rng = np.random.default_rng(0)
    raw_obs, actions = _episode(rng, 12)
    states = ckpt.obs_norm(raw_obs)
    H = ckpt.config.history_steps
    sampler = WindowSampler([states], [actions], [2], K=H)
    # Engine: feed the episode step by step, forcing the dataset's actions into the history.
    ctx = engine.new_context(goal=2)
    engine_actions = []
    for t in range(12):
        engine.act([ctx], [raw_obs[t]])
        engine_actions.append(ctx.actions[-1].copy())
        engine.pool.h_action[ctx.slot, t % H] = actions[t]
    # Training code: the sequence ending at each step, scored by the model's forward.
    for t in (0, 3, 4, 11):
        w = sampler.windows(torch.tensor([t]))
        w.actions[:, -1] = 0  # the action of the step being predicted is not known yet
        with torch.inference_mode():
            pred, _ = ckpt.model(*w.model_inputs())
        assert np.array_equal(pred[0, -1].numpy(), engine_actions[t]), f"step {t} differs"


def _drive(engines, n_sessions, steps, seed, calibrated=True, rebuild_at=(), leave_join_at=()):
    """Step identical sessions through every engine; returns each engine's [steps, n, A] actions."""
    rng = np.random.default_rng(seed)
    ctxs = [[e.new_context(i % 3, seed=100 + i) for i in range(n_sessions)] for e in engines]
    out = [[] for _ in engines]
    for t in range(steps):
        obs = list(rng.normal(size=(n_sessions, 17)).astype(np.float32))
        if t % 97 == 13:  # goal switches, some of them gradual
            i, goal, blend = t % n_sessions, (t // 97) % 3, (t // 97) % 2 * 7
            for e, cs in zip(engines, ctxs, strict=True):
                e.set_goal(cs[i], goal, blend)
        if t in leave_join_at:  # a session leaves and a new one takes its place (and maybe its slot)
            i = t % n_sessions
            for e, cs in zip(engines, ctxs, strict=True):
                e.release(cs[i])
                cs[i] = e.new_context((t + i) % 3, seed=t)
        if t in rebuild_at:  # a session moves: it is rebuilt from the stored form in a fresh slot
            i = (t + 1) % n_sessions
            for e, cs in zip(engines, ctxs, strict=True):
                stored = cs[i].to_stored()
                e.release(cs[i])
                cs[i] = e.from_stored(stored, key=f"moved-{t}")
        for e, cs, o in zip(engines, ctxs, out, strict=True):
            o.append(np.stack(e.act(cs, obs)))
    return [np.stack(o) for o in out]


@pytest.mark.parametrize("kernel", ["native", "torch"])
@pytest.mark.parametrize("n_sessions", [1, 6])
def test_incremental_path_matches_the_reference_over_long_episodes(n_sessions, kernel):
    ckpt = tiny_checkpoint(context_length=6, attention="window", calibrated=True, n_layer=3)
    inc, ref = PolicyEngine(ckpt, native=kernel == "native"), PolicyEngine(ckpt, incremental=False)
    assert inc.describe().path == "incremental" and ref.describe().path == "recompute"
    assert inc.describe().kernel == kernel
    a, b = _drive(
        [inc, ref], n_sessions, 1000, seed=n_sessions, rebuild_at=(150, 700), leave_join_at=(333, 801)
    )
    np.testing.assert_allclose(a, b, atol=1e-5, rtol=0)
    assert not np.allclose(a[100], a[101])  # the episode actually moves


@pytest.mark.parametrize("attention, kernel", [("full", "torch"), ("window", "torch"), ("window", "native")])
def test_rows_are_independent_each_batched_row_equals_its_session_run_alone(attention, kernel):
    """Sessions batched together (different goals, seeds, start steps, a blended switch) get, row for row, the
    very actions the same session gets when it is run alone in an engine of its own."""
    ckpt = tiny_checkpoint(context_length=5, attention=attention, calibrated=True)
    n, steps, joins = 5, 30, (0, 0, 3, 7, 12)  # sessions 2..4 join the batch later, so their steps differ
    rng = np.random.default_rng(5)
    obs = rng.normal(size=(steps, n, 17)).astype(np.float32)
    native = kernel == "native" if attention == "window" else None
    batched = PolicyEngine(ckpt, native=native)
    rows: list = [None] * n
    together = np.full((steps, n, 6), np.nan, np.float32)
    for t in range(steps):
        for i in range(n):
            if t == joins[i]:
                rows[i] = batched.new_context(i % 3, seed=i)
        if t == 15:
            batched.set_goal(rows[3], 0, 4)
        live = [i for i in range(n) if rows[i] is not None]
        for i, a in zip(live, batched.act([rows[i] for i in live], [obs[t, i] for i in live]), strict=True):
            together[t, i] = a
    for i in range(n):
        alone = PolicyEngine(ckpt, native=native)
        ctx = alone.new_context(i % 3, seed=i)
        for t in range(joins[i], steps):
            if t == 15 and i == 3:
                alone.set_goal(ctx, 0, 4)
            (single,) = alone.act([ctx], [obs[t, i]])
            assert np.array_equal(together[t, i], single), (t, i)
    assert not np.array_equal(together[-1, 0], together[-1, 1])  # the rows do differ


def test_contexts_roll_and_report_their_history():
    engine = PolicyEngine(tiny_checkpoint(context_length=4))
    rng = np.random.default_rng(1)
    a, b = engine.new_context(0), engine.new_context(2)
    for _ in range(7):
        both = engine.act([a, b], list(rng.normal(size=(2, 17))))
        assert all(np.all(np.abs(x) <= 1.0) for x in both)
    assert a.size == 4 and a.step == 7 and list(a.timesteps) == [3, 4, 5, 6]
    assert list(b.goals) == [2, 2, 2, 2]


def test_a_context_of_another_engines_pool_is_refused_and_carried_over_exactly():
    """A context acts only in the pool it lives in (another engine of the same checkpoint would read its own slot
    of that index); carried over by `to_stored` / `from_stored` it continues exactly."""
    ckpt = tiny_checkpoint(context_length=4)
    first, second = PolicyEngine(ckpt), PolicyEngine(ckpt)
    obs = list(np.random.default_rng(2).normal(size=(6, 17)))
    ctx, ref = first.new_context(1, seed=3), first.new_context(1, seed=3)
    other = second.new_context(0)  # the same slot index in the second pool
    for o in obs[:3]:
        first.act([ctx], [o])
        first.act([ref], [o])
    with pytest.raises(ValueError, match="another engine's pool"):
        second.act([ctx], [obs[3]])
    assert other.step == 0 and ctx.step == 3
    moved = second.from_stored(ctx.to_stored())
    for o in obs[3:]:
        np.testing.assert_array_equal(second.act([moved], [o])[0], first.act([ref], [o])[0])
    assert moved.step == 6 and other.step == 0


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
def test_bad_observation_fails_alone_and_leaves_its_context_untouched(bad, message):
    engine = PolicyEngine(tiny_checkpoint())
    ctx, other = engine.new_context(1), engine.new_context(1)
    engine.act([ctx, other], [np.ones(17), np.ones(17)])
    before = (ctx.step, ctx.states.copy())
    out = engine.act([ctx, other], [bad, np.ones(17)])
    assert isinstance(out[0], InvalidObservation) and message in str(out[0])
    assert other.step == 2 and np.all(np.isfinite(out[1]))
    assert ctx.step == before[0] and np.array_equal(ctx.states, before[1])
    engine.act([ctx], [np.ones(17)])
    assert ctx.step == 2


@pytest.mark.parametrize("attention", ["full", "window"])
def test_a_non_finite_forward_fails_only_its_row(attention):
    engine = PolicyEngine(tiny_checkpoint(attention=attention))
    twin = PolicyEngine(tiny_checkpoint(attention=attention))
    ctx, nb, tw = engine.new_context(0), engine.new_context(2), twin.new_context(2)
    ok = np.ones(17, np.float32)
    engine.act([ctx, nb], [ok, ok], prepared=True)
    twin.act([tw], [ok], prepared=True)
    # A prepared observation skips validation: an infinite value makes the forward non-finite in every kernel
    # (a merely huge finite one overflows in torch's step, while the native step's products stay finite).
    huge = np.full(17, 3e38, np.float32)
    huge[3] = np.inf
    out = engine.act([ctx, nb], [huge, ok], prepared=True)
    assert isinstance(out[0], StepFailed) and ctx.step == 1
    assert np.array_equal(out[1], twin.act([tw], [ok], prepared=True)[0])
    # The failed session continues as if the bad step never happened.
    fresh = PolicyEngine(tiny_checkpoint(attention=attention))
    f = fresh.new_context(0)
    fresh.act([f], [ok], prepared=True)
    assert np.array_equal(engine.act([ctx], [ok], prepared=True)[0], fresh.act([f], [ok], prepared=True)[0])


@pytest.mark.parametrize("native", [False, True])
@pytest.mark.parametrize("restart", ["reset", "new session in the slot"])
def test_a_failed_forward_leaves_nothing_behind_in_its_slot(native, restart):
    # The failed step's keys and values (NaN) sit in ring positions that a restarted episode reaches only
    # much later; until then they are masked, and a masked NaN must not leak into the attention sum.
    engine = PolicyEngine(tiny_checkpoint(attention="window", context_length=5), native=native)
    fresh = PolicyEngine(tiny_checkpoint(attention="window", context_length=5), native=native)
    ok = np.ones(17, np.float32)
    ctx = engine.new_context(1)
    for _ in range(4):
        engine.act([ctx], [ok], prepared=True)
    huge = np.full(17, 3e38, np.float32)
    huge[3] = np.inf
    assert isinstance(engine.act([ctx], [huge], prepared=True)[0], StepFailed)
    if restart == "reset":
        engine.reset(ctx, 1)
    else:
        engine.release(ctx)
        ctx = engine.new_context(1)
    f = fresh.new_context(1)
    for _ in range(3):
        got, want = engine.act([ctx], [ok], prepared=True)[0], fresh.act([f], [ok], prepared=True)[0]
        assert not isinstance(got, Exception), got
        np.testing.assert_array_equal(got, want)


def test_unknown_goal_is_refused():
    engine = PolicyEngine(tiny_checkpoint())
    with pytest.raises(ValueError, match="not a goal id"):
        engine.new_context(3)


def test_discrete_modes_pick_valid_actions(tmp_path):
    tiny_checkpoint(tmp_path / "c", env_id="CartPole-v1")
    engine = PolicyEngine(load_checkpoint(tmp_path / "c"))
    for mode in ("argmax", "sample", "expert"):
        runs = []
        for seed in (0, 1):
            ctx = engine.new_context(0, action_mode=mode, seed=seed)
            runs.append([engine.act([ctx], [np.zeros(4)])[0] for _ in range(40)])
        assert all(isinstance(a, int) and 0 <= a < 2 for a in runs[0] + runs[1])
        # argmax ignores the seed; sampling draws different actions under different seeds; expert keeps the
        # logits above the 0.6 quantile, which of two actions is the top one only (argmax again).
        assert (runs[0] == runs[1]) == (mode != "sample"), mode


def test_a_checkpoint_names_its_default_action_mode(tmp_path):
    tiny_checkpoint(tmp_path / "c", env_id="CartPole-v1", default_action_mode="sample")
    ckpt = load_checkpoint(tmp_path / "c")  # stored in gmt.json and read back
    assert ckpt.default_action_mode == "sample"
    engine = PolicyEngine(ckpt)
    assert engine.action_modes == ("sample", "expert", "argmax") and engine.default_action_mode == "sample"
    assert engine.new_context(0).action_mode == "sample"
    ckpt.default_action_mode = "mean"  # not a discrete mode
    with pytest.raises(CheckpointError, match="default_action_mode 'mean'"):
        PolicyEngine(ckpt)


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
        a, b, m = (
            engine.new_context(goal, seed=7),
            engine.new_context(goal, seed=7),
            engine.new_context(goal, "mean"),
        )
        for t in range(3):
            (x,) = engine.act([a], [obs[t]])
            (y,) = engine.act([b], [obs[t]])
            (mean,) = engine.act([m], [obs[t]])
            engine.pool.h_action[m.slot, t] = engine.pool.h_action[a.slot, t]  # same history as `a`
            std = min(ckpt.action_noise[goal][0], SAMPLE_STD_CAP)  # goal 2's 0.4 is capped
            noise = normals(np.array([7], np.uint64), np.array([t]), 6)[0]
            want = ckpt.action_codec.decode(np.clip(ckpt.action_codec.encode(mean) + std * noise, -1, 1))
            np.testing.assert_allclose(x, want, atol=1e-5)
            assert np.array_equal(x, y)  # same seed, same actions


def test_pool_shrinks_back_once_every_session_has_gone():
    engine = PolicyEngine(tiny_checkpoint(context_length=4, attention="window"))
    first = engine.pool.n_slots
    ctxs = [engine.new_context(i % 3) for i in range(3 * first)]
    engine.act(ctxs, list(np.zeros((len(ctxs), 17), np.float32)))
    grown = engine.pool.n_slots
    assert grown >= 3 * first
    for c in ctxs[:-1]:
        engine.release(c)
    assert engine.pool.n_slots == grown  # a live slot pins the pool: slots in use never move
    engine.release(ctxs[-1])
    assert engine.pool.n_slots == first and engine.pool.cache.k.shape[1] == first
    twin, fresh = PolicyEngine(tiny_checkpoint(context_length=4, attention="window")), engine.new_context(1)
    t = twin.new_context(1)
    obs = np.random.default_rng(0).normal(size=17).astype(np.float32)
    assert np.array_equal(engine.act([fresh], [obs])[0], twin.act([t], [obs])[0])


# ----- the rules the engine owns (the service calls them and maps ValueError to invalid_argument) --------------
def test_goal_ids_modes_and_blend_lengths_are_the_engines_rules():
    engine = PolicyEngine(tiny_checkpoint())
    with pytest.raises(
        ValueError, match=r"^goal 3 is not a goal id of model 'tiny-gmt'; goals are 0=low, 1=medium"
    ):
        engine.check_goal(3)
    for bad in (-1, True, "1", 1.0):
        with pytest.raises(ValueError, match="is not a goal id"):
            engine.check_goal(bad)
    engine.check_goal(np.int64(2))
    assert engine.check_mode(None) == "mean" and engine.check_mode("mean") == "mean"
    with pytest.raises(ValueError, match=r"action_mode 'sample' is not available .* \(continuous actions\)"):
        engine.new_context(0, action_mode="sample")
    ctx = engine.new_context(0)
    for bad in (-1, 100_001, True, 2.5):
        with pytest.raises(ValueError, match=r"blend_steps must be an integer in 0\.\.100000"):
            engine.set_goal(ctx, 1, blend_steps=bad)
    assert ctx.goal == 0 and ctx.version == 0  # a refused change leaves the context as it was
    engine.set_goal(ctx, 1, blend_steps=100_000)
    assert ctx.blend_remaining == 100_000


def test_an_image_model_takes_only_values_a_frame_can_hold():
    import gymnasium as gym

    frames = gym.spaces.Box(0, 255, (4, 84, 84), np.uint8)
    engine = PolicyEngine(
        tiny_checkpoint(env_id="ALE/Breakout-v5", observation_space=frames, context_length=4)
    )
    frame = np.random.default_rng(0).integers(0, 256, (4, 84, 84))
    for x in (frame.astype(np.uint8), frame.astype(np.float32), frame):  # the same frame in any numeric dtype
        np.testing.assert_array_equal(engine.prepare_observation(x), frame.astype(np.uint8))
    for bad in (
        frame + 0.5,
        frame - 1,
        np.where(frame == frame.max(), 256, frame),
        np.full(frame.shape, np.nan),
    ):
        with pytest.raises(
            InvalidObservation, match=r"image observation values must be integers in 0\.\.255"
        ):
            engine.prepare_observation(bad)
