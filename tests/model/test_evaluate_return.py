"""The game protocol (paper A.2.2) on a random-weight Breakout model: holds, switches, the expected return."""

import json

import gymnasium as gym
import numpy as np
import pytest
from typer.testing import CliRunner

from gmt.model.evaluate_return import (
    evaluate_returns,
    expected_return,
    expected_return_per_step,
    return_protocol,
    switch_goals,
)
from gmt.model.fixtures import tiny_checkpoint

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

FRAMES = gym.spaces.Box(0, 255, (4, 64, 64), np.uint8)


def _ckpt(directory=None):
    return tiny_checkpoint(
        directory,
        env_id="ALE/Breakout-v5",
        name="tiny-breakout",
        observation_space=FRAMES,
        statistic="return",
        context_length=4,
    )


def test_the_protocol_holds_every_goal_and_switches_low_middle_high_both_ways():
    assert switch_goals(3) == [0, 1, 2] and switch_goals(5) == [0, 2, 4] and switch_goals(2) == [0, 1]
    conds = return_protocol(5, switch_at=300)
    assert [c.name for c in conds[:5]] == [f"hold {g}" for g in range(5)]
    assert sorted((c.first, c.second) for c in conds[5:]) == [
        (0, 2), (0, 4), (2, 0), (2, 4), (4, 0), (4, 2)
    ]  # fmt: skip
    c = conds[5]
    assert c.goal_at(299) == c.first and c.goal_at(300) == c.second


def test_switch_returns_add_up_and_are_judged_against_the_share_weighted_holds():
    res = evaluate_returns(_ckpt(), seeds=[0, 1], steps=60, switch_at=20, progress=False)
    d = res.to_dict()
    assert [h["goal"] for h in d["holds"]] == [0, 1, 2] and len(d["switches"]) == 6
    means = {h["goal"]: h["mean"] for h in d["holds"]}
    rates = {h["goal"]: np.sum(h["returns"]) / np.sum(h["lengths"]) for h in d["holds"]}
    for ci in range(len(res.conditions)):  # rewards stop where each episode stopped
        for e, n in enumerate(res.lengths[ci]):
            assert 1 <= n <= 60 and not res.rewards[ci, e, n:].any()
    for s in d["switches"]:
        np.testing.assert_allclose(np.add(s["before"], s["after"]), s["returns"])
        n = np.asarray(s["lengths"])
        share = np.mean(np.minimum(n, 20) / n)
        assert s["alive_at_switch"] == int((n > 20).sum())  # only these games were still running to switch
        assert s["share_first"] == pytest.approx(share)
        assert s["expected"] == pytest.approx(share * means[s["first"]] + (1 - share) * means[s["second"]])
        switched = s["alive_at_switch"] == len(n)  # an episode over before the switch fails it
        assert s["within_20pct"] == (switched and abs(s["mean"] - s["expected"]) <= 0.2 * abs(s["expected"]))
        per_step = np.mean([min(k, 20) * rates[s["first"]] + max(k - 20, 0) * rates[s["second"]] for k in n])
        assert s["expected_per_step"] == pytest.approx(per_step)
        assert s["within_20pct_per_step"] == (
            switched and abs(s["mean"] - s["expected_per_step"]) <= 0.2 * abs(s["expected_per_step"])
        )
    assert d["summary"]["switches_within_20pct"] == sum(s["within_20pct"] for s in d["switches"])
    assert expected_return(10.0, 40.0, 0.3) == pytest.approx(31.0)  # the paper's 0.3 / 0.7 example


def test_the_per_step_expectation_agrees_with_the_papers_formula_for_full_length_episodes():
    # Holds of 1000 steps earning 10 and 40: a 1000-step switch at 300 expects 0.3 x 10 + 0.7 x 40.
    assert expected_return_per_step(np.array([1000, 1000]), 300, 10 / 1000, 40 / 1000) == pytest.approx(31.0)
    # A game over at step 200 never reaches the second goal: only the first goal's rate counts.
    assert expected_return_per_step(np.array([200]), 300, 0.05, 1.0) == pytest.approx(10.0)


def test_gmt_eval_uses_the_game_protocol_for_return_goals(tmp_path):
    from gmt.service.cli import app

    _ckpt(tmp_path / "ckpt")
    out = tmp_path / "eval.json"
    args = [
        "eval",
        str(tmp_path / "ckpt"),
        "--seeds",
        "2",
        "--steps",
        "30",
        "--threads",
        "1",
        "--json",
        str(out),
    ]
    r = CliRunner().invoke(app, [*args, "--plot", str(tmp_path / "eval.png")])
    assert r.exit_code == 0, r.output
    doc = json.loads(out.read_text())
    assert doc["statistic"] == "return" and doc["action_mode"] == "expert" and "switches" in doc
    assert (tmp_path / "eval.png").stat().st_size > 1000
    assert "switch" in r.output and "within 20%" in r.output


def test_a_switch_whose_episodes_ended_before_it_is_reported_and_not_a_pass():
    from gmt.model.checkpoint import Goal
    from gmt.model.evaluate_return import ReturnCondition, ReturnEvalResult

    conds = [ReturnCondition(0), ReturnCondition(1), ReturnCondition(0, 1, 20), ReturnCondition(1, 0, 20)]
    rewards = np.zeros((4, 3, 40))
    lengths = np.array([[10] * 3, [40] * 3, [10] * 3, [40] * 3])  # goal 0's games end at step 10, before 20
    rewards[0, :, :10] = 1.0  # hold 0: return 10
    rewards[1, :, :40] = 1.0  # hold 1: return 40
    rewards[2, :, :10] = 1.0  # switch 0->1: over at step 10, never switched; its return is the expected 10
    rewards[3, :, :25] = 1.0  # switch 1->0: half the steps at each goal, 0.5 x 40 + 0.5 x 10
    goals = [Goal(0, "low", 10.0, 1.0, 9, 11, 3), Goal(1, "high", 40.0, 1.0, 39, 41, 3)]
    res = ReturnEvalResult(
        "m", "E", "return", "expert", [0, 1, 2], 40, 20, goals, conds, rewards, lengths, 0.0
    )
    d = res.to_dict()
    never = next(s for s in d["switches"] if s["first"] == 0)
    assert never["alive_at_switch"] == 0 and never["relative_error"] == pytest.approx(0.0)
    assert not never["within_20pct"] and not never["within_20pct_per_step"]  # was a pass: 0 error
    assert d["summary"]["switches_unreached"] == 1 and d["summary"]["switches_within_20pct"] == 1
    assert "ended before the switch" in res.markdown()
