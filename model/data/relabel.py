"""Unsupervised goals: k-means over a 1-D per-trajectory statistic, k chosen by silhouette score (paper 2.1).

Goals over several statistics at once (e.g. speed and energy): k-means and the silhouette run on the vectors
standardised per statistic (z-scores), goals are ordered by the first statistic, and each goal records its vector
of per-statistic means (`GoalTable.vectors`); a goal's mean, std, min and max are the first statistic's.

For every k in a range, k-means is fitted and scored by silhouette; the scores are min-max normalised to
[0, 1]; the candidates are the k scoring at least `threshold` (0.85), and one is drawn with probability
proportional to its normalised score (seeded) unless k is given. Goal 0 has the lowest mean statistic.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gmt.common.tables import text_table
from gmt.model.goals import Goal

GOAL_NAMES = {
    1: ["all"],
    2: ["low", "high"],
    3: ["low", "medium", "high"],
    4: ["lowest", "low", "high", "highest"],
    5: ["lowest", "low", "medium", "high", "highest"],
}


def goal_names(k: int) -> list[str]:
    """Goal names by rank of mean statistic (goal-<id> beyond five goals)."""
    return GOAL_NAMES.get(k, [f"goal-{i}" for i in range(k)])


@dataclass
class GoalTable:
    """Result of relabelling a dataset.

    Attributes:
        statistic: Name of the per-trajectory statistic clustered.
        k: Number of goals chosen.
        silhouette: Silhouette score per k tried.
        normalised: Min-max normalised silhouette score per k.
        candidates: The k with normalised score >= threshold.
        k_given: Whether k was fixed by the caller rather than sampled.
        seed: Seed of k-means and of the sampling of k.
        labels: Goal id of every episode, in dataset order.
        values: The statistic of every episode, in dataset order.
        goals: Per-goal summary, ordered by id (ascending mean).
        vectors: With several statistics, each goal's mean of every statistic (in the order named), by id;
            None for one statistic.
    """

    statistic: str
    k: int
    silhouette: dict[int, float]
    normalised: dict[int, float]
    candidates: list[int]
    k_given: bool
    seed: int
    labels: np.ndarray
    values: np.ndarray
    goals: list[Goal]
    vectors: list[list[float]] | None = None

    def to_dict(self) -> dict:
        """A JSON-ready dict (inverse of `from_dict`)."""
        d = asdict(self)
        d["labels"] = [int(x) for x in self.labels]
        d["values"] = np.asarray(self.values, dtype=np.float64).tolist()
        d["silhouette"] = {str(k): v for k, v in self.silhouette.items()}
        d["normalised"] = {str(k): v for k, v in self.normalised.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GoalTable:
        """Rebuild a table from `to_dict` output."""
        return cls(
            statistic=d["statistic"],
            k=int(d["k"]),
            silhouette={int(k): float(v) for k, v in d["silhouette"].items()},
            normalised={int(k): float(v) for k, v in d["normalised"].items()},
            candidates=[int(k) for k in d["candidates"]],
            k_given=bool(d["k_given"]),
            seed=int(d["seed"]),
            labels=np.asarray(d["labels"], dtype=np.int64),
            values=np.asarray(d["values"], dtype=np.float64),
            goals=[Goal(**g) for g in d["goals"]],
            vectors=d.get("vectors"),
        )

    def save(self, path: str | Path) -> None:
        """Write the table as JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> GoalTable:
        """Read a table written by `save`."""
        return cls.from_dict(json.loads(Path(path).read_text()))

    def format(self) -> str:
        """The silhouette scores, the chosen k and the per-goal table as text."""
        scores = text_table(
            ("k", "silhouette", "normalised", "candidate"),
            [
                (k, f"{sc:.4f}", f"{self.normalised[k]:.3f}", "yes" if k in self.candidates else "")
                for k, sc in self.silhouette.items()
            ],
            align="<>>",
            rule=False,
        )
        how = "given" if self.k_given else f"sampled from candidates {self.candidates}, seed {self.seed}"
        vec = ["(" + ", ".join(f"{x:.3f}" for x in v) + ")" for v in self.vectors] if self.vectors else None
        goals = text_table(
            ("id", "name", "count", "mean", "std", "min", "max") + (("vector",) if vec else ()),
            [
                (g.id, g.name, g.count, f"{g.mean:.3f}", f"{g.std:.3f}", f"{g.min:.3f}", f"{g.max:.3f}")
                + ((vec[g.id],) if vec else ())
                for g in self.goals
            ],
            align="><>>>>>" + (">" if vec else ""),
            rule=False,
        )
        lines = [scores, "", f"chosen k = {self.k} ({how}); statistic: {self.statistic}", "", goals]
        return "\n".join(lines)


def silhouette_scores(
    values: np.ndarray, ks: list[int], seed: int
) -> tuple[dict[int, float], dict[int, np.ndarray]]:
    """Fit k-means for every k and score it; returns (score per k, labels per k) for the k that fit."""
    from sklearn.cluster import KMeans
    from sklearn.metrics import silhouette_score

    x = np.asarray(values, dtype=np.float64)
    x = x.reshape(-1, 1) if x.ndim == 1 else x
    n_distinct = len(np.unique(x, axis=0))
    scores, labels = {}, {}
    for k in ks:
        if k >= n_distinct:  # silhouette needs 2 <= k <= n_distinct - 1
            continue
        lab = KMeans(n_clusters=k, n_init=10, random_state=seed).fit_predict(x)
        scores[k] = float(silhouette_score(x, lab))
        labels[k] = lab
    return scores, labels


def relabel(
    values: np.ndarray | list[float],
    statistic: str = "",
    k: int | None = None,
    k_range: tuple[int, int] = (2, 8),
    seed: int = 0,
    threshold: float = 0.85,
) -> GoalTable:
    """Cluster per-trajectory statistic values into goals.

    Args:
        values: The statistic of each trajectory, shape [N]; or [N, d] for d statistics (clustered as z-scores,
            ordered by the first).
        statistic: Name recorded in the table.
        k: Fix the number of goals (it is still scored); None samples it from the candidates.
        k_range: Inclusive range of k to score.
        seed: Seed of k-means and of the sampling of k.
        threshold: Minimum normalised silhouette score of a candidate.

    Returns:
        The goal table; goal ids are ordered by ascending mean value.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 2 and values.shape[1] == 1:
        values = values[:, 0]
    if values.ndim == 2:  # several statistics: each standardised, so none outweighs the others by its unit
        spread = values.std(axis=0)
        features = (values - values.mean(axis=0)) / np.where(spread > 0, spread, 1.0)
    else:
        features = values
    first = values if values.ndim == 1 else values[:, 0]
    ks = sorted(set(range(k_range[0], k_range[1] + 1)) | ({k} if k else set()))
    scores, labels_by_k = silhouette_scores(features, ks, seed)
    if not scores:
        raise ValueError(
            f"cannot cluster {len(values)} trajectories with {len(np.unique(values, axis=0))} distinct values"
        )
    lo, hi = min(scores.values()), max(scores.values())
    normalised = {kk: (s - lo) / (hi - lo) if hi > lo else 1.0 for kk, s in scores.items()}
    candidates = [kk for kk, s in normalised.items() if s >= threshold]
    if k is None:
        weights = np.asarray([normalised[kk] for kk in candidates])
        chosen = int(np.random.default_rng(seed).choice(candidates, p=weights / weights.sum()))
    elif k not in labels_by_k:
        raise ValueError(f"k={k} needs more than {k} distinct statistic values")
    else:
        chosen = k
    raw = labels_by_k[chosen]
    order = np.argsort([first[raw == c].mean() for c in range(chosen)])
    labels = np.empty_like(raw, dtype=np.int64)
    for new, old in enumerate(order):
        labels[raw == old] = new
    names = goal_names(chosen)
    goals = []
    for g in range(chosen):
        v = first[labels == g]
        goals.append(
            Goal(g, names[g], float(v.mean()), float(v.std()), float(v.min()), float(v.max()), len(v))
        )
    vectors = (
        [[float(x) for x in values[labels == g].mean(axis=0)] for g in range(chosen)]
        if values.ndim == 2
        else None
    )
    return GoalTable(
        statistic, chosen, scores, normalised, candidates, k is not None, seed, labels, values, goals, vectors
    )


def separation(table: GoalTable) -> list[float]:
    """For each pair of neighbouring goals, |mean difference| / the larger of their two stds."""
    out = []
    for a, b in zip(table.goals, table.goals[1:], strict=False):
        spread = max(a.std, b.std)
        out.append(float("inf") if spread == 0 else (b.mean - a.mean) / spread)
    return out
