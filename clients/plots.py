"""PNG of one episode: the statistic over time, goal switch points, and each segment's target band."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gmt.common.segments import MOVING_AVERAGE, Segment, moving_average
from gmt.common.statistics import is_sum


def plot_episode(
    path: Path, signal: Sequence[float], segments: Sequence[Segment], statistic: str, title: str
) -> Path:
    """Draw the per-step signal, its moving average, dashed lines at goal changes, and target ± tolerance bands.

    A summed statistic (`return`) is drawn as its running total, each segment
    shaded and labelled with its sum.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4), dpi=100)
    steps = np.arange(len(signal))
    if is_sum(statistic):  # a summed statistic (return): its running total
        ax.plot(steps, np.nancumsum(signal), color="C0", lw=1.8, label=f"{statistic} so far")
        for s in segments:
            c = f"C{1 + s.goal % 9}"
            ax.axvspan(
                s.start, s.end, color=c, alpha=0.15, label=f"goal {s.goal} ({s.name}): +{s.achieved:g}"
            )
            if s.start > 0:
                ax.axvline(s.start, color="k", ls="--", lw=1)
        return _finish(fig, ax, path, statistic, title)
    ax.plot(steps, signal, color="0.75", lw=0.8, label="per step")
    ax.plot(steps, moving_average(signal), color="C0", lw=1.8, label=f"moving average ({MOVING_AVERAGE})")
    seen: set[int] = set()
    for i, s in enumerate(segments):
        first = s.goal not in seen
        seen.add(s.goal)
        c = f"C{1 + s.goal % 9}"
        ax.fill_between(
            [s.start, s.end],
            s.target - s.tolerance,
            s.target + s.tolerance,
            color=c,
            alpha=0.2,
            label=f"goal {s.goal} ({s.name}) target ± tolerance" if first else None,
        )
        ax.hlines(
            s.achieved,
            s.measured_from,
            s.end,
            colors=c,
            linestyles=":",
            lw=1.5,
            label="achieved mean (measured steps)" if i == 0 else None,
        )
        if s.start > 0:
            ax.axvline(s.start, color="k", ls="--", lw=1)
    return _finish(fig, ax, path, statistic, title)


def _finish(fig, ax, path: Path, statistic: str, title: str) -> Path:
    import matplotlib.pyplot as plt

    ax.set_xlabel("step")
    ax.set_ylabel(statistic)
    ax.set_title(title)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
