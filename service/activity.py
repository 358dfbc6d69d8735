"""A session's recent activity for the console: acts per second, the last act's latency, the replica that served it.

The act path updates it in O(1) with no allocation: acts/s is an exponentially decaying count of acts (time
constant `TAU_S`), so a steady rate r keeps the count near r * TAU_S and an idle session decays towards 0. It travels
with the session (a shared store writes it with the session's state), so any replica can list it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TAU_S = 3.0  # seconds over which acts/s is averaged (the decay's time constant)


class Activity:
    """Acts/s and last latency of one session.

    Attributes:
        count: The decayed count of acts as of `at`.
        at: Clock time (seconds) of the last act.
        latency_s: The last act's time in the server (lock, batch, forward pass, store write), or None.
        by: The replica id that served the last act, or None.
    """

    __slots__ = ("count", "at", "latency_s", "by")

    def __init__(
        self, count: float = 0.0, at: float = 0.0, latency_s: float | None = None, by: str | None = None
    ) -> None:
        self.count, self.at, self.latency_s, self.by = count, at, latency_s, by

    def record(self, now: float, latency_s: float, by: str) -> None:
        """Count one act answered at `now` after `latency_s` seconds, served by replica `by`."""
        if self.count:
            self.count *= math.exp(min(self.at - now, 0.0) / TAU_S)
        self.count += 1.0
        self.at, self.latency_s, self.by = now, latency_s, by

    def rate(self, now: float) -> float:
        """Acts per second over the last few `TAU_S`, as of `now`."""
        return self.count * math.exp(min(self.at - now, 0.0) / TAU_S) / TAU_S

    def dump(self) -> list:
        """A JSON-ready form (`load` reads it back)."""
        return [self.count, self.at, self.latency_s, self.by]

    @classmethod
    def load(cls, raw: object) -> Activity:
        """From `dump`'s form; anything else (an older record without it) is no activity."""
        if isinstance(raw, list) and len(raw) == 4:
            count, at, latency, by = raw
            if isinstance(count, int | float) and isinstance(at, int | float):
                return cls(
                    float(count),
                    float(at),
                    float(latency) if isinstance(latency, int | float) else None,
                    by if isinstance(by, str) else None,
                )
        return cls()


@dataclass(frozen=True)
class SessionBrief:
    """What a store tells of a live session for the listing, without reading its history.

    Attributes:
        held_here: Whether this replica holds the session's live context (a shared store's listing).
    """

    session_id: str
    model: str
    goal: int
    step: int
    created_at: float
    last_used: float
    activity: Activity
    held_here: bool = True


@dataclass(frozen=True)
class SessionRow:
    """One live session as the listing shows it.

    Attributes:
        idle_s: Seconds since its last act, goal change or reset.
        acts_per_s: Acts per second over the last few seconds (None before its first act).
        last_latency_ms: The last act's time in the server (None before its first act).
        served_by: The replica that served its last act (None when unknown: a shared store's session that no
            replica has acted for yet).
    """

    session_id: str
    model: str
    goal: int
    goal_name: str
    step: int
    idle_s: float
    acts_per_s: float | None
    last_latency_ms: float | None
    served_by: str | None
