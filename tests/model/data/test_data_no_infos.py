"""Datasets recorded without infos (Minari's D4RL ports): x-velocity comes from the observations."""

import json
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from gmt.model.data.minari_io import Episode, load_dataset, write_dataset, x_velocity_obs_index


def _rollouts(env_id: str, speeds=(-1.0, -0.6, 0.6, 1.0), steps: int = 60) -> list[Episode]:
    """Short episodes at different mean speeds, with their `x_velocity` infos."""
    env = gym.make(env_id)
    rng = np.random.default_rng(0)
    episodes = []
    for i, bias in enumerate(speeds):
        obs, _ = env.reset(seed=i)
        o, a, r, vx = [obs], [], [], []
        for _ in range(steps):
            act = np.clip(rng.normal(bias, 0.5, env.action_space.shape), -1, 1).astype(np.float32)
            obs, rew, term, trunc, info = env.step(act)
            o.append(obs), a.append(act), r.append(rew), vx.append(info["x_velocity"])
            if term or trunc:
                break
        n = len(a)
        episodes.append(
            Episode(
                observations=np.asarray(o[:n], np.float64),
                actions=np.asarray(a),
                rewards=np.asarray(r, np.float32),
                terminated=bool(term),
                truncated=False,
                infos={"x_velocity": np.asarray(vx)},
                final_observation=np.asarray(o[n]),
                episode_id=i,
            )
        )
    return episodes, env


@pytest.mark.parametrize(
    "env_id, index", [("HalfCheetah-v5", 8), ("Hopper-v5", 5), ("Walker2d-v5", 8), ("Ant-v5", 13)]
)
def test_the_index_is_each_tasks_root_x_velocity(env_id, index):
    assert x_velocity_obs_index(env_id) == index
    assert x_velocity_obs_index(env_id, {"exclude_current_positions_from_observation": False}) > index
    episodes, _ = _rollouts(env_id, speeds=(0.0,), steps=40)
    ep = episodes[0]
    after = np.concatenate([ep.observations[1:], ep.final_observation[None]])  # [T, D]
    with np.errstate(invalid="ignore", divide="ignore"):  # constant entries (Ant's contact forces) give NaN
        corr = [np.corrcoef(after[:, j], ep.infos["x_velocity"])[0, 1] for j in range(after.shape[1])]
    assert int(np.nanargmax(corr)) == index  # of every entry, the best match of env.step's x_velocity


def test_a_dataset_without_infos_derives_x_velocity_from_the_next_observations(tmp_path):
    episodes, env = _rollouts("HalfCheetah-v5")
    bare = [Episode(**{**ep.__dict__, "infos": {}}) for ep in episodes]
    kw = dict(env_id="HalfCheetah-v5", observation_space=env.observation_space, action_space=env.action_space)
    write_dataset("t/halfcheetah/infos-v0", episodes, data_dir=tmp_path, **kw)
    write_dataset("t/halfcheetah/bare-v0", bare, data_dir=tmp_path, **kw)
    with_infos = load_dataset("t/halfcheetah/infos-v0", tmp_path)
    without = load_dataset("t/halfcheetah/bare-v0", tmp_path)
    raw = tmp_path / "t/halfcheetah/bare-v0/data/main_data.hdf5"
    import h5py

    with h5py.File(raw) as f:  # the layout of the D4RL ports: T + 1 observations, no infos
        ep0 = f["episode_0"]
        assert "infos" not in ep0 or len(ep0["infos"]) == 0
        assert len(ep0["observations"]) == len(ep0["actions"]) + 1
    for a, b in zip(with_infos.episodes, without.episodes, strict=True):
        derived, recorded = b.infos["x_velocity"], a.infos["x_velocity"]
        assert len(derived) == len(a)
        assert np.corrcoef(derived, recorded)[0, 1] > 0.9
        assert abs(derived.mean() - recorded.mean()) < 0.05 * (1 + abs(recorded.mean()))


def test_gmt_train_relabels_a_dataset_without_infos_by_the_observation_statistic(tmp_path):
    episodes, env = _rollouts("HalfCheetah-v5")
    bare = [Episode(**{**ep.__dict__, "infos": {}}) for ep in episodes]
    write_dataset(
        "t/halfcheetah/bare-v0",
        bare,
        env_id="HalfCheetah-v5",
        observation_space=env.observation_space,
        action_space=env.action_space,
        data_dir=tmp_path,
    )
    gmt = Path(sys.executable).parent / "gmt"
    out = tmp_path / "ckpt"
    args = ["train", "--dataset", str(tmp_path / "t/halfcheetah/bare-v0"), "--out", str(out), "--k", "2"]
    args += ["--steps", "3", "--batch-size", "4", "--context-length", "4", "--n-layer", "1", "--n-embd", "16"]
    args += ["--threads", "1", "--calibration-batches", "1", "--log-every", "1"]
    first = subprocess.run([str(gmt), *args], check=True, capture_output=True, text=True)
    assert "describe the previous weights" not in first.stderr
    (out / "eval.json").write_text("{}")  # an evaluation of these weights; training again makes it stale
    again = subprocess.run([str(gmt), *args, "--no-resume"], check=True, capture_output=True, text=True)
    assert "note: eval.json in" in again.stderr and "describe the previous weights" in again.stderr
    relabel = json.loads((out / "gmt.json").read_text())["relabel"]
    assert relabel["statistic"] == "mean_x_velocity" and relabel["k"] == 2
    means = [float(np.mean(ep.observations[1:, 8].tolist() + [ep.final_observation[8]])) for ep in bare]
    np.testing.assert_allclose(relabel["values"], means, rtol=1e-5)
