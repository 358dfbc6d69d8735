"""Episode files: the language-agnostic format `gmt data import` reads, and a small writer for Python collectors.

One episode per `.npz` file (numpy's zip of arrays; any language with a zip and .npy writer can make one):

| array | shape | |
| --- | --- | --- |
| `observations` | [T + 1, ...] or [T, ...] | the observation before each action (and, with T + 1, the one after the last) |
| `actions` | [T, ...] or [T] | float for Box actions, integers for Discrete |
| `rewards` | [T] | |
| `terminations`, `truncations` | [T] | optional; only the last step is read (how the episode ended) |
| `info.KEY` | [T] | optional: a per-step number env.step reported, e.g. `info.x_velocity` |
| `observations.KEY` | [T + 1, ...] or [T, ...] | instead of `observations`, one array per key of a Dict observation |

Torch-free (numpy only), so a thin-client install can write them.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


def _numbers(info: Mapping[str, Any]) -> dict[str, float]:
    return {
        k: float(v)
        for k, v in info.items()
        if np.ndim(v) == 0 and isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
    }


def _obs_arrays(observations: list[Any]) -> dict[str, np.ndarray]:
    if isinstance(observations[0], Mapping):
        return {
            f"observations.{k}": np.stack([np.asarray(o[k]) for o in observations]) for k in observations[0]
        }
    return {"observations": np.stack([np.asarray(o) for o in observations])}


class EpisodeWriter:
    """Write episodes as you step an environment, one `.npz` file each, for `gmt data import`.

    Example:
        writer = EpisodeWriter("my-episodes")
        obs, info = env.reset(seed=0)
        writer.reset(obs)
        while True:
            action = my_policy(obs)
            obs, reward, terminated, truncated, info = env.step(action)
            writer.step(action, obs, reward, terminated, truncated, info)
            if terminated or truncated:
                break  # the episode was written to my-episodes/episode-000000.npz

    Per-step numeric infos become `info.KEY` arrays (keys present at every step only).
    """

    def __init__(self, folder: str | Path, prefix: str = "episode") -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.prefix = prefix
        self.count = len(list(self.folder.glob(f"{prefix}-*.npz")))
        self._obs: list[Any] | None = None

    def reset(self, observation: Any) -> None:
        """Start an episode at its first observation (an unfinished one is dropped)."""
        self._obs, self._actions, self._rewards, self._infos = [observation], [], [], []
        self._ends: list[tuple[bool, bool]] = []

    def step(
        self,
        action: Any,
        observation: Any,
        reward: float,
        terminated: bool,
        truncated: bool,
        info: Mapping[str, Any] | None = None,
    ) -> Path | None:
        """Record one `env.step`; at the episode's end write its file and return its path."""
        if self._obs is None:
            raise RuntimeError("call reset(first_observation) before step()")
        self._actions.append(np.asarray(action))
        self._obs.append(observation)
        self._rewards.append(float(reward))
        self._infos.append(_numbers(info or {}))
        self._ends.append((bool(terminated), bool(truncated)))
        return self.end() if terminated or truncated else None

    def end(self) -> Path:
        """Write the episode so far (e.g. one you stop yourself) and return its path."""
        if not self._actions:
            raise RuntimeError("an episode needs at least one step")
        keys = set.intersection(*(set(i) for i in self._infos))
        arrays = {
            **_obs_arrays(self._obs),
            "actions": np.stack(self._actions),
            "rewards": np.asarray(self._rewards, dtype=np.float32),
            "terminations": np.asarray([t for t, _ in self._ends]),
            "truncations": np.asarray([t for _, t in self._ends]),
            **{f"info.{k}": np.asarray([i[k] for i in self._infos]) for k in sorted(keys)},
        }
        path = self.folder / f"{self.prefix}-{self.count:06d}.npz"
        np.savez_compressed(path, **arrays)
        self.count += 1
        self._obs = None
        return path
