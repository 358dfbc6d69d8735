"""The one definition of segment measurement, moving averages and tables, shared by `gmt eval` and `gmt run`."""

from __future__ import annotations

import numpy as np
import pytest

from gmt.common.segments import (
    achieved,
    held_windows,
    measure,
    measured_spans,
    moving_average,
    settle_in,
    tolerance,
    within,
)
from gmt.common.spec import GoalInfo
from gmt.common.tables import markdown_table, text_table


def test_eval_uses_the_same_definitions_as_the_runner():
    import gmt.model.eval_plot
    import gmt.model.evaluate

    assert gmt.model.evaluate.tolerance is tolerance
    assert gmt.model.eval_plot.moving_average is moving_average
    hold = gmt.model.evaluate.protocol(2, steps=400, multi_every=(150,))
    for c in hold:
        goals = [c.goal_at(t) for t in range(400)]
        assert c.segments == measured_spans(goals)
    every = next(c for c in hold if c.kind == "multi_switch")
    # cycles of 150 steps: two whole ones measured after 150 // 4, the last 100 steps after 100 // 4
    starts = [s for s, _ in every.schedule]
    assert [a - s for (_, a, _), s in zip(every.segments, starts, strict=True)] == [37, 37, 25]


def test_moving_average_is_trailing_and_ignores_nan():
    x = np.array([1.0, 2.0, 3.0, np.nan, 5.0])
    np.testing.assert_allclose(moving_average(x, 2), [1.0, 1.5, 2.5, 3.0, 5.0])
    two = moving_average(np.stack([x, 2 * x]), 3)
    np.testing.assert_allclose(two[1], 2 * moving_average(x, 3))
    assert np.isnan(moving_average([np.nan, np.nan], 5)).all()


def test_achieved_and_within_ignore_steps_after_an_early_end():
    sig = np.array([[1.0, 2.0, 3.0, 4.0], [1.0, 1.0, np.nan, np.nan], [np.nan] * 4])
    np.testing.assert_allclose(achieved(sig, 1, 4)[:2], [3.0, 1.0])
    assert np.isnan(achieved(sig, 1, 4)[2]) and achieved(sig[0], 0, 2) == 1.5
    assert list(within(achieved(sig, 1, 4), 3.0, 0.5)) == [True, False, False]  # NaN is never within


def test_measure_reads_any_goal_table():
    from gmt.model.checkpoint import Goal

    signal = np.r_[np.zeros(40), np.full(40, 2.0)]
    for row in (GoalInfo, Goal):
        table = [row(0, "low", 0.0, 0.1, 0, 0, 1), row(1, "high", 2.0, 0.1, 2, 2, 1)]
        segs = measure([0] * 40 + [1] * 40, signal, table)
        assert [(s.goal, s.name, s.start, s.measured_from, s.end) for s in segs] == [
            (0, "low", 0, settle_in(40), 40),
            (1, "high", 40, 40 + settle_in(40), 80),
        ]
        assert all(s.within for s in segs) and segs[1].tolerance == pytest.approx(tolerance(table[1], table))


def test_a_summed_statistic_is_summed_over_each_whole_segment_and_not_judged():
    table = [GoalInfo(0, "low", 4.0, 1, 0, 9, 5), GoalInfo(1, "high", 30.0, 5, 20, 50, 5)]
    reward = np.r_[np.ones(40), np.zeros(10), np.full(20, 2.0), [np.nan]]  # NaN: a step after the game ended
    segs = measure([1] * 50 + [0] * 21, reward, table, "return")
    assert [(s.goal, s.start, s.measured_from, s.end, s.achieved) for s in segs] == [
        (1, 0, 0, 50, 40.0),
        (0, 50, 50, 71, 40.0),
    ]
    assert all(s.within is None and s.tolerance is None for s in segs)
    assert "30.000 per episode" in text_table_of(segs)
    mean = measure([1] * 50 + [0] * 21, reward, table, "mean_x_velocity")  # the same signal, averaged
    assert mean[0].achieved == pytest.approx(np.mean(reward[settle_in(50) : 50])) and mean[0].within is False


def text_table_of(segs):
    from gmt.common.segments import table

    return table(segs, "return")


def test_tables():
    assert text_table(("a", "bb"), [(1, "x"), (22, "")], align="><") == " a  bb\n--  --\n 1  x\n22"
    assert markdown_table(("a", "b"), [(1, 2)]) == "| a | b |\n| --- | --- |\n| 1 | 2 |"
    with pytest.raises(ValueError):
        text_table(("a",), [(1, 2)])


def test_held_windows_cover_the_episode_and_fail_a_window_with_a_fall():
    signal = np.tile(np.arange(1000, dtype=float), (2, 1))  # [2 episodes, 1000 steps]
    signal[1, 700:] = np.nan  # episode 1 ended at step 700
    w = held_windows(signal)
    assert w.shape == (14, 2)  # starts 200, 250, ..., 850
    assert w[0, 0] == np.mean(np.arange(200, 350)) and w[-1, 0] == np.mean(np.arange(850, 1000))
    assert not np.isnan(w[:, 0]).any()
    assert (
        np.isnan(w[:, 1]).sum() == 6
    )  # windows from 600 on reach past step 700, though most steps are before
    assert not within(w[-5, 1], 650.0, 1000.0)  # a partly measured window is not within
    assert held_windows(signal[0], first=0, length=500, every=500).tolist() == [249.5, 749.5]


def test_a_statistic_of_another_aggregation_is_measured_by_it_per_segment():
    sig = np.array([[1.0, 5.0, 2.0, 3.0], [4.0, 1.0, np.nan, np.nan]])
    np.testing.assert_allclose(achieved(sig, 0, 4, "max(info.height)"), [5.0, 4.0])
    np.testing.assert_allclose(achieved(sig, 1, 4, "mean(info.height)"), [10 / 3, 1.0])  # the mean, as before
    assert achieved(sig[0], 0, 4, "std(reward)") == pytest.approx(np.std([1.0, 5.0, 2.0, 3.0]))
    table = [GoalInfo(0, "low", 2.0, 0.5, 1, 3, 5), GoalInfo(1, "high", 5.0, 0.5, 4, 6, 5)]
    segs = measure([1, 1, 1, 1], sig[0], table, "max(info.height)")
    assert segs[0].achieved == 5.0 and segs[0].within
