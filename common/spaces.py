"""JSON form of Gymnasium spaces (the checkpoint's and the API's description of an environment)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np


def _finite_or_none(x: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(x, dtype=np.float64).ravel()]


def space_to_dict(space: gym.Space) -> dict:
    """Describe a Box or Discrete space; infinite bounds become null."""
    if isinstance(space, gym.spaces.Discrete):
        return {"type": "discrete", "n": int(space.n), "shape": [], "dtype": "int64"}
    if isinstance(space, gym.spaces.Box):
        d = {"type": "box", "shape": list(space.shape), "dtype": str(space.dtype)}
        if space.dtype == np.uint8:
            d["low"], d["high"] = None, None  # images: 0..255 everywhere
        else:
            d["low"], d["high"] = _finite_or_none(space.low), _finite_or_none(space.high)
        return d
    raise TypeError(f"unsupported space {space!r}: only Box and Discrete")


def space_from_dict(d: dict) -> gym.Space:
    """Inverse of `space_to_dict`."""
    if d["type"] == "discrete":
        return gym.spaces.Discrete(d["n"])
    shape = tuple(d["shape"])
    dtype = np.dtype(d["dtype"])
    if dtype == np.uint8:
        return gym.spaces.Box(0, 255, shape=shape, dtype=np.uint8)
    low = np.array([-np.inf if v is None else v for v in d["low"]], dtype=np.float64).reshape(shape)
    high = np.array([np.inf if v is None else v for v in d["high"]], dtype=np.float64).reshape(shape)
    return gym.spaces.Box(low.astype(dtype), high.astype(dtype), shape=shape, dtype=dtype)


def spaces_match(a: dict, b: dict) -> bool:
    """Whether two described spaces are the same kind, shape and (for Discrete) size."""
    if a["type"] != b["type"] or list(a.get("shape", [])) != list(b.get("shape", [])):
        return False
    return a["type"] != "discrete" or a["n"] == b["n"]
