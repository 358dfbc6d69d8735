"""Offline Breakout data without RL Unplugged: scripted agents that read the ball and paddle from RAM.

A tracking agent moves the paddle under the ball or its predicted landing point (FIRE launches a new ball);
weaker levels of it see late (`lag`), aim badly (`jitter`), press random buttons (`random_prob`) or wait until the
ball is low before moving (`react_y`); a uniform-random policy is the lowest level. `RECIPES` name the level
sets: `mixed` (random actions), `react` (late reactions) and `late` (both). Every level is rolled out in the
preprocessed environment a checkpoint will declare (`Preprocessing`: Gymnasium's `AtariPreprocessing` +
`FrameStackObservation`, the same wrappers `gmt.common.envs` applies), and the frames are stored as uint8 in a
Minari dataset with the rewards, so the statistic `return` (sum of rewards) of a trajectory and of any segment is
a plain sum.

RAM (ALE Breakout, 128 bytes): ball x at 99, ball y at 101 (0 while no ball is in play), paddle x at 72, score
as two BCD bytes at 76 (hundreds) and 77 (tens and units). The often-quoted "score at 84" is not the score in
ale-py 0.12 (measured: it does not follow the rewards). The paddle-ball offset was calibrated at the frame level
(no frame skip, no sticky actions): the paddle was parked at a random offset from the ball before each catch
and hits and misses were recorded against ``ball_x - paddle_x`` at the moment of contact; every catch with
1 <= ball_x - paddle_x <= 17 bounced back, every one at <= -5 or >= 21 was missed, so the paddle's centre is
at ``ball_x - PADDLE_OFFSET`` with ``PADDLE_OFFSET = 8`` (docs/breakout-data.md has the numbers).

    .venv/bin/python -m gmt.datagen.breakout            # writes gmt/breakout/mixed-v0 into the data root
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from gmt.common.envs import atari_env
from gmt.datagen.collect import CollectResult
from gmt.model.data.minari_io import Episode, data_root, write_dataset

ENV_ID = "ALE/Breakout-v5"
DATASET_ID = "gmt/breakout/mixed-v0"

RAM_BALL_X = 99
RAM_BALL_Y = 101
RAM_PADDLE_X = 72
RAM_SCORE_HUNDREDS = 76  # BCD
RAM_SCORE_UNITS = 77  # BCD

NOOP, FIRE, RIGHT, LEFT = 0, 1, 2, 3
PADDLE_OFFSET = 8  # ball_x - paddle_x when the ball meets the paddle's centre (calibrated, see above)
PADDLE_Y = 183  # ball y (RAM) at which it meets the paddle
WALL_LEFT, WALL_RIGHT = 51, 201  # extreme ball x (RAM) measured in play: it bounces off the side walls there
PADDLE_MIN, PADDLE_MAX = 55, 191  # extreme paddle x (RAM)
# Paddle response per agent step (frame skip 4, measured): a move shifts the paddle ~12 during its own step and
# ~11 more during the next one, whatever comes next, so it comes to rest ~23 from where the move started. The
# agents plan with 18 (stopping short missed less than overshooting).
PADDLE_CARRY = 11
PADDLE_MOVE = 18


@dataclass(frozen=True)
class Preprocessing:
    """The observation pipeline of the dataset; a checkpoint trained on it declares exactly this.

    `make_env` builds it from Gymnasium's maintained wrappers:
    ``gym.make(env_id, frameskip=1, repeat_action_probability=...)`` ->
    ``AtariPreprocessing(frame_skip, screen_size, grayscale_obs=True, noop_max, terminal_on_life_loss=False)``
    (max-pool of the last two frames, INTER_AREA resize with OpenCV) -> ``FrameStackObservation(stack)``
    (padded with the reset frame). Observations are uint8 [stack, screen_size, screen_size].

    Attributes:
        env_id: ALE id.
        frame_skip: Emulator frames per agent step (the action is repeated).
        screen_size: Side of the square grayscale frame.
        stack: Frames stacked per observation (oldest first).
        noop_max: At most this many no-ops after reset (random, from the reset seed).
        repeat_action_probability: Sticky actions of ALE v5 (0.25 is its default and what `gmt run` gets).
    """

    env_id: str = ENV_ID
    frame_skip: int = 4
    screen_size: int = 64
    stack: int = 4
    noop_max: int = 30
    repeat_action_probability: float = 0.25

    @property
    def shape(self) -> tuple[int, int, int]:
        """Observation shape [stack, H, W]."""
        return (self.stack, self.screen_size, self.screen_size)

    def to_dict(self) -> dict:
        """JSON-ready description, with the wrapper names and fixed arguments spelled out."""
        return {
            **asdict(self),
            "grayscale": True,
            "terminal_on_life_loss": False,
            "scale_obs": False,
            "resize": "cv2.INTER_AREA",
            "wrappers": ["gymnasium.wrappers.AtariPreprocessing", "gymnasium.wrappers.FrameStackObservation"],
            "observation_shape": list(self.shape),
            "dtype": "uint8",
        }


def make_env(prep: Preprocessing | None = None) -> gym.Env:
    """The preprocessed Breakout environment of `prep` (needs ale-py and opencv-python-headless)."""
    import ale_py

    prep = prep or Preprocessing()
    gym.register_envs(ale_py)
    return atari_env(
        prep.env_id,
        prep.screen_size,
        prep.stack,
        frame_skip=prep.frame_skip,
        noop_max=prep.noop_max,
        repeat_action_probability=prep.repeat_action_probability,
    )


def _bcd(byte: int) -> int:
    return 10 * (byte >> 4) + (byte & 0x0F)


@dataclass(frozen=True)
class RamState:
    """What the scripted agents read of the game."""

    ball_x: int
    ball_y: int
    paddle_x: int
    score: int

    @property
    def in_play(self) -> bool:
        """Whether a ball is on the screen (its y is 0 until FIRE launches one)."""
        return self.ball_y != 0


def read_ram(env: gym.Env) -> RamState:
    """Ball, paddle and score of `env`'s current frame."""
    ram = env.unwrapped.ale.getRAM()
    score = 100 * _bcd(int(ram[RAM_SCORE_HUNDREDS])) + _bcd(int(ram[RAM_SCORE_UNITS]))
    return RamState(int(ram[RAM_BALL_X]), int(ram[RAM_BALL_Y]), int(ram[RAM_PADDLE_X]), score)


class RandomAgent:
    """Uniform over the four actions."""

    name = "random"

    def reset(self) -> None:
        pass

    def act(self, state: RamState, rng: np.random.Generator) -> int:
        return int(rng.integers(4))


@dataclass(frozen=True)
class Skill:
    """How well a `TrackingAgent` plays.

    Attributes:
        name: Level name (episode metadata `policy`).
        lag: Agent steps between seeing the ball and acting on it (the agent aims at an old position).
        jitter: Std (RAM x units; the paddle is 16 wide) of an aiming error drawn afresh for every approach.
        random_prob: Probability of a uniform-random action instead of the aimed one.
        predict: Aim at where the descending ball will meet the paddle (walls included) instead of at the ball.
        lead: Without `predict`: aim where the descending ball will be `lead` agent steps ahead (walls
            included, and no further than where it meets the paddle) instead of at the ball. A short lead is
            a rule of the ball's position and velocity that a frame stack shows, unlike the whole flight
            that `predict` extrapolates (docs/breakout.md).
        react_y: The paddle stays put until the descending ball is below this RAM y (the paddle meets it at
            183); 0 reacts at once. A late reaction cannot reach far landing points: balls are lost by a rule
            of the visible ball, so a weaker level plays worse by policy, not only by random actions.
        disturb: Probability of a disturbance (DART, Laskey et al. 2017): the game gets a uniform-random action,
            but the step records the level's own action. The data then shows the level recovering from states
            off its own path, and what it records is always its policy (`infos["executed_action"]` holds what
            the game got).
    """

    name: str
    lag: int = 0
    jitter: float = 0.0
    random_prob: float = 0.0
    predict: bool = True
    lead: int = 0
    react_y: int = 0
    disturb: float = 0.0


# One tracker (aims at the ball's x, no lag, no aiming error) weakened only by random actions: a rate that is
# the same at every step, so a policy conditioned on the goal can reproduce it from any single frame. The levels
# of the first dataset also differed in lag, aiming jitter and landing-point prediction, latent traits that a
# model trained here did not pick up from pixels (docs/breakout.md). Measured over 12 episodes each (sticky
# actions), return within 1000 agent steps: random 1.5, weak 5.1 +- 2.1, medium 14.4 +- 5.5, good 24.7 +- 8.3,
# strong 37.5 +- 7.9.
LEVELS: dict[str, Skill] = {
    s.name: s
    for s in (
        Skill("weak", random_prob=0.6, predict=False),
        Skill("medium", random_prob=0.35, predict=False),
        Skill("good", random_prob=0.15, predict=False),
        Skill("strong", predict=False),
        # The second recipe (gmt/breakout/react-v1, docs/breakout.md): one tracker that predicts the landing
        # point, weakened by a late reaction (it waits until the descending ball is below `react_y`): a
        # deterministic rule of the visible ball, so the levels differ by policy and an argmax policy keeps them
        # apart. Only the best level also presses 2% random buttons, for states off its own narrow path.
        # Measured (8 episodes each, 1000 steps): ace 66.5 +- 19.8, late135 36.9, late152 28.9, late164 9.1.
        Skill("ace", random_prob=0.02),
        Skill("late135", react_y=135),
        Skill("late152", react_y=152),
        Skill("late164", react_y=164),
        Skill("late172", react_y=172),
        # The third recipe (gmt/breakout/late-v1): the tracker of the ball's x (`strong`, which the shipped model
        # learnt to imitate) with both weaknesses at once: a late reaction (policy) and random actions (rate).
        # Measured (10 episodes each, 1000 steps): strong 29.1, slow140 20.9, slow150 11.6, slow160 8.0,
        # slow168 4.1.
        Skill("slow140", react_y=140, random_prob=0.1, predict=False),
        Skill("slow150", react_y=150, random_prob=0.2, predict=False),
        Skill("slow160", react_y=160, random_prob=0.3, predict=False),
        Skill("slow168", react_y=168, random_prob=0.45, predict=False),
        # The fourth recipe (gmt/breakout/dart-v1): the `react` levels, each disturbed at 20% of its steps and
        # recording its own action there, so that a model imitating the best level sees how it recovers (a
        # model trained on react-v1 fitted its data and still lost the ball: docs/breakout.md).
        Skill("dart0", disturb=0.2),
        Skill("dart135", react_y=135, disturb=0.2),
        Skill("dart152", react_y=152, disturb=0.2),
        Skill("dart164", react_y=164, disturb=0.2),
        Skill("dart172", react_y=172, disturb=0.2),
        # The fifth recipe (gmt/breakout/lead-v1): a tracker that aims where the descending ball will be 4 steps
        # ahead (no further than the paddle's line), a rule of the ball's position and velocity that a frame
        # stack shows (a model learnt the ball-x tracker at 89% agreement, the landing-point one at 80%:
        # docs/breakout.md), weakened by late reactions. Measured (40 episodes, 1000 steps, seed 1): lead4
        # 66.5 +- 39.3 (lead 3 / 6: 60.7 / 57.8, all with tunnels); lead4 with 2% random actions 56.8 (30, seed 0).
        Skill("lead4", predict=False, lead=4),
        Skill("lead140", predict=False, lead=4, react_y=140),
        Skill("lead152", predict=False, lead=4, react_y=152),
        Skill("lead162", predict=False, lead=4, react_y=162),
        Skill("lead170", predict=False, lead=4, react_y=170),
    )
}
# Episodes per level: the same number each, so that no level outweighs the others in the k-means + silhouette
# relabelling (with many more short low-return episodes it settles on k = 2).
DEFAULT_EPISODES = {"random": 80, "weak": 80, "medium": 80, "good": 80, "strong": 80}


@dataclass(frozen=True)
class Recipe:
    """A named collection: which levels, how many episodes each, the dataset id and the burst filter.

    Attributes:
        episodes: Episodes per level (order = dataset order).
        dataset_id: Minari id it writes.
        max_burst: `CollectConfig.max_burst` (None keeps every episode).
    """

    episodes: dict[str, int]
    dataset_id: str
    max_burst: float | None


RECIPES: dict[str, Recipe] = {
    # checkpoints/breakout-gmt before 2026-11-26: one tracker weakened only by random actions.
    "mixed": Recipe(DEFAULT_EPISODES, DATASET_ID, 30.0),
    # Late reactions, a deterministic weakness (docs/breakout.md); tunnels up to 60 points are kept, since the
    # best level's high returns come from them.
    "react": Recipe(
        {"ace": 100, "late135": 100, "late152": 100, "late164": 100, "late172": 100},
        "gmt/breakout/react-v1",
        60.0,
    ),
    # Late reactions and random actions on the ball-x tracker.
    "late": Recipe(
        {"strong": 80, "slow140": 80, "slow150": 80, "slow160": 80, "slow168": 80},
        "gmt/breakout/late-v1",
        30.0,
    ),
    # The `react` levels with disturbances whose steps record the level's own action (DART).
    "dart": Recipe(
        {"dart0": 100, "dart135": 100, "dart152": 100, "dart164": 100, "dart172": 100},
        "gmt/breakout/dart-v1",
        60.0,
    ),
    # Trackers that lead the ball by 4 steps, weakened by late reactions (the `react` ladder on a learnable rule).
    "lead": Recipe(
        {"lead4": 120, "lead140": 120, "lead152": 120, "lead162": 120, "lead170": 120},
        "gmt/breakout/lead-v1",
        60.0,
    ),
}
DEFAULT_RECIPE = "mixed"
# Agent steps per episode at most: the 1000-step episodes of the evaluation protocol (docs/architecture.md; the
# paper's Breakout switch at step 300 splits an episode 0.3 / 0.7). At 2000 the strong level's returns (~280)
# dwarf the others and the relabelling picks k = 2.
DEFAULT_MAX_STEPS = 1000


class TrackingAgent:
    """Moves the paddle's centre under the ball (or under its predicted landing point); FIRE launches a ball."""

    def __init__(self, skill: Skill, offset: int = PADDLE_OFFSET):
        self.skill = skill
        self.offset = offset
        self.name = skill.name
        self.reset()

    def reset(self) -> None:
        """Forget the ball's history (call at every episode start)."""
        self._seen: deque[RamState] = deque(maxlen=self.skill.lag + 2)
        self._aim_error = 0.0
        self._descending = False
        self._prev_dir = 0

    def target(self, now: RamState, before: RamState | None) -> float:
        """Paddle x to move to, from the ball now and one step before."""
        x = float(now.ball_x)
        s = self.skill
        if (s.predict or s.lead) and before is not None and before.in_play:
            vx, vy = now.ball_x - before.ball_x, now.ball_y - before.ball_y
            if vy > 0 and now.ball_y < PADDLE_Y:
                steps = (PADDLE_Y - now.ball_y) / vy
                x = _reflect(now.ball_x + vx * (steps if s.predict else min(s.lead, steps)))
        return x - self.offset + self._aim_error

    def act(self, state: RamState, rng: np.random.Generator) -> int:
        """The action the game gets; `self.label` is then the action the step records (they differ only
        under a disturbance)."""
        s = self.skill
        if s.random_prob and rng.random() < s.random_prob:
            self._seen.append(state)
            self.label = self.played(int(rng.integers(4)))
            return self.label
        self.label = self.decide(state, rng)
        if s.disturb and rng.random() < s.disturb:
            return self.played(int(rng.integers(4)))
        return self.label

    def decide(self, state: RamState, rng: np.random.Generator) -> int:
        """The level's own action on `state` (no random action, no disturbance), taken as played; call
        `played` when the game got another one."""
        self._seen.append(state)
        return self._policy(state, rng)

    def played(self, action: int) -> int:
        """Note that the game got `action` (the paddle's carry follows it); returns it."""
        self._prev_dir = {RIGHT: 1, LEFT: -1}.get(action, 0)
        return action

    def _policy(self, state: RamState, rng: np.random.Generator) -> int:
        s = self.skill
        if not state.in_play:
            self._seen.clear()
            self._prev_dir = 0
            return FIRE
        seen = list(self._seen)
        now = seen[max(0, len(seen) - 1 - s.lag)]
        before = seen[len(seen) - 2 - s.lag] if len(seen) >= s.lag + 2 else None
        descending = before is not None and now.ball_y > before.ball_y
        if descending and not self._descending and s.jitter:
            self._aim_error = float(rng.normal(0.0, s.jitter))
        self._descending = descending
        if not now.in_play:
            return self._move(0)
        if s.react_y and not (descending and now.ball_y >= s.react_y):
            return self._move(0)  # not yet: wait for the ball to come down
        goal = self.target(now, before)
        # Where the paddle comes to rest for each move: the last move still carries it PADDLE_CARRY further.
        rest = state.paddle_x + PADDLE_CARRY * self._prev_dir
        best = min((-1, 0, 1), key=lambda d: (abs(rest + PADDLE_MOVE * d - goal), d != 0))
        return self._move(best)

    def _move(self, direction: int) -> int:
        self._prev_dir = direction
        return {-1: LEFT, 0: NOOP, 1: RIGHT}[direction]


def _reflect(x: float) -> float:
    """Fold an extrapolated ball x back between the side walls."""
    width = WALL_RIGHT - WALL_LEFT
    y = (x - WALL_LEFT) % (2 * width)
    return WALL_LEFT + (y if y <= width else 2 * width - y)


def describe_level(level: str) -> str:
    """A level's play in words, e.g. "tracks the landing point, reacts below y 135"."""
    if level == "random":
        return "uniform-random actions"
    s = LEVELS[level]
    if s.predict:
        parts = ["tracks the landing point"]
    else:
        parts = [f"tracks the ball {s.lead} steps ahead" if s.lead else "tracks the ball"]
    parts += [f"reacts below y {s.react_y}"] if s.react_y else []
    parts += [f"lag {s.lag} steps"] if s.lag else []
    parts += [f"aim error std {s.jitter:g}"] if s.jitter else []
    parts += [f"{s.random_prob:.0%} random actions"] if s.random_prob else []
    parts += [f"{s.disturb:.0%} disturbed steps recording its own action"] if s.disturb else []
    return ", ".join(parts)


def make_agent(level: str) -> RandomAgent | TrackingAgent:
    """The agent of a level name: "random" or a key of `LEVELS`."""
    if level == "random":
        return RandomAgent()
    if level not in LEVELS:
        raise ValueError(f"unknown level {level!r}; levels: random, {', '.join(LEVELS)}")
    return TrackingAgent(LEVELS[level])


@dataclass
class Played:
    """One episode as played: T actions, T + 1 observations."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    lives: np.ndarray
    terminated: bool
    truncated: bool
    ball_y: np.ndarray  # [T + 1] RAM ball y after reset and after every step (0: no ball in play)
    executed: np.ndarray | None = None  # [T] the actions the game got, for an agent that disturbs its play

    def to_episode(self, episode_id: int) -> Episode:
        infos = {"lives": self.lives}
        if self.executed is not None:
            infos["executed_action"] = self.executed
        return Episode(
            observations=self.observations[:-1],
            actions=self.actions,
            rewards=self.rewards,
            terminated=self.terminated,
            truncated=self.truncated,
            infos=infos,
            final_observation=self.observations[-1],
            episode_id=episode_id,
        )

    @classmethod
    def from_steps(
        cls,
        frames: list,
        actions: list[int],
        rewards: list[float],
        lives: list[float],
        terminated: bool,
        truncated: bool,
        ball_y: list[int],
        executed: list[int] | None = None,
    ) -> Played:
        """An episode from the per-step lists a player gathers (frames and ball_y: T + 1 entries, the rest T)."""
        return cls(
            observations=np.asarray(frames, dtype=np.uint8),
            actions=np.asarray(actions, dtype=np.int64),
            rewards=np.asarray(rewards, dtype=np.float32),
            lives=np.asarray(lives, dtype=np.float64),
            terminated=bool(terminated),
            truncated=bool(truncated),
            ball_y=np.asarray(ball_y, dtype=np.int64),
            executed=None if executed is None else np.asarray(executed, dtype=np.int64),
        )

    @property
    def ret(self) -> float:
        return float(self.rewards.sum())

    @property
    def max_burst(self) -> float:
        """Most points scored between two touches of the paddle (see `bursts`)."""
        b = bursts(self.ball_y, self.rewards)
        return float(b.max()) if len(b) else 0.0


def bursts(ball_y: np.ndarray, rewards: np.ndarray, low: int = 150) -> np.ndarray:
    """Points scored in each stretch of play between two paddle touches (or losses of the ball).

    Args:
        ball_y: [T + 1] RAM ball y after reset and after each step (0 while no ball is in play).
        rewards: [T] reward of each step.
        low: A touch is a turn from falling to rising with the ball below this y (the paddle is at ~183).

    Normally the ball breaks one brick (1-7 points) per trip up: in 90 measured episodes of the medium, good and
    strong levels no stretch scored more than 18, except two "tunnel" bursts (the ball got through the wall and
    bounced behind it) of 84 and 175 points.
    """
    y = np.asarray(ball_y, dtype=np.int64)
    touch = np.zeros(len(rewards), dtype=bool)  # touch[t - 1]: the ball turned up at the paddle at y[t]
    if len(y) >= 3:
        mid = y[1:-1]
        touch[:-1] = (mid > low) & (y[:-2] < mid) & (y[2:] < mid) & (y[:-2] > 0) & (y[2:] > 0)
    lost = y[1:] == 0
    ends = np.flatnonzero(touch | lost)
    return np.asarray([seg.sum() for seg in np.split(np.asarray(rewards), ends + 1)], dtype=np.float64)


def play(
    env: gym.Env,
    agent,
    seed: int,
    rng: np.random.Generator,
    max_steps: int,
    keep_frames: bool = True,
) -> Played:
    """One episode from `env.reset(seed=seed)` until game over or `max_steps` agent steps (then truncated)."""
    obs, _ = env.reset(seed=seed)
    agent.reset()
    frames = [obs] if keep_frames else []
    actions, executed, rewards, lives = [], [], [], []
    state = read_ram(env)
    ball_y = [state.ball_y]
    terminated = truncated = False
    while not (terminated or truncated):
        action = agent.act(state, rng)
        obs, reward, terminated, truncated, info = env.step(action)
        state = read_ram(env)
        if keep_frames:
            frames.append(obs)
        actions.append(getattr(agent, "label", action))  # the agent's own action (DART: not the executed one)
        executed.append(action)
        rewards.append(reward)
        lives.append(info["lives"])
        ball_y.append(state.ball_y)
        if len(actions) >= max_steps and not terminated:
            truncated = True
    return Played.from_steps(
        frames if keep_frames else np.zeros((0,), np.uint8),
        actions,
        rewards,
        lives,
        terminated,
        truncated,
        ball_y,
        executed if _disturbs(agent) else None,
    )


def _disturbs(agent) -> bool:
    skill = getattr(agent, "skill", None)
    return bool(skill is not None and skill.disturb)


@dataclass
class CollectConfig:
    """One Breakout collection run.

    Attributes:
        episodes: Episodes per level, by level name (order = dataset order).
        max_steps: Cap on an episode's agent steps (truncated there).
        seed: Root seed of reset seeds and of the agents' randomness.
        dataset_id: Minari id to write.
        data_dir: Datasets root (None: $GMT_DATA_DIR, else data/minari).
        preprocessing: The observation pipeline (stored in the dataset metadata).
        compress: gzip level (0-9) the frames are recompressed with after writing; 0 keeps Minari's raw file.
        max_burst: Replace an episode in which the ball scored more than this many points between two touches
            of the paddle (a "tunnel" burst: the ball got behind the wall and scored by itself, so the return
            says more about luck than about the level; one such episode of a medium agent scored 255 in 1000
            steps, 10x its level, and became a goal of its own). None keeps every episode.
        max_attempts: Episodes tried per level at most, as a multiple of its episode count.
        overwrite: Replace an existing dataset with the same id.
    """

    episodes: dict[str, int] = field(default_factory=lambda: dict(DEFAULT_EPISODES))
    max_steps: int = DEFAULT_MAX_STEPS
    seed: int = 0
    dataset_id: str = DATASET_ID
    data_dir: Path | None = None
    preprocessing: Preprocessing = field(default_factory=Preprocessing)
    compress: int = 4
    max_burst: float | None = 30.0
    max_attempts: int = 3
    overwrite: bool = True

    def __post_init__(self) -> None:
        for level, n in self.episodes.items():
            make_agent(level)
            if n < 1:
                raise ValueError(f"episodes[{level!r}] must be >= 1, got {n}")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {self.max_attempts}")
        if not 0 <= self.compress <= 9:
            raise ValueError(f"compress must be a gzip level 0-9, got {self.compress}")


def collect_breakout(cfg: CollectConfig | None = None, progress: bool = True) -> CollectResult:
    """Roll out every level `cfg.episodes[level]` times and write one Minari dataset.

    Each level draws its reset seeds and agent randomness from its own child of `SeedSequence(cfg.seed)`, so
    the same config writes the same arrays. Episode metadata: policy, reset_seed, score (RAM), return and
    max_burst. Episodes with a burst above `cfg.max_burst` are replaced by new ones (their returns are listed
    per level in the result).
    """
    from tqdm import tqdm

    cfg = cfg or CollectConfig()
    start = time.time()
    env = make_env(cfg.preprocessing)
    episodes, metadata, levels = [], [], {}
    children = np.random.SeedSequence(cfg.seed).spawn(len(cfg.episodes))
    total = sum(cfg.episodes.values())
    with tqdm(total=total, desc=f"collect {ENV_ID}", unit="ep", disable=not progress) as bar:
        for (level, n), seeds in zip(cfg.episodes.items(), children, strict=True):
            agent = make_agent(level)
            reset_seeds = iter(seeds.generate_state(n * cfg.max_attempts, dtype=np.uint32))
            rng = np.random.default_rng(seeds)
            returns, lengths, replaced = [], [], []
            while len(returns) < n:
                reset_seed = next(reset_seeds, None)
                if reset_seed is None:
                    raise RuntimeError(
                        f"{level}: {len(replaced)} of {len(returns) + len(replaced)} episodes had a burst of more "
                        f"than {cfg.max_burst} points; giving up"
                    )
                ep = play(env, agent, int(reset_seed), rng, cfg.max_steps)
                if cfg.max_burst is not None and ep.max_burst > cfg.max_burst:
                    replaced.append(ep.ret)
                    continue
                episodes.append(ep.to_episode(len(episodes)))
                metadata.append(
                    {
                        "policy": level,
                        "reset_seed": int(reset_seed),
                        "score": read_ram(env).score,
                        "return": ep.ret,
                        "max_burst": ep.max_burst,
                    }
                )
                returns.append(ep.ret)
                lengths.append(len(ep.actions))
                bar.update(1)
                bar.set_postfix(level=level, ret=f"{np.mean(returns):.1f}", replaced=len(replaced))
            levels[level] = {**_summary(returns, lengths, cfg.max_steps), "replaced_returns": replaced}
    env.close()
    replaced = ", ".join(f"{k} {len(v['replaced_returns'])}" for k, v in levels.items())
    description = (
        f"Mixed-skill {ENV_ID} data from scripted agents reading the ball and paddle from RAM: "
        f"{', '.join(f'{k} ({describe_level(k)}, {n} episodes)' for k, n in cfg.episodes.items())}. "
        "Episodes capped at "
        f"{cfg.max_steps} agent steps, seed {cfg.seed}. "
        + (
            f"Episodes in which the ball scored more than {cfg.max_burst:g} points between two paddle touches "
            f"(it got behind the wall) were replaced ({replaced}). "
            if cfg.max_burst is not None
            else ""
        )
        + f"Observations: {json.dumps(cfg.preprocessing.to_dict())}. Written by `python -m gmt.datagen.breakout`."
    )
    path = write_dataset(
        cfg.dataset_id,
        episodes,
        ENV_ID,
        env.observation_space,
        env.action_space,
        cfg.data_dir,
        episode_metadata=metadata,
        description=description,
        algorithm_name="gmt-scripted-breakout-ram",
        overwrite=cfg.overwrite,
    )
    # The stacked frames are no "image space" to Minari, so they were stored raw, not JPEG: say so.
    update_metadata(
        path,
        {
            "preprocessing": cfg.preprocessing.to_dict(),
            "max_episode_steps": cfg.max_steps,
            "max_burst": cfg.max_burst,
            "jpeg_encoding": False,
        },
    )
    if cfg.compress:
        recompress(path, cfg.compress)
    return CollectResult(
        dataset_id=cfg.dataset_id,
        path=path,
        levels=levels,
        episodes=len(episodes),
        transitions=sum(len(e) for e in episodes),
        seconds=time.time() - start,
        bytes=sum(f.stat().st_size for f in path.rglob("*") if f.is_file()),
    )


def _summary(returns: list[float], lengths: list[int], cap: int) -> dict:
    r, n = np.asarray(returns), np.asarray(lengths)
    return {
        "episodes": len(r),
        "mean_return": float(r.mean()),
        "std_return": float(r.std()),
        "min_return": float(r.min()),
        "max_return": float(r.max()),
        "mean_length": float(n.mean()),
        "capped": int((n >= cap).sum()),
    }


def update_metadata(path: Path, extra: dict) -> None:
    """Add keys to the dataset's metadata.json (Minari keeps keys it does not know)."""
    meta_path = path / "metadata.json"
    meta = json.loads(meta_path.read_text())
    meta.update(extra)
    meta_path.write_text(json.dumps(meta))


def recompress(path: Path, level: int = 4) -> None:
    """Rewrite `path`/main_data.hdf5 with every dataset gzip-compressed (h5py reads it transparently).

    Minari writes the [T + 1, 4, H, W] frame arrays raw (a stack is not an "image space" to it, so it neither
    JPEG-encodes nor compresses them); Breakout frames are mostly black: gzip level 4 stores them in 1/68 of
    the space, losslessly.
    """
    import h5py

    src = path / "main_data.hdf5"
    tmp = path / "main_data.hdf5.tmp"

    def copy(s: h5py.Group, d: h5py.Group) -> None:
        d.attrs.update(dict(s.attrs))
        for key, item in s.items():
            if isinstance(item, h5py.Group):
                copy(item, d.create_group(key))
                continue
            data = item[()]
            if item.ndim == 0:
                d.create_dataset(key, data=data)
            else:
                chunks = (min(len(data), 256), *data.shape[1:]) if len(data) else None
                d.create_dataset(
                    key,
                    data=data,
                    chunks=chunks,
                    maxshape=(None, *data.shape[1:]),
                    compression="gzip" if len(data) else None,
                    compression_opts=level if len(data) else None,
                )
            d[key].attrs.update(dict(item.attrs))

    with h5py.File(src, "r") as s, h5py.File(tmp, "w") as d:
        copy(s, d)
    shutil.move(tmp, src)


def measure_levels(
    levels: list[str],
    episodes: int = 10,
    max_steps: int = DEFAULT_MAX_STEPS,
    seed: int = 0,
    prep: Preprocessing | None = None,
) -> dict[str, dict]:
    """Mean return and length of each level over `episodes` episodes (no frames kept)."""
    env = make_env(prep)
    out = {}
    for i, level in enumerate(levels):
        agent = make_agent(level)
        seeds = np.random.SeedSequence([seed, i])
        rng = np.random.default_rng(seeds)
        rets, lens, burst = [], [], []
        for reset_seed in seeds.generate_state(episodes, dtype=np.uint32):
            ep = play(env, agent, int(reset_seed), rng, max_steps, keep_frames=False)
            rets.append(ep.ret)
            lens.append(len(ep.actions))
            burst.append(ep.max_burst)
        out[level] = {**_summary(rets, lens, max_steps), "max_burst": float(max(burst))}
    env.close()
    return out


def _parse_episodes(items: list[str] | None) -> dict[str, int] | None:
    if not items:
        return None
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if not value.isdigit():
            raise argparse.ArgumentTypeError(f"expected LEVEL=N, got {item!r}")
        out[name] = int(value)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: collect (default) or measure the levels."""
    p = argparse.ArgumentParser(
        prog="python -m gmt.datagen.breakout",
        description="Scripted Breakout agents (RAM) at several skill levels into a Minari dataset.",
    )
    recipes = "; ".join(
        f"{name}: {' '.join(f'{k}={v}' for k, v in r.episodes.items())} -> {r.dataset_id}"
        for name, r in RECIPES.items()
    )
    p.add_argument(
        "--recipe",
        choices=sorted(RECIPES),
        default=DEFAULT_RECIPE,
        help=f"Levels, episodes, dataset id and burst filter to start from (default {DEFAULT_RECIPE}; {recipes}).",
    )
    p.add_argument(
        "--episodes",
        nargs="*",
        metavar="LEVEL=N",
        help="Episodes per level instead of the recipe's, e.g. random=10 strong=5.",
    )
    p.add_argument(
        "--max-steps",
        type=int,
        default=DEFAULT_MAX_STEPS,
        help=f"Cap on agent steps per episode (default {DEFAULT_MAX_STEPS}).",
    )
    p.add_argument("--seed", type=int, default=0, help="Root seed (default 0).")
    p.add_argument("--out-id", help="Dataset id (default: the recipe's).")
    p.add_argument("--data-dir", type=Path, help="Datasets root (default $GMT_DATA_DIR, else data/minari).")
    p.add_argument("--screen-size", type=int, default=64, help="Square frame side (default 64).")
    p.add_argument("--stack", type=int, default=4, help="Stacked frames (default 4).")
    p.add_argument("--sticky", type=float, default=0.25, help="repeat_action_probability (default 0.25).")
    p.add_argument("--compress", type=int, default=4, help="gzip level of the arrays, 0 = none (default 4).")
    p.add_argument(
        "--max-burst",
        type=float,
        help="Replace episodes scoring more than this between two paddle touches; < 0 keeps all (default: the "
        "recipe's).",
    )
    p.add_argument(
        "--measure",
        type=int,
        default=0,
        metavar="N",
        help="Instead of collecting, print each level's return and length over N episodes (no frames kept).",
    )
    p.add_argument("--no-progress", action="store_true", help="No progress bar.")
    args = p.parse_args(argv)
    prep = Preprocessing(
        screen_size=args.screen_size, stack=args.stack, repeat_action_probability=args.sticky
    )
    recipe = RECIPES[args.recipe]
    try:
        episodes = _parse_episodes(args.episodes) or dict(recipe.episodes)
        for level in episodes:
            make_agent(level)
    except (argparse.ArgumentTypeError, ValueError) as e:
        p.error(str(e))
    if args.measure:
        levels = list(episodes)
        for level, s in measure_levels(levels, args.measure, args.max_steps, args.seed, prep).items():
            print(f"{level:<8} {json.dumps(s)}")
        return 0
    max_burst = recipe.max_burst if args.max_burst is None else args.max_burst
    cfg = CollectConfig(
        episodes=episodes,
        max_steps=args.max_steps,
        seed=args.seed,
        dataset_id=args.out_id or recipe.dataset_id,
        data_dir=args.data_dir,
        preprocessing=prep,
        compress=args.compress,
        max_burst=max_burst if max_burst is not None and max_burst >= 0 else None,
    )
    res = collect_breakout(cfg, progress=not args.no_progress)
    print(f"wrote {res.dataset_id} to {res.path} ({res.bytes / 2**20:.1f} MiB)")
    print(f"{res.episodes} episodes, {res.transitions} transitions in {res.seconds:.1f} s")
    for level, s in res.levels.items():
        print(
            f"  {level:<8} {s['episodes']} episodes, return {s['mean_return']:.1f} +- {s['std_return']:.1f} "
            f"[{s['min_return']:g}, {s['max_return']:g}], length {s['mean_length']:.0f}, {s['capped']} capped, "
            f"replaced {s['replaced_returns']}"
        )
    print(f"root: {data_root(args.data_dir)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
