import json

import numpy as np
import pytest

from gmt.model.data.relabel import GoalTable, goal_names, relabel, separation

MEANS = [0.0, 1.0, 3.0, 6.0]


def synthetic(seed: int = 0, n: int = 40, spread: float = 0.05):
    """Four tight clusters, shuffled; returns values and the true cluster rank of each."""
    rng = np.random.default_rng(seed)
    truth = np.repeat(np.arange(len(MEANS)), n)
    values = np.asarray(MEANS)[truth] + rng.normal(0, spread, truth.shape)
    perm = rng.permutation(len(values))
    return values[perm], truth[perm]


def test_recovers_known_clusters_and_k():
    values, truth = synthetic()
    table = relabel(values, statistic="mean_x_velocity", seed=0)
    assert table.k == 4
    assert table.candidates == [4]
    np.testing.assert_array_equal(table.labels, truth)
    assert [g.name for g in table.goals] == ["lowest", "low", "high", "highest"]
    np.testing.assert_allclose([g.mean for g in table.goals], MEANS, atol=0.05)
    assert [g.count for g in table.goals] == [40] * 4
    assert min(separation(table)) > 4


def test_goal_zero_has_lowest_mean_with_given_k():
    values, _ = synthetic()
    table = relabel(values, k=2, seed=3)
    assert table.k == 2 and table.k_given
    assert table.goals[0].mean < table.goals[1].mean
    # k=2 on these clusters splits {0, 1, 3} from {6}.
    assert table.goals[1].count == 40
    assert table.goals[0].max < table.goals[1].min


def test_scores_are_normalised_and_candidates_thresholded():
    values, _ = synthetic()
    table = relabel(values, seed=0, threshold=0.5)
    assert set(table.silhouette) == set(range(2, 9))
    assert min(table.normalised.values()) == 0.0 and max(table.normalised.values()) == 1.0
    assert table.candidates == sorted(k for k, s in table.normalised.items() if s >= 0.5)
    assert table.k in table.candidates


def test_sampling_of_k_is_seeded_and_stays_in_candidates():
    # Two equally good structures: 2 far groups, each made of 2 close groups.
    rng = np.random.default_rng(1)
    values = np.concatenate([rng.normal(m, 0.05, 50) for m in (0.0, 0.6, 10.0, 10.6)])
    chosen = {relabel(values, seed=s, threshold=0.0).k for s in range(20)}
    assert len(chosen) > 1
    for s in range(5):
        a, b = relabel(values, seed=s, threshold=0.0), relabel(values, seed=s, threshold=0.0)
        assert a.k == b.k
        np.testing.assert_array_equal(a.labels, b.labels)


def test_json_round_trip(tmp_path):
    values, _ = synthetic()
    table = relabel(values, statistic="return", seed=0)
    path = tmp_path / "labels.json"
    table.save(path)
    back = GoalTable.load(path)
    assert back.to_dict() == json.loads(path.read_text())
    np.testing.assert_array_equal(back.labels, table.labels)
    assert back.goals == table.goals and back.silhouette == table.silhouette and back.k == table.k


def test_names_and_errors():
    assert goal_names(3) == ["low", "medium", "high"]
    assert goal_names(5) == ["lowest", "low", "medium", "high", "highest"]
    assert goal_names(7)[6] == "goal-6"
    with pytest.raises(ValueError, match="distinct"):
        relabel([1.0, 1.0, 1.0])


def test_goals_over_two_statistics_cluster_the_standardised_vectors():
    rng = np.random.default_rng(0)
    # Four behaviours: two speeds x two energies. Speed alone (m/s) would find two goals; energy is in the
    # thousands, so unstandardised it would drown the speed.
    speed = np.repeat([1.0, 1.0, 3.0, 3.0], 30) + rng.normal(0, 0.05, 120)
    energy = np.repeat([1000.0, 5000.0, 1000.0, 5000.0], 30) + rng.normal(0, 100, 120)
    table = relabel(
        np.stack([speed, energy], axis=1), statistic="mean(info.speed), sum(info.energy)", k=4, seed=0
    )
    assert sorted(np.bincount(table.labels).tolist()) == [30, 30, 30, 30]
    truth = np.repeat([0, 1, 2, 3], 30)
    for g in range(4):  # every cluster is one behaviour
        assert len(set(truth[table.labels == g])) == 1
    means = [g.mean for g in table.goals]
    assert means == sorted(means) and table.goals[0].mean == pytest.approx(1.0, abs=0.05)  # ordered by speed
    energies = [round(v[1], -3) for v in table.vectors]
    assert sorted(energies[:2]) == sorted(energies[2:]) == [1000, 5000]  # both energies at each speed
    again = GoalTable.from_dict(table.to_dict())
    assert again.vectors == table.vectors and again.values.shape == (120, 2)
    assert "vector" in table.format() and "(1.0" in table.format()


def test_a_list_of_statistics_measures_each_and_is_judged_by_the_first():
    from gmt.common.statistics import canonical, get_statistic, statistic_names
    from gmt.model.data.minari_io import Episode, OfflineDataset
    from gmt.model.data.statistics import per_trajectory

    name = "return, mean(abs(obs[1]))"
    assert statistic_names(name) == ["return", "mean(abs(obs[1]))"]
    assert canonical(name) == "sum(reward), mean(abs(obs[1]))"
    assert get_statistic(name).name == "return"
    with pytest.raises(KeyError, match="median"):
        get_statistic("return, median(reward)")  # every one is checked
    eps = [Episode(np.full((3, 2), -float(i)), np.zeros((3, 1), np.float32), np.full(3, i, np.float32), False, True, {}, None, i)
           for i in range(3)]  # fmt: skip
    box = __import__("gymnasium").spaces.Box(-9, 9, (2,))
    values = per_trajectory(name, OfflineDataset("t/x-v0", "X", box, box, eps, ""))
    np.testing.assert_allclose(values, [[0, 0], [3, 1], [6, 2]])
