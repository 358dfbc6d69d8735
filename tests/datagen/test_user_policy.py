"""`gmt data collect` on an environment the project does not ship: a Discrete action space, a user's policy at
named levels, and the locomotion filters off."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from typer.testing import CliRunner

from gmt.datagen.behaviour import RandomPolicy
from gmt.datagen.collect import CollectConfig, collect
from gmt.model.data.minari_io import load_dataset
from gmt.model.data.statistics import per_trajectory
from gmt.service.cli import app

POLICY = "tests.datagen.cartpole_policy:careful"


def test_a_random_policy_draws_discrete_actions():
    space = gym.spaces.Discrete(3, start=1)
    rng = np.random.default_rng(0)
    drawn = {int(RandomPolicy(space).act(None, rng)) for _ in range(200)}
    assert drawn == {1, 2, 3}
    with pytest.raises(ValueError, match="Box or Discrete"):
        RandomPolicy(gym.spaces.MultiBinary(3))


def test_a_users_policy_is_collected_at_its_levels_on_cartpole(tmp_path):
    cfg = CollectConfig("CartPole-v1", episodes_per_level=6, seed=1, dataset_id="t/cartpole/mixed-v0",
                        data_dir=tmp_path, policy=POLICY, levels=["0.05", "0.6"])  # fmt: skip
    assert not cfg.drop_stuck and not cfg.drop_falls  # a CartPole episode ends by termination: kept
    res = collect(cfg, progress=False)
    assert list(res.levels) == ["random", "0.05", "0.6"] and res.episodes == 18
    ds = load_dataset("t/cartpole/mixed-v0", tmp_path)
    assert isinstance(ds.action_space, gym.spaces.Discrete)
    assert all(ep.actions.dtype == np.int64 and ep.actions.ndim == 1 for ep in ds.episodes)
    lengths = [np.mean([len(e) for e in ds.episodes[i : i + 6]]) for i in (0, 6, 12)]
    assert lengths[1] > 2 * lengths[2] and lengths[1] > 2 * lengths[0]  # careful balances longest
    wobble = per_trajectory("mean(abs(obs[2]))", ds)
    assert wobble[6:12].mean() < wobble[12:].mean()


def test_the_collect_command_takes_a_policy_and_refuses_a_bad_one(tmp_path, monkeypatch):
    monkeypatch.setenv("GMT_DATA_DIR", str(tmp_path))
    run = CliRunner().invoke
    args = ["data", "collect", "--env", "CartPole-v1", "--out-id", "t/cp/x-v0", "--episodes-per-level", "2"]
    r = run(app, [*args, "--policy", POLICY, "--level", "0.1", "--level", "0.9", "--no-random"])
    assert r.exit_code == 0, r.output
    assert "0.1 " in r.output and load_dataset("t/cp/x-v0").env_id == "CartPole-v1"
    r = run(app, [*args, "--policy", "tests.datagen.nosuch:f", "--level", "a", "--level", "b"])
    assert r.exit_code == 2 and "cannot import" in r.output
    r = run(app, [*args, "--policy", POLICY])
    assert r.exit_code == 2 and "--level" in r.output


def test_the_standstill_test_is_relative_to_the_episodes_own_speed_outside_the_shipped_tasks():
    from gmt.datagen.rollout import stuck_step

    rng = np.random.default_rng(0)
    # Swimmer-like: a jolt at the start, then a steady few cm/s.
    swims = np.r_[np.full(20, 2.0), np.full(980, 0.04)] + rng.normal(0, 0.01, 1000)
    assert stuck_step(swims, 100) is not None  # HalfCheetah's m/s thresholds: a normal episode looks stuck
    assert stuck_step(swims, 100, relative=True) is None
    stalls = np.concatenate([np.full(400, 0.05), np.full(600, 0.001)]) + rng.normal(0, 0.001, 1000)
    assert 400 <= stuck_step(stalls, 100, relative=True) < 520  # the same scale, but it stopped


def test_stable_baselines3_models_are_levels_too(tmp_path):
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO

    for i in range(2):
        model = PPO("MlpPolicy", "CartPole-v1", n_steps=32, batch_size=32, n_epochs=1, seed=i, device="cpu")
        model.save(tmp_path / f"ppo{i}.zip")
    levels = [f"first={tmp_path / 'ppo0.zip'}", f"second={tmp_path / 'ppo1.zip'}", "0.6"]
    prints = []
    for out_id in ("t/cp/sb3-v0", "t/cp/sb3-v1"):
        cfg = CollectConfig("CartPole-v1", episodes_per_level=2, seed=5, dataset_id=out_id, data_dir=tmp_path,
                            policy=POLICY, levels=levels, include_random=False)  # fmt: skip
        res = collect(cfg, progress=False)
        assert list(res.levels) == ["first", "second", "0.6"]
        prints.append(load_dataset(out_id, tmp_path).fingerprint)
    assert prints[0] == prints[1]  # the models' noise is seeded from the collection's seed
    with pytest.raises(ValueError, match="not a Stable-Baselines3 model"):
        (tmp_path / "bad.zip").write_bytes(b"not a zip")
        collect(CollectConfig("CartPole-v1", 1, 0, "t/cp/bad-v0", tmp_path, levels=[f"x={tmp_path / 'bad.zip'}", "y=z.zip"]),
                progress=False)  # fmt: skip
