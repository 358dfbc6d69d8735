"""Pools of simulator states visited by other behaviour levels, used as episode start states.

A behaviour level that only ever starts from the environment's rest pose never shows how to reach its speed from
another level's gait (braking from a sprint, standing up after a random policy's flailing). Rolling the other
levels out and keeping their MuJoCo (qpos, qvel) lets a level be trained (`refine_behaviour`) and collected
(`collect`) from those states too. Each episode still has one policy, hence one goal label.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np


@dataclass
class StatePool:
    """MuJoCo states with where they came from.

    Attributes:
        qpos: [N, nq] generalised positions.
        qvel: [N, nv] generalised velocities.
        source: [N] name of the policy whose rollout visited the state.
        step: [N] step of that rollout at which the state was visited.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    source: np.ndarray
    step: np.ndarray

    def __len__(self) -> int:
        return len(self.qpos)

    def sample(self, rng: np.random.Generator) -> int:
        """Index of a uniformly drawn state."""
        return int(rng.integers(len(self)))


def build_pool(
    env, policies: dict, episodes: int, seed: int, skip: int = 20, every: int = 10, max_steps: int = 1000
) -> StatePool:
    """Roll out each policy (stochastically) and keep every `every`-th state after the first `skip` steps.

    Args:
        env: A MuJoCo Gymnasium environment (its `unwrapped` has `data.qpos` / `data.qvel`).
        policies: name -> policy with `act(obs, rng)`.
        episodes: Episodes per policy.
        seed: Seeds the resets (seed, seed + 1, ...) and the action noise.
        skip: Leading steps of each episode not kept (the rest pose is the env's own start).
        every: Keep one state in this many.
        max_steps: Steps per episode at most.

    Returns:
        The pool, ordered by policy, episode and step.
    """
    rng = np.random.default_rng(seed)
    qpos, qvel, source, steps = [], [], [], []
    sim = env.unwrapped
    for name, policy in policies.items():
        for ep in range(episodes):
            obs, _ = env.reset(seed=seed + ep)
            if hasattr(policy, "start_episode"):
                policy.start_episode()
            for t in range(max_steps):
                obs, _, terminated, truncated, _ = env.step(policy.act(obs, rng))
                if terminated:
                    break
                if t >= skip and (t - skip) % every == 0:
                    qpos.append(sim.data.qpos.copy())
                    qvel.append(sim.data.qvel.copy())
                    source.append(name)
                    steps.append(t + 1)
                if truncated:
                    break
    if not qpos:
        raise ValueError("no states collected: every episode ended before `skip` steps")
    return StatePool(np.asarray(qpos), np.asarray(qvel), np.asarray(source), np.asarray(steps))


def start_from(env, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """Put a freshly reset MuJoCo env into state (qpos, qvel) and return its observation there."""
    sim = env.unwrapped
    sim.set_state(qpos, qvel)
    return sim._get_obs()


class PoolStart(gym.Wrapper):
    """On reset, with probability `fraction`, move the simulator to a random pool state."""

    def __init__(self, env, pool: StatePool, fraction: float, seed: int):
        super().__init__(env)
        self.pool, self.fraction, self.rng = pool, fraction, np.random.default_rng(seed)

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        if self.rng.random() < self.fraction:
            i = self.pool.sample(self.rng)
            obs = start_from(self.env, self.pool.qpos[i], self.pool.qvel[i])
        return obs, info


class CheckpointPolicy:
    """A trained GMT holding one goal, as a rollout policy: its visited states can be a start-state pool.

    A GMT imitates its data's transitions from the states its data visited; where its own gait visits other
    states (a little faster, another point of the stride at the moment its goal changes), it has no example of
    the change from there. Starting the behaviour's episodes from the model's own states shows it one, as
    DAgger does for imitation.

    Args:
        engine: A `gmt.model.engine.PolicyEngine` over the checkpoint.
        goal: The goal id held for every episode (the first goal of a cycle).
        seed: First seed of the sampled action noise (one more per episode).
        cycle_every: Instead of holding `goal`, switch to the next goal id (wrapping) every this many steps,
            as the evaluation's multi-switch cycles do: the pool then also holds the states between two
            speeds that a quickly switched model passes through. None: hold.
    """

    def __init__(self, engine, goal: int, seed: int = 0, cycle_every: int | None = None):
        engine.check_goal(goal)
        if cycle_every is not None and cycle_every < 1:
            raise ValueError(f"cycle_every must be >= 1, got {cycle_every}")
        self.engine, self.goal, self.seed, self.ctx = engine, goal, seed, None
        self.cycle_every, self.t = cycle_every, 0

    def start_episode(self) -> None:
        """A fresh context (empty history) for the next episode."""
        if self.ctx is not None:
            self.engine.release(self.ctx)
        self.ctx = self.engine.new_context(self.goal, seed=self.seed)
        self.seed += 1
        self.t = 0

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The model's action for the goal (its own sampling, seeded per episode; `rng` is not used)."""
        if self.ctx is None:
            self.start_episode()
        if self.cycle_every and self.t and self.t % self.cycle_every == 0:
            n = self.engine.n_goals
            self.engine.set_goal(self.ctx, (self.goal + self.t // self.cycle_every) % n)
        self.t += 1
        (action,) = self.engine.act([self.ctx], [obs])
        if isinstance(action, Exception):
            raise action
        return action
