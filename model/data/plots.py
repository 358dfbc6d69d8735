"""Histogram of a per-trajectory statistic coloured by goal."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gmt.model.data.relabel import GoalTable


def plot_goals(table: GoalTable, path: str | Path, title: str = "") -> None:
    """Save a stacked histogram of `table.values`, one colour per goal, with goal means marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    values = table.values if table.values.ndim == 1 else table.values[:, 0]  # several statistics: the first
    bins = np.histogram_bin_edges(values, bins=60)
    data = [values[table.labels == g.id] for g in table.goals]
    labels = [f"{g.id} {g.name} ({g.mean:.2f} ± {g.std:.2f}, n={g.count})" for g in table.goals]
    ax.hist(data, bins=bins, stacked=True, label=labels)
    for g in table.goals:
        ax.axvline(g.mean, color="k", lw=0.8, ls="--")
    ax.set_xlabel(table.statistic)
    ax.set_ylabel("trajectories")
    ax.set_title(title or f"{table.statistic}, k={table.k}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
