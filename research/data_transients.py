"""How often a dataset's own episodes would pass the GMT protocol's segments: the ceiling its transitions set.

A GMT learns its transitions (braking from a sprint, speeding up from a walk) from the data's episodes that start
in another level's states (`gmt data collect --pool-start`). This measures those episodes, and the ones started
at rest, on the spans the protocol measures a segment of each length (its settle-in skipped, `gmt.common.segments`),
against the tolerance of the goal their episode is labelled with, and multiplies the shares along each
multi-switch schedule (the first segment from rest, every later one from another level's states). A schedule the
data itself passes in a few episodes of 15 asks a GMT for transitions faster than any it was shown. The last
column measures a held gait instead of a transition: every 150-step window from step 200 on (a 200-step cycle's
measured span, wherever in the episode it falls), so a level whose speed wanders over a few hundred steps shows
there even when it settles quickly.

Usage:
    python -m research.data_transients gmt/hopper/mixed-v0 [--k 2]
"""

from __future__ import annotations

import argparse

import numpy as np

from gmt.common.segments import achieved, held_windows, settle_in, tolerance, within
from gmt.common.statistics import get_statistic
from gmt.common.tables import markdown_table
from gmt.model.data.minari_io import load_dataset
from gmt.model.data.relabel import relabel
from gmt.model.evaluate import MULTI_SWITCH_EVERY, protocol
from research.settle import episode_metadata, pool_started

STEPS = 1000  # the protocol's episode length


def spans(steps: int) -> dict[str, tuple[int, int]]:
    """Name -> measured [start, end) of a segment that begins at step 0: a hold, a switch's first half, a cycle."""
    out = {"hold": (settle_in(steps), steps), "switch": (settle_in(steps // 2), steps // 2)}
    for n in MULTI_SWITCH_EVERY:
        out[f"cycle {n}"] = (settle_in(n), n)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="Minari dataset id or folder.")
    ap.add_argument("--statistic", default="mean_x_velocity", help="Per-trajectory statistic of the goals.")
    ap.add_argument("--k", type=int, default=None, help="Number of goals (None: picked by silhouette).")
    ap.add_argument("--seed", type=int, default=0, help="Seed of the relabelling.")
    args = ap.parse_args()
    ds = load_dataset(args.dataset)
    stat = get_statistic(args.statistic)
    # Goals as `gmt train` labels them (every episode); only full-length episodes are measured.
    table = relabel([stat.of_episode(e) for e in ds.episodes], args.statistic, k=args.k, seed=args.seed)
    kinds = ["pool" if p else "rest" for p in pool_started(episode_metadata(args.dataset, len(ds.episodes)))]
    full = [i for i, e in enumerate(ds.episodes) if len(e) >= STEPS]
    if len(full) < len(ds.episodes):
        print(f"{len(ds.episodes) - len(full)} episodes shorter than {STEPS} steps are not measured")
    signal = {i: stat.per_step(ds.episodes[i])[:STEPS] for i in full}
    rate: dict[tuple[int, str, str], float] = {}
    rows = []
    for goal in table.goals:
        tol = tolerance(goal, table.goals)
        for kind in ("rest", "pool"):
            idx = [i for i in full if table.labels[i] == goal.id and kinds[i] == kind]
            if not idx:
                continue
            v = np.stack([signal[i] for i in idx])  # [E, STEPS]
            cells = []
            for name, (a, b) in spans(STEPS).items():
                m = achieved(v, a, b)  # [E]
                rate[goal.id, kind, name] = float(np.mean(within(m, goal.mean, tol)))
                cells.append(f"{rate[goal.id, kind, name]:.2f} ({np.mean(m):.3f})")
            m = held_windows(v)  # [windows, E]
            cells.append(f"{np.mean(within(m, goal.mean, tol)):.2f} ({np.nanmean(m):.3f})")
            rows.append((f"{goal.id} {goal.name} ({goal.mean:.3f} ± {tol:.3f})", kind, len(idx), *cells))
    head = (
        "goal",
        "start",
        "episodes",
        *(f"{n} [{a},{b})" for n, (a, b) in spans(STEPS).items()),
        "held: 150-step windows from 200",
    )
    print(f"Share of episodes within tolerance over each span (mean statistic), {ds.dataset_id}:\n")
    print(markdown_table(head, rows))
    print("\nMulti-switch schedules, if every segment were an independent draw of these episodes:\n")
    est = []
    for cond in protocol(len(table.goals), STEPS):
        if cond.kind != "multi_switch":
            continue
        n = cond.schedule[1][0]  # the cycle's length: the step of its first switch
        p = 1.0
        for i, (g, a, b) in enumerate(cond.segments):
            if b - a < n - settle_in(n):  # a shorter last segment (every 300) is left out
                continue
            p *= rate.get((g, "rest" if i == 0 else "pool", f"cycle {n}"), float("nan"))
        est.append((cond.name, f"{p:.3f}", f"{15 * p:.1f}/15"))
    print(markdown_table(("schedule", "all segments within", "of 15 episodes"), est))


if __name__ == "__main__":
    main()
