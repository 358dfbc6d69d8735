"""Sessions and where they live: the `SessionStore` interface and its in-memory default.

A store enforces the idle timeout (an expired session answers `SessionExpired`, a `NotFound`) and the maximum
number of live sessions (`ResourceExhausted`). It does not order calls: the core holds one lock per session, which
the store's sweep respects (`SessionStore.locks`).
"""

from __future__ import annotations

import abc
import itertools
from collections import Counter, OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from gmt.model.context import Context, StoredContext
from gmt.service.activity import Activity, SessionBrief
from gmt.service.errors import (
    AlreadyExists,
    FailedPrecondition,
    NotFound,
    ResourceExhausted,
    ServiceError,
    SessionExpired,
)
from gmt.service.ids import SessionLocks
from gmt.service.records import Ledger

Clock = Callable[[], float]
# Told of a recorded session that expires, before it is removed, with its timeline entries and step records: what
# the core writes to the recordings directory. A shared store awaits what it returns before it removes the session.
Archive = Callable[["Session", list[bytes], list[bytes]], Awaitable[None] | None]
TOMBSTONES = 100_000  # expired ids remembered so that they answer "expired" rather than "not found"


@dataclass
class Session:
    """One client's episode on one model.

    Attributes:
        id: Session id (opaque string).
        model: Name of the model it runs on.
        ctx: The engine's live context, or its stored form as read back from a shared store (the core turns
            it into a live context of the model's engine before use).
        created_at: Clock time of creation (seconds).
        last_used: Clock time of the last act / set_goal / reset.
        request: What created it (model, goal, seed, action mode): a retried create must repeat it to be
            answered this session.
        model_version: The model version it runs for its whole life ('' for a session stored before versions
            were: the model's default version).
        fingerprint: That version's checkpoint fingerprint (how a replica that lacks the version finds it).
        activity: Acts/s and last latency (the console's listing).
        ledger: Its goal timeline and recording (`gmt.service.records`).
        relabelled_from: The first step whose stored record a goal change relabelled since the session was
            last written (None: none); a store that writes only new steps writes these again.
        owner: The name of the key that created it ('' for none: anyone's), `gmt.service.keys`.
    """

    id: str
    model: str
    ctx: Context | StoredContext
    created_at: float
    last_used: float
    request: str = ""
    model_version: str = ""
    fingerprint: str = ""
    activity: Activity = field(default_factory=Activity)
    ledger: Ledger = field(default_factory=Ledger)
    relabelled_from: int | None = None
    owner: str = ""

    def written(self) -> None:
        """The store now holds every change made so far: forget what was pending (records, relabelled steps)."""
        self.relabelled_from = None
        self.ledger.written()

    @property
    def key(self) -> str:
        """`model@version`: the engine, batcher and per-version count it belongs to."""
        return f"{self.model}@{self.model_version}"


def brief(s: Session, held_here: bool = True) -> SessionBrief:
    """The listing's view of a session held as a `Session`."""
    return SessionBrief(
        s.id, s.model, int(s.ctx.goal), int(s.ctx.step), s.created_at, s.last_used, s.activity, held_here
    )


def expired_message(sid: str, idle_timeout_s: float) -> str:
    """The one wording of an expiry, shared by every store."""
    return f"session {sid!r} expired: it was idle for more than the idle timeout of {idle_timeout_s:g} s"


def not_found_message(sid: str) -> str:
    """The one wording of an unknown session, shared by every store."""
    return f"session {sid!r} not found (never created, or closed)"


class SessionStore(abc.ABC):
    """Where sessions live between calls.

    Args:
        idle_timeout_s: Sessions unused for longer expire.
        max_sessions: Live sessions allowed at once.
        clock: Wall-clock seconds (injectable for tests).

    Attributes:
        remote: Whether a write waits for another process (Redis): an act is answered only once its write is
            acknowledged, so the micro-batcher keeps more, smaller passes in flight (`MicroBatcher(parts=...)`).
    """

    remote = False

    def __init__(self, idle_timeout_s: float, max_sessions: int, clock: Clock) -> None:
        self.idle_timeout_s = idle_timeout_s
        self.max_sessions = max_sessions
        self.clock = clock
        # Told (session id, `Session.key`) of every session this store drops, so the engine can free its slot.
        self.on_remove: Callable[[str, str], None] = lambda sid, key: None
        # Told of every session that expires (see `Archive`), when set.
        self.on_expire: Archive | None = None
        # The sessions' locks (the core's, `gmt.service.core_state`): a sweep expires no session whose lock is busy
        # (a call on it is under way: an act renews it), and a sweep that awaits (Redis) holds a session's lock while
        # it checks and expires it.
        self.locks = SessionLocks()

    def is_idle(self, session: Session) -> bool:
        """Whether `session` has been unused for longer than the idle timeout."""
        return self.clock() - session.last_used > self.idle_timeout_s

    @abc.abstractmethod
    async def create(self, session: Session) -> None:
        """Add a new session.

        Raises:
            AlreadyExists: a live session has this id (the caller decides whether it is a retried create).
            ResourceExhausted: the store already holds `max_sessions` live sessions.
        """

    @abc.abstractmethod
    async def get(self, sid: str, hold: bool = True) -> Session:
        """The session `sid` (a copy for remote stores: write changes back with `save`).

        Args:
            hold: This replica is about to change the session and serve it from now on: a shared store keeps
                its copy and serves it again without reading (False for a look that changes nothing).

        Raises:
            SessionExpired: it was idle for too long (it is then removed).
            NotFound: it does not exist.
        """

    @abc.abstractmethod
    async def save(self, session: Session, read_version: int | None = None) -> None:
        """Persist the session's context and `last_used`; never brings back a removed session.

        Args:
            session: The session as changed by this request.
            read_version: The context version this request read; a shared store writes only if the stored
                version is still that one (compare-and-set).

        Raises:
            Aborted: another replica wrote the session since it was read (retry the request).
            NotFound: the session was closed or expired meanwhile.
        """

    @abc.abstractmethod
    async def entries(
        self, sid: str, records: bool, page: tuple[int, int] | None = None
    ) -> tuple[Session, list[bytes], list[bytes]]:
        """The session with its timeline entries and (when `records`) its step records, as one snapshot; a look
        that changes nothing and holds nothing.

        Args:
            page: (offset, limit): only those timeline entries (all of them when None).

        Raises:
            SessionExpired: it was idle for too long (it is then removed).
            NotFound: it does not exist.
        """

    async def save_many(self, items: list[tuple[Session, int | None]]) -> list[ServiceError | None]:
        """`save` for each (session, read version), all at once (a shared store writes them in one round trip).

        Returns:
            Per item: None when saved, else the error `save` would have raised.
        """
        out: list[ServiceError | None] = []
        for session, read_version in items:
            try:
                await self.save(session, read_version)
                out.append(None)
            except ServiceError as e:
                out.append(e)
        return out

    @abc.abstractmethod
    async def delete(self, sid: str, read: Session | None = None) -> None:
        """Remove the session (its timeline and recording with it).

        Args:
            read: The session as a snapshot of `entries` read it: a shared store removes it only if it has not
                changed since (so that nothing answered after the snapshot is lost with it).

        Raises:
            SessionExpired: it had already expired.
            NotFound: it does not exist.
            Aborted: it changed since `read`.
        """

    def unknown(self, sid: str) -> NotFound:
        """The error for an id this store never held (also what another key gets for a session: `gmt.service.keys`)."""
        return NotFound(not_found_message(sid))

    @abc.abstractmethod
    async def count(self) -> int:
        """Number of live (not expired) sessions."""

    @abc.abstractmethod
    async def sweep(self) -> list[Session]:
        """Remove expired sessions and return them; none that is in use (`locks.busy`): its act renews it."""

    @abc.abstractmethod
    def local_count(self, key: str) -> int:
        """Sessions of model version `key` (`Session.key`) that this process may serve (exact in memory, an upper
        estimate otherwise)."""

    async def close(self) -> None:  # noqa: B027 - optional hook
        """Release connections."""

    async def list_page(
        self, offset: int, limit: int, visible: Callable[[str], bool] | None = None
    ) -> tuple[int, list[SessionBrief]]:
        """(live sessions held, up to `limit` of them from `offset`), newest first.

        Args:
            visible: Whether a session of this owner is listed (None: every session); the count is of those.

        Raises:
            FailedPrecondition: this store cannot list its sessions.
        """
        raise FailedPrecondition(f"the session store {type(self).__name__} cannot list its sessions")


class MemorySessionStore(SessionStore):
    """Sessions in a dict of this process (the default; lost on restart)."""

    def __init__(self, idle_timeout_s: float, max_sessions: int, clock: Clock) -> None:
        super().__init__(idle_timeout_s, max_sessions, clock)
        self._sessions: dict[str, Session] = {}
        self._per_model: Counter[str] = Counter()
        self._expired: OrderedDict[str, None] = OrderedDict()

    async def create(self, session: Session) -> None:
        old = self._sessions.get(session.id)
        if old is not None:
            if not self.is_idle(old):
                raise AlreadyExists(f"session {session.id!r} exists")
            self._remove(old, expired=True)
        if len(self._sessions) >= self.max_sessions:
            await self.sweep()
        if len(self._sessions) >= self.max_sessions:
            raise ResourceExhausted(
                f"server is full: {len(self._sessions)} live sessions (maximum {self.max_sessions}); "
                "close a session or retry later"
            )
        session.ledger.timeline = []
        session.ledger.records = [] if session.ledger.recording else None
        session.written()
        self._sessions[session.id] = session
        self._per_model[session.key] += 1

    def _lookup(self, sid: str) -> Session:
        s = self._sessions.get(sid)
        if s is None:
            if sid in self._expired:
                raise SessionExpired(expired_message(sid, self.idle_timeout_s))
            raise self.unknown(sid)
        if self.is_idle(s):
            self._remove(s, expired=True)
            raise SessionExpired(expired_message(sid, self.idle_timeout_s))
        return s

    def _remove(self, s: Session, expired: bool) -> None:
        del self._sessions[s.id]
        self._per_model[s.key] -= 1
        self.on_remove(s.id, s.key)
        if expired and self.on_expire is not None and s.ledger.recording:
            self.on_expire(s, list(s.ledger.timeline or ()), list(s.ledger.records or ()))
        if expired:
            self._expired[s.id] = None
            while len(self._expired) > TOMBSTONES:
                self._expired.popitem(last=False)

    async def get(self, sid: str, hold: bool = True) -> Session:
        return self._lookup(sid)

    async def save(self, session: Session, read_version: int | None = None) -> None:
        # One process, one lock per session in the core: no other writer can interleave. A session the sweeper
        # removed meanwhile is not resurrected.
        if session.id in self._sessions:
            self._sessions[session.id] = session
        session.written()

    async def entries(
        self, sid: str, records: bool, page: tuple[int, int] | None = None
    ) -> tuple[Session, list[bytes], list[bytes]]:
        s = self._lookup(sid)
        timeline = s.ledger.timeline or []
        timeline = timeline[page[0] : page[0] + page[1]] if page else list(timeline)
        return s, timeline, list(s.ledger.records or ()) if records else []

    async def delete(self, sid: str, read: Session | None = None) -> None:
        self._remove(self._lookup(sid), expired=False)

    def live(self) -> list[Session]:
        """Every session held (what a shutdown drops)."""
        return list(self._sessions.values())

    async def count(self) -> int:
        return len(self._sessions)

    async def sweep(self) -> list[Session]:
        gone = [s for s in self._sessions.values() if self.is_idle(s) and not self.locks.busy(s.id)]
        for s in gone:
            self._remove(s, expired=True)
        return gone

    def local_count(self, key: str) -> int:
        return self._per_model[key]

    async def list_page(
        self, offset: int, limit: int, visible: Callable[[str], bool] | None = None
    ) -> tuple[int, list[SessionBrief]]:
        if visible is None:
            page = itertools.islice(reversed(self._sessions.values()), offset, offset + limit)
            return len(self._sessions), [brief(s) for s in page]
        shown = [s for s in reversed(self._sessions.values()) if visible(s.owner)]
        return len(shown), [brief(s) for s in shown[offset : offset + limit]]
