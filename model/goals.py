"""A goal of a trained model: one cluster of training trajectories and the spread of their statistic.

Relabelling (`gmt.model.data.relabel`) finds the goals; a checkpoint stores them (`gmt.model.checkpoint`). The record
is the one goal record clients and server share (`gmt.common.spec.GoalInfo`).
"""

from __future__ import annotations

from gmt.common.spec import GoalInfo as Goal

__all__ = ["Goal"]
