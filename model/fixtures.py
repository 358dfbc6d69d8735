"""Tiny random-weight checkpoints for tests, demos and benchmarks (built in milliseconds, no data needed)."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from gmt.common.spaces import space_to_dict
from gmt.model.checkpoint import Checkpoint, Goal, save_checkpoint
from gmt.model.config import GMTConfig
from gmt.model.gmt import GMT
from gmt.model.tokens import ActionCodec, ObsNormalizer

GOAL_NAMES = ("low", "medium", "high")
# HalfCheetah-v5's spaces, for a machine without the simulator (a GPU machine running the engine's tests).
_HALFCHEETAH_SPACES = (
    gym.spaces.Box(-np.inf, np.inf, (17,), np.float64),
    gym.spaces.Box(-1.0, 1.0, (6,), np.float32),
)


def _spaces(env_id: str) -> tuple[gym.spaces.Space, gym.spaces.Space]:
    """`env_id`'s observation and action spaces (HalfCheetah-v5's known ones where MuJoCo is not installed)."""
    try:
        env = gym.make(env_id)
    except gym.error.DependencyNotInstalled:
        if env_id != "HalfCheetah-v5":
            raise
        return _HALFCHEETAH_SPACES
    spaces = env.observation_space, env.action_space
    env.close()
    return spaces


def tiny_checkpoint(
    directory: str | Path | None = None,
    env_id: str = "HalfCheetah-v5",
    n_goals: int = 3,
    context_length: int = 5,
    seed: int = 0,
    name: str = "tiny-gmt",
    calibrated: bool = False,
    attention: str = "full",
    n_layer: int = 2,
    observation_space: gym.spaces.Space | None = None,
    statistic: str = "mean_x_velocity",
    preprocessing: dict | None = None,
    default_action_mode: str | None = None,
    switch_relabel_steps: int = 0,
) -> Checkpoint:
    """A random-weight checkpoint with the spaces of `env_id` (saved to `directory` when given).

    The goal table is synthetic (means 0, 1, 2, ...); weights are random but seeded. `calibrated` gives a
    continuous-action model a synthetic action noise (std 0.1 * (goal + 1)), enabling its `sample` mode.
    `observation_space` replaces the environment's (e.g. preprocessed Atari frames [stack, H, W]);
    `preprocessing`, `default_action_mode` and `switch_relabel_steps` are stored as a trained checkpoint would
    store them.
    """
    if env_id.startswith("ALE/"):
        import ale_py

        gym.register_envs(ale_py)
    env_obs, act_space = _spaces(env_id)
    obs_space = observation_space or env_obs
    discrete = isinstance(act_space, gym.spaces.Discrete)
    obs_shape = obs_space.shape if len(obs_space.shape) != 2 else (1, *obs_space.shape)
    cfg = GMTConfig(
        obs_shape=obs_shape,
        act_dim=int(act_space.n) if discrete else int(np.prod(act_space.shape)),
        discrete_actions=discrete,
        n_goals=n_goals,
        context_length=context_length,
        n_layer=n_layer,
        n_head=2,
        n_embd=32,
        attention=attention,
    )
    torch.manual_seed(seed)
    model = GMT(cfg).eval()
    if obs_space.dtype == np.uint8:
        norm = ObsNormalizer()
    else:
        rng = np.random.default_rng(seed)
        norm = ObsNormalizer(rng.normal(size=obs_shape).astype(np.float32), np.ones(obs_shape, np.float32))
    codec = (
        ActionCodec()
        if discrete
        else ActionCodec(act_space.low.astype(np.float32), act_space.high.astype(np.float32))
    )
    goals = [
        Goal(
            id=i,
            name=GOAL_NAMES[i] if n_goals == 3 else f"goal-{i}",
            mean=float(i),
            std=0.1,
            min=i - 0.3,
            max=i + 0.3,
            count=10,
        )
        for i in range(n_goals)
    ]
    ckpt = Checkpoint(
        name=name,
        model=model,
        env_id=env_id,
        observation_space=space_to_dict(obs_space),
        action_space=space_to_dict(act_space),
        obs_norm=norm,
        action_codec=codec,
        statistic=statistic,
        goals=goals,
        meta={"note": "random weights for tests"},
        action_noise=(
            np.repeat(0.1 * np.arange(1, n_goals + 1, dtype=np.float32)[:, None], cfg.act_dim, axis=1)
            if calibrated and not discrete
            else None
        ),
        preprocessing=preprocessing,
        default_action_mode=default_action_mode,
        switch_relabel_steps=switch_relabel_steps,
    )
    if directory is not None:
        save_checkpoint(ckpt, directory)
    return ckpt


class _Episode:
    def __init__(self, observations: np.ndarray, actions: np.ndarray, rewards: np.ndarray) -> None:
        self.observations, self.actions, self.rewards = observations, actions, rewards


class SyntheticDataset:
    """A tiny dataset with the attributes training reads (`OfflineDataset`'s duck type).

    HalfCheetah-v5 spaces; episode i has goal i % n_goals and acts as a = tanh(0.5 s[:6] + goal - 1), so the
    action depends on both the state and the goal. Its rewards are goal + 1 per step (plus noise), so the
    return-to-go tells the goal too.
    """

    def __init__(self, n_episodes: int = 12, length: int = 40, n_goals: int = 3, seed: int = 0) -> None:
        self.observation_space, self.action_space = _spaces("HalfCheetah-v5")
        rng = np.random.default_rng(seed)
        self.env_id, self.dataset_id, self.fingerprint = "HalfCheetah-v5", "synthetic", f"synthetic-{seed}"
        self.preprocessing = None  # raw observations
        self.labels = [i % n_goals for i in range(n_episodes)]
        self.episodes = []
        for g in self.labels:
            obs = rng.normal(size=(length, 17)).astype(np.float32)
            act = np.tanh(0.5 * obs[:, :6] + (g - 1.0)).astype(np.float32)
            rew = (g + 1.0 + 0.1 * rng.normal(size=length)).astype(np.float32)
            self.episodes.append(_Episode(obs, act, rew))
        self.goals = [
            Goal(
                id=i,
                name=GOAL_NAMES[i] if n_goals == 3 else f"goal-{i}",
                mean=float(i),
                std=0.0,
                min=float(i),
                max=float(i),
                count=self.labels.count(i),
            )
            for i in range(n_goals)
        ]
