"""Per-trajectory statistics of offline datasets; the statistics themselves are `gmt.common.statistics`."""

from __future__ import annotations

import numpy as np

from gmt.common.statistics import (
    MissingInfoError,
    Statistic,
    aggregate,
    available_statistics,
    get_statistic,
    list_statistics,
    missing_message,
    register,
    register_statistic,
    signal_from_step,
)
from gmt.model.data.minari_io import OfflineDataset

__all__ = [
    "MissingInfoError",
    "Statistic",
    "aggregate",
    "available_statistics",
    "check_dataset",
    "get_statistic",
    "list_statistics",
    "missing_message",
    "per_trajectory",
    "register",
    "register_statistic",
    "signal_from_step",
]


def check_dataset(name: str, dataset: OfflineDataset) -> Statistic:
    """The statistic `name`, after checking that every episode of `dataset` has what it needs.

    Raises:
        MissingInfoError: Naming the missing info keys and the statistics still available.
    """
    stat = get_statistic(name)
    keys = dataset.info_keys
    if not stat.requires <= keys:
        raise MissingInfoError(f"{dataset.dataset_id}: {missing_message(stat, keys)}")
    return stat


def per_trajectory(name: str, dataset: OfflineDataset) -> np.ndarray:
    """The statistic of every episode of `dataset`, shape [N]."""
    stat = check_dataset(name, dataset)
    return np.asarray([stat.of_episode(ep) for ep in dataset.episodes], dtype=np.float64)
