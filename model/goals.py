"""A goal of a trained model: one cluster of training trajectories and the spread of their statistic.

Relabelling (`gmt.model.data.relabel`) finds the goals; a checkpoint stores them (`gmt.model.checkpoint`).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Goal:
    """One goal: a cluster of trajectories and the spread of their statistic."""

    id: int
    name: str
    mean: float
    std: float
    min: float
    max: float
    count: int
