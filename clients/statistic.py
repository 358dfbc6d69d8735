"""The per-step signal of a model's statistic, measured live from `env.step`'s reward and info."""

from __future__ import annotations

from collections.abc import Mapping


def step_signal(statistic: str, reward: float, info: Mapping) -> float:
    """The per-step value of `statistic` (e.g. x_velocity for mean_x_velocity, the reward for return).

    Raises:
        KeyError: an unknown statistic, or an info that lacks what the statistic needs.
    """
    from model.data.statistics import signal_from_step

    return float(signal_from_step(statistic, reward, info))
