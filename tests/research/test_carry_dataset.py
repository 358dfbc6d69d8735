"""research/carry_dataset.py: a packed frame-stack dataset unpacks to the same arrays, and loads with the same
fingerprint."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from research.carry_dataset import from_stream, is_stacked, pack, to_stream, unpack


def stacks(frames: np.ndarray, S: int) -> np.ndarray:
    """[T + S - 1, H, W] frames -> [T, S, H, W] stacks, written the plain way."""
    return np.stack([frames[t : t + S] for t in range(len(frames) - S + 1)])


def test_stream_round_trip_and_detection():
    rng = np.random.default_rng(0)
    obs = stacks(rng.integers(0, 255, (12, 5, 6), dtype=np.uint8), 4)  # [9, 4, 5, 6]
    assert is_stacked(obs)
    assert to_stream(obs).shape == (12, 5, 6)
    assert np.array_equal(from_stream(to_stream(obs), 4), obs)
    broken = obs.copy()
    broken[3, 0, 0, 0] ^= 1  # one pixel differs from the step before's newer frame
    assert not is_stacked(broken)
    assert not is_stacked(rng.normal(size=(9, 17)))  # flat vectors are never stacks


def write_fake(path, episodes):
    """A Minari-shaped HDF5 file: episode groups with attributes, observations, actions and nested infos."""
    (path / "data").mkdir(parents=True)
    (path / "data" / "metadata.json").write_text(json.dumps({"total_episodes": len(episodes)}))
    with h5py.File(path / "data" / "main_data.hdf5", "w") as f:
        for i, obs in enumerate(episodes):
            g = f.create_group(f"episode_{i}")
            g.attrs.update({"id": i, "policy": f"p{i % 2}", "return": float(i) / 3})
            g.create_dataset("observations", data=obs, compression="gzip")
            g.create_dataset("actions", data=np.arange(len(obs) - 1) % 4, compression="gzip")
            g.create_group("infos").create_dataset("lives", data=np.full(len(obs), 5.0))


def read_all(path):
    out = {}
    with h5py.File(path / "data" / "main_data.hdf5", "r") as f:

        def visit(name, obj):
            out[name] = dict(obj.attrs) if isinstance(obj, h5py.Group) else (obj[()], dict(obj.attrs))

        f.visititems(visit)
    return out


def test_pack_unpack_gives_identical_hdf5_contents(tmp_path):
    rng = np.random.default_rng(1)
    episodes = [stacks(rng.integers(0, 4, (n + 3, 8, 8), dtype=np.uint8), 4) for n in (30, 7, 55)]
    episodes.append(rng.integers(0, 255, (9, 4, 8, 8), dtype=np.uint8))  # not a stack: stored whole
    write_fake(tmp_path / "src", episodes)
    index = pack(tmp_path / "src", tmp_path / "pack", chunk=2)
    assert [e["stack"] for e in index["episodes"].values()] == [4, 4, 4, 0]
    assert len(list((tmp_path / "pack").glob("frames-*.xz"))) == 2
    assert unpack(tmp_path / "pack", tmp_path / "dst", workers=2) == 4
    a, b = read_all(tmp_path / "src"), read_all(tmp_path / "dst")
    assert a.keys() == b.keys()
    for name, v in a.items():
        if isinstance(v, tuple):
            assert np.array_equal(v[0], b[name][0]) and v[0].dtype == b[name][0].dtype, name
            assert v[1] == b[name][1], name
        else:
            assert v.keys() == b[name].keys() and all(v[k] == b[name][k] for k in v), name
    assert (tmp_path / "dst" / "data" / "metadata.json").read_text() == (
        tmp_path / "src" / "data" / "metadata.json"
    ).read_text()


def test_a_real_minari_dataset_keeps_its_fingerprint(tmp_path):
    gym = pytest.importorskip("gymnasium")
    from gmt.model.data.minari_io import Episode, load_dataset, write_dataset

    rng = np.random.default_rng(2)
    eps = []
    for i, n in enumerate((20, 13)):
        obs = stacks(rng.integers(0, 255, (n + 4, 6, 6), dtype=np.uint8), 4)  # T + 1 stacks
        eps.append(
            Episode(
                observations=obs[:-1],
                actions=rng.integers(0, 3, n).astype(np.int64),
                rewards=rng.random(n).astype(np.float32),
                terminated=i == 0,
                truncated=i == 1,
                infos={},
                final_observation=obs[-1],
                episode_id=i,
            )
        )
    space = gym.spaces.Box(0, 255, (4, 6, 6), np.uint8)
    root = tmp_path / "root"
    write_dataset(
        "test/stack/tiny-v0",
        eps,
        observation_space=space,
        action_space=gym.spaces.Discrete(3),
        env_id=None,
        data_dir=root,
    )
    before = load_dataset("test/stack/tiny-v0", data_dir=root)
    pack(root / "test" / "stack" / "tiny-v0", tmp_path / "pack")
    out = tmp_path / "root2"
    unpack(tmp_path / "pack", out / "test" / "stack" / "tiny-v0")
    after = load_dataset("test/stack/tiny-v0", data_dir=out)
    assert after.fingerprint == before.fingerprint
    assert np.array_equal(after.episodes[1].observations, before.episodes[1].observations)
