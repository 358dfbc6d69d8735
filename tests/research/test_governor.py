"""The speed governor around a commanded actor (research/governor.py) and governed snapshots."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

from gmt.datagen.behaviour import BehaviourMeta, BehaviourPolicy, load_behaviour, save_behaviour
from gmt.datagen.rollout import rollout
from research.governor import GovernedPolicy, GovernorConfig, SpeedGovernor, write_governed

ENV = "Hopper-v5"
VX = 5  # Hopper's x-velocity entry


def _obs(speed: float) -> np.ndarray:
    obs = np.zeros(11)
    obs[VX] = speed
    return obs


def test_the_governor_commands_against_the_speed_error_within_the_range():
    cfg = GovernorConfig(VX, (0.5, 2.5), window=2, kp=1.0, ki=0.0)
    gov = SpeedGovernor(cfg, target=1.0)
    assert gov.command(_obs(1.0)) == pytest.approx(1.0)  # on target: the target itself
    assert gov.command(_obs(1.4)) == pytest.approx(1.0 + (1.0 - 1.2))  # mean of the last 2 speeds is 1.2
    assert gov.command(_obs(3.0)) == 0.5  # far too fast: clipped to the range's floor
    gov.target = 2.4
    assert gov.command(_obs(0.0)) == 2.5  # far too slow: the ceiling
    gov.reset()
    assert gov.command(_obs(2.5)) == pytest.approx(2.4 - 0.1)  # the window forgot the old speeds
    with pytest.raises(ValueError, match="one observation"):
        gov.command(np.zeros((2, 11)))


def test_the_integral_removes_a_steady_bias_and_does_not_wind_up_while_clipped():
    cfg = GovernorConfig(VX, (0.5, 2.5), window=10, kp=0.5, ki=0.02, integral_limit=0.5)

    def run(gov: SpeedGovernor, steps: int, bias: float, speed: float = 1.0) -> float:
        for _ in range(steps):  # a plant that runs `bias` slower than its command, with some lag
            speed = 0.8 * speed + 0.2 * (gov.command(_obs(speed)) - bias)
        return speed

    gov = SpeedGovernor(cfg, target=1.0)
    assert run(gov, 2000, bias=0.3) == pytest.approx(1.0, abs=1e-3)  # the integral closes the gap
    assert gov.integral == pytest.approx(0.3, abs=1e-3)
    p_only = SpeedGovernor(GovernorConfig(VX, (0.5, 2.5), window=10, kp=0.5, ki=0.0), target=1.0)
    assert run(p_only, 2000, bias=0.3) < 0.85  # without it a bias stays
    saturated = SpeedGovernor(cfg, target=1.0)
    for _ in range(200):
        assert saturated.command(_obs(5.0)) == 0.5  # clipped every step ...
    assert saturated.integral == 0.0  # ... so nothing was integrated
    with pytest.raises(ValueError, match="command_range"):
        GovernorConfig(VX, (2.0, 1.0))
    with pytest.raises(ValueError, match="window"):
        GovernorConfig(VX, (0.5, 2.5), window=0)
    with pytest.raises(ValueError, match=">= 0"):
        GovernorConfig(VX, (0.5, 2.5), ki=-1.0)


def _commanded_actor(path, obs_dim=11, hidden=8):
    torch.manual_seed(0)
    state = {
        "mean_net.0.weight": 0.3 * torch.randn(hidden, obs_dim + 1),
        "mean_net.0.bias": torch.zeros(hidden),
        "mean_net.2.weight": 0.3 * torch.randn(3, hidden),
        "mean_net.2.bias": torch.zeros(3),
        "log_std": torch.zeros(3),
    }
    meta = BehaviourMeta(ENV, "slow", [hidden], "tanh", [0.0] * 12, [1.0] * 12, extra={"command": 1.0})
    save_behaviour(path, state, meta)
    return path


def test_governed_levels_steer_the_actor_by_their_target(tmp_path):
    env = gym.make(ENV)
    source = _commanded_actor(tmp_path / "actor")
    cfg = GovernorConfig(VX, (0.5, 2.5), window=5, kp=1.0, ki=0.01)
    written = write_governed(
        source, {"slow": 1.0, "fast": 2.0}, cfg, tmp_path / "levels", "python -m research.governor levels ..."
    )
    assert [p.name for p in written] == ["slow", "fast"]
    meta = json.loads((tmp_path / "levels" / "fast.json").read_text())
    assert meta["extra"]["command"] == 2.0 and meta["extra"]["governor"] == cfg.to_json()
    assert "python -m research.governor levels ..." in (tmp_path / "levels" / "GOVERNED_WITH.md").read_text()
    slow = load_behaviour(tmp_path / "levels" / "slow", env.action_space)
    plain = load_behaviour(source, env.action_space)
    assert isinstance(slow, GovernedPolicy) and isinstance(plain, BehaviourPolicy)
    assert slow.target == 1.0 and plain.target == 1.0
    fast_obs = _obs(2.0)
    plain.command = 0.5  # the governor's first command at 2 m/s: 1.0 + (1.0 - 2.0), clipped to the floor
    np.testing.assert_allclose(slow.act(fast_obs), plain.act(fast_obs), rtol=1e-6)
    assert slow.command == 0.5
    slow.target = 2.0
    assert slow.governor.target == 2.0
    with pytest.raises(ValueError, match="one observation"):
        slow.act(np.stack([fast_obs, fast_obs]))
    # Each episode starts afresh: the same seed gives the same actions twice in a row.
    a = rollout(env, slow, seed=3, rng=np.random.default_rng(0), max_steps=40)
    b = rollout(env, slow, seed=3, rng=np.random.default_rng(0), max_steps=40)
    np.testing.assert_array_equal(a.actions, b.actions)
    with pytest.raises(ValueError, match="outside the command range"):
        write_governed(source, {"slow": 0.2, "fast": 2.0}, cfg, tmp_path / "bad", "")
    with pytest.raises(ValueError, match="not a commanded snapshot"):
        meta = BehaviourMeta(ENV, "x", [8], "tanh", [0.0] * 11, [1.0] * 11)
        save_behaviour(tmp_path / "uncommanded", {"log_std": torch.zeros(3)}, meta)
        write_governed(tmp_path / "uncommanded", {"slow": 1.0}, cfg, tmp_path / "bad", "")


def test_governed_levels_are_listed_slowest_target_first(tmp_path):
    from gmt.datagen.behaviour import list_snapshots

    source = _commanded_actor(tmp_path / "actor")
    cfg = GovernorConfig(VX, (0.5, 2.5))
    write_governed(source, {"walk": 1.0, "amble": 1.5, "run": 2.0}, cfg, tmp_path / "hopper", "")
    assert [p.stem for p in list_snapshots(ENV, tmp_path)] == ["walk", "amble", "run"]


def test_governed_levels_are_collected_through_the_research_module(tmp_path):
    from typer.testing import CliRunner

    from gmt.model.data.minari_io import load_dataset
    from research.governor import app

    source = _commanded_actor(tmp_path / "actor")
    write_governed(
        source, {"slow": 1.0, "fast": 2.0}, GovernorConfig(VX, (0.5, 2.5)), tmp_path / "beh" / "hopper", ""
    )
    args = ["collect", "--env", ENV, "--no-random", "--behaviour-dir", str(tmp_path / "beh"), "--episodes-per-level",
            "2", "--max-steps", "20", "--keep-falls", "--keep-stuck", "--out-id", "t/hopper/governed-v0", "--data-dir", str(tmp_path / "data")]  # fmt: skip
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    episodes = load_dataset("t/hopper/governed-v0", tmp_path / "data").episodes
    assert len(episodes) == 4
