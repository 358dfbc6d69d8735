"""The speed-commanded behaviour agent: its training wrapper, commanded snapshots, and the switch measurement."""

import gymnasium as gym
import numpy as np
import pytest
import torch

from gmt.datagen.behaviour import BehaviourMeta, load_behaviour, save_behaviour
from gmt.datagen.train_commanded import CommandedConfig, SpeedCommand, cycle_schedule, play, play_schedule

ENV = "Hopper-v5"


def test_the_command_is_appended_tracked_and_changed():
    env = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=1.0, seed=0)
    assert env.observation_space.shape == (12,)  # Hopper's 11 + the command
    obs, _ = env.reset(seed=0)
    assert obs.shape == (12,) and obs[-1] in (1.0, 2.2) and obs[-1] == env.command
    seen = []
    for _ in range(4):
        before = env.command
        obs, reward, terminated, _, info = env.step(np.zeros(3, np.float32))
        v, fwd = info["x_velocity"], info["reward_forward"]
        base = info["reward_survive"] + info["reward_ctrl"]  # Hopper's reward without its forward term
        assert reward == pytest.approx(base + before - abs(v - before))  # tracked: the command of this step
        assert env.command != before and obs[-1] == env.command  # switch_prob 1: every step
        assert fwd == pytest.approx(v)
        seen.append(env.command)
        if terminated:
            break
    assert set(seen) == {1.0, 2.2}
    weighted = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=0.0, seed=0, track_weight=3.0)
    weighted.reset(seed=0)
    command = weighted.command
    _, reward, _, _, info = weighted.step(np.zeros(3, np.float32))
    base = info["reward_survive"] + info["reward_ctrl"]
    assert reward == pytest.approx(base + command - 3.0 * abs(info["x_velocity"] - command))
    braking = SpeedCommand(gym.make(ENV), [0.0, 0.5], switch_prob=0.0, seed=1, overspeed_weight=2.0)
    obs, _ = braking.reset(seed=0)
    over = 0
    for _ in range(20):
        command = braking.command
        _, reward, terminated, _, info = braking.step(np.ones(3, np.float32))
        v, base = info["x_velocity"], info["reward_survive"] + info["reward_ctrl"]
        assert reward == pytest.approx(base + command - abs(v - command) - 2.0 * max(0.0, v - command))
        over += v > command
        if terminated:
            break
    assert over > 0  # the overspeed term was exercised
    held = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=0.0, seed=0)
    held.reset(seed=0)
    first = held.command
    for _ in range(5):
        held.step(np.zeros(3, np.float32))
    assert held.command == first


def test_a_ceiling_docks_the_reward_per_metre_of_torso_height_above_it():
    with pytest.raises(ValueError, match="needs a ceiling"):
        SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=0.0, seed=0, ceiling_weight=1.0)
    with pytest.raises(ValueError, match="ceiling_weight"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, ceiling=1.0, ceiling_weight=-1.0)
    plain = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=0.0, seed=0)
    capped = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=0.0, seed=0, ceiling=1.0, ceiling_weight=4.0)
    plain.reset(seed=0), capped.reset(seed=0)
    docked = 0
    for _ in range(10):  # Hopper's torso starts at ~1.25 m: above the ceiling
        _, r_plain, done, _, _ = plain.step(np.zeros(3, np.float32))
        _, r_capped, _, _, _ = capped.step(np.zeros(3, np.float32))
        height = capped.unwrapped.data.body("torso").xpos[2]
        assert r_plain - r_capped == pytest.approx(4.0 * max(0.0, height - 1.0))
        docked += height > 1.0
        if done:
            break
    assert docked > 0


def test_an_entropy_bonus_overrides_only_the_presets_entropy():
    from dataclasses import replace

    from gmt.datagen.ppo import PRESETS

    cfg = CommandedConfig("Ant-v5", {"slow": 0.5, "fast": 1.0}, ent_coef=0.005)
    assert cfg.preset == replace(PRESETS["ant"], ent_coef=0.005)
    assert CommandedConfig("Ant-v5", {"slow": 0.5, "fast": 1.0}).preset == PRESETS["ant"]
    with pytest.raises(ValueError, match="ent_coef"):
        CommandedConfig("Ant-v5", {"slow": 0.5, "fast": 1.0}, ent_coef=-0.1)


def test_a_track_window_tracks_the_mean_speed_of_the_last_steps():
    env = SpeedCommand(
        gym.make(ENV), [0.0, 0.5], switch_prob=0.0, seed=1, overspeed_weight=2.0, track_window=3
    )
    env.reset(seed=0)
    speeds, differs = [], 0
    for _ in range(12):
        command = env.command
        _, reward, terminated, _, info = env.step(np.ones(3, np.float32))
        speeds.append(info["x_velocity"])
        v = float(np.mean(speeds[-3:]))  # the mean of the last 3 steps, fewer right after the reset
        base = info["reward_survive"] + info["reward_ctrl"]
        assert reward == pytest.approx(base + command - abs(v - command) - 2.0 * max(0.0, v - command))
        own = base + command - abs(speeds[-1] - command) - 2.0 * max(0.0, speeds[-1] - command)
        differs += reward != pytest.approx(own)
        if terminated:
            break
    assert differs > 0  # the window, not the step's own speed, was read
    env.reset(seed=1)
    _, reward, _, _, info = env.step(np.zeros(3, np.float32))  # a reset forgets the previous episode's speeds
    v, base = info["x_velocity"], info["reward_survive"] + info["reward_ctrl"]
    assert reward == pytest.approx(
        base + env.command - abs(v - env.command) - 2.0 * max(0.0, v - env.command)
    )
    with pytest.raises(ValueError, match="track_window"):
        SpeedCommand(gym.make(ENV), [0.0, 0.5], switch_prob=0.0, seed=1, track_window=0)


def _snapshot(path, seed: int) -> dict[str, torch.Tensor]:
    """A tiny commanded Hopper actor (11 observations + the command -> 8 -> 3), saved at `path`; its weights."""
    torch.manual_seed(seed)
    state = {
        "mean_net.0.weight": 0.1 * torch.randn(8, 12),
        "mean_net.0.bias": torch.zeros(8),
        "mean_net.2.weight": 0.1 * torch.randn(3, 8),
        "mean_net.2.bias": torch.zeros(3),
        "log_std": torch.zeros(3),
    }
    meta = BehaviourMeta(ENV, path.name, [8], "tanh", [0.0] * 12, [1.0] * 12, extra={"command": 1.0})
    save_behaviour(path, state, meta)
    return state


def test_a_commanded_snapshot_reads_its_command(tmp_path):
    env = gym.make(ENV)
    state = _snapshot(tmp_path / "slow", 0)
    policy = load_behaviour(tmp_path / "slow", env.action_space)
    obs = np.linspace(-0.5, 0.5, 11)
    expected = torch.tanh(
        torch.as_tensor(np.append(obs, 1.0), dtype=torch.float32) @ state["mean_net.0.weight"].T
    )
    expected = (expected @ state["mean_net.2.weight"].T).clamp(-1, 1).numpy()
    np.testing.assert_allclose(policy.act(obs), expected, rtol=1e-5, atol=1e-6)
    slow = policy.act(obs)
    policy.command = 2.2
    assert not np.allclose(policy.act(obs), slow)  # the command changes the action
    batch = policy.act(np.stack([obs, obs]))
    assert batch.shape == (2, 3)


class _Recorder:
    """A stand-in actor that stands still and records the target it was given at each step."""

    def __init__(self):
        self.target, self.seen = None, []

    def act(self, obs, rng=None):
        self.seen.append(self.target)
        return np.zeros(3, np.float32)


def test_play_switches_the_command_at_the_given_step():
    env = gym.make(ENV)
    rec = _Recorder()
    out = play(env, rec, [1.0, 2.2], switch_at=5, seed=0, rng=np.random.default_rng(0))
    assert rec.seen[:5] == [1.0] * 5 and set(rec.seen[5:]) <= {2.2}
    assert out["fell"] == (len(rec.seen) < 1000)  # a Hopper that does nothing falls over


def test_a_cycle_follows_the_protocol_and_is_measured_after_each_settle_in():
    assert cycle_schedule([1.0, 2.2], 300) == [(0, 1.0), (300, 2.2), (600, 1.0), (900, 2.2)]
    env = gym.make(ENV)
    rec = _Recorder()
    out = play_schedule(env, rec, [(0, 1.0), (3, 2.2), (6, 1.0)], seed=0, rng=None)
    assert rec.seen[:6] == [1.0, 1.0, 1.0, 2.2, 2.2, 2.2] and set(rec.seen[6:]) <= {1.0}
    assert len(out["speeds"]) == 3 and out["fell"] == (len(rec.seen) < 1000)
    env.reset(seed=0)  # the same episode again, its speeds recorded by hand
    speeds = []
    for _ in range(len(rec.seen)):
        _, _, terminated, _, info = env.step(np.zeros(3, np.float32))
        speeds.append(info["x_velocity"])
    assert out["speeds"][0] == pytest.approx(np.mean(speeds[0:3]))  # settle-in min(100, 3 // 4) = 0
    assert out["speeds"][1] == pytest.approx(np.mean(speeds[3:6]))


def test_commanded_levels_need_two_numeric_speeds():
    with pytest.raises(ValueError, match="at least two"):
        CommandedConfig(ENV, {"slow": 1.0})
    with pytest.raises(ValueError, match="numeric"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": "max"})
    with pytest.raises(ValueError, match="track_weight"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, track_weight=0.0)
    with pytest.raises(ValueError, match="overspeed_weight"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, overspeed_weight=-1.0)
    with pytest.raises(ValueError, match="cycle_every"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, cycle_every=1000)
    with pytest.raises(ValueError, match="track_window"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, track_window=0)


def test_a_named_snapshot_is_exported_instead_of_the_best_scored(tmp_path):
    import json

    from typer.testing import CliRunner

    from gmt.datagen.cli import app

    work, out = tmp_path / "work", tmp_path / "out"
    work.mkdir()
    for step in (100, 200):
        _snapshot(work / f"step_{step:08d}", step)
    records = [{"step": 100, "score": 9.0}, {"step": 200, "score": 1.0}]  # 200 scored best
    (work / "records.json").write_text(json.dumps(records))
    base = ["commanded", "--env", ENV, "--target", "slow=1.0", "--target", "fast=2.2", "--final-seeds", "1"]
    base += ["--work-dir", str(work), "--out-dir", str(out)]
    runner = CliRunner()

    res = runner.invoke(app, [*base, "--snapshot", "100"])  # training would overwrite the kept snapshots
    assert res.exit_code != 0 and "--select-only" in res.output
    res = runner.invoke(app, [*base, "--select-only", "--snapshot", "300"])
    assert res.exit_code != 0 and "no snapshot at step 300" in res.output

    res = runner.invoke(app, [*base, "--select-only", "--snapshot", "100"])
    assert res.exit_code == 0, res.output
    for level, command in (("slow", 1.0), ("fast", 2.2)):
        meta = json.loads((out / f"{level}.json").read_text())
        assert meta["train_step"] == 100 and meta["extra"]["command"] == command
    assert "step 100 was named by hand" in (out / "TRAINED_WITH.md").read_text()

    res = runner.invoke(app, [*base, "--select-only"])  # without a name, the best score wins
    assert res.exit_code == 0, res.output
    assert json.loads((out / "slow.json").read_text())["train_step"] == 200


def test_training_commands_can_be_drawn_from_a_range():
    env = SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=1.0, seed=0, command_range=(0.5, 2.5))
    assert env.observation_space.low[-1] == 0.5 and env.observation_space.high[-1] == 2.5
    obs, _ = env.reset(seed=0)
    seen = [env.command]
    for _ in range(30):
        obs, _, terminated, _, _ = env.step(np.zeros(3, np.float32))
        assert obs[-1] == env.command
        seen.append(env.command)
        if terminated:
            obs, _ = env.reset(seed=1)
            seen.append(env.command)
    assert all(0.5 <= c <= 2.5 for c in seen)
    assert len(set(seen)) > 10 and not set(seen) <= {1.0, 2.2}  # anywhere in the range, not only the levels
    with pytest.raises(ValueError, match="command_range"):
        SpeedCommand(gym.make(ENV), [1.0, 2.2], switch_prob=1.0, seed=0, command_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="command_range"):
        CommandedConfig(ENV, {"slow": 1.0, "fast": 2.2}, command_range=(1.2, 2.5))
