"""Per-goal segments of an episode and how well each reached its goal (the evaluation protocol's measure).

A segment is a run of steps whose actions the server reported for the same goal, so goal changes made by any
client show up. Each segment is measured after a settle-in of min(100, length / 4) steps: the mean of the
per-step statistic signal over the rest, compared with the goal's dataset mean within `model.evaluate`'s
tolerance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from clients.base import ModelInfo

SETTLE_MAX = 100


def settle_in(length: int) -> int:
    """Steps skipped at the start of a segment of `length` steps before measuring: min(100, length // 4)."""
    return min(SETTLE_MAX, length // 4)


@dataclass(frozen=True)
class Segment:
    """One segment's measurement.

    Attributes:
        goal: Goal id the server reported for every action of the segment.
        name: That goal's name.
        start: First step.
        end: One past the last step.
        measured_from: First measured step (start + settle-in).
        target: The goal's dataset mean of the statistic.
        tolerance: Allowed distance from the target.
        achieved: Mean signal over [measured_from, end).
        within: Whether |achieved - target| <= tolerance.
    """

    goal: int
    name: str
    start: int
    end: int
    measured_from: int
    target: float
    tolerance: float
    achieved: float
    within: bool

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def runs(goals: Sequence[int]) -> list[tuple[int, int, int]]:
    """(goal, start, end) of each maximal run of equal consecutive goals."""
    out: list[tuple[int, int, int]] = []
    for t, g in enumerate(goals):
        if out and out[-1][0] == g:
            out[-1] = (g, out[-1][1], t + 1)
        else:
            out.append((g, t, t + 1))
    return out


def measure(goals: Sequence[int], signal: Sequence[float], spec: ModelInfo) -> list[Segment]:
    """The segments of an episode, from the goal reported with each step's action and the step's signal."""
    from model.evaluate import tolerance

    sig = np.asarray(signal, dtype=np.float64)
    segs = []
    for g, a, b in runs(goals):
        goal = spec.goal(g)
        m = a + settle_in(b - a)
        achieved = float(np.mean(sig[m:b]))
        tol = float(tolerance(goal, spec.goals))
        segs.append(
            Segment(g, goal.name, a, b, m, goal.mean, tol, achieved, bool(abs(achieved - goal.mean) <= tol))
        )
    return segs


def table(segments: Sequence[Segment], statistic: str) -> str:
    """A plain-text table: one row per segment."""
    head = ("goal", "steps", "measured", f"target {statistic}", "achieved", "within tolerance")
    rows = [
        (
            f"{s.goal} ({s.name})",
            f"{s.start}-{s.end - 1}",
            f"{s.measured_from}-{s.end - 1}",
            f"{s.target:.3f} ± {s.tolerance:.3f}",
            f"{s.achieved:.3f}",
            "yes" if s.within else "no",
        )
        for s in segments
    ]
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head))]
    fmt = "  ".join(f"{{:<{w}}}" for w in widths)
    return "\n".join(
        [fmt.format(*head), fmt.format(*("-" * w for w in widths)), *(fmt.format(*r) for r in rows)]
    )
