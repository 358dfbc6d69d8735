"""The per-session event feed of one replica: what the core did to a session, for whoever watches it.

The core publishes after each act, goal change, reset and close; `GET /sessions/{id}/events` subscribes. A
subscriber's queue is bounded and drops its oldest events when full (counting them), so a slow browser never slows
the act path nor grows memory; a session nobody watches costs the act path one dict lookup.
"""

from __future__ import annotations

import asyncio
from collections import deque

from gmt.service.errors import ResourceExhausted, Unavailable

Event = tuple[str, dict]  # (kind, JSON-ready data)


class Subscription:
    """One watcher's queue of a session's events.

    Attributes:
        session_id: The session watched.
        dropped: Events lost to the bound since the last `take` (the oldest go first).
        closed: No event will come any more (the session ended, the server stops, or the watcher left).
    """

    def __init__(self, session_id: str, size: int) -> None:
        self.session_id = session_id
        self._queue: deque[Event] = deque(maxlen=size)
        self._wake = asyncio.Event()
        self.dropped = 0
        self.closed = False

    def put(self, event: Event) -> None:
        """Queue `event` (dropping the oldest when full); never blocks."""
        if len(self._queue) == self._queue.maxlen:
            self.dropped += 1
        self._queue.append(event)
        self._wake.set()

    def close(self) -> None:
        """End the feed: `wait` returns at once from now on."""
        self.closed = True
        self._wake.set()

    async def wait(self, timeout_s: float) -> None:
        """Return once an event is queued or the feed is closed, or after `timeout_s` seconds."""
        if not self._queue and not self.closed:
            try:
                await asyncio.wait_for(self._wake.wait(), timeout_s)
            except TimeoutError:
                pass
        self._wake.clear()

    def take(self) -> tuple[list[Event], int]:
        """The queued events, oldest first, and how many were dropped before them; the queue is emptied."""
        events, dropped = list(self._queue), self.dropped
        self._queue.clear()
        self.dropped = 0
        return events, dropped


class EventHub:
    """Subscriptions by session id, with bounds.

    Args:
        per_session: Watchers allowed per session.
        total: Watchers allowed on this replica.
        queue: Events a watcher's queue holds before it drops the oldest.
    """

    def __init__(self, per_session: int = 8, total: int = 256, queue: int = 1024) -> None:
        self.per_session, self.total, self.queue = per_session, total, queue
        self._subs: dict[str, set[Subscription]] = {}
        self.count = 0
        self.closed = False

    def __contains__(self, sid: str) -> bool:
        """Whether anyone watches session `sid` (the act path's only cost when nobody does)."""
        return sid in self._subs

    def subscribe(self, sid: str) -> Subscription:
        """A new subscription to `sid`'s events.

        Raises:
            ResourceExhausted: the session or this replica has its maximum of watchers.
            Unavailable: the server is shutting down.
        """
        if self.closed:
            raise Unavailable("server is shutting down")
        subs = self._subs.get(sid, ())
        if len(subs) >= self.per_session or self.count >= self.total:
            raise ResourceExhausted(
                f"too many event streams: at most {self.per_session} per session and {self.total} per replica; "
                "close one and retry"
            )
        sub = Subscription(sid, self.queue)
        self._subs.setdefault(sid, set()).add(sub)
        self.count += 1
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        """Forget `sub` (idempotent)."""
        sub.close()
        subs = self._subs.get(sub.session_id)
        if subs is not None and sub in subs:
            subs.discard(sub)
            self.count -= 1
            if not subs:
                del self._subs[sub.session_id]

    def publish(self, sid: str, kind: str, data: dict) -> None:
        """Queue one event for every watcher of `sid`."""
        for sub in self._subs.get(sid, ()):
            sub.put((kind, data))

    def end(self, sid: str, kind: str, data: dict) -> None:
        """Publish the last event of `sid` (closed, expired) and end its feeds."""
        for sub in list(self._subs.get(sid, ())):
            sub.put((kind, data))
            self.unsubscribe(sub)

    def close(self) -> None:
        """End every feed and refuse new ones (shutdown)."""
        self.closed = True
        for subs in list(self._subs.values()):
            for sub in list(subs):
                self.unsubscribe(sub)
