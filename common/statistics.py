"""Named per-trajectory statistics: a per-step signal and an aggregation over any range of steps.

Torch-free and dataset-free: the remote runner measures a live episode with the same definitions that
relabelling (`gmt.model.data.statistics`) and evaluation apply to datasets.

Evaluation needs the value over step ranges (e.g. steps [100, 1000)), so every statistic is defined by
`per_step(episode) -> [T]` and `aggregate(values) -> float`; `of_episode` is the aggregate over all steps.
Register new ones with `@register_statistic(...)` on a function `(reward, info) -> float`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

Signal = Callable[[float, Mapping[str, float]], float]
Aggregation = Callable[[np.ndarray], float]


class Episode(Protocol):
    """What a statistic reads of an episode (e.g. `gmt.model.data.minari_io.Episode`)."""

    rewards: np.ndarray
    infos: Mapping[str, np.ndarray]

    def __len__(self) -> int: ...


class MissingInfoError(KeyError):
    """A statistic needs info keys the data does not have."""

    def __str__(self) -> str:  # KeyError would print the message quoted
        return str(self.args[0])


@dataclass(frozen=True)
class Statistic:
    """A per-trajectory statistic.

    Attributes:
        name: Registry name, e.g. "mean_x_velocity".
        signal: Per-step value from the step's reward and info.
        aggregate: Reduces per-step values to one number (mean, sum, ...).
        requires: Info keys the signal reads.
        description: One line for listings.
    """

    name: str
    signal: Signal
    aggregate: Aggregation
    requires: frozenset[str] = field(default_factory=frozenset)
    description: str = ""

    def per_step(self, episode: Episode) -> np.ndarray:
        """The signal at every step of `episode`, shape [T]."""
        missing = self.requires - set(episode.infos)
        if missing:
            raise MissingInfoError(missing_message(self, set(episode.infos)))
        n = len(episode)
        infos = [{k: episode.infos[k][t] for k in self.requires} for t in range(n)]
        return np.asarray(
            [self.signal(float(episode.rewards[t]), infos[t]) for t in range(n)], dtype=np.float64
        )

    def of_episode(self, episode: Episode) -> float:
        """The statistic of a whole episode."""
        return float(self.aggregate(self.per_step(episode)))


@dataclass(frozen=True)
class FieldStatistic(Statistic):
    """A statistic whose signal is one info key, or the reward when `key` is None (vectorised per_step)."""

    key: str | None = None

    def per_step(self, episode: Episode) -> np.ndarray:
        if self.key is None:
            return np.asarray(episode.rewards, dtype=np.float64)
        if self.key not in episode.infos:
            raise MissingInfoError(missing_message(self, set(episode.infos)))
        return np.asarray(episode.infos[self.key], dtype=np.float64)


_REGISTRY: dict[str, Statistic] = {}


def register(stat: Statistic, overwrite: bool = False) -> Statistic:
    """Add a statistic to the registry under `stat.name`."""
    if stat.name in _REGISTRY and not overwrite:
        raise ValueError(f"statistic {stat.name!r} is already registered")
    _REGISTRY[stat.name] = stat
    return stat


def register_statistic(
    name: str, aggregate: Aggregation = np.mean, requires: set[str] | None = None, description: str = ""
) -> Callable[[Signal], Signal]:
    """Decorator: register `fn(reward, info) -> float` as the per-step signal of statistic `name`."""

    def deco(fn: Signal) -> Signal:
        register(Statistic(name, fn, aggregate, frozenset(requires or ()), description or (fn.__doc__ or "")))
        return fn

    return deco


def get_statistic(name: str) -> Statistic:
    """Look a statistic up by name."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown statistic {name!r}; registered: {', '.join(sorted(_REGISTRY))}") from None


def list_statistics() -> list[str]:
    """Names of all registered statistics."""
    return sorted(_REGISTRY)


def available_statistics(info_keys: set[str]) -> list[str]:
    """Statistics computable from data having `info_keys`."""
    return sorted(n for n, s in _REGISTRY.items() if s.requires <= info_keys)


def missing_message(stat: Statistic, info_keys: set[str]) -> str:
    """Error text: what is missing and which statistics remain available."""
    missing = sorted(stat.requires - info_keys)
    return (
        f"statistic {stat.name!r} needs per-step info {missing}, which this dataset does not record "
        f"(its infos: {sorted(info_keys) or 'none'}); statistics still available: "
        f"{', '.join(available_statistics(info_keys)) or 'none'}"
    )


def signal_from_step(name: str, reward: float, info: Mapping[str, float]) -> float:
    """The per-step signal of statistic `name` for one live `env.step` (reward, info).

    Raises:
        MissingInfoError: If `info` lacks a key the statistic needs.
    """
    stat = get_statistic(name)
    if not stat.requires <= set(info):
        raise MissingInfoError(missing_message(stat, set(info)))
    return float(stat.signal(float(reward), info))


def aggregate(name: str, values: np.ndarray | list[float]) -> float:
    """Aggregate per-step signals of statistic `name` (e.g. over a step range) into its value."""
    return float(get_statistic(name).aggregate(np.asarray(values, dtype=np.float64)))


def is_sum(name: str) -> bool:
    """Whether statistic `name` sums its per-step signal (e.g. `return`): a segment's value is then a sum over
    that segment, not comparable with a whole episode's value. Unknown names are not sums."""
    return name in _REGISTRY and _REGISTRY[name].aggregate is _sum


def _sum(values: np.ndarray) -> float:
    return float(np.sum(values))


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values))


register(
    FieldStatistic(
        "mean_x_velocity",
        lambda reward, info: float(info["x_velocity"]),
        _mean,
        frozenset({"x_velocity"}),
        "mean forward velocity (info x_velocity), m/s",
        key="x_velocity",
    )
)
register(FieldStatistic("return", lambda reward, info: float(reward), _sum, frozenset(), "sum of rewards"))
register(
    FieldStatistic(
        "mean_reward", lambda reward, info: float(reward), _mean, frozenset(), "mean reward per step"
    )
)
