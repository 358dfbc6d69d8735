"""Keep the transitions that settle: drop pool-started episodes that reach their goal too slowly.

`gmt data collect --pool-start` starts part of a level's episodes from states the other levels visited, so the
dataset shows each level braking or speeding up into its own speed; these episodes are all a GMT sees of a goal
change. How quickly a behaviour agent settles varies from episode to episode: the commanded Hopper agent brakes
from a sprint inside the slow goal's tolerance within 50 steps in only ~57% of its episodes
(`research/data_transients.py`), and a GMT imitating the average of the rest brakes too late for a goal switched
every 200 steps. This writes a new dataset that keeps every episode started at rest and a pool-started episode
only when its per-step statistic over `span` (default [50, 200): a segment of a 200-step cycle after its
settle-in, `gmt.common.segments.settle_in`) is within its goal's tolerance (`gmt.common.segments.tolerance`), the goals
relabelled over the whole source dataset as `gmt train` relabels them.

It is a choice of demonstrations, in the same spirit as dropping falls at collection: the model only sees
transitions the protocol would accept. The kept episodes keep their Minari episode metadata, plus their index in
the source dataset.

Research: no shipped dataset uses it. Run `python -m research.settle DATASET --out-id ID` (research/README.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import typer

from gmt.common.segments import achieved, tolerance, within
from gmt.common.tables import text_table
from gmt.model.data.minari_io import fingerprint, load_dataset, resolve, write_dataset
from gmt.model.data.relabel import GoalTable, relabel
from gmt.model.data.statistics import check_dataset


@dataclass
class SettleConfig:
    """One filtering run.

    Attributes:
        source: Dataset id or folder to filter.
        out_id: Minari id of the dataset to write.
        span: [start, end) steps after an episode's start over which a pool-started episode is measured.
        tolerance_scale: Multiplier of each goal's tolerance (below 1 keeps only the closer episodes).
        statistic: Per-trajectory statistic of the goals, as `gmt train --statistic`.
        k: Number of goals (None: picked by silhouette, as `gmt train` does).
        seed: Seed of the relabelling.
        data_dir: Datasets root to read and write (None: $GMT_DATA_DIR, else data/minari).
    """

    source: str
    out_id: str
    span: tuple[int, int] = (50, 200)
    tolerance_scale: float = 1.0
    statistic: str = "mean_x_velocity"
    k: int | None = None
    seed: int = 0
    data_dir: Path | None = None

    def __post_init__(self) -> None:
        a, b = self.span
        if not 0 <= a < b:
            raise ValueError(f"span must be [start, end) with 0 <= start < end, got {self.span}")
        from minari.dataset.minari_dataset import parse_dataset_id

        parse_dataset_id(self.out_id)  # ValueError naming the expected form, before any work
        if not self.tolerance_scale > 0:
            raise ValueError(f"tolerance_scale must be > 0, got {self.tolerance_scale}")


@dataclass
class SettleResult:
    """What a filtering run kept, per goal."""

    out_id: str
    path: Path
    source_fingerprint: str
    fingerprint: str
    table: GoalTable
    rows: list[dict] = field(default_factory=list)  # goal, rest, pool judged, pool kept, span mean of each
    kept: int = 0
    total: int = 0


def episode_metadata(dataset: str, n: int, data_dir: Path | None = None) -> list[dict]:
    """The Minari episode metadata of the first `n` episodes (`gmt data collect` writes policy and start)."""
    from minari import MinariDataset

    return list(MinariDataset(resolve(dataset, data_dir)).storage.get_episode_metadata(range(n)))


def pool_started(metadata: list[dict]) -> np.ndarray:
    """[N] bool: the episode started from another level's state (`start_from` in its metadata)."""
    return np.asarray(["start_from" in m for m in metadata], dtype=bool)


def keep_mask(
    span_means: np.ndarray, labels: np.ndarray, table: GoalTable, pooled: np.ndarray, scale: float = 1.0
) -> np.ndarray:
    """[N] bool: every rest-started episode, and a pool-started one whose span mean is within its goal's tolerance.

    Args:
        span_means: [N] mean per-step statistic over the span (NaN where the episode ended before it).
        labels: [N] goal id of each episode.
        table: The goal table the labels refer to.
        pooled: [N] whether each episode started from another level's state.
        scale: Multiplier of each goal's tolerance.
    """
    goals = {g.id: g for g in table.goals}
    ok = np.array(
        [
            within(m, goals[int(g)].mean, scale * tolerance(goals[int(g)], table.goals))
            for m, g in zip(span_means, labels, strict=True)
        ],
        dtype=bool,
    )
    return ~pooled | ok


def _mean(x: np.ndarray) -> float | None:
    """Mean of the measured (non-NaN) values, None if there are none."""
    x = x[~np.isnan(x)]
    return float(x.mean()) if len(x) else None


def settle_filter(cfg: SettleConfig) -> SettleResult:
    """Write `cfg.out_id`: the source's rest-started episodes and its pool-started ones that settle in `cfg.span`."""
    ds = load_dataset(cfg.source, cfg.data_dir)
    stat = check_dataset(cfg.statistic, ds)
    signals = [stat.per_step(e) for e in ds.episodes]  # [T_i] each, read once for the goals and the span
    table = relabel([float(stat.aggregate(v)) for v in signals], cfg.statistic, k=cfg.k, seed=cfg.seed)
    labels = np.asarray(table.labels)
    meta = episode_metadata(cfg.source, len(ds.episodes), cfg.data_dir)
    pooled = pool_started(meta)
    a, b = cfg.span
    span_means = np.asarray([achieved(v, a, b) if len(v) >= b else np.nan for v in signals], dtype=np.float64)
    keep = keep_mask(span_means, labels, table, pooled, cfg.tolerance_scale)
    rows = []
    for g in table.goals:
        mine = labels == g.id
        rows.append(
            {
                "goal": g.id,
                "name": g.name,
                "mean": g.mean,
                "tolerance": cfg.tolerance_scale * tolerance(g, table.goals),
                "rest": int(np.sum(mine & ~pooled)),
                "pool": int(np.sum(mine & pooled)),
                "pool_kept": int(np.sum(mine & pooled & keep)),
                "pool_span_mean": _mean(span_means[mine & pooled]),
                "kept_span_mean": _mean(span_means[mine & pooled & keep]),
            }
        )
    idx = np.flatnonzero(keep)
    episodes = [ds.episodes[i] for i in idx]
    out_meta = [{**meta[i], "source_episode": int(i)} for i in idx]
    description = (
        f"{cfg.source} (fingerprint {ds.fingerprint[:8]}) filtered by `python -m research.settle`: every rest-started "
        f"episode, and the pool-started ones whose {cfg.statistic} over steps [{a}, {b}) is within "
        f"{cfg.tolerance_scale} x their goal's tolerance; {len(idx)} of {len(ds.episodes)} episodes kept."
    )
    path = write_dataset(
        cfg.out_id,
        episodes,
        ds.env_id,
        ds.observation_space,
        ds.action_space,
        cfg.data_dir,
        episode_metadata=out_meta,
        description=description,
        algorithm_name="python -m research.settle",
        overwrite=True,
    )
    return SettleResult(
        out_id=cfg.out_id,
        path=path,
        source_fingerprint=ds.fingerprint,
        fingerprint=fingerprint(episodes),
        table=table,
        rows=rows,
        kept=len(idx),
        total=len(ds.episodes),
    )


def main(
    dataset: str = typer.Argument(..., help="Dataset id or path to filter."),
    out_id: str = typer.Option(..., help="Minari id of the filtered dataset to write."),
    span: str = typer.Option("50:200", help="START:END steps after an episode's start that are measured."),
    tolerance_scale: float = typer.Option(1.0, help="Multiplier of each goal's tolerance."),
    statistic: str = typer.Option("mean_x_velocity", help="Per-trajectory statistic of the goals."),
    k: int = typer.Option(None, help="Fix the number of goals instead of sampling it."),
    seed: int = typer.Option(0, help="Seed of the relabelling."),
    data_dir: Path = typer.Option(None, help="Datasets root (default $GMT_DATA_DIR, else data/minari)."),
) -> None:
    """Keep every rest-started episode and the pool-started ones inside their goal's tolerance over SPAN.

    Pool-started episodes (`gmt data collect --pool-start`) are the data's goal changes; this drops those that
    reach their goal too slowly for a multi-switch segment (`research.settle`).
    """
    start, _, end = span.partition(":")
    try:
        bounds = (int(start), int(end))
        cfg = SettleConfig(dataset, out_id, bounds, tolerance_scale, statistic, k, seed, data_dir)
    except ValueError as e:
        raise typer.BadParameter(f"{e} (--span {span!r}, --out-id {out_id!r})") from None
    res = settle_filter(cfg)

    def fmt(x):
        return "-" if x is None else f"{x:.3f}"

    rows = [
        (
            r["goal"],
            r["name"],
            f"{r['mean']:.3f} +- {r['tolerance']:.3f}",
            r["rest"],
            f"{r['pool_kept']}/{r['pool']}",
            fmt(r["pool_span_mean"]),
            fmt(r["kept_span_mean"]),
        )
        for r in res.rows
    ]
    head = (
        "id",
        "name",
        "goal band",
        "rest",
        "pool kept",
        f"pool mean [{bounds[0]},{bounds[1]})",
        "kept mean",
    )
    typer.echo(text_table(head, rows, align="<<>>>>>", rule=False))
    typer.echo(
        f"\nwrote {res.out_id} to {res.path}: {res.kept} of {res.total} episodes "
        f"(source fingerprint {res.source_fingerprint[:8]}, new {res.fingerprint[:8]})"
    )


if __name__ == "__main__":
    typer.run(main)
