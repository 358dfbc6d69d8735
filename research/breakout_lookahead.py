"""Can a scripted Breakout level aim? Lookahead in the emulator on top of the lead-4 tracker (measure only).

Issue 43 wants a top goal of 60 points in 1000 steps; the trackers' median game scores 48-56 and their means reach
60 only through rare tunnels (docs/breakout.md). A level that aims the ball (at a hole, at the most valuable
brick) would be a stronger teacher. This module measures two ways to aim, both with ALE's `cloneState` /
`restoreState` (no RNG cloned: sticky actions stay random in the lookahead, as in play):

- `offset`: when the descending ball crosses `--plan-y`, try the tracker with each paddle offset of `--offsets`
  (where under the paddle the ball should land; the calibrated centre is 8, catches hold for 1-17) until the ball
  hits a brick, and play the best one. `--score value` takes the most points of that first hit; `--score dig` the
  first hit nearest the median x of the last three real hits (digging one column); `--score total` the points
  within `--horizon` steps, the tracker playing on. `--rollouts` averages several lookaheads per offset.
- `sequence`: the same moment, every sequence of `--depth` moves (NOOP / RIGHT / LEFT), then NOOPs, played open
  loop; the best by `--score value` or `dig`.

Each prints every episode's return, its largest burst and the lives left, then the mean and median, and (offset
mode) how far apart the candidates' first hits are: when they all hit the same x, the choice changes nothing.

    python -m research.breakout_lookahead --mode offset --score dig --episodes 12
    python -m research.breakout_lookahead --mode offset --offsets 8 --episodes 12      # the plain lead-4 tracker
"""

from __future__ import annotations

import argparse
import copy
import itertools
import time

import numpy as np

from gmt.datagen.breakout import (
    LEFT,
    LEVELS,
    NOOP,
    PADDLE_OFFSET,
    RIGHT,
    RamState,
    TrackingAgent,
    bursts,
    make_env,
    read_ram,
)

FRAME_SKIP = 4
LOST = -1000.0  # a lookahead that loses a life


class Lookahead:
    """The lead-4 tracker, aimed at each descent by a search in a cloned emulator."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.base = TrackingAgent(LEVELS["lead4"])
        self.sequences = list(itertools.product((NOOP, RIGHT, LEFT), repeat=args.depth))
        self.spreads: list[int] = []

    def reset(self, env) -> None:
        """A new episode of `env` (the lookahead steps its ALE directly, under the wrappers)."""
        self.env, self.ale = env, env.unwrapped.ale
        self.base.reset()
        self.base.offset = PADDLE_OFFSET
        self.hits: list[int] = []
        self.plan: list[int] = []
        self.planned = False
        self.prev: RamState | None = None

    def _score(self, reward: float, first_x: int | None) -> float:
        if first_x is None:
            return -1.0
        if self.args.score == "dig" and self.hits:
            return -abs(first_x - float(np.median(self.hits[-3:]))) + 0.1 * reward
        return reward

    def _simulate(self, next_action) -> tuple[float, int | None]:
        """Steps the cloned game with `next_action(t, state)` to the first brick (or `--horizon`)."""
        ale, lives, total, first_x = self.ale, self.ale.lives(), 0.0, None
        state = read_ram(self.env)
        for t in range(self.args.horizon):
            a = next_action(t, state)
            r = sum(ale.act(a) for _ in range(FRAME_SKIP))
            state = read_ram(self.env)
            if ale.lives() < lives or ale.game_over():
                return LOST, None
            total += r
            if r > 0 and first_x is None:
                first_x = state.ball_x
                if self.args.score != "total":
                    break
        return total, first_x

    def _plan_offset(self) -> None:
        snap, scores, firsts = self.ale.cloneState(), {}, []
        rng = np.random.default_rng(0)
        for offset in self.args.offsets:
            values = []
            for _ in range(self.args.rollouts):
                agent = copy.deepcopy(self.base)
                agent.offset = offset
                total, first_x = self._simulate(lambda t, s, agent=agent: agent.act(s, rng))
                self.ale.restoreState(snap)
                values.append(LOST if total == LOST else self._score(total, first_x))
                if first_x is not None:
                    firsts.append(first_x)
            scores[offset] = float(np.mean(values))
        best = max(scores.values())
        self.base.offset = min((o for o in scores if scores[o] >= best), key=lambda o: abs(o - PADDLE_OFFSET))
        if firsts:
            self.spreads.append(max(firsts) - min(firsts))

    def _plan_sequence(self) -> None:
        snap, best = self.ale.cloneState(), None
        for seq in self.sequences:
            total, first_x = self._simulate(lambda t, s, seq=seq: seq[t] if t < len(seq) else NOOP)
            self.ale.restoreState(snap)
            value = LOST if total == LOST else self._score(total, first_x)
            if best is None or value > best[0]:
                best = (value, seq)
        self.plan = list(best[1]) if best and best[0] > LOST else []

    def act(self, state: RamState, rng: np.random.Generator) -> int:
        prev, self.prev = self.prev, state
        descending = prev is not None and prev.in_play and state.in_play and state.ball_y > prev.ball_y
        if not descending and state.ball_y < 150:
            self.planned = False
            self.base.offset = PADDLE_OFFSET
        if descending and not self.planned and state.ball_y >= self.args.plan_y:
            self.planned = True
            self._plan_offset() if self.args.mode == "offset" else self._plan_sequence()
        if prev is not None and state.score > prev.score:
            self.hits.append(state.ball_x)
        if self.plan:
            a = self.plan.pop(0)
            self.base.decide(state, rng)
            return self.base.played(a)
        return self.base.act(state, rng)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mode", choices=["offset", "sequence"], default="offset")
    p.add_argument("--score", choices=["value", "dig", "total"], default="dig")
    p.add_argument("--offsets", type=int, nargs="+", default=[2, 4, 6, 8, 10, 12, 14])
    p.add_argument("--depth", type=int, default=4, help="moves per sequence (sequence mode)")
    p.add_argument(
        "--plan-y", type=int, default=120, help="plan when the descending ball is below this RAM y"
    )
    p.add_argument("--horizon", type=int, default=80, help="agent steps a lookahead plays at most")
    p.add_argument("--rollouts", type=int, default=1, help="lookaheads per offset, averaged")
    p.add_argument("--episodes", type=int, default=12)
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--seed", type=int, default=7, help="reset seeds from SeedSequence(seed)")
    args = p.parse_args(argv)
    env = make_env()
    agent = Lookahead(args)
    returns, start = [], time.time()
    for seed in np.random.SeedSequence(args.seed).generate_state(args.episodes):
        env.reset(seed=int(seed))
        agent.reset(env)
        rng = np.random.default_rng(int(seed))
        state, ret, ys, rewards, info = read_ram(env), 0.0, [], [], {"lives": 5}
        ys.append(state.ball_y)
        for _ in range(args.max_steps):
            _, r, terminated, _, info = env.step(agent.act(state, rng))
            state = read_ram(env)
            ret += r
            rewards.append(r)
            ys.append(state.ball_y)
            if terminated:
                break
        burst = bursts(np.asarray(ys), np.asarray(rewards)).max()
        returns.append(ret)
        print(
            f"seed {seed}: return {ret:.0f}, largest burst {burst:.0f}, lives {info['lives']}, {time.time() - start:.0f}s"
        )
    if agent.spreads:
        print(
            f"first-hit x spread over the candidates: median {np.median(agent.spreads):.0f} over {len(agent.spreads)} plans"
        )
    print(
        f"mean {np.mean(returns):.1f} +- {np.std(returns) / np.sqrt(len(returns)):.1f}, median {np.median(returns):.1f}"
    )


if __name__ == "__main__":
    main()
