"""Sessions in Redis, shared by replicas: any replica can continue any session exactly where it stopped.

The key layout is `redis_keys`; each write is one of `redis_scripts`' compare-and-set calls; the writes of one
event-loop turn go together (`redis_commit`); what this replica holds and has seen is `redis_local`.

The hot path costs one write and no read: a replica keeps the sessions it serves (their live contexts and the
version it last stored) and acts on them without reading the store; every write is a compare-and-set on the
version, so a change by another replica meanwhile is detected (`aborted`: the copy is dropped and adopted afresh
on the next request). The writes of one event-loop turn (one micro-batch, one batch call) go to Redis in one
pipeline, and each change is answered once that pipeline is acknowledged: an answered step is a stored step.

With a minimum number of replicas (`--store-min-replicas`), every write that answers a client is followed on the
same connection by `WAIT`: a change is acknowledged only once that many Redis replicas hold it, so a replica that
Sentinel promotes has every acknowledged step (docs/reliability.md).

Expiry follows each session's own `last_used`; `live`'s scores are refreshed by each replica's sweep (for the
sessions it served), so they can be stale by one sweep period and the sweep checks the session itself before it
expires one. Redis key TTLs only collect sessions nobody touched for twice the timeout: the same sweep sets them
again for the sessions it served (an act does not), so they run out at least the idle timeout after a last use.
"""

from __future__ import annotations

import contextlib
import uuid
from collections.abc import Callable

import orjson

from gmt.service import redis_scripts, session_codec
from gmt.service.activity import Activity, SessionBrief
from gmt.service.errors import (
    Aborted,
    AlreadyExists,
    Internal,
    NotFound,
    ResourceExhausted,
    ServiceError,
    SessionExpired,
    Unavailable,
)
from gmt.service.redis_commit import GroupCommit
from gmt.service.redis_keys import TOMBSTONE_TTL_S, RedisKeys
from gmt.service.redis_local import Held, LocalView
from gmt.service.sessions import Clock, Session, SessionStore, brief, expired_message, not_found_message
from gmt.service.settings import Settings


class RedisSessionStore(SessionStore):
    """A `SessionStore` over Redis: one server, or a primary that Redis Sentinel watches (redis-py asyncio client).

    Args:
        url: Redis URL, e.g. redis://localhost:6379/0 or redis+sentinel://h1:26379,h2:26379/mymaster
            (`gmt.service.redis_connect`).
        idle_timeout_s: Sessions unused for longer expire.
        max_sessions: Live sessions allowed at once, counted over all replicas.
        clock: Wall-clock seconds; replicas must agree, so use real time outside tests.
        prefix: Key prefix.
        min_replicas: Redis replicas that must hold a write before it is acknowledged (0: do not wait).
        wait_timeout_s: Longest wait for them.
        spin_s: How long a lone session's write polls for its reply (`Settings.store_spin_us`; 0: never).
    """

    remote = True

    def __init__(
        self,
        url: str,
        idle_timeout_s: float,
        max_sessions: int,
        clock: Clock,
        prefix: str = "gmt:",
        *,
        min_replicas: int = 0,
        wait_timeout_s: float = 1.0,
        spin_s: float = 0.0,
    ) -> None:
        super().__init__(idle_timeout_s, max_sessions, clock)
        import redis.asyncio as aioredis  # optional dependency: only needed with --redis-url

        from gmt.service import redis_connect

        self._errors = (aioredis.RedisError, OSError)
        # A bounded pool that makes callers wait for a free connection (the default pool answered "Too many
        # connections" past 100 requests in flight); socket timeouts bound a call to a paused or unreachable Redis:
        # it answers `unavailable` (retryable).
        socket_timeout_s = 5.0
        self._client = redis_connect.connect(
            url, max_connections=64, pool_timeout_s=10, socket_timeout_s=socket_timeout_s
        )
        self.redis = self._client.redis
        self.min_replicas = min_replicas
        self.prefix = prefix
        self.layout = RedisKeys(prefix, idle_timeout_s)
        self.local = LocalView(lambda sid, key: self.on_remove(sid, key))
        self.commit = GroupCommit(
            self._client,
            self._errors,
            socket_timeout_s,
            min_replicas=min_replicas,
            wait_ms=max(1, round(wait_timeout_s * 1000)),
            ttl_ms=self.layout.ttl_ms,
            spin_s=spin_s,
            lone=lambda: len(self.local.held) <= 1,
            encode=self._encode,
        )
        # Sessions whose last write here may not have reached `min_replicas` replicas: confirmed before use.
        self._unconfirmed: set[str] = set()
        self._epoch: bytes | None = None  # the store's epoch when this replica last checked (None: not yet)

    # ----- calls and errors -------------------------------------------------------------------------------------
    async def _call(self, coro):
        try:
            return await coro
        except self._errors as e:
            raise Unavailable(f"session store unreachable: {e}") from e

    async def ping(self) -> None:
        """Raise Unavailable unless Redis answers; learn the store's epoch (see `_missing`)."""
        await self._call(self.redis.ping())
        self._epoch = await self._current_epoch()

    async def _current_epoch(self) -> bytes:
        """The store's epoch: a random marker the first replica writes; it is gone when the store loses its data."""
        await self._call(self.redis.set(self.layout.epoch, uuid.uuid4().hex, nx=True))
        return await self._call(self.redis.get(self.layout.epoch)) or b""

    async def _missing(self, sid: str) -> NotFound:
        """The error for an id the store does not hold: expired, closed, lost with the store's data, or unknown."""
        tomb = await self._call(self.redis.get(self.layout.tomb(sid)))
        if tomb == b"closed":
            return NotFound(f"session {sid!r} was closed")
        if tomb is not None:
            return SessionExpired(expired_message(sid, self.idle_timeout_s))
        epoch = await self._call(self.redis.get(self.layout.epoch))
        if self._epoch is not None and epoch != self._epoch:
            self._epoch = await self._current_epoch()
            return NotFound(
                f"session {sid!r} not found in the session store, which was reset (lost its data) since this "
                "server last saw it; create a new session"
            )
        return self.unknown(sid)

    def unknown(self, sid: str) -> NotFound:
        return NotFound(not_found_message(sid) + "; or the session store lost its data")

    # ----- sessions ---------------------------------------------------------------------------------------------
    async def create(self, session: Session) -> None:
        k = self.layout
        flat = redis_scripts.flat(session_codec.create_fields(session))
        timeline, _ = session_codec.appends(session)
        args = [repr(self.clock()), self.max_sessions, session.id, k.ttl_ms, len(timeline), *timeline]
        keys = [k.live, k.session(session.id), *k.lists(session.id)]
        for attempt in range(2):
            async with self.redis.pipeline(transaction=False) as p:
                p.eval(redis_scripts.CREATE, len(keys), *keys, *args, *flat)
                if self.min_replicas:  # on the same connection: WAIT counts the writes of its own connection
                    p.wait(self.min_replicas, self.commit.wait_ms)
                n, *acked = await self._call(p.execute())
            if n == -1:
                if (e := self.commit.not_replicated(acked[0] if acked else None)) is not None:
                    # Nobody will learn of this session (the client creates it again): take it back if Redis can.
                    async with self.redis.pipeline(transaction=True) as p:
                        p.delete(k.session(session.id), *k.lists(session.id)).zrem(k.live, session.id)
                        with contextlib.suppress(*self._errors):
                            await p.execute()
                    raise e
                session.written()
                self.local.see(session.id, session.key, session.last_used)
                return
            if n == -2:
                raise AlreadyExists(f"session {session.id!r} exists")
            if attempt == 0:
                await self.sweep()  # the count may hold sessions that expired since the last sweep
        raise ResourceExhausted(
            f"server is full: {n} live sessions (maximum {self.max_sessions}); close a session or retry later"
        )

    async def get(self, sid: str, hold: bool = True) -> Session:
        held = self.local.held.get(sid)
        if held is not None and not self.is_idle(held.session):
            return held.session  # served here, and the compare-and-set write will notice any other writer
        if sid in self._unconfirmed:
            fields = await self._confirmed_read(sid)
        else:
            fields = await self._call(self.redis.hgetall(self.layout.session(sid)))
        if not fields:
            self.local.forget(sid)
            self._unconfirmed.discard(sid)
            raise await self._missing(sid)
        s = await self._unexpired(sid, fields)
        if held is not None:
            self.local.forget(sid)  # another replica used it meanwhile: adopt the stored copy, not ours
        if hold:
            self.local.hold(s)
        self.local.see(sid, s.key, s.last_used)
        return s

    async def _unexpired(self, sid: str, fields: dict) -> Session:
        """The session stored as `fields`, unless it has been idle too long (then it expires here).

        Raises:
            Internal: the fields are not a readable session.
            SessionExpired: it was idle for longer than the idle timeout.
        """
        try:
            s = session_codec.decode(fields)
        except session_codec.CodecError as e:
            raise Internal(f"session {sid!r} is stored in an unreadable form: {e}") from e
        if self.is_idle(s):
            await self._expire(sid, s)
            raise SessionExpired(expired_message(sid, self.idle_timeout_s))
        return s

    async def _confirmed_read(self, sid: str) -> dict:
        """The session's fields, once `min_replicas` replicas hold them: a retry after a write that was not
        acknowledged may be answered from that write, which must not be acknowledged before it is replicated.

        PEXPIRE (the key's TTL again) is a write, and WAIT after it covers every write before it on the primary's
        replication stream, the session's last one included."""
        key = self.layout.session(sid)
        async with self.redis.pipeline(transaction=False) as p:
            p.hgetall(key).pexpire(key, self.layout.ttl_ms).wait(self.min_replicas, self.commit.wait_ms)
            fields, _, acked = await self._call(p.execute())
        if fields and (e := self.commit.not_replicated(acked)) is not None:
            raise e
        self._unconfirmed.discard(sid)
        return fields

    async def save(self, session: Session, read_version: int | None = None) -> None:
        try:
            (outcome,) = await self.commit.enqueue([self._change(session, read_version)])
        except ServiceError as e:  # the whole write failed: unknown whether it was applied
            raise self._failed(session, e) from None
        if isinstance(outcome, ServiceError):
            raise self._failed(session, outcome)
        self._saved(session, outcome)

    async def save_many(self, items: list[tuple[Session, int | None]]) -> list[ServiceError | None]:
        changes, refused = [], {}
        for i, (session, read_version) in enumerate(items):
            try:
                changes.append(self._change(session, read_version))
            except ServiceError as e:
                refused[i] = e
        try:  # all in this turn: one script call writes them all
            outcomes = iter(await self.commit.enqueue(changes) if changes else ())
        except ServiceError as e:  # the whole write failed: unknown whether any of it was applied
            outcomes = iter([e] * len(changes))
        out: list[ServiceError | None] = []
        for i, (session, _) in enumerate(items):
            if i in refused:
                out.append(refused[i])
                continue
            outcome = next(outcomes)
            try:
                if isinstance(outcome, ServiceError):
                    raise self._failed(session, outcome)
                self._saved(session, outcome)
                out.append(None)
            except ServiceError as e:
                out.append(e)
        return out

    def _change(self, session: Session, read_version: int | None) -> tuple[Session, int, int, int | None]:
        """A change to write (`_encode` turns it into the save script's entry when its turn's write goes): the
        session, the version and step this replica last wrote of it, and the version the request read.

        Raises:
            Aborted: this replica's copy is not the version read (another request changed it meanwhile).
        """
        held = self._held(session, read_version)
        return session, held.version, held.step, read_version

    def _encode(self, changes: list[tuple[Session, int, int, int | None]]) -> list[tuple[list, bytes, int]]:
        """The save script's entries (`_script_entry`) of a turn's changes (`_change`), their fields built together
        (`session_codec.change_fields_many`). Called as the turn's write is sent: every change of the turn, from
        whichever request, is built in one go."""
        fields = session_codec.change_fields_many([c[0] for c in changes], [c[2] for c in changes])
        return [
            self._script_entry(session, version, read_version, f)
            for (session, version, _, read_version), f in zip(changes, fields, strict=True)
        ]

    def _held(self, session: Session, read_version: int | None) -> Held:
        """This replica's record of the session as last written.

        Raises:
            Aborted: this replica's copy is not the version read (another request changed it meanwhile).
        """
        held = self.local.held.get(session.id)
        if held is None or held.session is not session:
            raise ValueError(f"session {session.id!r} was not read from this store")
        if read_version is not None and read_version != held.version:
            raise Aborted(_aborted(session.id))
        return held

    def _script_entry(
        self, session: Session, held_version: int, read_version: int | None, fields: dict[str, bytes]
    ) -> tuple[list, bytes, int]:
        """The save script's entry writing `fields` (compared with the held version when read): its keys, its
        arguments as RESP bulk strings, and how many."""
        expect = session_codec.cas_token(session, held_version) if read_version is not None else b""
        keys, lists = [self.layout.session(session.id)], []
        timeline, records = session_codec.appends(session)
        if timeline or records:
            for key, values in zip(self.layout.lists(session.id), (timeline, records), strict=True):
                if values:
                    keys.append(key)
                    lists.append(values)
        return (keys, *redis_scripts.save_entry(expect, fields, lists))

    def _failed(self, session: Session, e: ServiceError) -> ServiceError:
        self.local.forget(
            session.id
        )  # unknown whether it was written (or replicated): adopt afresh next time
        if self.min_replicas:
            self._unconfirmed.add(session.id)
        return e

    def _saved(self, session: Session, n: int) -> None:
        """Account for the script's result `n` of a session's write (raising its error)."""
        if n == -1:
            self.local.forget(session.id)
            raise NotFound(f"session {session.id!r} was closed or expired while this request ran")
        if n == -2:
            self.local.forget(session.id)
            raise Aborted(_aborted(session.id))
        held = self.local.held[session.id]
        held.version, held.step = session.ctx.version, session.ctx.step
        session.written()

    async def _expire(self, sid: str, session: Session) -> None:
        """Remove an idle session; a recorded one is first handed to `on_expire` with its entries."""
        k = self.layout
        self._unconfirmed.discard(sid)
        if self.on_expire is not None and session.ledger.recording:
            async with self.redis.pipeline(transaction=True) as p:
                p.lrange(k.timeline(sid), 0, -1).lrange(k.recording(sid), 0, -1)
                timeline, records = await self._call(p.execute())
            done = self.on_expire(session, timeline, records)
            if done is not None:
                await done
        async with self.redis.pipeline(transaction=True) as p:
            p.delete(k.session(sid), *k.lists(sid)).zrem(k.live, sid)
            p.set(k.tomb(sid), b"1", ex=TOMBSTONE_TTL_S)
            await self._call(p.execute())
        self.local.forget(sid)

    async def entries(
        self, sid: str, records: bool, page: tuple[int, int] | None = None
    ) -> tuple[Session, list[bytes], list[bytes]]:
        if sid in self._unconfirmed:
            await self._confirmed_read(sid)  # nothing unacknowledged is reported
        first, last = (page[0], page[0] + page[1] - 1) if page else (0, -1)
        async with self.redis.pipeline(transaction=True) as p:
            p.hgetall(self.layout.session(sid)).lrange(self.layout.timeline(sid), first, last)
            if records:
                p.lrange(self.layout.recording(sid), 0, -1)
            fields, timeline, *rest = await self._call(p.execute())
        if not fields:
            raise await self._missing(sid)
        s = await self._unexpired(sid, fields)
        return s, timeline, rest[0] if records else []

    async def delete(self, sid: str, read: Session | None = None) -> None:
        k = self.layout
        if read is None:
            await self.get(sid)
            async with self.redis.pipeline(transaction=True) as p:
                p.delete(k.session(sid), *k.lists(sid)).zrem(k.live, sid)
                p.set(k.tomb(sid), b"closed", ex=TOMBSTONE_TTL_S)
                await self._call(p.execute())
        else:
            keys = [k.live, k.session(sid), *k.lists(sid), k.tomb(sid)]
            expect = session_codec.cas_token(read, read.ctx.version)
            n = await self._call(
                self.redis.eval(redis_scripts.CLOSE, len(keys), *keys, expect, sid, TOMBSTONE_TTL_S)
            )
            if n == -1:
                self.local.forget(sid)
                raise await self._missing(sid)
            if n == -2:
                self.local.forget(sid)
                raise Aborted(_aborted(sid))
        self.local.forget(sid)
        self._unconfirmed.discard(sid)

    async def count(self) -> int:
        return int(await self._call(self.redis.zcard(self.layout.live)))

    async def sweep(self) -> list[Session]:
        """Refresh `live`'s scores of the sessions used here, expire the idle ones, and let go of those this replica
        no longer serves."""
        live, held = self.layout.live, self.local.held
        low = self.clock() - self.idle_timeout_s
        used = {sid: h.session.last_used for sid, h in held.items() if h.session.last_used > h.refreshed}
        if used:
            # Their keys' TTLs too: an act does not set them (`redis_scripts.SAVE`).
            async with self.redis.pipeline(transaction=False) as p:
                p.zadd(live, used, xx=True, gt=True)
                for sid in used:
                    for key in (self.layout.session(sid), *self.layout.lists(sid)):
                        p.pexpire(key, self.layout.ttl_ms)
                await self._call(p.execute())
            for sid, t in used.items():
                held[sid].refreshed = t
        stale = [
            raw.decode() for raw in await self._call(self.redis.zrangebyscore(live, "-inf", f"({low!r}"))
        ]
        gone = []
        for sid in stale:
            if self.locks.busy(sid):  # a call on it is under way here (an act renews it): not now
                continue
            # Taken without waiting; no call on it starts here until it is expired or kept.
            async with self.locks(sid):
                if (s := await self._stale(sid)) is not None:
                    gone.append(s)
                    await self._expire(sid, s)
        self.local.let_go(low, self.locks.busy)
        return gone

    async def _stale(self, sid: str) -> Session | None:
        """The stored session `sid` if it is idle (then it is to expire); None when it is gone, unreadable or was used
        on a replica that has not refreshed its score in `live` yet (the score is set again)."""
        live = self.layout.live
        raw = await self._call(self.redis.hget(self.layout.session(sid), "st"))
        if raw is None:  # collected by its key TTL, or lost
            await self._call(self.redis.zrem(live, sid))
            return None
        fields = await self._call(self.redis.hgetall(self.layout.session(sid)))
        try:
            s = session_codec.decode(fields)
        except session_codec.CodecError:
            return None
        if not self.is_idle(s):
            await self._call(self.redis.zadd(live, {sid: s.last_used}, xx=True, gt=True))
            return None
        return s

    def local_count(self, key: str) -> int:
        return self.local.per_model[key]  # every held session was seen

    async def list_page(
        self, offset: int, limit: int, visible: Callable[[str], bool] | None = None
    ) -> tuple[int, list[SessionBrief]]:
        """What `live` holds, most recently used first (as of the replicas' last sweeps): two round trips, and
        only each session's `meta` and `st` are read (a session this replica holds is described from its copy).
        With `visible`, every live session's `meta` is read first, for its owner (one round trip more)."""
        if visible is None:
            async with self.redis.pipeline(transaction=False) as p:
                p.zcard(self.layout.live).zrevrange(self.layout.live, offset, offset + limit - 1)
                total, raw_ids = await self._call(p.execute())
            ids = [raw.decode() for raw in raw_ids]
        else:
            ids = await self._visible_ids(visible)
            total, ids = len(ids), ids[offset : offset + limit]
        async with self.redis.pipeline(transaction=False) as p:
            for sid in ids:
                p.hmget(self.layout.session(sid), "meta", "st")
            stored = await self._call(p.execute()) if ids else []
        out = []
        for sid, (meta, st) in zip(ids, stored, strict=True):
            held = self.local.held.get(sid)
            if held is not None:
                out.append(brief(held.session))
                continue
            try:
                m, s = orjson.loads(meta), orjson.loads(st)
                out.append(
                    SessionBrief(
                        sid,
                        str(m["model"]),
                        int(s["goal"]),
                        int(s["step"]),
                        float(m["created_at"]),
                        float(s["last_used"]),
                        Activity.load(s.get("activity")),
                        held_here=False,
                    )
                )
            except (TypeError, KeyError, ValueError, orjson.JSONDecodeError):
                continue  # gone since the index was read (or unreadable): not listed
        return int(total), out

    async def _visible_ids(self, visible: Callable[[str], bool]) -> list[str]:
        """The ids in `live`, most recently used first, of the sessions whose owner is `visible`."""
        ids = [raw.decode() for raw in await self._call(self.redis.zrevrange(self.layout.live, 0, -1))]
        async with self.redis.pipeline(transaction=False) as p:
            for sid in ids:
                p.hget(self.layout.session(sid), "meta")
            metas = await self._call(p.execute()) if ids else []
        out = []
        for sid, meta in zip(ids, metas, strict=True):
            try:
                owner = orjson.loads(meta).get("owner", "") if meta is not None else None
            except (AttributeError, orjson.JSONDecodeError):
                owner = None
            if owner is not None and visible(str(owner)):
                out.append(sid)
        return out

    async def model_states(self) -> dict[str, dict]:
        """Each model's saved default version and canary (`gmt.service.model_state`), by model name."""
        raw = await self._call(self.redis.hgetall(self.layout.models))
        return {k.decode(): orjson.loads(v) for k, v in raw.items()}

    async def save_model_state(self, name: str, entry: dict | None) -> None:
        """Save model `name`'s default version and canary (None: forget the model)."""
        if entry is None:
            await self._call(self.redis.hdel(self.layout.models, name))
        else:
            await self._call(self.redis.hset(self.layout.models, name, orjson.dumps(entry)))

    async def close(self) -> None:
        self.commit.close()
        await self._client.aclose()


def _aborted(sid: str) -> str:
    return (
        f"session {sid!r} was changed by another replica while this request ran; retry the request (with the same "
        "step: a repeat is answered without stepping twice)"
    )


def store_for(settings: Settings, clock: Clock) -> RedisSessionStore | None:
    """The Redis store `settings` ask for (URL, idle timeout, maximum sessions, replicas to wait for), or None."""
    if not settings.redis_url:
        return None
    return RedisSessionStore(
        settings.redis_url,
        settings.idle_timeout_s,
        settings.max_sessions,
        clock,
        min_replicas=settings.store_min_replicas,
        wait_timeout_s=settings.store_wait_timeout_s,
        spin_s=settings.store_spin_us / 1e6,
    )
