"""`gmt data import`: one's own episodes (.npz files, a Minari dataset) checked and written as a Minari dataset;
every problem named by file and field, nothing written then."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from typer.testing import CliRunner

from gmt.common.episode_files import EpisodeWriter
from gmt.model.data.importer import LAYOUT_KEY, ImportProblem, import_data
from gmt.model.data.minari_io import load_dataset


def _cartpole_files(folder, episodes=3):
    env, writer, rng = gym.make("CartPole-v1"), EpisodeWriter(folder), np.random.default_rng(0)
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        writer.reset(obs)
        while True:
            action = int(rng.integers(2))
            obs, reward, term, trunc, info = env.step(action)
            if writer.step(action, obs, reward, term, trunc, {"angle": float(obs[2]), "note": "text"}):
                break
    return sorted(folder.glob("*.npz"))


def test_the_writers_files_import_as_the_episodes_they_recorded(tmp_path):
    files = _cartpole_files(tmp_path / "eps")
    rep = import_data(tmp_path / "eps", "t/cartpole/own-v0", "CartPole-v1", tmp_path / "data")
    assert (rep.kind, rep.episodes, rep.info_keys) == ("npz", 3, ["angle"])
    ds = load_dataset("t/cartpole/own-v0", tmp_path / "data")
    assert ds.env_id == "CartPole-v1" and isinstance(ds.action_space, gym.spaces.Discrete)
    for f, ep in zip(files, ds.episodes, strict=True):
        z = np.load(f)
        np.testing.assert_array_equal(ep.observations, z["observations"][:-1])
        np.testing.assert_array_equal(ep.final_observation, z["observations"][-1])
        np.testing.assert_array_equal(ep.actions, z["actions"])
        np.testing.assert_allclose(ep.infos["angle"], z["observations"][1:, 2], rtol=1e-6)
        assert ep.terminated == bool(z["terminations"][-1])
    inferred = import_data(tmp_path / "eps", "t/cartpole/bare-v0", None, tmp_path / "data")
    assert inferred.action_space == "Discrete(2)" and inferred.env_id == "unknown"
    again = import_data("t/cartpole/own-v0", "t/cartpole/copy-v0", None, tmp_path / "data")  # a Minari source
    assert (
        again.kind == "minari"
        and load_dataset("t/cartpole/copy-v0", tmp_path / "data").fingerprint == ds.fingerprint
    )


def _write(path, **arrays):
    base = {"observations": np.zeros((4, 3)), "actions": np.zeros((3, 2), np.float32), "rewards": np.ones(3)}
    np.savez(path, **{k: v for k, v in {**base, **arrays}.items() if v is not None})


@pytest.mark.parametrize(
    ("arrays", "named"),
    [
        ({"rewards": np.ones(2)}, "'rewards' has shape (2,), expected (3,)"),
        ({"observations": np.zeros((7, 3))}, "'observations' has 7 steps, expected 3 or 4"),
        ({"actions": None}, "no 'actions' array"),
        ({"rewards": np.array([1.0, np.nan, 1.0])}, "'rewards' has a NaN or infinity at step 1"),
        ({"observations": np.array([[0, 0, 0]] * 2 + [[0, np.inf, 0]] * 2)}, "'observations' has a NaN or infinity at step 2"),
        ({"info.speed": np.ones(5)}, "'info.speed' has shape (5,)"),
        ({"truncations": np.ones(2, bool)}, "'truncations' has shape (2,)"),
        ({"observations": np.array(["a"] * 4)}, "'observations' holds <U1"),
    ],
)  # fmt: skip
def test_a_bad_file_is_named_with_its_field_and_nothing_is_written(tmp_path, arrays, named):
    (tmp_path / "eps").mkdir()
    _write(tmp_path / "eps" / "a.npz")
    _write(tmp_path / "eps" / "b.npz", **arrays)
    with pytest.raises(ImportProblem) as e:
        import_data(tmp_path / "eps", "t/x/y-v0", None, tmp_path / "data")
    assert str(e.value).startswith("b.npz: ") and named in str(e.value)
    assert not (tmp_path / "data" / "t/x/y-v0").exists()


def test_data_that_does_not_fit_the_environment_is_refused(tmp_path):
    (tmp_path / "eps").mkdir()
    _write(tmp_path / "eps" / "a.npz")
    with pytest.raises(
        ImportProblem, match=r"a.npz: field 'observations' has shape \(3,\) per step, CartPole-v1 \(4,\)"
    ):
        import_data(tmp_path / "eps", "t/x/y-v0", "CartPole-v1", tmp_path / "data")
    _write(tmp_path / "eps" / "a.npz", observations=np.zeros((4, 4)), actions=np.array([0, 1, 2]))
    with pytest.raises(ImportProblem, match=r"'actions' has 0..2, outside Discrete\(2\)"):
        import_data(tmp_path / "eps", "t/x/y-v0", "CartPole-v1", tmp_path / "data")


def test_dict_observations_are_flattened_with_their_layout_recorded(tmp_path):
    import json

    (tmp_path / "eps").mkdir()
    obs = {"observations.pos": np.arange(8.0).reshape(4, 2), "observations.cam": np.ones((4, 2, 2))}
    _write(tmp_path / "eps" / "a.npz", observations=None, **obs)
    rep = import_data(tmp_path / "eps", "t/dict/d-v0", None, tmp_path / "data")
    ep = load_dataset("t/dict/d-v0", tmp_path / "data").episodes[0]
    assert ep.observations.shape == (3, 6)  # cam (4 values) then pos (2): sorted keys
    np.testing.assert_array_equal(ep.observations[:, 4:], obs["observations.pos"][:3])
    layout = json.loads((rep.path / "metadata.json").read_text())[LAYOUT_KEY]
    assert layout == [
        {"key": "cam", "shape": [2, 2], "start": 0, "end": 4},
        {"key": "pos", "shape": [2], "start": 4, "end": 6},
    ]


def test_the_import_command_reports_or_refuses_in_one_line(tmp_path, monkeypatch):
    from gmt.service.cli import app

    monkeypatch.setenv("GMT_DATA_DIR", str(tmp_path / "data"))
    _cartpole_files(tmp_path / "eps", episodes=2)
    run = CliRunner().invoke
    r = run(app, ["data", "import", str(tmp_path / "eps"), "--id", "t/cp/own-v0", "--env", "CartPole-v1"])
    assert r.exit_code == 0 and "2 episodes" in r.output and "Discrete(2)" in r.output, r.output
    r = run(app, ["data", "import", str(tmp_path / "eps"), "--id", "t/cp/own-v0"])
    assert r.exit_code == 2 and "--overwrite" in r.output
    r = run(
        app,
        [
            "data",
            "import",
            str(tmp_path / "eps"),
            "--id",
            "t/cp/own-v0",
            "--env",
            "Pendulum-v1",
            "--overwrite",
        ],
    )
    assert r.exit_code == 2 and "Pendulum-v1 (3,)" in r.output
