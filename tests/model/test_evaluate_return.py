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
        assert s["within_20pct"] == (abs(s["mean"] - s["expected"]) <= 0.2 * abs(s["expected"]))
        per_step = np.mean([min(k, 20) * rates[s["first"]] + max(k - 20, 0) * rates[s["second"]] for k in n])
        assert s["expected_per_step"] == pytest.approx(per_step)
        assert s["within_20pct_per_step"] == (
            abs(s["mean"] - s["expected_per_step"]) <= 0.2 * abs(s["expected_per_step"])
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
