"""The scripted Ant gait: its configuration, the joint and actuator layout it assumes, phase matching, snapshots
that load like any behaviour level, and collection from them."""

import json
import math
import re

import gymnasium as gym
import numpy as np
import pytest

from gmt.datagen.behaviour import list_snapshots, load_behaviour, save_behaviour
from gmt.datagen.collect import CollectConfig, collect
from gmt.datagen.gait import (
    ENV_ID,
    JOINT_SPEEDS,
    JOINTS,
    GaitConfig,
    GaitPolicy,
    gait_meta,
    gait_state,
    joint_targets,
    match_phase,
    write_levels,
)
from gmt.datagen.rollout import measure
from gmt.model.data.minari_io import load_dataset

STRIDE = dict(
    hip_amp=0.4,
    ankle_amp=0.3,
    hip_phase=[0.0, math.pi, 0.0, math.pi],
    ankle_phase=[1.0, 2.0, 3.0, 4.0],
    ankle_centre=0.8,
    yaw_gain=0.5,
    kp=1.2,
)


@pytest.fixture(scope="module")
def env():
    e = gym.make(ENV_ID)
    yield e
    e.close()


def _policy(env, cfg: GaitConfig, noise: float = 0.1) -> GaitPolicy:
    return GaitPolicy(
        gait_meta("x", cfg), np.full(8, math.log(noise)), env.action_space.low, env.action_space.high
    )


@pytest.mark.parametrize(
    "bad",
    [
        {"freq": 0.0},
        {"freq": float("nan")},
        {"hip_phase": [0.0, 1.0]},
        {"kp": 0.0},
        {"hip_amp": float("inf")},
        {"kd": -1.0},
    ],
)
def test_a_gait_config_refuses_what_cannot_walk(bad):
    with pytest.raises(ValueError):
        GaitConfig(**{"freq": 1.5, **STRIDE, **bad})


def test_with_freq_keeps_the_stride():
    cfg = GaitConfig(freq=1.5, **STRIDE)
    slow = cfg.with_freq(1.0)
    assert slow.freq == 1.0 and slow.hip_phase == cfg.hip_phase and slow.kp == cfg.kp
    assert cfg.freq == 1.5  # the original is untouched


def test_each_legs_torque_reaches_its_own_actuators(env):
    """Only leg 1's hip is off its target: only actuator 2 (hip_1 in Ant-v5's actuator order) answers."""
    still = GaitConfig(freq=1.0, hip_amp=0.0, ankle_amp=0.0, ankle_centre=0.0, yaw_gain=0.0, kp=2.0, kd=0.0)
    policy = _policy(env, still)
    obs = np.zeros(env.observation_space.shape)
    obs[1] = 1.0  # identity quaternion: heading 0
    obs[JOINTS.start] = 0.1  # hip_1
    policy.start_episode()
    action = policy.act(obs)
    expected = np.zeros(8, dtype=np.float32)
    expected[2] = -0.2
    np.testing.assert_allclose(action, expected, atol=1e-6)


def test_the_actuator_layout_matches_the_simulator(env):
    """Pushing each leg's hip and ankle actuators moves that leg's joints in the observation, and no other's."""
    from gmt.datagen.gait import ACTUATORS

    def joints_after(action: np.ndarray) -> np.ndarray:
        env.reset(seed=0)
        for _ in range(3):
            obs, *_ = env.step(action)
        return obs[JOINTS]

    idle = joints_after(np.zeros(8, dtype=np.float32))  # the legs settle under the torso's weight
    for leg, (hip, ankle) in enumerate(ACTUATORS):
        for actuator, joint in ((hip, 2 * leg), (ankle, 2 * leg + 1)):
            action = np.zeros(8, dtype=np.float32)
            action[actuator] = 1.0
            moved = np.abs(joints_after(action) - idle)
            assert int(np.argmax(moved)) == joint, (leg, actuator, moved)


def test_match_phase_recovers_the_stride_point():
    cfg = GaitConfig(freq=1.5, **STRIDE)
    omega = 2 * math.pi * cfg.freq
    for phase in (0.0, 1.0, 2.5, 4.0, 6.0):
        obs = np.zeros(105)
        obs[JOINTS] = joint_targets(cfg, phase)
        eps = 1e-5
        obs[JOINT_SPEEDS] = (
            omega * (joint_targets(cfg, phase + eps) - joint_targets(cfg, phase - eps)) / (2 * eps)
        )
        found = match_phase(cfg, obs)
        gap = abs((found - phase + math.pi) % (2 * math.pi) - math.pi)
        assert gap <= math.pi / 72 + 1e-9, (phase, found)


def test_an_episode_starts_at_phase_zero_from_rest_and_matched_when_moving(env):
    cfg = GaitConfig(freq=1.5, **STRIDE)
    policy = _policy(env, cfg)
    obs, _ = env.reset(seed=0)
    policy.start_episode()
    first = policy.act(obs)
    assert policy.phase == pytest.approx(2 * math.pi * 1.5 * 0.05)  # from rest: phase 0, then one step
    for _ in range(30):
        obs, *_ = env.step(policy.act(obs))
    moving = np.abs(obs[JOINT_SPEEDS]).mean() > cfg.rest_speed
    assert moving
    policy.start_episode()
    policy.act(obs)
    assert policy.phase == pytest.approx((match_phase(cfg, obs) + 2 * math.pi * 1.5 * 0.05) % (2 * math.pi))
    assert first.dtype == np.float32 and np.all(np.abs(first) <= 1.0)


def test_noise_only_with_a_generator(env):
    policy = _policy(env, GaitConfig(freq=1.5, **STRIDE), noise=0.2)
    obs, _ = env.reset(seed=1)
    policy.start_episode()
    a = policy.act(obs)
    policy.start_episode()
    b = policy.act(obs)
    policy.start_episode()
    c = policy.act(obs, np.random.default_rng(0))
    np.testing.assert_array_equal(a, b)
    assert np.abs(c - a).max() > 0.01


def test_a_gait_snapshot_loads_as_a_gait_and_refuses_foreign_tensors(env, tmp_path):
    import torch

    cfg = GaitConfig(freq=1.2, **STRIDE)
    save_behaviour(tmp_path / "ant" / "slow", gait_state(0.1), gait_meta("slow", cfg, mean_speed=0.4))
    save_behaviour(
        tmp_path / "ant" / "fast", gait_state(0.1), gait_meta("fast", cfg.with_freq(1.7), mean_speed=0.9)
    )
    assert [p.stem for p in list_snapshots(ENV_ID, tmp_path)] == ["slow", "fast"]
    policy = load_behaviour(tmp_path / "ant" / "fast.safetensors", env.action_space)
    assert isinstance(policy, GaitPolicy) and policy.cfg == cfg.with_freq(1.7)
    np.testing.assert_allclose(np.exp(policy.log_std), 0.1, rtol=1e-6)
    save_behaviour(tmp_path / "bad", {**gait_state(0.1), "w": torch.zeros(2)}, gait_meta("bad", cfg))
    with pytest.raises(ValueError, match="log_std only"):
        load_behaviour(tmp_path / "bad", env.action_space)
    with pytest.raises(ValueError):
        gait_state(0.0)


def test_levels_are_measured_written_and_collected_with_pool_starts(tmp_path):
    cfg = GaitConfig(freq=1.5, **STRIDE)
    written = write_levels(cfg, {"slow": 1.0, "fast": 1.5}, 0.1, tmp_path / "ant", "gmt data gait X", episodes=2,
                           max_steps=40)  # fmt: skip
    assert {p.name for p in written} == {"slow.json", "fast.json", "TRAINED_WITH.md"}
    meta = json.loads((tmp_path / "ant" / "fast.json").read_text())
    assert meta["extra"]["gait"]["freq"] == 1.5 and meta["extra"]["episodes"] == 2
    # The recorded speeds are the fast level's own measurement: its noisy episodes from reset seeds 20000+.
    fast = load_behaviour(tmp_path / "ant" / "fast", gym.make(ENV_ID).action_space)
    m = measure(gym.make(ENV_ID), fast, 2, 20_000, 40)
    assert (meta["mean_speed"], meta["std_speed"]) == (m["mean_speed"], m["std_speed"])
    assert meta["std_speed"] > 0 and meta["extra"]["mean_length"] == 40 and meta["extra"]["falls"] == 0
    provenance = tmp_path / "ant" / "TRAINED_WITH.md"
    assert "gmt data gait X" in provenance.read_text()
    provenance.write_text(provenance.read_text() + "\n## Notes (added by hand)\n\nkeep me\n")
    write_levels(cfg, {"slow": 1.0}, 0.1, tmp_path / "ant", "gmt data gait Y", episodes=1, max_steps=5)
    assert "gmt data gait Y" in provenance.read_text() and provenance.read_text().endswith("\n\nkeep me\n")
    result = collect(
        CollectConfig(
            env_id=ENV_ID,
            episodes_per_level=4,
            dataset_id="test/ant/gait-v0",
            data_dir=tmp_path / "data",
            behaviour_dir=tmp_path,
            max_steps=30,
            include_random=False,
            drop_stuck=False,
            pool_start={"slow": 0.5},
        ),
        progress=False,
    )
    assert result.episodes == 8 and set(result.levels) == {"slow", "fast"}
    assert result.levels["slow"]["pool_starts"] == 2
    episodes = load_dataset("test/ant/gait-v0", tmp_path / "data").episodes
    first_speeds = [float(np.abs(ep.observations[0][JOINT_SPEEDS]).mean()) for ep in episodes]
    # Levels are stored in order of measured speed; slow's first two episodes start mid-stride in the fast
    # level's states, every other episode from rest.
    first = 4 * list(result.levels).index("slow")
    pooled = first_speeds[first : first + 2]
    assert min(pooled) > 3 * max(first_speeds[:first] + first_speeds[first + 2 :])


def test_the_shipped_ant_levels_walk_forward_at_their_measured_speeds(env):
    """behaviour/ant: the levels are ordered by speed, and a deterministic episode of each moves forward near its
    measured speed (over 400 steps: the gait's 100-step means ripple by about 0.1 m/s, the levels' spacing)."""
    paths = list_snapshots(ENV_ID)
    policies = [load_behaviour(p, env.action_space) for p in paths]
    assert all(isinstance(p, GaitPolicy) for p in policies)
    speeds = []
    for policy in policies:
        obs, _ = env.reset(seed=3)
        policy.start_episode()
        v = []
        for _ in range(500):
            obs, _, terminated, _, info = env.step(policy.act(obs))
            assert not terminated
            v.append(info["x_velocity"])
        speeds.append(float(np.mean(v[100:])))
        assert abs(speeds[-1] - policy.meta.mean_speed) < 0.25 * policy.meta.mean_speed
    assert speeds == sorted(speeds) and speeds[0] > 0.1


def test_the_speed_loop_moves_the_frequency_against_the_speed_error(env):
    cfg = GaitConfig(freq=1.5, **STRIDE, target_speed=0.6, speed_gain=2.0, speed_ki=0.1, speed_alpha=1.0,
                     integral_limit=0.15, freq_range=(1.0, 2.0), ff_slope=1.0)  # fmt: skip
    policy = _policy(env, cfg)
    obs = np.zeros(105)
    obs[1] = 1.0
    policy.start_episode()
    obs[13] = 0.5  # 0.1 m/s too slow: 1.5 + 2 * 0.1 + 0.1 * 0.1
    policy.act(obs)
    assert policy.freq == pytest.approx(1.71)
    obs[13] = 2.0  # far too fast: the integral is bounded, the frequency clipped to the range's floor
    for _ in range(5):
        policy.act(obs)
    assert policy.freq == 1.0 and policy.integral == pytest.approx(-0.15)
    policy.start_episode()
    assert policy.integral == 0.0 and policy.speed is None
    policy.target = 0.8  # a new target moves the stride by ff_slope as well
    assert policy.command == 0.8 and policy.cfg.freq == pytest.approx(1.7)
    open_loop = _policy(env, GaitConfig(freq=1.5, **STRIDE))
    open_loop.target = 1.2  # without a loop the command is the frequency
    assert open_loop.cfg.freq == 1.2 and open_loop.command == 1.2
    with pytest.raises(ValueError):
        GaitConfig(freq=1.5, **STRIDE, freq_range=(2.0, 1.0))


def test_gmt_data_gait_refuses_bad_input_and_writes_measured_levels(tmp_path):
    from typer.testing import CliRunner

    from gmt.service.cli import app

    runner = CliRunner()
    stride = tmp_path / "stride.json"
    stride.write_text(json.dumps({"gait": {"freq": 1.5, **STRIDE}}))
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"gait": {"freq": -1.0, **STRIDE}}))
    out = tmp_path / "ant"
    cases = [
        ([str(tmp_path / "missing.json")], "cannot read"),
        ([str(broken)], "is not a gait"),
        ([str(stride)], "names no levels"),
        ([str(stride), "--level", "slow=fast"], "LEVEL=HZ"),
        ([str(stride), "--level", "slow=1.2", "--target", "fast=0.8"], "needs one of the levels"),
        ([str(stride), "--level", "slow=1.2", "--noise", "0"], "--noise > 0"),
    ]
    for args, message in cases:
        result = runner.invoke(app, ["data", "gait", *args, "--out-dir", str(out)])
        text = " ".join(re.sub(r"[│╭╮╰╯─]", " ", result.output).split())  # unwrap the error box
        assert result.exit_code == 2 and message in text, (args, result.output)
    assert not out.exists()
    result = runner.invoke(
        app,
        ["data", "gait", str(stride), "--level", "slow=1.2", "--target", "slow=0.5", "--episodes", "1",
         "--out-dir", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "slow.json").read_text())
    assert meta["extra"]["gait"]["target_speed"] == 0.5 and meta["extra"]["gait"]["freq"] == 1.2
    assert "slow: " in result.output and "| slow | 1.2 | 0.5 |" in (out / "TRAINED_WITH.md").read_text()
