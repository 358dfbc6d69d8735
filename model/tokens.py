"""Normalisation of states and actions, and the one left-padding window convention.

Training, evaluation and serving all build model inputs with `Windows`; a window holds the last K steps of an
episode, left-padded with zeros and `valid = False` when fewer than K steps exist.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class ObsNormalizer:
    """Per-dimension standardisation for vector observations; identity (uint8 kept) for images.

    Attributes:
        mean: [D] dataset mean (None for images).
        std: [D] dataset standard deviation, floored at 1e-6 (None for images).
    """

    mean: np.ndarray | None = None
    std: np.ndarray | None = None

    @staticmethod
    def is_image(observations: np.ndarray) -> bool:
        """Whether a [N, *obs_shape] array holds images (uint8, 3 dims per obs), which pass unchanged."""
        return observations.dtype == np.uint8 and observations.ndim == 4

    @classmethod
    def fit(cls, observations: np.ndarray) -> ObsNormalizer:
        """Statistics of a [N, *obs_shape] array; images are not standardised."""
        if cls.is_image(observations):
            return cls()
        x = observations.astype(np.float64)
        return cls(mean=x.mean(0).astype(np.float32), std=np.maximum(x.std(0), 1e-6).astype(np.float32))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Normalise observations of shape [..., D] (float32) or pass images through (uint8)."""
        if self.mean is None:
            return np.asarray(obs, dtype=np.uint8)
        return ((np.asarray(obs, dtype=np.float32) - self.mean) / self.std).astype(np.float32)

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        if self.mean is None:
            return {"kind": "image"}
        return {"kind": "standard", "mean": self.mean.tolist(), "std": self.std.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> ObsNormalizer:
        """Inverse of `to_dict`."""
        if d["kind"] == "image":
            return cls()
        return cls(np.asarray(d["mean"], dtype=np.float32), np.asarray(d["std"], dtype=np.float32))


@dataclass
class ActionCodec:
    """Maps Box actions to [-1, 1] for the model and back (clipped); discrete actions pass as ids.

    Attributes:
        low: [A] lower bounds (None for discrete).
        high: [A] upper bounds (None for discrete).
    """

    low: np.ndarray | None = None
    high: np.ndarray | None = None

    @property
    def discrete(self) -> bool:
        """Whether actions are ids."""
        return self.low is None

    def encode(self, actions: np.ndarray) -> np.ndarray:
        """Environment actions -> model targets ([-1, 1] float32, or int64 ids)."""
        if self.discrete:
            return np.asarray(actions, dtype=np.int64)
        a = (np.asarray(actions, dtype=np.float32) - self.low) / (self.high - self.low) * 2.0 - 1.0
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def decode(self, y: np.ndarray) -> np.ndarray:
        """Model outputs in [-1, 1] -> environment actions, clipped to the bounds."""
        if self.discrete:
            return np.asarray(y, dtype=np.int64)
        a = (np.asarray(y, dtype=np.float32) + 1.0) / 2.0 * (self.high - self.low) + self.low
        return np.clip(a, self.low, self.high).astype(np.float32)

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        if self.discrete:
            return {"kind": "discrete"}
        return {"kind": "box", "low": self.low.tolist(), "high": self.high.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> ActionCodec:
        """Inverse of `to_dict`."""
        if d["kind"] == "discrete":
            return cls()
        return cls(np.asarray(d["low"], dtype=np.float32), np.asarray(d["high"], dtype=np.float32))


@dataclass
class Windows:
    """A batch of left-padded windows, ready for `GMT.forward` (all torch tensors).

    Attributes:
        goals: [B, K] goal ids (0 in padding).
        states: [B, K, *obs_shape] normalised states (0 in padding).
        actions: [B, K, A] float or [B, K] int64 (0 in padding).
        timesteps: [B, K] episode timesteps (0 in padding).
        valid: [B, K] True for real steps.
        rtg: [B, K] float32 returns-to-go (0 in padding), when the sampler has rewards (Decision Transformer).
    """

    goals: torch.Tensor
    states: torch.Tensor
    actions: torch.Tensor
    timesteps: torch.Tensor
    valid: torch.Tensor
    rtg: torch.Tensor | None = None

    def model_inputs(self) -> tuple[torch.Tensor, ...]:
        """Positional arguments of `GMT.forward`."""
        return self.goals, self.states, self.actions, self.timesteps, self.valid

    def select(self, rows: slice) -> Windows:
        """Rows `rows` of the batch."""
        return Windows(
            *(x[rows] for x in self.model_inputs()), rtg=None if self.rtg is None else self.rtg[rows]
        )

    def to(self, device: torch.device) -> Windows:
        """The batch on `device`."""
        rtg = None if self.rtg is None else self.rtg.to(device)
        return Windows(*(x.to(device) for x in self.model_inputs()), rtg=rtg)


def pad_left(
    goals: list[np.ndarray],
    states: list[np.ndarray],
    actions: list[np.ndarray],
    timesteps: list[np.ndarray],
    K: int,
) -> Windows:
    """Left-pad per-row sequences (each of length n <= K) into one `Windows` batch.

    Args:
        goals: per row [n] goal ids.
        states: per row [n, *obs_shape] normalised states.
        actions: per row [n, A] or [n] actions.
        timesteps: per row [n] timesteps.
        K: Window length.
    """
    B = len(goals)
    obs_shape = states[0].shape[1:]
    act_shape = actions[0].shape[1:]
    g = np.zeros((B, K), dtype=np.int64)
    s = np.zeros((B, K, *obs_shape), dtype=states[0].dtype)
    a = np.zeros((B, K, *act_shape), dtype=actions[0].dtype)
    t = np.zeros((B, K), dtype=np.int64)
    v = np.zeros((B, K), dtype=bool)
    for i in range(B):
        n = len(goals[i])
        if n > K:
            raise ValueError(f"row {i} has {n} steps, more than the window length {K}")
        g[i, K - n :] = goals[i]
        s[i, K - n :] = states[i]
        a[i, K - n :] = actions[i]
        t[i, K - n :] = timesteps[i]
        v[i, K - n :] = True
    return Windows(*(torch.from_numpy(x) for x in (g, s, a, t, v)))


class WindowSampler:
    """Samples training windows from concatenated episodes, proportional to episode length.

    A window ends at a uniformly drawn transition and holds up to K steps before it, left-padded at an
    episode's start.
    """

    def __init__(
        self,
        states: list[np.ndarray] | np.ndarray,
        actions: list[np.ndarray],
        goals: list[int | np.ndarray],
        K: int,
        rewards: list[np.ndarray] | None = None,
    ) -> None:
        """Build from per-episode arrays.

        Args:
            states: per episode [T, *obs_shape] normalised states (copied into one array), or all of them
                already concatenated [N, *obs_shape] (kept without a copy).
            actions: per episode [T, A] encoded actions (or [T] ids).
            goals: per episode its goal label, or [T] labels per step (served sessions with goal switches).
            K: Window length.
            rewards: per episode [T] rewards; windows then carry returns-to-go (the sum of the rewards from
                each step to the episode's end).
        """
        lengths = np.array([len(x) for x in actions])
        if isinstance(states, np.ndarray):
            if len(states) != lengths.sum():
                raise ValueError(f"{len(states)} concatenated states for {lengths.sum()} actions")
        elif [len(x) for x in states] != lengths.tolist():
            raise ValueError("every episode needs as many states as actions")
        self.K = K
        self.states = torch.from_numpy(states if isinstance(states, np.ndarray) else np.concatenate(states))
        self.actions = torch.from_numpy(np.concatenate(actions))  # [N, A] or [N]
        per_step = [
            np.full(n, g, dtype=np.int64) if np.ndim(g) == 0 else np.asarray(g, dtype=np.int64)
            for g, n in zip(goals, lengths, strict=True)
        ]
        if any(len(g) != n for g, n in zip(per_step, lengths, strict=True)):
            raise ValueError("per-step goal labels must have one label per step of their episode")
        self.goals = torch.from_numpy(np.concatenate(per_step) if per_step else np.zeros(0, np.int64))  # [N]
        starts = np.repeat(np.cumsum(lengths) - lengths, lengths)  # [N] start index of each row's episode
        self.start = torch.from_numpy(starts)
        self.timesteps = torch.from_numpy(np.arange(len(starts)) - starts)  # [N]
        self.n = len(starts)
        self.rtg = None
        if rewards is not None:
            rtg = [np.cumsum(np.asarray(r, dtype=np.float64)[::-1])[::-1] for r in rewards]
            self.rtg = torch.from_numpy(np.concatenate(rtg).astype(np.float32))  # [N]

    def to(self, device: torch.device) -> WindowSampler:
        """Move the concatenated episodes to `device` (in place); windows are then gathered there."""
        for name in ("states", "actions", "goals", "start", "timesteps", "rtg"):
            x = getattr(self, name)
            if x is not None:
                setattr(self, name, x.to(device))
        return self

    def windows(self, ends: torch.Tensor) -> Windows:
        """Windows ending at the given global transition indices ([B] int64, on any device)."""
        ends = ends.to(self.states.device)
        offs = torch.arange(-self.K + 1, 1, device=ends.device)  # [K]
        idx = ends[:, None] + offs[None, :]  # [B, K]
        valid = idx >= self.start[ends][:, None]  # [B, K]
        idx = torch.where(valid, idx, ends[:, None])  # padding reads a real row, then zeroed
        states = self.states[idx]  # [B, K, *obs_shape]
        actions = self.actions[idx]  # [B, K, A] or [B, K]
        zero_s = valid.view(*valid.shape, *([1] * (states.dim() - 2)))
        zero_a = valid.view(*valid.shape, *([1] * (actions.dim() - 2)))
        return Windows(
            goals=torch.where(valid, self.goals[idx], 0),
            states=torch.where(zero_s, states, torch.zeros((), dtype=states.dtype)),
            actions=torch.where(zero_a, actions, torch.zeros((), dtype=actions.dtype)),
            timesteps=torch.where(valid, self.timesteps[idx], 0),
            valid=valid,
            rtg=None if self.rtg is None else torch.where(valid, self.rtg[idx], 0.0),
        )

    def sample(self, batch_size: int, generator: torch.Generator) -> Windows:
        """A batch of windows ending at uniformly drawn transitions."""
        return self.windows(torch.randint(0, self.n, (batch_size,), generator=generator))
