"""`research.breakout_lookahead`: the search plays in a copy of the game and leaves the real one as it was."""

import argparse

import numpy as np
import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

from gmt.datagen.breakout import PADDLE_OFFSET, make_env, read_ram  # noqa: E402
from research.breakout_lookahead import Lookahead, main  # noqa: E402


def _args(**kw) -> argparse.Namespace:
    base = dict(mode="offset", score="dig", offsets=[2, 8, 14], depth=2, plan_y=120, horizon=80, rollouts=1)
    return argparse.Namespace(**{**base, **kw})


def _descending(env, agent, rng):
    """Plays lead4 until the ball comes down past y 120; returns the RAM state there."""
    prev = read_ram(env)
    for _ in range(400):
        env.step(agent.base.act(prev, rng))
        state = read_ram(env)
        if state.in_play and prev.in_play and state.ball_y > prev.ball_y and state.ball_y >= 120:
            return state
        prev = state
    raise AssertionError("the ball never came down")


@pytest.mark.parametrize("mode", ["offset", "sequence"])
def test_a_plan_leaves_the_real_game_untouched(mode):
    env = make_env()
    env.reset(seed=3)
    ale = env.unwrapped.ale
    agent = Lookahead(_args(mode=mode))
    agent.reset(env)
    _descending(env, agent, np.random.default_rng(0))
    ram, lives, frame = ale.getRAM().copy(), ale.lives(), ale.getFrameNumber()
    if mode == "offset":
        agent._plan_offset()
        assert agent.base.offset in (2, 8, 14)
    else:
        agent._plan_sequence()
        assert all(a in (0, 2, 3) for a in agent.plan) and len(agent.plan) in (0, 2)
    np.testing.assert_array_equal(ale.getRAM(), ram)
    assert ale.lives() == lives and ale.getFrameNumber() == frame
    env.close()


def test_the_command_plays_every_episode(capsys):
    main(["--offsets", str(PADDLE_OFFSET), "--episodes", "2", "--max-steps", "100"])
    lines = capsys.readouterr().out.splitlines()
    assert sum(line.startswith("seed ") for line in lines) == 2
    assert lines[-1].startswith("mean ")
