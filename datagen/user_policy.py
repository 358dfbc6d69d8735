"""A user's own behaviour policy for `gmt data collect --policy module:function --level NAME ...`.

The function is called for every step as `function(obs, level, rng) -> action`: `obs` the environment's
observation, `level` the name of the level being collected (a string, as given to `--level`; e.g. "0.2" or
"careful"), `rng` a seeded `numpy.random.Generator` for any randomness (use it, not a global one, so a seed
reproduces the data). The action must belong to the environment's action space (an int for Discrete). Every
level's episodes are one goal's data, so a level should behave the same way for a whole episode. An optional
`start_episode(level)` attribute of the function is called before each episode (per-episode state).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gmt.common.plugins import load_attribute


class UserPolicy:
    """One level of a user's policy function, with the `act(obs, rng)` interface `rollout` steps."""

    def __init__(self, fn: Callable[[Any, str, np.random.Generator | None], Any], level: str, name: str = ""):
        self.fn, self.level, self.name = fn, level, name or getattr(fn, "__name__", "policy")
        self.noise_scale = 1.0  # unused: the function draws its own noise from rng

    def start_episode(self) -> None:
        """Tell the function a new episode starts, when it asks to be told."""
        start = getattr(self.fn, "start_episode", None)
        if start is not None:
            start(self.level)

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> Any:
        """The function's action at this level."""
        return self.fn(obs, self.level, rng if rng is not None else np.random.default_rng(0))


def load_policy_function(spec: str) -> Callable:
    """The function named by "module:function" (`gmt.common.plugins.load_attribute`).

    Raises:
        ValueError: `spec` is not module:function, or it cannot be imported or is not callable.
    """
    module, sep, name = spec.partition(":")
    if not (sep and module and name.isidentifier()):
        raise ValueError(f"--policy must be module:function (e.g. my_policies:cartpole), got {spec!r}")
    try:
        fn = load_attribute(module, name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"--policy {spec}: cannot import it ({e})") from None
    if not callable(fn):
        raise ValueError(f"--policy {spec}: {fn!r} is not a function")
    return fn


class SB3Policy:
    """A Stable-Baselines3 model saved as a `.zip` (`model.save(path)`), acting with its stochastic policy.

    The algorithm is read from the file (PPO, A2C, SAC, TD3 or DQN; the `train` extra installs SB3). Its noise
    comes from torch's generator, seeded from the collection's `rng` at every episode, so a seed reproduces the
    data.
    """

    ALGORITHMS = ("PPO", "A2C", "SAC", "TD3", "DQN")

    def __init__(self, path: str, rng_seed: int = 0) -> None:
        import stable_baselines3

        self.path, self.noise_scale, self._seeds = path, 1.0, np.random.default_rng(rng_seed)
        errors = []
        for name in self.ALGORITHMS:
            try:
                self.model = getattr(stable_baselines3, name).load(path, device="cpu")
                self.algorithm = name
                return
            except Exception as e:  # noqa: BLE001 - the next algorithm may read it
                errors.append(f"{name}: {type(e).__name__}")
        raise ValueError(
            f"{path}: not a Stable-Baselines3 model of {', '.join(self.ALGORITHMS)} ({'; '.join(errors)})"
        )

    def start_episode(self) -> None:
        """Seed the model's noise for the episode."""
        import torch

        torch.manual_seed(int(self._seeds.integers(2**31)))

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> Any:
        """The model's action: sampled, or its deterministic one when `rng` is None."""
        action, _ = self.model.predict(obs, deterministic=rng is None)
        return action.item() if np.ndim(action) == 0 else action


def level_policies(policy: str | None, levels: list[str], seed: int) -> dict[str, Any]:
    """Level name -> policy: `NAME=FILE.zip` levels are Stable-Baselines3 models, other names levels of the
    `policy` function.

    Raises:
        ValueError: a level needs `policy` and none is given, or a file cannot be read.
    """
    fn = load_policy_function(policy) if policy is not None else None
    out = {}
    for i, level in enumerate(levels):
        name, sep, path = level.partition("=")
        if sep:
            if not path.endswith(".zip"):
                raise ValueError(f"--level {level}: NAME=FILE names a Stable-Baselines3 .zip")
            out[name] = SB3Policy(path, rng_seed=seed * 1000 + i)
        elif fn is None:
            raise ValueError(f"--level {level} is a level of a --policy module:function: give --policy")
        else:
            out[level] = UserPolicy(fn, level, policy)
    return out
