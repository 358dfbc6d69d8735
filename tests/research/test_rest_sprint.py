"""`research.rest_sprint`: a planned sprint from standing, held for a few steps and handed back to the level."""

import numpy as np
import pytest

from gmt.datagen.plan import PlanConfig
from research import rest_sprint

LEVEL = "behaviour/hopper3-gmt/hopper/slow"


def _first_span(commands: tuple[float, ...]) -> float:
    """Mean speed over every 100's first span, one reset, the sprint plan given `commands`."""
    sprint = PlanConfig(
        commands=commands, candidates=2 * len(commands), every=20, horizon=60, steps=100, target=2.6
    )
    settle = PlanConfig(commands=(1.6, 1.2), candidates=2, every=20, horizon=40, steps=100, target=1.7)
    _, (row,) = rest_sprint.run("Hopper-v5", LEVEL, sprint, settle, hold=20, settle_at=60, seeds=1, steps=300)
    assert set(row) == {"seed", "[25, 100)", "[50, 200)", "[75, 300)", "fell at"}
    return row["[25, 100)"]


def test_sprint_commands_get_the_hopper_going_faster_than_its_own_command():
    own = _first_span((1.6,))
    sprint = _first_span((4.6, 4.2))
    assert np.isfinite(own) and 0.5 < own < sprint - 0.05  # moving, and clearly faster when it may sprint


def test_a_continuation_hands_back_to_the_levels_command_and_the_plan_keeps_it():
    """After `hold` steps a simulated continuation runs on the level's own command; the policy's command is the
    level's own again after planning, whatever the candidates held."""
    import gymnasium as gym

    from gmt.datagen.behaviour import load_behaviour

    env = gym.make("Hopper-v5")
    policy = load_behaviour(LEVEL, env.action_space)
    own = policy.command
    seen = []
    act = policy.act

    def spy(obs, rng=None):
        seen.append(policy.command)
        return act(obs, rng)

    policy.act = spy
    cfg = PlanConfig(commands=(4.2,), candidates=1, every=5, horizon=12, steps=10, target=2.6)
    planner = rest_sprint.SprintPlan(policy, env, cfg, cfg, hold=5, settle_at=100)
    env.reset(seed=0)
    planner.start_episode()
    planner.act(env.unwrapped._get_obs(), np.random.default_rng(0))
    assert seen[:5] == [4.2] * 5 and set(seen[5:12]) == {own}  # held 5 steps, then the level's own
    assert policy.command == own


def test_bad_arguments_are_refused(monkeypatch):
    monkeypatch.setattr(
        "sys.argv",
        ["rest_sprint", "--env", "Hopper-v5", "--level", LEVEL, "--sprint-commands", "4", "--sprint-target", "2",
         "--hold", "0"],
    )  # fmt: skip
    with pytest.raises(SystemExit):
        rest_sprint.main()
