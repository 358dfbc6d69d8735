"""What one replica keeps of the sessions in a shared Redis store: the sessions it serves (its cache) and the ids it
created or read lately, counted per model version (what the micro-batcher waits for)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from gmt.service.sessions import Session


@dataclass
class Held:
    """A session this replica serves: the session (its live context once used) and what the store holds of it."""

    session: Session
    version: int  # the context version the store holds
    step: int  # the step the store holds the session at
    refreshed: float  # `last_used` as last written into `live`'s score


class LocalView:
    """The sessions this replica holds and has seen.

    Args:
        on_remove: Told (id, `Session.key`) of a held session let go (`SessionStore.on_remove`).
    """

    def __init__(self, on_remove: Callable[[str, str], None]) -> None:
        self.held: dict[str, Held] = {}
        # id -> (`Session.key`, last use) of every session created or read here: what this replica may soon serve
        # (the micro-batcher waits for as many acts as there are such sessions).
        self.seen: dict[str, tuple[str, float]] = {}
        self.per_model: Counter[str] = Counter()
        self._on_remove = on_remove

    def hold(self, s: Session) -> None:
        """Serve `s` from here, as the store holds it now."""
        self.held[s.id] = Held(s, s.ctx.version, s.ctx.step, s.last_used)

    def see(self, sid: str, key: str, last_used: float) -> None:
        """Count session `sid` (of model version `key`) as one this replica may soon serve."""
        seen = self.seen.get(sid)
        if seen is not None and seen[0] != key:
            self.unsee(sid)  # the id names a new session now (created again after the last ended)
            seen = None
        if seen is None:
            self.per_model[key] += 1
        self.seen[sid] = (key, last_used)

    def unsee(self, sid: str) -> None:
        """Stop counting `sid`."""
        seen = self.seen.pop(sid, None)
        if seen is not None:
            self.per_model[seen[0]] -= 1

    def forget(self, sid: str) -> None:
        """Let go of `sid`: no longer counted, no longer held (the next use reads the store)."""
        self.unsee(sid)
        held = self.held.pop(sid, None)
        if held is not None:
            self._on_remove(sid, held.session.key)

    def let_go(self, low: float, busy: Callable[[str], bool] = lambda sid: False) -> None:
        """Forget the sessions unused since clock time `low`, but none held that is `busy` (in use now)."""
        for sid in [sid for sid, h in self.held.items() if h.session.last_used < low and not busy(sid)]:
            self.forget(sid)
        for sid in [sid for sid, (_, t) in self.seen.items() if t < low and sid not in self.held]:
            self.unsee(sid)
