"""Figure of an evaluation (like the paper's Figure 2): step-wise statistic per goal and per switch."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from gmt.common.segments import moving_average
from gmt.model.evaluate import EvalResult

SMOOTH = 25  # steps of the trailing mean drawn per episode before the mean and std over seeds


def _band(ax, sig: np.ndarray, label: str, color) -> None:
    s = moving_average(sig, SMOOTH)
    # Steps after every seed's episode ended (falls) are all NaN: their mean is NaN, drawn as a gap, not a warning.
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        m, sd = np.nanmean(s, 0), np.nanstd(s, 0)
    t = np.arange(len(m))
    ax.plot(t, m, color=color, label=label, lw=1.3)
    ax.fill_between(t, m - sd, m + sd, color=color, alpha=0.2, lw=0)


def plot_eval(result: EvalResult, path: str | Path) -> Path:
    """Hold curves, one panel of switches per source goal, and the multi-switch curves; saved as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_goals = len(result.goals)
    by_kind: dict[str, list] = {"hold": [], "switch": [], "multi_switch": []}
    for r in result.results:
        by_kind[r.condition.kind].append(r)
    panels = 1 + n_goals + (1 if by_kind["multi_switch"] else 0)
    cols = min(panels, 3)
    rows = int(np.ceil(panels / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.4 * rows), squeeze=False)
    axes = axes.ravel()
    colors = plt.cm.viridis(np.linspace(0, 0.9, n_goals))
    ylabel = result.statistic.replace("_", " ")

    def targets(ax):
        for g in result.goals:
            ax.axhline(g.mean, color=colors[g.id], ls="--", lw=0.8, alpha=0.7)

    ax = axes[0]
    for r in by_kind["hold"]:
        g = r.condition.schedule[0][1]
        _band(ax, r.signal, f"goal {g} ({int(r.success.sum())}/{len(r.success)})", colors[g])
    targets(ax)
    ax.set_title("hold each goal")
    for a in range(n_goals):
        ax = axes[1 + a]
        for r in by_kind["switch"]:
            (s0, ga), (s1, gb) = r.condition.schedule
            if ga == a:
                _band(ax, r.signal, f"{ga}->{gb} ({int(r.success.sum())}/{len(r.success)})", colors[gb])
                ax.axvline(s1, color="grey", lw=0.8)
        targets(ax)
        ax.set_title(f"switch from goal {a} at step {result.episode_steps // 2}")
    if by_kind["multi_switch"]:
        ax = axes[1 + n_goals]
        cmap = plt.cm.plasma(np.linspace(0.1, 0.8, len(by_kind["multi_switch"])))
        for r, c in zip(by_kind["multi_switch"], cmap, strict=True):
            _band(ax, r.signal, f"{r.condition.name} ({int(r.success.sum())}/{len(r.success)})", c)
        targets(ax)
        ax.set_title("cycle through the goals")
    for ax in axes[:panels]:
        ax.set_xlabel("step")
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7, loc="upper left")
    for ax in axes[panels:]:
        ax.axis("off")
    fig.suptitle(f"{result.checkpoint} on {result.env_id}: mean ± std over {len(result.seeds)} seeds")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
