import gymnasium as gym
import numpy as np
import pytest
import torch

from model.data.behaviour import BehaviourMeta, RandomPolicy, load_behaviour, save_behaviour
from model.data.refine_behaviour import (
    FixedObsNorm,
    PoolStart,
    RefineConfig,
    TargetSpeedReward,
    refine,
    write_provenance,
)
from model.data.start_states import build_pool, start_from

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
    torch.manual_seed(seed)
    meta = BehaviourMeta(
        ENV, level, [256, 256], "relu", [0.5] * 17, [2.0] * 17, mean_speed=speed, train_step=7
    )
    sizes = [17, 256, 256, 6]
    state = {"log_std": torch.full((6,), -1.0)}
    for i in range(3):
        state[f"mean_net.{2 * i}.weight"] = 0.05 * torch.randn(sizes[i + 1], sizes[i])
        state[f"mean_net.{2 * i}.bias"] = 0.05 * torch.randn(sizes[i + 1])
    save_behaviour(folder / "halfcheetah" / level, state, meta)


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
    assert best["step"] in (0, 512, 1024)
    assert out.meta.level == "slow" and out.meta.extra["refined"]["refine_step"] == best["step"]
    assert out.meta.train_step == 7 + best["step"]
    path = write_provenance(cfg, best, 12.0)
    write_provenance(cfg, best, 12.0)
    text = path.read_text()
    assert text.count("<!-- refine:slow -->") == 1 and "gmt data refine --env HalfCheetah-v5" in text
