"""The evaluation protocol: conditions, tolerance, success judgement, JSON schema, plot."""

import json

import numpy as np
import pytest

from gmt.model.checkpoint import Goal
from gmt.model.evaluate import evaluate, protocol, tolerance
from gmt.model.fixtures import tiny_checkpoint


def test_protocol_has_every_hold_switch_and_multi_switch():
    conds = protocol(4, steps=1000)
    names = [c.name for c in conds]
    assert names[:4] == ["hold 0", "hold 1", "hold 2", "hold 3"]
    assert sum(c.kind == "switch" for c in conds) == 12
    sw = next(c for c in conds if c.name == "switch 2->0")
    assert sw.schedule == [(0, 2), (500, 0)] and sw.segments == [(2, 100, 500), (0, 600, 1000)]
    every = next(c for c in conds if c.name == "every 200")
    assert [g for _, g in every.schedule] == [0, 1, 2, 3, 0]
    assert every.segments[1] == (1, 250, 400)
    assert every.goal_at(399) == 1 and every.goal_at(400) == 2


def test_tolerance_is_the_larger_of_relative_and_span():
    goals = [Goal(i, f"g{i}", m, 0.1, m, m, 1) for i, m in enumerate([0.1, 1.0, 5.0])]
    assert tolerance(goals[0], goals) == pytest.approx(0.05 * 4.9)
    assert tolerance(goals[2], goals) == pytest.approx(0.5)


def test_tolerance_is_never_narrower_than_the_goals_own_spread():
    # Swimmer-like: speeds of a few cm/s whose episodes vary more than 10% of the mean.
    goals = [Goal(0, "low", 0.03, 0.012, 0.0, 0.06, 9), Goal(1, "high", 0.08, 0.015, 0.05, 0.1, 9)]
    assert tolerance(goals[0], goals) == pytest.approx(0.012)
    assert tolerance(goals[1], goals) == pytest.approx(0.015)


def test_evaluate_runs_lockstep_and_judges_segments(tmp_path):
    ckpt = tiny_checkpoint(n_goals=2)
    conds = protocol(2, steps=40, multi_every=(20,))
    result = evaluate(ckpt, seeds=2, steps=40, conditions=conds, progress=False)
    d = json.loads(json.dumps(result.to_dict()))
    assert [c["name"] for c in d["conditions"]] == [
        "hold 0",
        "hold 1",
        "switch 0->1",
        "switch 1->0",
        "every 20",
    ]
    for cr in result.results:
        assert cr.signal.shape == (2, 40) and not np.isnan(cr.signal).any()
        # success == every segment within tolerance, recomputed here from the raw signal
        for e in range(2):
            ok = all(
                abs(np.mean(cr.signal[e, a:b]) - ckpt.goals[g].mean) <= tolerance(ckpt.goals[g], ckpt.goals)
                for g, a, b in cr.condition.segments
            )
            assert bool(cr.success[e]) == ok
    # Same seeds, same hold goal: identical episodes whichever condition they belong to.
    assert np.array_equal(result.results[0].signal[:, :20], result.results[2].signal[:, :20])
    from gmt.model.eval_plot import plot_eval

    png = plot_eval(result, tmp_path / "eval.png")
    assert png.stat().st_size > 10_000


def test_an_episode_over_before_its_switch_is_reported_as_never_switched():
    from gmt.model.evaluate import judge

    ckpt = tiny_checkpoint(n_goals=2)
    conds = protocol(2, steps=40, multi_every=())  # hold 0, hold 1, switch 0->1 at 20, switch 1->0 at 20
    signal = np.stack([np.full((2, 40), ckpt.goals[c.goal_at(0)].mean) for c in conds])
    for ci, c in enumerate(conds):
        for t in range(40):
            signal[ci, :, t] = ckpt.goals[c.goal_at(t)].mean  # every episode right on its targets
    signal[2, 0, 15:] = np.nan  # episode 0 of switch 0->1 ended at step 15, before its switch at 20
    terminated = np.zeros(8, dtype=bool)  # truncated, not terminated: the early end alone must fail it
    res = judge(ckpt, conds, [0, 1], signal.reshape(8, 40), terminated, "mean", 40, 0.0)
    sw = res.results[2]
    assert sw.never_switched == 1 and sw.to_dict()["never_switched"] == 1
    assert list(sw.success) == [False, True]
    assert res.results[3].never_switched == 0 and all(res.results[3].success)
    assert "1/2 (1 never switched)" in res.markdown()
