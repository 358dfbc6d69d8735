"""A PPO learner saved and loaded whole, a warm start from an actor-only snapshot, and a resumed commanded run."""

import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3.common.monitor import Monitor

from gmt.datagen.behaviour import load_behaviour, save_behaviour
from gmt.datagen.ppo import PPOPreset, export_actor, make_ppo
from gmt.datagen.ppo_state import learner_path, load_learner, save_learner, warm_start_actor
from gmt.datagen.train_commanded import CommandedConfig, SpeedCommand, train_commanded

ENV = "Hopper-v5"
TINY = PPOPreset(n_steps=64, batch_size=32, n_epochs=1, hidden_sizes=[8, 8], activation="tanh")


def _learner(seed: int, preset: PPOPreset = TINY):
    return make_ppo(lambda: Monitor(SpeedCommand(gym.make(ENV), [1.0, 2.0], 0.01, seed)), preset, seed)


def _states(model, venv) -> dict[str, np.ndarray]:
    out = {f"policy.{k}": v.numpy().copy() for k, v in model.policy.state_dict().items()}
    for i, st in model.policy.optimizer.state_dict()["state"].items():
        out |= {f"optimizer.{i}.{k}": torch.as_tensor(v).numpy().copy() for k, v in st.items()}
    for name in ("obs_rms", "ret_rms"):
        rms = getattr(venv, name)
        out |= {
            f"{name}.mean": np.array(rms.mean),
            f"{name}.var": np.array(rms.var),
            f"{name}.count": rms.count,
        }
    return out


def test_a_saved_learner_loads_whole_into_a_fresh_one(tmp_path):
    model, venv = _learner(0)
    model.learn(
        128
    )  # two updates: Adam's moments and the running statistics are no longer their initial values
    save_learner(tmp_path / "learner", model, venv)
    other, other_venv = _learner(1)
    saved, fresh = _states(model, venv), _states(other, other_venv)
    assert any(k not in fresh or not np.array_equal(fresh[k], v) for k, v in saved.items())

    assert load_learner(tmp_path / "learner", other, other_venv) == 128
    loaded = _states(other, other_venv)
    assert loaded.keys() == saved.keys()
    for key, value in saved.items():
        assert np.array_equal(loaded[key], value), key
    obs = venv.normalize_obs(np.ones((1, *venv.observation_space.shape), dtype=np.float32))
    assert np.array_equal(other_venv.normalize_obs(np.ones_like(obs)), obs)
    other.learn(64, reset_num_timesteps=False)  # the loaded optimizer steps on
    assert other.num_timesteps == 192


def test_a_learner_of_other_sizes_is_refused(tmp_path):
    model, venv = _learner(0)
    save_learner(tmp_path / "learner", model, venv)
    other, other_venv = _learner(0, PPOPreset(n_steps=64, batch_size=32, n_epochs=1, hidden_sizes=[16, 16]))
    with pytest.raises(ValueError, match="does not fit"):
        load_learner(tmp_path / "learner", other, other_venv)
    meta = json.loads((tmp_path / "learner.json").read_text())
    (tmp_path / "learner.json").write_text(json.dumps({**meta, "format": 99}))
    with pytest.raises(ValueError, match="format 99"):
        load_learner(tmp_path / "learner", model, venv)


def test_an_actor_only_snapshot_warm_starts_the_actor_and_observation_statistics(tmp_path):
    model, venv = _learner(0)
    model.learn(128)
    state, meta = export_actor(model, venv, ENV, "", TINY.hidden_sizes, TINY.activation)
    save_behaviour(tmp_path / "step_00000128", state, meta)
    other, other_venv = _learner(1)
    critic = {k: v.clone() for k, v in other.policy.state_dict().items() if "value" in k}

    assert warm_start_actor(tmp_path / "step_00000128", other, other_venv, 128) == 128
    obs = np.linspace(-1, 1, venv.observation_space.shape[0]).astype(np.float32)[None]
    with torch.no_grad():
        a = model.policy.get_distribution(torch.as_tensor(venv.normalize_obs(obs))).distribution
        b = other.policy.get_distribution(torch.as_tensor(other_venv.normalize_obs(obs))).distribution
    assert torch.allclose(a.mean, b.mean, atol=1e-6) and torch.allclose(a.stddev, b.stddev)
    for k, v in critic.items():  # the critic is not in an actor snapshot: it stays the fresh learner's
        assert torch.equal(other.policy.state_dict()[k], v), k
    assert other.num_timesteps == 128


def test_a_commanded_run_resumes_from_its_learner_and_keeps_its_records(tmp_path, capsys):
    work, out = tmp_path / "work", tmp_path / "out"
    base = dict(env_id=ENV, targets={"slow": 1.0, "fast": 2.0}, eval_every=64, eval_seeds=1, final_seeds=1,
                candidates=1, work_dir=work, out_dir=out, preset=TINY)  # fmt: skip
    train_commanded(CommandedConfig(**base, total_timesteps=128))
    assert sorted(p.name for p in work.glob("learner_*.safetensors")) == [
        "learner_00000064.safetensors",
        "learner_00000128.safetensors",
    ]
    first = load_behaviour(work / "step_00000128", gym.make(ENV).action_space).state_dict()

    with pytest.raises(ValueError, match="resume_from"):
        CommandedConfig(**base, total_timesteps=128, resume_from=128)
    train_commanded(CommandedConfig(**base, total_timesteps=256, resume_from=64))
    assert "resumed PPO at step 64" in capsys.readouterr().out
    records = json.loads((work / "records.json").read_text())
    assert [r["step"] for r in records] == [64, 128, 192, 256]  # the first run's 64 kept, 128 redone
    again = load_behaviour(work / "step_00000128", gym.make(ENV).action_space).state_dict()
    assert any(not torch.equal(first[k], again[k]) for k in first)  # redone by the resumed run
    assert learner_path(work, 256).with_suffix(".json").exists()


def test_resuming_from_a_step_without_files_is_refused_before_training(tmp_path):
    from typer.testing import CliRunner

    from gmt.datagen.cli import app

    work = tmp_path / "work"
    work.mkdir()
    base = [
        "commanded",
        "--env",
        ENV,
        "--target",
        "slow=1.0",
        "--target",
        "fast=2.2",
        "--work-dir",
        str(work),
    ]
    runner = CliRunner()
    res = runner.invoke(app, [*base, "--resume-from", "100"])
    assert res.exit_code == 2 and "no learner or snapshot at step 100" in res.output, res.output
    res = runner.invoke(app, [*base, "--resume-from", "100", "--select-only"])
    assert res.exit_code == 2 and "drop --select-only" in res.output, res.output
    res = runner.invoke(app, [*base, "--resume-from", "3000000", "--timesteps", "2000000"])
    assert res.exit_code == 2 and "resume_from must lie within" in res.output, res.output
    assert not any(work.iterdir())
