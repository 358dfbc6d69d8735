"""`tiny_checkpoint` builds HalfCheetah-v5 models where MuJoCo is missing (a GPU machine running the engine's tests)
from spaces that must be the simulator's own."""

import gymnasium as gym
import pytest

from gmt.model import fixtures


def test_the_known_halfcheetah_spaces_are_the_simulators():
    env = gym.make("HalfCheetah-v5")
    try:
        assert fixtures._HALFCHEETAH_SPACES == (env.observation_space, env.action_space)
    finally:
        env.close()


def test_without_mujoco_halfcheetah_falls_back_to_its_known_spaces_and_other_ids_still_fail(monkeypatch):
    def no_simulator(env_id, **kwargs):
        raise gym.error.DependencyNotInstalled("MuJoCo is not installed")

    monkeypatch.setattr(fixtures.gym, "make", no_simulator)
    ckpt = fixtures.tiny_checkpoint()
    assert ckpt.config.obs_shape == (17,) and ckpt.config.act_dim == 6
    with pytest.raises(gym.error.DependencyNotInstalled):
        fixtures.tiny_checkpoint(env_id="Hopper-v5")
