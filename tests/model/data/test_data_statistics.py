import numpy as np
import pytest

from gmt.model.data.minari_io import Episode, OfflineDataset
from gmt.model.data.statistics import (
    MissingInfoError,
    aggregate,
    available_statistics,
    get_statistic,
    per_trajectory,
    register_statistic,
    signal_from_step,
)


def episode(x_velocity=None, rewards=(1.0, 2.0, 3.0)) -> Episode:
    n = len(rewards)
    infos = {} if x_velocity is None else {"x_velocity": np.asarray(x_velocity, dtype=np.float64)}
    return Episode(np.zeros((n, 2)), np.zeros((n, 1), np.float32), np.asarray(rewards, np.float32), False, True,
                   infos, np.zeros(2), 0)  # fmt: skip


def dataset(*episodes: Episode) -> OfflineDataset:
    import gymnasium as gym

    box = gym.spaces.Box(-1, 1, (2,))
    return OfflineDataset("test/ds-v0", "Test-v0", box, box, list(episodes), "")


def test_mean_x_velocity_and_return():
    ep = episode([0.5, 1.5, 4.0])
    mxv = get_statistic("mean_x_velocity")
    np.testing.assert_array_equal(mxv.per_step(ep), [0.5, 1.5, 4.0])
    assert mxv.of_episode(ep) == pytest.approx(2.0)
    assert mxv.aggregate(mxv.per_step(ep)[1:]) == pytest.approx(2.75)
    assert get_statistic("return").of_episode(ep) == pytest.approx(6.0)
    np.testing.assert_allclose(per_trajectory("return", dataset(ep, episode(rewards=(5.0,)))), [6.0, 5.0])


def test_live_signal_matches_dataset_statistic():
    ep = episode([0.5, 1.5, 4.0])
    live = [
        signal_from_step("mean_x_velocity", r, {"x_velocity": v})
        for r, v in zip(ep.rewards, [0.5, 1.5, 4.0], strict=True)
    ]
    assert aggregate("mean_x_velocity", live) == get_statistic("mean_x_velocity").of_episode(ep)
    assert aggregate("return", [signal_from_step("return", r, {}) for r in ep.rewards]) == pytest.approx(6.0)
    with pytest.raises(MissingInfoError, match="x_velocity"):
        signal_from_step("mean_x_velocity", 1.0, {"x_position": 3.0})


def test_dataset_without_x_velocity_gives_clear_error():
    ds = dataset(episode(), episode())
    with pytest.raises(MissingInfoError) as err:
        per_trajectory("mean_x_velocity", ds)
    msg = str(err.value)
    assert "x_velocity" in msg and "test/ds-v0" in msg
    assert "still available: mean_reward, return" in msg
    assert available_statistics(set()) == ["mean_reward", "return"]


def test_unknown_statistic_lists_registered():
    with pytest.raises(KeyError, match="mean_x_velocity"):
        get_statistic("speed")


def test_register_custom_statistic():
    @register_statistic("test_max_height", aggregate=np.max, requires={"z"})
    def height(reward, info):
        return info["z"]

    ep = episode()
    ep.infos["z"] = np.asarray([0.1, 0.7, 0.3])
    assert get_statistic("test_max_height").of_episode(ep) == pytest.approx(0.7)
    assert "test_max_height" in available_statistics({"z"})
    assert "test_max_height" not in available_statistics(set())
    with pytest.raises(ValueError, match="already registered"):
        register_statistic("test_max_height")(height)
