"""One example observation per model, so that a client sees what a real one looks like before sending its own.

Computed once, when the models load (`gmt.service.rest.app`'s lifespan), from what this machine has:
- `reset`: the environment's first observation after `reset(seed=0)`, when its simulator is installed here
  (MuJoCo with the `run` extra; the `serve` extra alone has none);
- `mean`: otherwise, the mean observation of the training data (the checkpoint's normalisation statistics), a
  real-looking vector;
- `hint`: image models get a description of the tensor to send instead of a frame (16 KiB and more).

`GET /models/{name}` answers it as `example_observation`, and the OpenAPI document's act examples use it.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np

from gmt.model.checkpoint import Checkpoint

log = logging.getLogger("gmt.examples")
SEED = 0
DECIMALS = 6  # readable, and still the environment's values to float32 precision or so


@dataclass(frozen=True)
class Example:
    """An example observation of one model.

    Attributes:
        source: "reset", "mean" or "hint" (see the module docstring).
        description: Where it comes from, or for images what to send.
        observation: The observation as nested lists of numbers, ready for `{"observation": ...}` in an act
            (None for images).
    """

    source: str
    description: str
    observation: list | None


def example_observation(ckpt: Checkpoint, seed: int = SEED) -> Example:
    """The example observation of `ckpt`'s model: from its environment if it can be made here, else from its
    normalisation statistics, or a hint for images."""
    space = ckpt.observation_space
    shape = [int(s) for s in space.get("shape", [])]
    if ckpt.obs_norm.mean is None or space.get("dtype") == "uint8":
        dims = " x ".join(map(str, shape))
        n = math.prod(shape)
        return Example(
            "hint",
            f"{dims} uint8 pixels: send them as a base64 tensor, "
            f'{{"data": "<base64 of the {n} raw bytes>", "dtype": "uint8", "shape": {shape}}}'
            + (" (frames made as `preprocessing` says)" if ckpt.preprocessing else ""),
            None,
        )
    first = _first_observation(ckpt.env_id, tuple(shape), seed)
    if first is not None:
        return Example("reset", f"the first observation of {ckpt.env_id} after reset(seed={seed})", first)
    mean = np.asarray(ckpt.obs_norm.mean, dtype=np.float64).reshape(shape)
    return Example(
        "mean",
        f"the mean observation of the training data (the checkpoint's normalisation statistics; {ckpt.env_id} "
        "cannot be made on this server)",
        _rounded(mean),
    )


@functools.lru_cache(maxsize=64)
def _first_observation(env_id: str, shape: tuple[int, ...], seed: int) -> list | None:
    """`reset(seed)`'s observation of `env_id`, or None when the environment cannot be made here or its
    observation does not have the model's shape (once per process: it does not change)."""
    try:
        import gymnasium as gym

        from gmt.common.envs import quiet_known_mujoco_warnings

        quiet_known_mujoco_warnings()
        env = gym.make(env_id)
        try:
            obs, _ = env.reset(seed=seed)
        finally:
            env.close()
    except Exception as e:  # noqa: BLE001 - a missing simulator (DependencyNotInstalled), an unknown id, ...
        log.info(
            "example observation from the normalisation statistics", extra={"env_id": env_id, "why": str(e)}
        )
        return None
    obs = np.asarray(obs, dtype=np.float64)
    if obs.shape != shape or not np.isfinite(obs).all():
        return None
    return _rounded(obs)


def _rounded(x: np.ndarray) -> list:
    return np.round(x, DECIMALS).tolist()


def examples_of(checkpoints: dict[str, Checkpoint]) -> dict[str, Example]:
    """The example observation of each model, by model name."""
    return {name: example_observation(ckpt) for name, ckpt in checkpoints.items()}
