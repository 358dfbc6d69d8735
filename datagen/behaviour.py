"""Behaviour policies used to collect offline data: snapshots (safetensors + JSON) of several kinds, and a random
policy.

A snapshot says what kind it is (`BehaviourMeta.kind`), and each kind has a loader, registered with
`register_kind`; `load_behaviour` calls the loader of the snapshot's kind. Kinds:

- `actor`: the deterministic mean network of a PPO actor plus its state-independent log-std and the observation
  normalisation it was trained with (`BehaviourPolicy`, defined here). A commanded actor
  (`gmt.datagen.train_commanded`) is one speed-conditioned actor with a fixed command: its network reads the
  observation with the commanded speed appended (`extra["command"]`), so several levels can share one actor, and
  each level's episodes still have one goal.
- `gait`: a scripted gait (`gmt.datagen.gait`), whose only tensor is the action noise.
- a kind defined outside this package registers its loader with `register_kind` when its module is imported.

A policy may keep per-episode state, so whoever rolls it out calls `start_episode()` at every reset.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from importlib import import_module
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh}
BEHAVIOUR_DIR = Path(__file__).resolve().parents[1] / "behaviour"


def env_slug(env_id: str) -> str:
    """Lower-case environment name without its version, e.g. HalfCheetah-v5 -> halfcheetah."""
    return env_id.split("/")[-1].rsplit("-v", 1)[0].lower()


@dataclass
class BehaviourMeta:
    """Everything besides the weights that a snapshot needs (the JSON sidecar).

    Attributes:
        env_id: Gymnasium id the policy was trained on.
        level: Skill-level name, e.g. "medium".
        hidden_sizes: Widths of the hidden layers of the mean network.
        activation: "relu" or "tanh".
        obs_mean: VecNormalize running mean of the observations.
        obs_var: VecNormalize running variance of the observations.
        obs_clip: Normalised observations are clipped to [-obs_clip, obs_clip].
        obs_epsilon: Added to the variance before the square root.
        mean_speed: Measured mean of the per-episode mean x-velocity (stochastic policy).
        std_speed: Standard deviation of the per-episode mean x-velocity.
        train_step: Environment steps of training when the snapshot was taken.
        extra: Free-form measurements (episodes used, mean return, mean length); `command` (m/s), when present,
            is appended to every observation before the network reads it; a kind may keep its own settings
            here (`gait`: the `GaitConfig`).
        kind: Which loader reads the snapshot (`register_kind`); None in snapshots written before kinds were
            recorded, whose kind `snapshot_kind` reads from `extra`.
    """

    env_id: str
    level: str
    hidden_sizes: list[int]
    activation: str
    obs_mean: list[float]
    obs_var: list[float]
    obs_clip: float = 10.0
    obs_epsilon: float = 1e-8
    mean_speed: float | None = None
    std_speed: float | None = None
    train_step: int | None = None
    extra: dict = field(default_factory=dict)
    kind: str | None = None


class BehaviourPolicy(nn.Module):
    """Gaussian MLP policy: normalise obs, mean network, fixed log-std, actions clipped to the space bounds."""

    def __init__(self, meta: BehaviourMeta, obs_dim: int, act_dim: int, low: np.ndarray, high: np.ndarray):
        super().__init__()
        self.meta = meta
        sizes = [obs_dim, *meta.hidden_sizes, act_dim]
        layers: list[nn.Module] = []
        for i in range(len(sizes) - 1):
            layers.append(nn.Linear(sizes[i], sizes[i + 1]))
            if i < len(sizes) - 2:
                layers.append(ACTIVATIONS[meta.activation]())
        self.mean_net = nn.Sequential(*layers)
        self.log_std = nn.Parameter(torch.zeros(act_dim))
        self.register_buffer("obs_mean", torch.as_tensor(meta.obs_mean, dtype=torch.float64))
        self.register_buffer("obs_var", torch.as_tensor(meta.obs_var, dtype=torch.float64))
        self.low = np.asarray(low, dtype=np.float32)
        self.high = np.asarray(high, dtype=np.float32)
        self.noise_scale = 1.0  # multiplies the Gaussian noise std of `act`
        command = meta.extra.get("command")
        self.command = None if command is None else float(command)

    @property
    def target(self) -> float | None:
        """The speed the level is asked for: its command."""
        return self.command

    @target.setter
    def target(self, value: float) -> None:
        self.command = float(value)

    def start_episode(self) -> None:
        """Nothing to forget: an actor keeps no per-episode state."""

    def normalise(self, obs: np.ndarray) -> torch.Tensor:
        """VecNormalize's observation transform (after appending the command, if any), float64 then float32."""
        obs = np.asarray(obs, dtype=np.float64)
        if self.command is not None:
            obs = np.concatenate([obs, np.full((*obs.shape[:-1], 1), self.command)], axis=-1)
        x = torch.as_tensor(obs, dtype=torch.float64)
        x = (x - self.obs_mean) / torch.sqrt(self.obs_var + self.meta.obs_epsilon)
        return x.clamp(-self.meta.obs_clip, self.meta.obs_clip).float()

    @torch.no_grad()
    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Action for one observation (or a batch): the mean if `rng` is None, else a Gaussian sample.

        Args:
            obs: Raw observation(s) of shape [obs_dim] or [B, obs_dim].
            rng: Source of the Gaussian noise; None for the deterministic mean action.

        Returns:
            float32 action(s) clipped to the action-space bounds.
        """
        mean = self.mean_net(self.normalise(obs)).numpy()
        if rng is not None:
            std = self.log_std.exp().numpy() * self.noise_scale
            mean = mean + std * rng.standard_normal(mean.shape)
        return np.clip(mean, self.low, self.high).astype(np.float32)


def save_behaviour(path: str | Path, state: dict[str, torch.Tensor], meta: BehaviourMeta) -> None:
    """Write `<path>.safetensors` (the kind's tensors) and `<path>.json` (the metadata, its kind recorded)."""
    path = Path(path).with_suffix("")
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().float().contiguous() for k, v in state.items()}, f"{path}.safetensors")
    meta = replace(meta, kind=snapshot_kind(meta))
    Path(f"{path}.json").write_text(json.dumps(asdict(meta), indent=1) + "\n")


# (path without suffix, metadata, tensors, the environment's action space) -> a policy with `act(obs, rng)`,
# `start_episode()`, `noise_scale` and `meta`.
Loader = Callable[[Path, BehaviourMeta, dict[str, torch.Tensor], Any], Any]
_LOADERS: dict[str, Loader] = {}
# The modules of this package that define a kind, imported when a snapshot of that kind is first loaded (so
# this module imports none of them).
_KIND_MODULES = {"gait": "gmt.datagen.gait"}


def register_kind(kind: str) -> Callable[[Loader], Loader]:
    """Decorator: `loader` reads the snapshots of `kind` (a later registration replaces an earlier one)."""

    def add(loader: Loader) -> Loader:
        _LOADERS[kind] = loader
        return loader

    return add


def snapshot_kind(meta: BehaviourMeta) -> str:
    """The snapshot's kind: `meta.kind`, else (older snapshots) `gait` by their `extra`, else `actor`."""
    if meta.kind:
        return meta.kind
    if "gait" in meta.extra:
        return "gait"
    return "actor"


def load_behaviour(path: str | Path, action_space):
    """Load a snapshot written by `save_behaviour` with the loader of its kind.

    Args:
        path: The `.safetensors` file (or the same path without suffix).
        action_space: The environment's Box action space (its bounds clip the actions).

    Raises:
        ValueError: no loader is registered for the snapshot's kind, or its tensors do not fit it.
    """
    path = Path(path).with_suffix("")
    meta = BehaviourMeta(**json.loads(Path(f"{path}.json").read_text()))
    kind = snapshot_kind(meta)
    if kind not in _LOADERS and kind in _KIND_MODULES:
        import_module(_KIND_MODULES[kind])
    if kind not in _LOADERS:
        raise ValueError(
            f"{path}: no loader for behaviour snapshots of kind {kind!r} (registered: {sorted(_LOADERS)}); "
            "a kind defined outside gmt.datagen registers one when its module is imported"
        )
    return _LOADERS[kind](path, meta, load_file(f"{path}.safetensors"), action_space)


@register_kind("actor")
def load_actor(
    path: Path, meta: BehaviourMeta, state: dict[str, torch.Tensor], action_space
) -> BehaviourPolicy:
    """A `BehaviourPolicy` from an actor snapshot's tensors."""
    policy = BehaviourPolicy(
        meta, len(meta.obs_mean), action_space.shape[0], action_space.low, action_space.high
    )
    missing, unexpected = policy.load_state_dict(state, strict=False)
    missing = [k for k in missing if k not in ("obs_mean", "obs_var")]
    if missing or unexpected:
        raise ValueError(f"{path}.safetensors: missing {missing}, unexpected {unexpected}")
    return policy.eval()


def list_snapshots(env_id: str, behaviour_dir: str | Path | None = None) -> list[Path]:
    """The snapshot files of one environment, slowest measured (else target) speed first."""
    folder = Path(behaviour_dir or BEHAVIOUR_DIR) / env_slug(env_id)
    files = sorted(folder.glob("*.safetensors"))
    if not files:
        raise FileNotFoundError(f"no behaviour snapshots in {folder}; train them with `gmt data behaviour`")
    metas = [json.loads(f.with_suffix(".json").read_text()) for f in files]
    # A level with no measured speed yet (e.g. a governed one) is ordered by its target.
    speeds = [m.get("mean_speed") or m.get("extra", {}).get("target_speed") or 0.0 for m in metas]
    return [f for _, f in sorted(zip(speeds, files, strict=True))]


class RandomPolicy:
    """Uniform-random actions over a Box or Discrete space, drawn from the given generator."""

    def __init__(self, action_space):
        import gymnasium as gym

        self.discrete = isinstance(action_space, gym.spaces.Discrete)
        if self.discrete:
            self.start, self.n = int(action_space.start), int(action_space.n)
        elif isinstance(action_space, gym.spaces.Box):
            self.low = np.asarray(action_space.low, dtype=np.float32)
            self.high = np.asarray(action_space.high, dtype=np.float32)
        else:
            raise ValueError(f"a random policy needs a Box or Discrete action space, got {action_space}")

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """A uniform sample (the midpoint of the box, or the first action, when `rng` is None)."""
        if self.discrete:
            return np.int64(self.start + (0 if rng is None else int(rng.integers(self.n))))
        if rng is None:
            return (self.low + self.high) / 2
        return rng.uniform(self.low, self.high).astype(np.float32)
