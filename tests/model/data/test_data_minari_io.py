import gymnasium as gym
import numpy as np
import pytest

from gmt.model.data.minari_io import Episode, load_dataset, write_dataset

OBS = gym.spaces.Box(-np.inf, np.inf, (3,), np.float64)
ACT = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)


def make_episodes(rng: np.random.Generator, lengths=(5, 3, 7)) -> list[Episode]:
    eps = []
    for i, n in enumerate(lengths):
        eps.append(
            Episode(
                observations=rng.normal(size=(n, 3)),
                actions=rng.uniform(-1, 1, (n, 2)).astype(np.float32),
                rewards=rng.normal(size=n).astype(np.float32),
                terminated=i == 1,
                truncated=i != 1,
                infos={"x_velocity": rng.normal(size=n), "x_position": rng.normal(size=n)},
                final_observation=rng.normal(size=3),
                episode_id=i,
            )
        )
    return eps


def test_round_trip_identical_arrays(tmp_path):
    eps = make_episodes(np.random.default_rng(0))
    path = write_dataset("test/thing/mixed-v0", eps, "HalfCheetah-v5", OBS, ACT, tmp_path)
    assert path == tmp_path / "test/thing/mixed-v0/data"
    ds = load_dataset("test/thing/mixed-v0", tmp_path)
    assert ds.dataset_id == "test/thing/mixed-v0"
    assert ds.env_id == "HalfCheetah-v5"
    assert ds.observation_space == OBS and ds.action_space == ACT
    assert ds.n_transitions == 15 and len(ds.episodes) == 3
    assert ds.info_keys == {"x_velocity", "x_position"}
    for a, b in zip(eps, ds.episodes, strict=True):
        np.testing.assert_array_equal(a.observations, b.observations)
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.rewards, b.rewards)
        np.testing.assert_array_equal(a.final_observation, b.final_observation)
        for k in a.infos:
            np.testing.assert_array_equal(a.infos[k], b.infos[k])
        assert (a.terminated, a.truncated, a.episode_id) == (b.terminated, b.truncated, b.episode_id)
        assert b.actions.dtype == np.float32 and b.rewards.dtype == np.float32


def test_fingerprint_is_stable_and_sensitive(tmp_path):
    eps = make_episodes(np.random.default_rng(0))
    write_dataset("test/a-v0", eps, "HalfCheetah-v5", OBS, ACT, tmp_path)
    first = load_dataset("test/a-v0", tmp_path).fingerprint
    assert load_dataset("test/a-v0", tmp_path).fingerprint == first
    eps[2].actions[0, 0] += 0.5
    write_dataset("test/a-v0", eps, "HalfCheetah-v5", OBS, ACT, tmp_path, overwrite=True)
    assert load_dataset("test/a-v0", tmp_path).fingerprint != first
    assert len(first) == 64


def test_load_by_path_env_var_and_missing(tmp_path, monkeypatch):
    eps = make_episodes(np.random.default_rng(1), lengths=(4,))
    write_dataset("test/b-v0", eps, "Hopper-v5", OBS, ACT, tmp_path)
    by_path = load_dataset(str(tmp_path / "test/b-v0"))
    assert by_path.dataset_id == "test/b-v0"
    monkeypatch.setenv("GMT_DATA_DIR", str(tmp_path))
    assert load_dataset("test/b-v0").fingerprint == by_path.fingerprint
    with pytest.raises(FileExistsError):
        write_dataset("test/b-v0", eps, "Hopper-v5", OBS, ACT)
    with pytest.raises(FileNotFoundError, match="test/nothing-v0"):
        load_dataset("test/nothing-v0")


def test_discrete_actions_load_as_int64(tmp_path):
    rng = np.random.default_rng(2)
    ep = Episode(rng.normal(size=(4, 3)), np.asarray([0, 3, 1, 2]), np.ones(4, np.float32), False, True, {},
                 None, 0)  # fmt: skip
    write_dataset("test/d-v0", [ep], "HalfCheetah-v5", OBS, gym.spaces.Discrete(4), tmp_path)
    back = load_dataset("test/d-v0", tmp_path).episodes[0]
    assert back.actions.dtype == np.int64
    np.testing.assert_array_equal(back.actions, [0, 3, 1, 2])
    assert back.infos == {}
    # A missing final observation is written as a copy of the last one.
    np.testing.assert_array_equal(back.final_observation, ep.observations[-1])
