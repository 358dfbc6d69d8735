"""Per-trajectory statistics of offline datasets; the statistics themselves are `gmt.common.statistics`."""

from __future__ import annotations

import numpy as np

from gmt.common.statistics import (
    MissingInfoError,
    Statistic,
    aggregate,
    available_statistics,
    canonical,
    default_statistic,
    get_statistic,
    list_statistics,
    missing_message,
    register,
    register_statistic,
    signal_from_step,
    statistic_names,
)
from gmt.model.data.minari_io import OfflineDataset

__all__ = [
    "MissingInfoError",
    "Statistic",
    "aggregate",
    "available_statistics",
    "canonical",
    "check_dataset",
    "chosen_statistic",
    "default_statistic",
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
    if stat.requires <= dataset.info_keys and dataset.episodes:
        stat.per_step(dataset.episodes[0])  # an obs[i] / action[i] out of range fails here, naming its size
    keys = dataset.info_keys
    if not stat.requires <= keys:
        raise MissingInfoError(f"{dataset.dataset_id}: {missing_message(stat, keys)}")
    return stat


def per_trajectory(name: str, dataset: OfflineDataset) -> np.ndarray:
    """The statistic of every episode of `dataset`, shape [N]; for a comma-separated list of statistics
    (`statistic_names`), [N, d], one column each."""
    names = statistic_names(name)
    if len(names) > 1:
        return np.stack([per_trajectory(n, dataset) for n in names], axis=1)
    stat = check_dataset(name, dataset)
    return np.asarray([stat.of_episode(ep) for ep in dataset.episodes], dtype=np.float64)


def chosen_statistic(dataset: OfflineDataset, echo=print) -> str:
    """The statistic to cluster when the user named none (`default_statistic` of the data's infos), printed
    with what it stands for and how to choose another."""
    name, why = default_statistic(dataset.info_keys)
    echo(f"statistic: {name} = {canonical(name)} ({why}; --statistic picks another, e.g. mean(abs(obs[0])))")
    return name
