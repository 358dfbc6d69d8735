"""Local environments are made from the model's spec, refused when their spaces differ, filmed by a camera that
follows the agent."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from gmt.common.envs import VIDEO_SIZE, SpaceMismatch, describe_space, make_env
from gmt.common.spaces import space_to_dict
from gmt.common.spec import ModelInfo

PONG_ACTIONS = {"type": "discrete", "n": 6, "shape": []}
PONG_FRAMES = {"type": "box", "shape": [210, 160, 3], "dtype": "uint8", "low": None, "high": None}


def spec(env_id: str, obs: dict, act: dict) -> ModelInfo:
    return ModelInfo("m", env_id, obs, act, context_length=5, statistic="return")


def test_atari_spec_of_raw_frames_gets_the_raw_game():
    env = make_env(spec("ALE/Pong-v5", PONG_FRAMES, {"type": "discrete", "n": 6, "shape": []}), max_steps=3)
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (210, 160, 3) and env.action_space.n == 6
        assert env.step(0)[0].shape == (210, 160, 3)
    finally:
        env.close()


def test_atari_frames_follow_the_specs_declared_preprocessing():
    frames = {"type": "box", "shape": [2, 48, 48], "dtype": "uint8", "low": None, "high": None}
    prep = {"screen_size": 48, "stack": 2, "frame_skip": 2, "noop_max": 0, "repeat_action_probability": 0.0}
    s = ModelInfo(
        "m", "ALE/Pong-v5", frames, PONG_ACTIONS, context_length=5, statistic="return", preprocessing=prep
    )
    env = make_env(s, max_steps=3)
    try:
        prep = env
        while not isinstance(prep, gym.wrappers.AtariPreprocessing):
            prep = prep.env
        assert prep.frame_skip == 2 and prep.noop_max == 0 and prep.screen_size == (48, 48)
        assert env.unwrapped.ale.getFloat("repeat_action_probability") == 0.0
        assert env.reset(seed=0)[0].shape == (2, 48, 48)
    finally:
        env.close()


def test_atari_with_other_action_count_is_refused():
    with pytest.raises(SpaceMismatch, match=r"action space Discrete\(6\) of ALE/Pong-v5 vs Discrete\(4\)"):
        make_env(spec("ALE/Pong-v5", PONG_FRAMES, {"type": "discrete", "n": 4, "shape": []}))


def test_time_limit_is_the_episode_length():
    obs17 = {"type": "box", "shape": [17], "dtype": "float64"}
    act6 = {"type": "box", "shape": [6], "dtype": "float32"}
    env = make_env(spec("HalfCheetah-v5", obs17, act6), max_steps=3)
    env.reset(seed=0)
    truncated = [env.step(env.action_space.sample())[3] for _ in range(3)]
    env.close()
    assert truncated == [False, False, True]


def test_describe_space():
    assert describe_space({"type": "discrete", "n": 6}) == "Discrete(6)"
    assert describe_space({"type": "box", "shape": [17], "dtype": "float64"}) == "Box(float64, shape=[17])"


def _agent_share(frame: np.ndarray) -> float:
    """Share of a frame's pixels in the agents' tan / pink colours (floor and sky are grey, green or blue)."""
    rgb = frame.astype(int)
    return float(((rgb[..., 0] - rgb[..., 2]) > 40).mean())


def _frame_at(env: gym.Env, x: float) -> np.ndarray:
    u = env.unwrapped
    qpos = u.data.qpos.copy()
    qpos[0] = x  # the root's forward position
    u.set_state(qpos, u.data.qvel.copy())
    return env.render()


@pytest.mark.parametrize("env_id", ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5"])
def test_videos_follow_the_agent_where_a_fixed_camera_loses_it(env_id):
    local = gym.make(env_id)
    s = spec(env_id, space_to_dict(local.observation_space), space_to_dict(local.action_space))
    local.close()
    width, height = VIDEO_SIZE
    tracked = make_env(s, render=True)
    # Gymnasium's default camera, as gmt run used it
    fixed = gym.make(env_id, render_mode="rgb_array", width=width, height=height)
    try:
        for env in (tracked, fixed):
            env.reset(seed=0)
        start = _agent_share(_frame_at(tracked, 0.0))
        assert start > 0.003 and _agent_share(_frame_at(fixed, 0.0)) > 0.002  # both see it at the start
        far = 30.0  # ~600 steps at 1 m/s (HalfCheetah's dt is 0.05 s)
        assert _agent_share(_frame_at(tracked, far)) > 0.5 * start
        assert _agent_share(_frame_at(fixed, far)) < 0.0005  # the fixed camera lost it
    finally:
        tracked.close()
        fixed.close()


def test_mujocos_settotalmass_notice_is_not_printed_and_other_warnings_still_surface(tmp_path):
    """MuJoCo prints (from C, to stderr and MUJOCO_LOG.TXT) a deprecation notice for Gymnasium's v5 model files on
    every environment made: known noise, dropped; any other MuJoCo warning becomes a Python RuntimeWarning."""
    import subprocess
    import sys

    code = """
import warnings, mujoco
from gmt.common.envs import make_env
from gmt.common.spec import ModelInfo
obs = {"type": "box", "shape": [17], "dtype": "float64"}
act = {"type": "box", "shape": [6], "dtype": "float32"}
make_env(ModelInfo("m", "HalfCheetah-v5", obs, act, context_length=5, statistic="return"), max_steps=3).close()
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    mujoco.get_mju_user_warning()("something else")
print([str(w.message) for w in seen])
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert "settotalmass" not in out.stderr + out.stdout and not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert out.stdout.strip() == "['MuJoCo: something else']"
