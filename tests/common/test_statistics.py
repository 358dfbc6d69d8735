"""Statistics of the user's choosing: `AGG(SOURCE)` expressions, plug-ins and entry points, parsed without eval,
measuring a dataset episode and a live episode alike."""

from __future__ import annotations

import numpy as np
import pytest

from gmt.common import statistics as st
from gmt.common.statistics import (
    MissingInfoError,
    StatisticError,
    canonical,
    default_statistic,
    get_statistic,
    is_sum,
    signal_from_step,
)
from gmt.model.data.minari_io import Episode


def episode() -> Episode:
    obs = np.array([[0.0, 1.0, -2.0], [0.5, -1.0, 3.0], [1.0, 2.0, -4.0]])
    act = np.array([[0.1, -0.3], [0.2, 0.4], [-0.6, 0.0]], dtype=np.float32)
    infos = {"x_velocity": np.array([1.0, 2.0, 4.0]), "lives": np.array([3.0, 3.0, 2.0])}
    return Episode(obs, act, np.array([1.0, -2.0, 3.0], np.float32), False, True, infos, np.zeros(3), 0)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("mean(info.x_velocity)", 7 / 3),
        ("mean_x_velocity", 7 / 3),
        ("sum(reward)", 2.0),
        ("return", 2.0),
        ("mean(abs(obs[2]))", 3.0),
        ("max(obs[1])", 2.0),
        ("min(action[1])", -0.3),
        ("first(info.lives)", 3.0),
        ("last(info.lives)", 2.0),
        ("std(reward)", float(np.std([1.0, -2.0, 3.0]))),
        ("sum(abs(reward))", 6.0),
        (" mean ( abs ( obs [ 2 ] ) ) ", 3.0),
    ],
)
def test_an_expression_measures_a_dataset_episode_and_a_live_one_alike(name, value):
    ep, stat = episode(), get_statistic(name)
    assert stat.of_episode(ep) == pytest.approx(value, abs=1e-6)
    live = [
        signal_from_step(
            name, ep.rewards[t], {k: v[t] for k, v in ep.infos.items()}, ep.observations[t], ep.actions[t]
        )
        for t in range(len(ep))
    ]
    np.testing.assert_allclose(live, stat.per_step(ep), atol=1e-6)


def test_aliases_are_the_expressions_they_stand_for():
    assert canonical("return") == canonical("sum( reward )") == "sum(reward)"
    assert canonical("mean_x_velocity") == "mean(info.x_velocity)"
    assert is_sum("return") and is_sum("sum(info.blocks)") and not is_sum("mean(reward)")
    assert get_statistic("mean(info.x_velocity)").requires == {"x_velocity"}


def test_a_discrete_action_is_action_0():
    ep = episode()
    ep.actions = np.array([0, 1, 1], dtype=np.int64)
    assert get_statistic("mean(action[0])").of_episode(ep) == pytest.approx(2 / 3)
    assert signal_from_step("mean(action[0])", 0.0, {}, None, np.int64(1)) == 1.0


@pytest.mark.parametrize(
    "name",
    ["__import__('os').system('true')", "mean(obs[1]", "median(reward)", "mean(reward) + 1", "mean(info.)",
     "mean(obs[-1])", "os.system:true x"],
)  # fmt: skip
def test_anything_else_is_refused_naming_the_grammar(name):
    with pytest.raises(StatisticError, match=r"AGG\(SOURCE\)"):
        get_statistic(name)


def test_what_the_data_lacks_is_named():
    ep = episode()
    with pytest.raises(MissingInfoError, match="blocks"):
        get_statistic("sum(info.blocks)").of_episode(ep)
    with pytest.raises(MissingInfoError, match="obs\\[7\\].*3 entries"):
        get_statistic("mean(obs[7])").of_episode(ep)
    with pytest.raises(MissingInfoError, match="blocks"):
        signal_from_step("sum(info.blocks)", 1.0, {"x_velocity": 1.0})


def test_a_plugin_is_imported_by_module_and_function():
    ep = episode()
    assert get_statistic("tests.common.statistic_plugin:speed_squared").of_episode(ep) == pytest.approx(7.0)
    assert get_statistic("max(tests.common.statistic_plugin:speed_squared)").of_episode(ep) == 16.0
    norm = get_statistic("tests.common.statistic_plugin:action_norm")
    assert norm.of_episode(ep) == pytest.approx(np.mean(np.linalg.norm(ep.actions, axis=1)), rel=1e-6)
    with pytest.raises(MissingInfoError, match="x_velocity"):
        signal_from_step("tests.common.statistic_plugin:speed_squared", 1.0, {})
    with pytest.raises(StatisticError, match="cannot import"):
        get_statistic("tests.common.nosuch:f")


def test_a_name_from_a_server_never_imports_a_plugin():
    with pytest.raises(StatisticError, match="--statistic"):
        get_statistic("tests.common.statistic_plugin:speed_squared", plugins=False)
    assert not is_sum("sum(tests.common.statistic_plugin:speed_squared)")  # not resolved, so not imported


def test_an_entry_point_names_a_statistic(monkeypatch):
    from importlib.metadata import EntryPoint

    ep = EntryPoint("speed2", "tests.common.statistic_plugin:speed_squared", st.ENTRY_POINT_GROUP)
    monkeypatch.setattr(
        "importlib.metadata.entry_points", lambda group: [ep] if group == st.ENTRY_POINT_GROUP else []
    )
    assert get_statistic("speed2").of_episode(episode()) == pytest.approx(7.0)


def test_the_default_follows_the_data():
    assert default_statistic({"x_velocity", "x_position"})[0] == "mean_x_velocity"
    assert canonical(default_statistic(set())[0]) == "sum(reward)"


def test_the_statistics_stay_torch_free(imports_of):
    assert "torch" not in imports_of("gmt.common.statistics")


def test_a_plugin_beside_the_user_is_found_as_python_m_would(tmp_path, monkeypatch):
    import sys

    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_stats_56.py").write_text(
        "def reward_twice(reward, info, obs, action):\n    return 2 * reward\n"
    )
    assert get_statistic("sum(my_stats_56:reward_twice)").of_episode(episode()) == pytest.approx(4.0)
