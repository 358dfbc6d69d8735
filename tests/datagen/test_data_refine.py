import json

import gymnasium as gym
import numpy as np
import pytest

from gmt.datagen.behaviour import RandomPolicy, load_behaviour
from gmt.datagen.fixtures import random_behaviour
from gmt.datagen.refine_behaviour import (
    FixedObsNorm,
    RefineConfig,
    TargetSpeedReward,
    refine,
    write_provenance,
)
from gmt.datagen.start_states import PoolStart, build_pool, start_from

ENV = "HalfCheetah-v5"


def test_start_from_puts_the_simulator_in_a_pooled_state():
    env = gym.make(ENV)
    pool = build_pool(
        env, {"random": RandomPolicy(env.action_space)}, episodes=2, seed=0, skip=5, every=5, max_steps=30
    )
    assert len(pool) == 2 * 5 and set(pool.source) == {"random"} and pool.step.min() == 6
    i = 7
    env.reset(seed=123)
    obs = start_from(env, pool.qpos[i], pool.qvel[i])
    np.testing.assert_array_equal(env.unwrapped.data.qpos, pool.qpos[i])
    np.testing.assert_array_equal(obs[:8], pool.qpos[i][1:])  # HalfCheetah's observation drops x
    np.testing.assert_array_equal(obs[8:], pool.qvel[i])
    again = build_pool(
        env, {"random": RandomPolicy(env.action_space)}, episodes=2, seed=0, skip=5, every=5, max_steps=30
    )
    np.testing.assert_array_equal(again.qvel, pool.qvel)


def test_wrappers_reward_the_target_speed_and_start_from_the_pool():
    env = gym.make(ENV)
    pool = build_pool(
        env, {"random": RandomPolicy(env.action_space)}, episodes=1, seed=0, skip=5, every=5, max_steps=30
    )
    wrapped = TargetSpeedReward(gym.make(ENV), target=1.5)
    wrapped.reset(seed=0)
    _, reward, _, _, info = wrapped.step(np.full(6, 0.5, dtype=np.float32))
    assert reward == pytest.approx(-abs(info["x_velocity"] - 1.5) + info["reward_ctrl"])
    always = PoolStart(gym.make(ENV), pool, fraction=1.0, seed=0)
    obs, _ = always.reset(seed=0)
    assert any(np.array_equal(obs[8:], v) for v in pool.qvel)
    never = PoolStart(gym.make(ENV), pool, fraction=0.0, seed=0)
    obs, _ = never.reset(seed=0)
    np.testing.assert_array_equal(obs, gym.make(ENV).reset(seed=0)[0])
    with pytest.raises(ValueError, match="pool_fraction"):
        RefineConfig(ENV, pool_fraction=2.0)


def _snapshot(folder, level: str, speed: float, seed: int) -> None:
    random_behaviour(
        folder,
        level,
        speed,
        seed,
        hidden_sizes=(256, 256),
        activation="relu",
        weight_scale=0.05,
        bias_scale=0.05,
        obs_mean=0.5,
        obs_var=2.0,
        train_step=7,
    )


def test_refine_starts_from_the_level_and_writes_a_snapshot_with_provenance(tmp_path):
    beh = tmp_path / "behaviour"
    _snapshot(beh, "slow", 1.0, 0)
    _snapshot(beh, "fast", 3.0, 1)
    cfg = RefineConfig(
        ENV, timesteps=1024, critic_warmup=512, eval_every=512, eval_episodes=1, pool_episodes=1,
        behaviour_dir=beh, work_dir=tmp_path / "work", out_dir=tmp_path / "out",
    )  # fmt: skip
    best = refine(cfg)
    env = gym.make(ENV)
    init = load_behaviour(beh / "halfcheetah" / "slow", env.action_space)
    step0 = load_behaviour(tmp_path / "work" / "step_00000000", env.action_space)
    obs = np.random.default_rng(0).normal(size=(5, 17))
    np.testing.assert_array_equal(step0.act(obs), init.act(obs))  # PPO's actor began as the level's actor
    # FixedObsNorm feeds PPO exactly what the exported policy normalises.
    wrapped = FixedObsNorm(gym.make(ENV), init)
    np.testing.assert_array_equal(wrapped.observation(obs[0]), init.normalise(obs[0]).numpy())
    out = load_behaviour(tmp_path / "out" / "slow", env.action_space)
    # The chosen snapshot is the best-scoring of those measured (every eval_every steps), and it is what was written.
    records = json.loads((tmp_path / "work" / "records.json").read_text())
    assert [r["step"] for r in records] == [0, 512, 1024]
    assert best == min(records, key=lambda r: r["score"])
    chosen = load_behaviour(tmp_path / "work" / f"step_{best['step']:08d}", env.action_space)
    np.testing.assert_array_equal(out.act(obs), chosen.act(obs))
    assert (out.meta.mean_speed, out.meta.std_speed) == (best["rest_mean"], best["rest_std"])
    assert out.meta.level == "slow" and out.meta.extra["refined"]["refine_step"] == best["step"]
    assert out.meta.train_step == 7 + best["step"]
    path = write_provenance(cfg, best, 12.0)
    write_provenance(cfg, best, 12.0)
    text = path.read_text()
    assert text.count("<!-- refine:slow -->") == 1 and "gmt data refine --env HalfCheetah-v5" in text


def test_speed_tent_pays_the_speed_up_to_the_target_and_charges_overshoot():
    from gmt.datagen.train_behaviour import SpeedTent

    action = np.full(3, 0.8, dtype=np.float32)

    def last_step(env):
        env.reset(seed=3)
        for _ in range(5):
            _, reward, _, _, info = env.step(action)
        return reward, info["x_velocity"]

    r_env, v = last_step(gym.make("Hopper-v5"))
    assert abs(v) > 0.01
    below, _ = last_step(SpeedTent(gym.make("Hopper-v5"), target=v + 0.5))
    assert below == pytest.approx(r_env)  # under the target: the env's own reward, healthy reward included
    above, _ = last_step(SpeedTent(gym.make("Hopper-v5"), target=v - 0.5))
    assert above == pytest.approx(r_env - 1.0)  # 0.5 m/s over: pays v - 0.5 - 0.5 instead of v


def test_refine_defaults_follow_the_task():
    assert RefineConfig(ENV).reward == "absolute" and RefineConfig(ENV).noise_scale == pytest.approx(0.35)
    hopper = RefineConfig("Hopper-v5")
    assert hopper.reward == "tent" and hopper.noise_scale == 1.0
    with pytest.raises(ValueError, match="reward"):
        RefineConfig("Hopper-v5", reward="speed")


def test_a_fall_is_a_failed_measurement():
    from gmt.datagen.refine_behaviour import measure_refined

    env = gym.make("Hopper-v5")
    pool = build_pool(env, {"random": RandomPolicy(env.action_space)}, episodes=1, seed=0, skip=2, every=2)
    m = measure_refined(env, RandomPolicy(env.action_space), pool, target=0.0, episodes=2, seed=0)
    assert m["falls"] == 4 and m["fails"] == 4  # a random Hopper falls within ~30 steps, whatever its speed
    assert all(np.isfinite(m["speeds"]["rest"] + m["speeds"]["pool"]))


def test_tracking_with_pool_starts_begins_from_the_other_levels_states(tmp_path):
    from gmt.datagen.train_behaviour import BehaviourTrainConfig, other_levels_pool

    with pytest.raises(ValueError, match="needs track"):
        BehaviourTrainConfig(ENV, targets={"slow": 1.0}, pool_start=0.5)
    beh = tmp_path / "behaviour"
    _snapshot(beh, "slow", 1.0, 0)
    _snapshot(beh, "fast", 3.0, 1)
    cfg = BehaviourTrainConfig(
        ENV, targets={"slow": 1.0}, track=True, pool_start=0.5, pool_episodes=1, out_dir=beh / "halfcheetah"
    )
    assert cfg.level_work_dir("slow").name == "track-slow-pool0.5"  # never mixed with a plain run's snapshots
    pool = other_levels_pool(cfg, "slow")
    assert set(pool.source) == {"fast"} and len(pool) > 0
    with pytest.raises(ValueError, match="other levels"):
        lonely = BehaviourTrainConfig(ENV, targets={"x": 1.0}, track=True, pool_start=0.5, out_dir=tmp_path)
        other_levels_pool(lonely, "x")
