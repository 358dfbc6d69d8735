import gymnasium as gym
import numpy as np
import pytest
import torch

from gmt.datagen.behaviour import BehaviourMeta, load_behaviour, save_behaviour
from gmt.datagen.collect import DEFAULT_NOISE_SCALE, CollectConfig, collect
from gmt.datagen.fixtures import random_behaviour
from gmt.model.data.minari_io import load_dataset
from gmt.model.data.statistics import per_trajectory

ENV = "HalfCheetah-v5"


def fake_snapshot(folder, level: str, speed: float, seed: int) -> None:
    """A random-weight snapshot in the exported format."""
    random_behaviour(folder, level, speed, seed)


def test_collects_valid_reproducible_dataset(tmp_path):
    beh = tmp_path / "behaviour"
    fake_snapshot(beh, "fast", 2.0, 0)
    fake_snapshot(beh, "slow", 1.0, 1)
    cfg = CollectConfig(
        ENV, episodes_per_level=2, seed=3, data_dir=tmp_path / "d", behaviour_dir=beh, max_steps=12,
        pool_start={},
    )  # fmt: skip
    res = collect(cfg, progress=False)
    assert res.dataset_id == "gmt/halfcheetah/mixed-v0"
    assert list(res.levels) == ["random", "slow", "fast"]
    ds = load_dataset(res.dataset_id, tmp_path / "d")
    assert ds.env_id == ENV and len(ds.episodes) == 6 and ds.n_transitions == 72
    for ep in ds.episodes:
        assert ep.observations.shape == (12, 17) and ep.actions.shape == (12, 6)
        assert ep.truncated and not ep.terminated
        assert np.all(np.abs(ep.actions) <= 1.0)
        assert ep.infos["x_velocity"].shape == (12,)
    assert np.isfinite(per_trajectory("mean_x_velocity", ds)).all()
    # Each episode records its reset seed and policy; resetting with that seed gives its first observation.
    meta = _episode_attrs(tmp_path / "d", 2)
    assert meta["policy"] == "slow"
    obs, _ = gym.make(ENV).reset(seed=int(meta["reset_seed"]))
    np.testing.assert_array_equal(obs, ds.episodes[2].observations[0])
    again = collect(
        CollectConfig(ENV, 2, 3, "gmt/other-v0", tmp_path / "d", beh, 12, pool_start={}), progress=False
    )
    assert load_dataset(again.dataset_id, tmp_path / "d").fingerprint == ds.fingerprint
    other = collect(
        CollectConfig(ENV, 2, 4, "gmt/other2-v0", tmp_path / "d", beh, 12, pool_start={}), progress=False
    )
    assert load_dataset(other.dataset_id, tmp_path / "d").fingerprint != ds.fingerprint


def _episode_attrs(root, i: int) -> dict:
    import h5py

    with h5py.File(root / "gmt/halfcheetah/mixed-v0/data/main_data.hdf5", "r") as f:
        return dict(f[f"episode_{i}"].attrs)


def test_exported_policy_matches_sb3():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from gmt.datagen.ppo import as_policy, export_actor

    venv = VecNormalize(DummyVecEnv([lambda: gym.make(ENV)]))
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu",
                policy_kwargs=dict(net_arch=dict(pi=[16, 16], vf=[16])))  # fmt: skip
    model.learn(128)  # moves the observation statistics away from 0/1
    state, meta = export_actor(model, venv, ENV, "x", [16, 16], "tanh")
    policy = as_policy(state, meta, venv.action_space)
    raw = np.random.default_rng(0).normal(size=(5, 17)) * 3
    expected, _ = model.predict(venv.normalize_obs(raw), deterministic=True)
    np.testing.assert_allclose(policy.act(raw), expected, atol=1e-5)
    np.testing.assert_allclose(policy.log_std.detach().numpy(), model.policy.log_std.detach().numpy())


def test_saved_snapshot_round_trip(tmp_path):
    fake_snapshot(tmp_path, "mid", 1.5, 0)
    space = gym.make(ENV).action_space
    pol = load_behaviour(tmp_path / "halfcheetah" / "mid.safetensors", space)
    assert pol.meta.mean_speed == 1.5
    obs = np.ones(17)
    a1 = pol.act(obs, np.random.default_rng(0))
    assert not np.array_equal(a1, pol.act(obs))  # stochastic vs mean
    np.testing.assert_array_equal(a1, pol.act(obs, np.random.default_rng(0)))


def test_stuck_step_finds_a_runner_that_stopped():
    from gmt.datagen.rollout import stuck_step

    ran_then_stopped = np.r_[np.full(50, 2.0), np.zeros(200)]
    assert stuck_step(ran_then_stopped) == 69
    assert stuck_step(ran_then_stopped, window=100) == 145
    assert stuck_step(np.zeros(300)) is None  # never ran
    assert stuck_step(np.r_[np.zeros(100), np.full(150, 2.0)], window=100) is None  # stopped before running
    assert stuck_step(np.full(300, 0.9)) is None  # slow but steady


def test_noise_scale_multiplies_the_behaviour_noise(tmp_path):
    assert CollectConfig(ENV).noise_scale == DEFAULT_NOISE_SCALE["halfcheetah"] != 1.0
    assert "hopper" not in DEFAULT_NOISE_SCALE and CollectConfig("Hopper-v5").noise_scale == 1.0
    with pytest.raises(ValueError, match="noise_scale"):
        CollectConfig(ENV, noise_scale=-1.0)
    beh = tmp_path / "behaviour"
    fake_snapshot(beh, "slow", 1.0, 1)
    pol = load_behaviour(beh / "halfcheetah" / "slow.safetensors", gym.make(ENV).action_space)
    spread = {}
    for scale in (0.0, 0.5, 1.0):
        cfg = CollectConfig(
            ENV, 1, 0, f"gmt/s{int(scale * 10)}-v0", tmp_path / "d", beh, 30, scale, include_random=False
        )
        ep = load_dataset(collect(cfg, progress=False).dataset_id, tmp_path / "d").episodes[0]
        spread[scale] = float(np.std(ep.actions - pol.act(ep.observations)))
    assert spread[0.0] < 1e-6  # no noise: the mean action (up to float32 storage)
    assert 0.4 < spread[0.5] / spread[1.0] < 0.6  # log-std -1: std 0.37 and 0.18, far from the bounds


def test_pool_starts_begin_where_another_policy_was(tmp_path):
    beh = tmp_path / "behaviour"
    fake_snapshot(beh, "fast", 2.0, 0)
    fake_snapshot(beh, "slow", 1.0, 1)
    assert CollectConfig(ENV).pool_start == {"slow": 0.5} and CollectConfig("Ant-v5").pool_start == {
        "slow": 0.5,
        "fast": 0.5,
    }
    with pytest.raises(ValueError, match="pool_start"):
        CollectConfig(ENV, pool_start={"slow": 1.5})
    with pytest.raises(
        ValueError, match="name-vN"
    ):  # Minari would only fail when writing, after the collection
        CollectConfig(ENV, dataset_id="gmt/ant/gait-check")
    assert (
        CollectConfig(ENV, dataset_id="gmt/ant/gait-0608-check-v1").dataset_id == "gmt/ant/gait-0608-check-v1"
    )
    # These random-weight snapshots barely move: pool-started episodes that end standing still are replaced
    # (from-rest ones, which never ran, are kept), a failed pooled start is retried from another pool state, and here every try fails.
    with pytest.raises(ValueError, match=r"unknown levels \['slwo'\]"):
        collect(
            CollectConfig(ENV, 4, 3, data_dir=tmp_path / "d", behaviour_dir=beh, pool_start={"slwo": 0.5})
        )
    cfg = CollectConfig(
        ENV, 4, 3, data_dir=tmp_path / "d", behaviour_dir=beh, max_steps=40, pool_start={"slow": 0.5}
    )
    with pytest.raises(RuntimeError, match="slow: 12 of 12 episodes got stuck"):
        collect(cfg, progress=False)
    cfg.drop_stuck = False
    res = collect(cfg, progress=False)
    assert res.levels["slow"]["pool_starts"] == 2 and res.levels["fast"]["pool_starts"] == 0
    ds = load_dataset(res.dataset_id, tmp_path / "d")
    env = gym.make(ENV)
    for i, pooled in ((4, True), (5, True), (6, False), (8, False)):
        meta = _episode_attrs(tmp_path / "d", i)
        assert meta["policy"] == ("slow" if i < 8 else "fast")
        rest_obs, _ = env.reset(seed=int(meta["reset_seed"]))
        first = ds.episodes[i].observations[0]
        if pooled:
            assert meta["start_from"] in ("random", "fast") and 20 <= meta["start_step"] <= 40
            assert not np.allclose(first, rest_obs)  # a pooled start is not the reset pose
        else:
            assert "start_from" not in meta
            np.testing.assert_array_equal(first, rest_obs)
    again = collect(CollectConfig(ENV, 4, 3, "gmt/again-v0", tmp_path / "d", beh, 40, pool_start={"slow": 0.5},
                                  drop_stuck=False), progress=False)  # fmt: skip
    assert load_dataset(again.dataset_id, tmp_path / "d").fingerprint == ds.fingerprint


def test_snapshot_episodes_that_fall_are_replaced(tmp_path):
    beh = tmp_path / "behaviour"
    torch.manual_seed(0)
    meta = BehaviourMeta("Hopper-v5", "slow", [8], "tanh", [0.0] * 11, [1.0] * 11, mean_speed=1.0)
    state = {
        "mean_net.0.weight": 0.1 * torch.randn(8, 11),
        "mean_net.0.bias": 0.1 * torch.randn(8),
        "mean_net.2.weight": 0.1 * torch.randn(3, 8),
        "mean_net.2.bias": 0.1 * torch.randn(3),
        "log_std": torch.zeros(3),  # std 1: this hopper topples within a few dozen steps
    }
    save_behaviour(beh / "hopper" / "slow", state, meta)
    cfg = CollectConfig("Hopper-v5", 2, 0, data_dir=tmp_path / "d", behaviour_dir=beh, include_random=False)
    assert cfg.drop_falls and cfg.pool_start == {"slow": 0.5, "fast": 0.5}
    cfg.pool_start = {}
    with pytest.raises(RuntimeError, match=r"slow: 0 of 6 episodes got stuck and 6 fell"):
        collect(cfg, progress=False)
    cfg.drop_falls = False
    res = collect(cfg, progress=False)
    assert res.levels["slow"]["falls_dropped"] == 0
    ds = load_dataset(res.dataset_id, tmp_path / "d")
    assert all(ep.terminated for ep in ds.episodes)  # kept: both end in a fall


def test_pool_starts_can_come_from_a_trained_models_own_states(tmp_path):
    from gmt.datagen.collect import checkpoint_sources
    from gmt.datagen.start_states import CheckpointPolicy, build_pool, start_from
    from gmt.model.engine import PolicyEngine
    from gmt.model.fixtures import tiny_checkpoint

    beh, root = tmp_path / "behaviour", tmp_path / "d"
    fake_snapshot(beh, "fast", 1.8, 0)  # nearest the tiny model's goal 2 (means 0, 1, 2)
    fake_snapshot(beh, "slow", 0.9, 1)  # nearest goal 1
    ckpt = tiny_checkpoint(tmp_path / "ckpt", ENV, n_goals=3, calibrated=True)
    cfg = CollectConfig(
        ENV, 4, 3, data_dir=root, behaviour_dir=beh, max_steps=40, include_random=False, drop_stuck=False,
        pool_start={"slow": 0.5}, pool_checkpoint=tmp_path / "ckpt",
    )  # fmt: skip
    res = collect(cfg, progress=False)
    assert res.levels["slow"]["pool_starts"] == 2
    ds = load_dataset(res.dataset_id, root)
    # The slow level started from the model holding the goal of the fast level's speed, and from nowhere else.
    env = gym.make(ENV)
    engine = PolicyEngine(ckpt)
    pool = build_pool(
        env, {"gmt:" + ckpt.goals[2].name: CheckpointPolicy(engine, 2)}, 10, 3 + 50_000, 20, 4, 40
    )
    for i in (0, 1):
        meta = _episode_attrs(root, i)
        assert meta["start_from"] == "gmt:" + ckpt.goals[2].name
        first = ds.episodes[i].observations[0]
        env.reset(seed=0)
        visited = [start_from(env, q, v) for q, v in zip(pool.qpos, pool.qvel, strict=True)]
        assert any(np.array_equal(first, o) for o in visited)
    with pytest.raises(ValueError, match="no measured speed"):
        checkpoint_sources(tmp_path / "ckpt", {"random": object()})


def test_a_cycling_pool_checkpoint_switches_its_goals_on_schedule_and_feeds_every_level(tmp_path):
    """`pool_cycle`: the model's rollouts cycle goals 0, 1, 2, 0, ... every N steps, as the evaluation's cycles do."""
    from gmt.datagen.start_states import CheckpointPolicy
    from gmt.model.engine import PolicyEngine
    from gmt.model.fixtures import tiny_checkpoint

    ckpt = tiny_checkpoint(tmp_path / "ckpt", ENV, n_goals=3, calibrated=True)
    engine = PolicyEngine(ckpt)
    policy = CheckpointPolicy(engine, 0, cycle_every=3)
    env = gym.make(ENV)
    obs, _ = env.reset(seed=0)
    goals = []
    for _ in range(10):
        obs, *_ = env.step(policy.act(obs))
        goals.append(int(engine.pool.goal[policy.ctx.slot]))
    assert goals == [0, 0, 0, 1, 1, 1, 2, 2, 2, 0]
    policy.start_episode()  # a new episode starts the cycle again
    policy.act(obs)
    assert int(engine.pool.goal[policy.ctx.slot]) == 0
    with pytest.raises(ValueError, match="cycle_every"):
        CheckpointPolicy(engine, 0, cycle_every=0)

    beh, root = tmp_path / "behaviour", tmp_path / "d"
    fake_snapshot(beh, "fast", 1.8, 0)
    fake_snapshot(beh, "slow", 0.9, 1)
    cfg = CollectConfig(
        ENV, 4, 3, data_dir=root, behaviour_dir=beh, max_steps=40, include_random=False, drop_stuck=False,
        pool_start={"slow": 0.5, "fast": 0.5}, pool_checkpoint=tmp_path / "ckpt", pool_cycle=10,
    )  # fmt: skip
    res = collect(cfg, progress=False)
    assert res.levels["slow"]["pool_starts"] == 2 and res.levels["fast"]["pool_starts"] == 2
    starts = {_episode_attrs(root, i).get("start_from") for i in range(8)}
    assert starts == {"gmt:cycle10", None}  # both levels start from the cycling model, or from rest
    with pytest.raises(ValueError, match="needs a pool_checkpoint"):
        CollectConfig(ENV, pool_cycle=10)
