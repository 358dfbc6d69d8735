"""How well an episode followed its goals: the one definition that `gmt eval`, `gmt run` and the tests use.

A segment is a maximal run of steps acted on for the same goal (for `gmt run` the goal the server reported
with each action, so goal changes made by any client show up; for `gmt eval` the scheduled goal). Each segment
is measured after a settle-in of min(100, length // 4) steps: the mean of the per-step statistic signal over
the rest (`achieved`), compared with the goal's dataset mean within `tolerance`. An episode succeeds when it
never terminated early and every segment is `within` tolerance.

A statistic that sums its signal (`return`) is measured as the sum over the whole segment, with no settle-in
and no judgement (`within` None): its goals are whole-episode returns, which part of an episode cannot be held
to (`gmt eval` judges such models on whole episodes, `model/evaluate_return.py`).

Torch-free (numpy only), like everything under `clients/`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np

from gmt.common.statistics import AGGREGATIONS, get_statistic, is_sum
from gmt.common.tables import text_table

SETTLE_MAX = 100
MOVING_AVERAGE = 50  # steps of the trailing mean shown live by `gmt run` and drawn in its plots


class GoalLike(Protocol):
    """A row of a goal table: `gmt.client.base.GoalInfo` (from a server) or `gmt.model.checkpoint.Goal`."""

    id: int
    name: str
    mean: float


def settle_in(length: int) -> int:
    """Steps skipped at the start of a segment of `length` steps before measuring: min(100, length // 4)."""
    return min(SETTLE_MAX, length // 4)


def runs(goals: Sequence[int]) -> list[tuple[int, int, int]]:
    """(goal, start, end) of each maximal run of equal consecutive goals."""
    out: list[tuple[int, int, int]] = []
    for t, g in enumerate(goals):
        if out and out[-1][0] == g:
            out[-1] = (g, out[-1][1], t + 1)
        else:
            out.append((g, t, t + 1))
    return out


def measured_spans(goals: Sequence[int]) -> list[tuple[int, int, int]]:
    """(goal, first measured step, end) of each segment of the per-step goals: `runs` after the settle-in."""
    return [(g, a + settle_in(b - a), b) for g, a, b in runs(goals)]


def tolerance(goal: GoalLike, goals: Sequence[GoalLike]) -> float:
    """max(10% of |goal mean|, 5% of the span of goal means, the goal's own std across its data's episodes).

    The std keeps a goal from being held to less than its own trajectories vary by (a small statistic, e.g.
    Swimmer's speed, whose 10% is narrower than its episodes' spread); a goal without one (0) adds nothing.
    """
    means = [g.mean for g in goals]
    spread = float(getattr(goal, "std", 0.0) or 0.0)
    return max(0.1 * abs(goal.mean), 0.05 * (max(means) - min(means)), spread)


def achieved(
    signal: np.ndarray | Sequence[float], start: int, end: int, statistic: str = ""
) -> np.ndarray | float:
    """Mean signal over steps [start, end) along the last axis, ignoring NaN (steps after an early end).

    A statistic that aggregates otherwise than by mean or sum (`max(info.height)`, `std(reward)`, ...) is
    measured by its own aggregation over those steps instead, as its goals were over whole episodes.
    A 1-D signal gives a float, an [E, T] array one value per episode; NaN where nothing was measured.
    """
    x = np.asarray(signal, dtype=np.float64)[..., start:end]
    agg = own_aggregation(statistic)
    if agg is not None:
        rows = x.reshape(-1, x.shape[-1])
        out = np.asarray([agg(r[~np.isnan(r)]) if (~np.isnan(r)).any() else np.nan for r in rows])
        return float(out[0]) if x.ndim == 1 else out.reshape(x.shape[:-1])
    n = np.sum(~np.isnan(x), axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.nansum(x, axis=-1) / n
    return float(m) if np.ndim(m) == 0 else m


def own_aggregation(statistic: str):
    """The aggregation of `statistic` when it is neither a mean nor a sum (else None: segments take the mean)."""
    if not statistic:
        return None
    try:
        agg = get_statistic(statistic, plugins=False).aggregate
    except KeyError:
        return None
    return None if agg in (AGGREGATIONS["mean"], AGGREGATIONS["sum"], np.mean) else agg


def within(value: np.ndarray | float, target: float, tol: float) -> np.ndarray | bool:
    """|value - target| <= tol; never for NaN."""
    ok = np.abs(np.asarray(value, dtype=np.float64) - target) <= tol
    return bool(ok) if np.ndim(ok) == 0 else ok


def held_windows(
    signal: np.ndarray | Sequence[float], first: int = 200, length: int = 150, every: int = 50
) -> np.ndarray:
    """Means of a held goal's signal over windows [a, a + length) for a = first, first + every, ...

    How steady a held gait is where a multi-switch cycle would measure a segment (a 200-step cycle measures 150
    steps after its settle-in), wherever in the episode that segment falls. A window that holds any NaN (steps
    after an early end) is NaN, so `within` fails it.

    Returns:
        [windows, *signal.shape[:-1]] window means.
    """
    x = np.asarray(signal, dtype=np.float64)
    starts = range(first, x.shape[-1] - length + 1, every)
    return np.stack([x[..., a : a + length].mean(axis=-1) for a in starts])  # NaN anywhere -> NaN


def moving_average(x: np.ndarray | Sequence[float], window: int = MOVING_AVERAGE) -> np.ndarray:
    """Trailing mean over the last `window` values along the last axis (fewer at the start; NaN ignored)."""
    a = np.asarray(x, dtype=np.float64)
    valid = ~np.isnan(a)
    zero = np.zeros((*a.shape[:-1], 1))
    s = np.concatenate([zero, np.cumsum(np.where(valid, a, 0.0), axis=-1)], axis=-1)
    c = np.concatenate([zero, np.cumsum(valid, axis=-1)], axis=-1)
    n = np.arange(1, a.shape[-1] + 1)
    lo = np.maximum(n - window, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (s[..., n] - s[..., lo]) / (c[..., n] - c[..., lo])


@dataclass(frozen=True)
class Segment:
    """One segment's measurement.

    Attributes:
        goal: Goal id acted on for every step of the segment.
        name: That goal's name.
        start: First step.
        end: One past the last step.
        measured_from: First measured step (start + settle-in).
        target: The goal's dataset mean of the statistic.
        tolerance: Allowed distance from the target (None when not judged).
        achieved: Mean signal over [measured_from, end); for a summed statistic, the sum over [start, end).
        within: Whether |achieved - target| <= tolerance; None for a summed statistic (not judged).
    """

    goal: int
    name: str
    start: int
    end: int
    measured_from: int
    target: float
    tolerance: float | None
    achieved: float
    within: bool | None

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def measure(
    goals: Sequence[int], signal: Sequence[float], table: Sequence[GoalLike], statistic: str = ""
) -> list[Segment]:
    """The segments of one episode, from the goal acted on at each step and the step's signal.

    Args:
        goals: Goal id of each step's action.
        signal: The statistic's per-step signal.
        table: The model's goal table (ids, names and dataset means).
        statistic: The statistic's name; one that sums (`return`) is summed per segment and not judged.
    """
    by_id = {g.id: g for g in table}
    segs = []
    summed = np.asarray(signal, dtype=np.float64) if is_sum(statistic) else None
    for (g, a, b), (_, m, _) in zip(runs(goals), measured_spans(goals), strict=True):
        goal = by_id[g]
        if summed is not None:
            total = float(np.nansum(summed[a:b]))
            segs.append(Segment(g, goal.name, a, b, a, goal.mean, None, total, None))
            continue
        value, tol = achieved(signal, m, b, statistic), tolerance(goal, table)
        segs.append(Segment(g, goal.name, a, b, m, goal.mean, tol, value, within(value, goal.mean, tol)))
    return segs


def table(segments: Sequence[Segment], statistic: str) -> str:
    """A plain-text table: one row per segment."""
    head = ("goal", "steps", "measured", f"target {statistic}", "achieved", "within tolerance")
    rows = [
        (
            f"{s.goal} ({s.name})",
            f"{s.start}-{s.end - 1}",
            f"{s.measured_from}-{s.end - 1}",
            f"{s.target:.3f} ± {s.tolerance:.3f}" if s.within is not None else f"{s.target:.3f} per episode",
            f"{s.achieved:.3f}",
            "-" if s.within is None else "yes" if s.within else "no",
        )
        for s in segments
    ]
    return text_table(head, rows)
