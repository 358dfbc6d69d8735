"""Run one episode of a policy in a Gymnasium environment and keep everything a dataset needs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from gmt.datagen.start_states import start_from
from gmt.model.data.minari_io import Episode


class Policy(Protocol):
    """Anything with `act(obs, rng) -> action` (rng None means deterministic); a policy with per-episode state
    also has `start_episode()`, called before each episode's first action."""

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray: ...


@dataclass
class Rollout:
    """One episode as stepped: T actions, T + 1 observations, per-step scalar infos of length T."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: bool
    truncated: bool
    infos: dict[str, np.ndarray]
    reset_info: dict

    def __len__(self) -> int:
        return len(self.actions)

    def to_episode(self, episode_id: int) -> Episode:
        """The dataset view: observations at which actions were taken, the last one kept apart."""
        return Episode(
            observations=self.observations[:-1],
            actions=self.actions.astype(np.float32 if self.actions.dtype.kind == "f" else np.int64),
            rewards=self.rewards,
            terminated=self.terminated,
            truncated=self.truncated,
            infos=self.infos,
            final_observation=self.observations[-1],
            episode_id=episode_id,
        )


def scalar_items(info: dict) -> dict[str, float]:
    """The numeric scalar entries of an info dict (what statistics can use)."""
    return {
        k: float(v) for k, v in info.items() if np.ndim(v) == 0 and isinstance(v, (int, float, np.number))
    }


def rollout(
    env,
    policy: Policy,
    seed: int,
    rng: np.random.Generator | None,
    max_steps: int | None = None,
    start_state: tuple[np.ndarray, np.ndarray] | None = None,
) -> Rollout:
    """Step `policy` in `env` from `env.reset(seed=seed)` until the episode ends or `max_steps` is reached.

    Args:
        env: A Gymnasium environment (its own TimeLimit still applies).
        policy: Chooses actions; `rng` is passed on for stochastic policies.
        seed: Reset seed of the episode.
        rng: Source of action noise (None for deterministic actions).
        max_steps: Optional extra cap; reaching it marks the episode truncated.
        start_state: Optional MuJoCo (qpos, qvel) to start from instead of the reset pose.

    Returns:
        The episode's arrays. Info keys are those present, as numeric scalars, at every step.
    """
    obs, reset_info = env.reset(seed=seed)
    if start_state is not None:
        obs = start_from(env, *start_state)
    if hasattr(policy, "start_episode"):
        policy.start_episode()
    observations, actions, rewards, infos = [obs], [], [], []
    terminated = truncated = False
    while not (terminated or truncated):
        action = policy.act(obs, rng)
        obs, reward, terminated, truncated, info = env.step(action)
        observations.append(obs)
        actions.append(action)
        rewards.append(reward)
        infos.append(scalar_items(info))
        if max_steps is not None and len(actions) >= max_steps:
            truncated = truncated or not terminated
    keys = set.intersection(*(set(i) for i in infos)) if infos else set()
    return Rollout(
        observations=np.asarray(observations),
        actions=np.asarray(actions),
        rewards=np.asarray(rewards, dtype=np.float32),
        terminated=bool(terminated),
        truncated=bool(truncated),
        infos={k: np.asarray([i[k] for i in infos], dtype=np.float64) for k in sorted(keys)},
        reset_info=reset_info,
    )


def stuck_step(
    x_velocity: np.ndarray,
    window: int = 20,
    run_speed: float = 1.0,
    stop_speed: float = 0.1,
    run_window: int = 20,
    relative: bool = False,
) -> int | None:
    """First step at which an agent that was running has come to a standstill, else None.

    "Running" means a `run_window`-step mean x-velocity above `run_speed` at some earlier point; "standstill"
    means a later `window`-step mean |x-velocity| below `stop_speed`. With `relative` the thresholds come from
    the episode itself, for tasks of any speed scale (the defaults are HalfCheetah's m/s): both windows are
    `window` steps, and with `peak` the 90th percentile of the episode's window means (a start-up transient does
    not set it), running is above half of it and standing still below a tenth of it.
    """
    v = np.asarray(x_velocity, dtype=np.float64)
    if relative:
        if len(v) < window:
            return None
        peak = float(np.quantile(np.convolve(v, np.ones(window) / window, mode="valid"), 0.9))
        if not peak > 0:
            return None
        return stuck_step(v, window, 0.5 * peak, 0.1 * peak, window)
    if len(v) < max(window, run_window):
        return None
    run_means = np.convolve(
        v, np.ones(run_window) / run_window, mode="valid"
    )  # [i] covers i .. i+run_window-1
    ran_by_end = np.maximum.accumulate(run_means > run_speed)  # indexed by window end - run_window + 1
    stop_means = np.convolve(v, np.ones(window) / window, mode="valid")
    ends = np.arange(len(stop_means)) + window - 1  # last step of each stop window
    ran = ran_by_end[np.minimum(ends - run_window + 1, len(ran_by_end) - 1)]
    hits = np.flatnonzero(ran & (np.abs(stop_means) < stop_speed))
    return int(ends[hits[0]]) if len(hits) else None


def measure(env, policy: Policy, episodes: int, seed: int, max_steps: int | None = None) -> dict:
    """Roll out `episodes` stochastic episodes (reset seeds seed, seed + 1, ...): per-episode mean x-velocity,
    length, return, and how many ended in a fall (termination)."""
    rng = np.random.default_rng(seed)
    speeds, lengths, returns, falls = [], [], [], 0
    for i in range(episodes):
        ep = rollout(env, policy, seed=seed + i, rng=rng, max_steps=max_steps)
        speeds.append(float(ep.infos["x_velocity"].mean()))
        lengths.append(len(ep))
        returns.append(float(ep.rewards.sum()))
        falls += ep.terminated
    return {
        "mean_speed": float(np.mean(speeds)),
        "std_speed": float(np.std(speeds)),
        "speeds": speeds,
        "mean_length": float(np.mean(lengths)),
        "min_length": int(np.min(lengths)),
        "mean_return": float(np.mean(returns)),
        "falls": int(falls),
    }
