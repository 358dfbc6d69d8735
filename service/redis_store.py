"""Sessions in Redis, shared by replicas: any replica can continue any session exactly where it stopped.

Keys (prefix `gmt:` by default), each session's hash-tagged so that Redis Cluster keeps them on one shard:
`{<id>}:s` is the session's hash (`session_codec`: written once at creation, then only what each change changed);
`{<id>}:x` marks an expired (`1`) or closed (`closed`) session for a day, so that it answers that rather than "not
found"; `live` is the index of live sessions (the maximum-sessions count, the expiry sweep), written only by
creates, closes and sweeps, never by an act; `epoch` is a random marker written once: when it is gone or changed,
the store lost its data; `models` is a hash of each model's default version and canary (`model_state`), written by
management calls and read by a replica at start.

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
expires one. Redis key TTLs only collect sessions nobody touched for twice the timeout.
"""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import orjson

from gmt.service import resp, session_codec
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
from gmt.service.sessions import Clock, Session, SessionStore, brief, expired_message, not_found_message
from gmt.service.settings import Settings

TOMBSTONE_TTL_S = 86_400

# KEYS: live, session hash, its timeline list, its recording list. ARGV: now, max sessions, id, key TTL ms, the
# number c of timeline entries, the c entries, then field/value pairs. Returns -1 when created, -2 when a live
# session has the id, else the live count that made the store full.
_CREATE = """
if redis.call('ZSCORE', KEYS[1], ARGV[3]) and redis.call('EXISTS', KEYS[2]) == 1 then return -2 end
local n = redis.call('ZCARD', KEYS[1])
if n >= tonumber(ARGV[2]) then return n end
redis.call('ZADD', KEYS[1], ARGV[1], ARGV[3])
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
local c = tonumber(ARGV[5])
redis.call('HSET', KEYS[2], unpack(ARGV, 6 + c))
redis.call('PEXPIRE', KEYS[2], ARGV[4])
if c > 0 then
  redis.call('RPUSH', KEYS[3], unpack(ARGV, 6, 5 + c))
  redis.call('PEXPIRE', KEYS[3], ARGV[4])
end
return -1
"""

# Many sessions' changes in one call (one per session on Redis Cluster, where one call may touch one slot only).
# KEYS: per session its hash, then the lists its change appends to (its timeline, its recording: 0 to 2 keys, all
# in the session's slot). ARGV: key TTL ms, then per session: the expected `ver` ('' = any), the number n of
# fields, the number m of lists, the n field/value pairs, then per list the number c of values and the c values.
# The fields are written and the values appended only if the compare-and-set passes. Returns per session 0 when
# written, -1 when the session is gone (never revived), -2 when another writer came first.
_SAVE = """
local ttl, a, k, out = ARGV[1], 2, 1, {}
while k <= #KEYS do
  local key, expect, n, m = KEYS[k], ARGV[a], tonumber(ARGV[a + 1]), tonumber(ARGV[a + 2])
  a = a + 3
  local cur = redis.call('HGET', key, 'ver')
  local ok = cur and (expect == '' or cur == expect)
  if ok then
    redis.call('HSET', key, unpack(ARGV, a, a + 2 * n - 1))
    redis.call('PEXPIRE', key, ttl)
  end
  a = a + 2 * n
  for j = 1, m do
    local c = tonumber(ARGV[a])
    if ok then
      redis.call('RPUSH', KEYS[k + j], unpack(ARGV, a + 1, a + c))
      redis.call('PEXPIRE', KEYS[k + j], ttl)
    end
    a = a + 1 + c
  end
  if not cur then out[#out + 1] = -1 elseif not ok then out[#out + 1] = -2 else out[#out + 1] = 0 end
  k = k + 1 + m
end
return out
"""

# KEYS: live, session hash, timeline, recording, tombstone. ARGV: the expected `ver`, id, tombstone TTL s.
# Removes the session (and marks it closed) only if it has not changed; returns 0, -1 (gone) or -2 (changed).
_CLOSE = """
local cur = redis.call('HGET', KEYS[2], 'ver')
if not cur then return -1 end
if cur ~= ARGV[1] then return -2 end
redis.call('DEL', KEYS[2], KEYS[3], KEYS[4])
redis.call('ZREM', KEYS[1], ARGV[2])
redis.call('SET', KEYS[5], 'closed', 'EX', ARGV[3])
return 0
"""


@dataclass
class _Held:
    """A session this replica serves: the session (its live context once used) and what the store holds of it."""

    session: Session
    version: int  # the context version the store holds
    step: int  # the step the store holds the session at
    refreshed: float  # `last_used` as last written into `live`'s score


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
        self._socket_timeout_s = 5.0
        self._client = redis_connect.connect(
            url, max_connections=64, pool_timeout_s=10, socket_timeout_s=self._socket_timeout_s
        )
        self._fast: resp.RespConnection | None = None  # the hot path's own connection (`_send`)
        self._fast_lock = asyncio.Lock()
        self.redis = self._client.redis
        self.min_replicas = min_replicas
        self.spin_s = spin_s
        self._wait_ms = max(1, round(wait_timeout_s * 1000))
        # Sessions whose last write here may not have reached `min_replicas` replicas: confirmed before use.
        self._unconfirmed: set[str] = set()
        self.prefix = prefix
        self._live = f"{prefix}live"
        self._epoch_key = f"{prefix}epoch"
        self._models_key = f"{prefix}models"
        self._epoch: bytes | None = None  # the store's epoch when this replica last checked (None: not yet)
        self._held: dict[str, _Held] = {}
        # id -> (`Session.key`, last use) of every session created or read here: what this replica may soon serve (the
        # micro-batcher waits for as many acts as there are such sessions).
        self._seen: dict[str, tuple[str, float]] = {}
        self._seen_per_model: Counter[str] = Counter()
        self._queue: list[
            tuple[list, asyncio.Future]
        ] = []  # (changes, their caller) waiting for this turn's write
        self._flushes: set[asyncio.Task] = set()
        # Group commit (`min_replicas`): the fast connection a WAIT is in flight on, and the writes sent on it
        # since, each with the list its script's replies arrive in: the next WAIT covers them all.
        self._waiting_on: resp.RespConnection | None = None
        self._uncovered: list[tuple[list, list]] = []

    # ----- keys and calls ---------------------------------------------------------------------------------------
    def _key(self, sid: str) -> str:
        return f"{self.prefix}{{{sid}}}:s"

    def _tomb(self, sid: str) -> str:
        return f"{self.prefix}{{{sid}}}:x"

    def _timeline(self, sid: str) -> str:
        return f"{self.prefix}{{{sid}}}:tl"

    def _recording(self, sid: str) -> str:
        return f"{self.prefix}{{{sid}}}:rec"

    def _lists(self, sid: str) -> list[str]:
        """The session's keys beside its hash: timeline, recording."""
        return [self._timeline(sid), self._recording(sid)]

    @property
    def _ttl_ms(self) -> int:
        return int((2 * self.idle_timeout_s + 60) * 1000)

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
        await self._call(self.redis.set(self._epoch_key, uuid.uuid4().hex, nx=True))
        return await self._call(self.redis.get(self._epoch_key)) or b""

    async def _missing(self, sid: str) -> NotFound:
        """The error for an id the store does not hold: expired, closed, lost with the store's data, or unknown."""
        tomb = await self._call(self.redis.get(self._tomb(sid)))
        if tomb == b"closed":
            return NotFound(f"session {sid!r} was closed")
        if tomb is not None:
            return SessionExpired(expired_message(sid, self.idle_timeout_s))
        epoch = await self._call(self.redis.get(self._epoch_key))
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
    def _not_replicated(self, acked: int | None) -> Unavailable | None:
        if acked is None or acked >= self.min_replicas:
            return None
        return Unavailable(
            f"session store: the write reached {acked} of the {self.min_replicas} Redis replica(s) required "
            f"within {self._wait_ms} ms, so it is not acknowledged; retry (an act with the same step is "
            "answered without stepping twice)"
        )

    async def create(self, session: Session) -> None:
        flat = _flat(session_codec.create_fields(session))
        timeline, _ = session_codec.appends(session)
        args = [repr(self.clock()), self.max_sessions, session.id, self._ttl_ms, len(timeline), *timeline]
        keys = [self._live, self._key(session.id), *self._lists(session.id)]
        for attempt in range(2):
            async with self.redis.pipeline(transaction=False) as p:
                p.eval(_CREATE, len(keys), *keys, *args, *flat)
                if self.min_replicas:  # on the same connection: WAIT counts the writes of its own connection
                    p.wait(self.min_replicas, self._wait_ms)
                n, *acked = await self._call(p.execute())
            if n == -1:
                if (e := self._not_replicated(acked[0] if acked else None)) is not None:
                    # Nobody will learn of this session (the client creates it again): take it back if Redis can.
                    async with self.redis.pipeline(transaction=True) as p:
                        p.delete(self._key(session.id), *self._lists(session.id)).zrem(self._live, session.id)
                        with contextlib.suppress(*self._errors):
                            await p.execute()
                    raise e
                session.written()
                self._see(session.id, session.key, session.last_used)
                return
            if n == -2:
                raise AlreadyExists(f"session {session.id!r} exists")
            if attempt == 0:
                await self.sweep()  # the count may hold sessions that expired since the last sweep
        raise ResourceExhausted(
            f"server is full: {n} live sessions (maximum {self.max_sessions}); close a session or retry later"
        )

    async def get(self, sid: str, hold: bool = True) -> Session:
        held = self._held.get(sid)
        if held is not None and not self.is_idle(held.session):
            return held.session  # served here, and the compare-and-set write will notice any other writer
        if sid in self._unconfirmed:
            fields = await self._confirmed_read(sid)
        else:
            fields = await self._call(self.redis.hgetall(self._key(sid)))
        if not fields:
            self._forget(sid)
            self._unconfirmed.discard(sid)
            raise await self._missing(sid)
        s = await self._unexpired(sid, fields)
        if held is not None:
            self._forget(sid)  # another replica used it meanwhile: adopt the stored copy, not ours
        if hold:
            self._held[sid] = _Held(s, s.ctx.version, s.ctx.step, s.last_used)
        self._see(sid, s.key, s.last_used)
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
        key = self._key(sid)
        async with self.redis.pipeline(transaction=False) as p:
            p.hgetall(key).pexpire(key, self._ttl_ms).wait(self.min_replicas, self._wait_ms)
            fields, _, acked = await self._call(p.execute())
        if fields and (e := self._not_replicated(acked)) is not None:
            raise e
        self._unconfirmed.discard(sid)
        return fields

    async def save(self, session: Session, read_version: int | None = None) -> None:
        try:
            (outcome,) = await self._enqueue([self._entry(session, read_version)])
        except ServiceError as e:  # the whole write failed: unknown whether it was applied
            raise self._failed(session, e) from None
        if isinstance(outcome, ServiceError):
            raise self._failed(session, outcome)
        self._saved(session, outcome)

    async def save_many(self, items: list[tuple[Session, int | None]]) -> list[ServiceError | None]:
        entries, refused = [], {}
        for i, (session, read_version) in enumerate(
            items
        ):  # all in this turn: one script call writes them all
            try:
                entries.append(self._entry(session, read_version))
            except ServiceError as e:
                refused[i] = e
        try:
            outcomes = iter(await self._enqueue(entries) if entries else ())
        except ServiceError as e:  # the whole write failed: unknown whether any of it was applied
            outcomes = iter([e] * len(entries))
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

    def _entry(self, session: Session, read_version: int | None) -> tuple[list, list]:
        """The (keys, arguments) of the session's change in the save script.

        Raises:
            Aborted: this replica's copy is not the version read (another request changed it meanwhile).
        """
        held = self._held.get(session.id)
        if held is None or held.session is not session:
            raise ValueError(f"session {session.id!r} was not read from this store")
        if read_version is not None and read_version != held.version:
            raise Aborted(_aborted(session.id))
        fields = session_codec.change_fields(session, held.step)
        expect = session_codec.cas_token(session, held.version) if read_version is not None else b""
        keys, args = [self._key(session.id)], [expect, len(fields), 0, *_flat(fields)]
        for key, values in zip(self._lists(session.id), session_codec.appends(session), strict=True):
            if values:
                keys.append(key)
                args += [len(values), *values]
        args[2] = len(keys) - 1
        return keys, args

    def _enqueue(self, entries: list[tuple[list, list]]) -> asyncio.Future:
        """Queue changes for this turn's write; the future answers, per change, the script's result for it or
        the error that failed it (one future per caller, not per session)."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        first = not self._queue
        self._queue.append((entries, fut))
        if first:
            if self.spin_s > 0 and len(self._held) <= 1 and self._fast is not None and not self._fast.closed:
                # A lone session's write (the only session served here): sent now, its reply polled for, so the
                # future is answered before the caller awaits it.
                self._flush(self.spin_s)
            else:
                loop.call_soon(self._flush)
        return fut

    def _failed(self, session: Session, e: ServiceError) -> ServiceError:
        self._forget(session.id)  # unknown whether it was written (or replicated): adopt afresh next time
        if self.min_replicas:
            self._unconfirmed.add(session.id)
        return e

    def _saved(self, session: Session, n: int) -> None:
        """Account for the script's result `n` of a session's write (raising its error)."""
        if n == -1:
            self._forget(session.id)
            raise NotFound(f"session {session.id!r} was closed or expired while this request ran")
        if n == -2:
            self._forget(session.id)
            raise Aborted(_aborted(session.id))
        held = self._held[session.id]
        held.version, held.step = session.ctx.version, session.ctx.step
        session.written()

    def _flush(self, spin_s: float = 0.0) -> None:
        """Send the turn's writes as one script call (then WAIT on the same connection when replicas must hold
        them, one WAIT in flight at a time: the writes sent while one is in flight share the next, `_waited`): at
        once on the open fast connection (polling for the reply up to `spin_s`, `RespConnection.send`), else from
        a task that connects first."""
        queue, self._queue = self._queue, []
        keys = [k for entries, _ in queue for ks, _ in entries for k in ks]
        argv = [a for entries, _ in queue for _, args in entries for a in args]
        # EVAL, not EVALSHA: no script-cache round trip, and a promoted replica needs no script loaded.
        commands = [["EVAL", _SAVE, len(keys), *keys, self._ttl_ms, *argv]]
        conn = self._fast
        if conn is not None and not conn.closed:
            if not self.min_replicas:
                conn.send(lambda replies: self._answer(queue, conn, replies), *commands, spin_s=spin_s)
            elif self._waiting_on is conn:
                # Group commit: a WAIT is in flight on this connection (Redis holds the connection's later
                # commands until it is answered). The write goes now; one WAIT for every write sent meanwhile
                # follows once that one is answered (`_waited`).
                got: list = []
                self._uncovered.append((queue, got))
                conn.send(got.append, *commands)
            else:
                self._waiting_on = conn
                wait = ["WAIT", self.min_replicas, self._wait_ms]
                conn.send(
                    lambda replies: self._waited(conn, [(queue, None)], replies),
                    *commands,
                    wait,
                    spin_s=spin_s,
                )
            return
        if self.min_replicas:
            commands.append(["WAIT", self.min_replicas, self._wait_ms])
        task = asyncio.get_running_loop().create_task(self._flush_slowly(queue, commands))
        self._flushes.add(task)  # the loop holds tasks weakly
        task.add_done_callback(self._flushes.discard)

    def _waited(self, conn: resp.RespConnection, group: list[tuple[list, list | None]], replies) -> None:
        """Answer the writes a WAIT covered, from their script's replies and the WAIT's (`replies`: [script, WAIT]
        for the write sent with it, then the WAIT alone for those sent while another WAIT was in flight); then
        send one WAIT for the writes sent meanwhile, or fail them with the connection."""
        for queue, got in group:
            if got is None or isinstance(replies, BaseException):
                self._answer(queue, conn, replies)
            elif got and not isinstance(got[0], BaseException):
                self._answer(queue, conn, [*got[0], *replies])
            else:
                self._answer(queue, conn, got[0] if got else resp.ConnectionLost("no reply to the write"))
        if self._waiting_on is not conn:
            return
        uncovered, self._uncovered = self._uncovered, []
        if not uncovered:
            self._waiting_on = None
            return
        try:
            conn.send(lambda r: self._waited(conn, uncovered, r), ["WAIT", self.min_replicas, self._wait_ms])
        except resp.ConnectionLost as e:
            self._waiting_on = None
            for queue, _ in uncovered:
                self._answer(queue, conn, e)

    async def _flush_slowly(self, queue: list, commands: list[list]) -> None:
        try:
            replies = await self._send(commands)
        except BaseException as e:  # noqa: BLE001 - every waiter gets the failure
            self._resolve(queue, e)
            if not isinstance(e, Exception):
                raise
            return
        self._resolve(queue, replies)

    def _answer(self, queue: list, conn: resp.RespConnection, replies: list | BaseException) -> None:
        """Resolve the turn's writes from the fast connection's replies (called as they are parsed)."""
        if isinstance(replies, resp.ConnectionLost):
            replies = Unavailable(f"session store unreachable: {replies}")
        elif not isinstance(replies, BaseException):
            try:
                replies = self._checked(conn, replies)
            except ServiceError as e:
                replies = e
        self._resolve(queue, replies)

    def _resolve(self, queue: list, replies: list | BaseException) -> None:
        """Answer each queued caller, per change, from the replies of its turn (or fail them all)."""
        changes = sum(len(entries) for entries, _ in queue)
        if not isinstance(replies, BaseException) and len(replies[0]) != changes:
            replies = Internal(f"the store answered {len(replies[0])} of {changes} writes")
        if isinstance(replies, BaseException):
            err = (
                replies
                if isinstance(replies, ServiceError)
                else Unavailable(f"session store unreachable: {replies}")
            )
            for _, fut in queue:
                if not fut.done():
                    fut.set_exception(err)
            return
        results, *acked = replies
        short = self._not_replicated(acked[0] if acked else None)
        at = 0
        for entries, fut in queue:
            mine, at = results[at : at + len(entries)], at + len(entries)
            if not fut.done():
                # A change written on the primary only is not acknowledged (`_failed` marks it unconfirmed).
                fut.set_result([short if short is not None and int(r) == 0 else int(r) for r in mine])

    async def _send(self, commands: list[list]) -> list:
        """The replies to `commands`, sent together on the store's own pipelined connection to the primary
        (`gmt.service.resp`, over TCP or a Unix socket; redis-py's pipeline where the URL is TLS).

        Raises:
            Unavailable: Redis cannot be reached, or answered an error.
        """
        conn = await self._connection()
        if conn is None:
            async with self.redis.pipeline(transaction=False) as p:
                for c in commands:
                    p.execute_command(*c)
                return await self._call(p.execute())
        try:
            return self._checked(conn, await conn.call(*commands))
        except resp.ConnectionLost as e:
            raise Unavailable(f"session store unreachable: {e}") from e

    @staticmethod
    def _checked(conn: resp.RespConnection, replies: list) -> list:
        """`replies`, unless one is an error: then Unavailable (and a primary that stopped being one is let go)."""
        for r in replies:
            if isinstance(r, resp.RespError):
                if str(r).startswith(("READONLY", "MASTERDOWN", "LOADING")):
                    conn.close()  # a demoted or restarting primary: find the primary again next time
                raise Unavailable(f"session store error: {r}")
        return replies

    async def _connection(self) -> resp.RespConnection | None:
        """The open fast connection (opened to the current primary when there is none); None: use redis-py."""
        if self._fast is not None and not self._fast.closed:
            return self._fast
        async with self._fast_lock:
            if self._fast is not None and not self._fast.closed:
                return self._fast
            try:
                where = await self._client.primary()
            except self._errors as e:
                raise Unavailable(f"session store unreachable: {e}") from e
            if where is None:
                return None
            conn = resp.RespConnection(
                where["host"],
                where["port"],
                path=where.get("path"),
                username=where["username"],
                password=where["password"],
                db=where["db"],
                timeout_s=self._socket_timeout_s,
            )
            try:
                await conn.open()
            except resp.ConnectionLost as e:
                raise Unavailable(f"session store unreachable: {e}") from e
            self._fast = conn
            return conn

    async def _expire(self, sid: str, session: Session) -> None:
        """Remove an idle session; a recorded one is first handed to `on_expire` with its entries."""
        self._unconfirmed.discard(sid)
        if self.on_expire is not None and session.ledger.recording:
            async with self.redis.pipeline(transaction=True) as p:
                p.lrange(self._timeline(sid), 0, -1).lrange(self._recording(sid), 0, -1)
                timeline, records = await self._call(p.execute())
            done = self.on_expire(session, timeline, records)
            if done is not None:
                await done
        async with self.redis.pipeline(transaction=True) as p:
            p.delete(self._key(sid), *self._lists(sid)).zrem(self._live, sid)
            p.set(self._tomb(sid), b"1", ex=TOMBSTONE_TTL_S)
            await self._call(p.execute())
        self._forget(sid)

    def _see(self, sid: str, key: str, last_used: float) -> None:
        seen = self._seen.get(sid)
        if seen is not None and seen[0] != key:
            self._unsee(sid)  # the id names a new session now (created again after the last ended)
            seen = None
        if seen is None:
            self._seen_per_model[key] += 1
        self._seen[sid] = (key, last_used)

    def _unsee(self, sid: str) -> None:
        seen = self._seen.pop(sid, None)
        if seen is not None:
            self._seen_per_model[seen[0]] -= 1

    def _forget(self, sid: str) -> None:
        self._unsee(sid)
        held = self._held.pop(sid, None)
        if held is not None:
            self.on_remove(sid, held.session.key)

    async def entries(
        self, sid: str, records: bool, page: tuple[int, int] | None = None
    ) -> tuple[Session, list[bytes], list[bytes]]:
        if sid in self._unconfirmed:
            await self._confirmed_read(sid)  # nothing unacknowledged is reported
        first, last = (page[0], page[0] + page[1] - 1) if page else (0, -1)
        async with self.redis.pipeline(transaction=True) as p:
            p.hgetall(self._key(sid)).lrange(self._timeline(sid), first, last)
            if records:
                p.lrange(self._recording(sid), 0, -1)
            fields, timeline, *rest = await self._call(p.execute())
        if not fields:
            raise await self._missing(sid)
        s = await self._unexpired(sid, fields)
        return s, timeline, rest[0] if records else []

    async def delete(self, sid: str, read: Session | None = None) -> None:
        if read is None:
            await self.get(sid)
            async with self.redis.pipeline(transaction=True) as p:
                p.delete(self._key(sid), *self._lists(sid)).zrem(self._live, sid)
                p.set(self._tomb(sid), b"closed", ex=TOMBSTONE_TTL_S)
                await self._call(p.execute())
        else:
            keys = [self._live, self._key(sid), *self._lists(sid), self._tomb(sid)]
            expect = session_codec.cas_token(read, read.ctx.version)
            n = await self._call(self.redis.eval(_CLOSE, len(keys), *keys, expect, sid, TOMBSTONE_TTL_S))
            if n == -1:
                self._forget(sid)
                raise await self._missing(sid)
            if n == -2:
                self._forget(sid)
                raise Aborted(_aborted(sid))
        self._forget(sid)
        self._unconfirmed.discard(sid)

    async def count(self) -> int:
        return int(await self._call(self.redis.zcard(self._live)))

    async def sweep(self) -> list[Session]:
        """Refresh `live`'s scores of the sessions used here, expire the idle ones, and let go of those this replica
        no longer serves."""
        low = self.clock() - self.idle_timeout_s
        used = {
            sid: h.session.last_used for sid, h in self._held.items() if h.session.last_used > h.refreshed
        }
        if used:
            await self._call(self.redis.zadd(self._live, used, xx=True, gt=True))
            for sid, t in used.items():
                self._held[sid].refreshed = t
        stale = [
            raw.decode()
            for raw in await self._call(self.redis.zrangebyscore(self._live, "-inf", f"({low!r}"))
        ]
        gone = []
        for sid in stale:
            raw = await self._call(self.redis.hget(self._key(sid), "st"))
            if raw is None:  # collected by its key TTL, or lost
                await self._call(self.redis.zrem(self._live, sid))
                continue
            fields = await self._call(self.redis.hgetall(self._key(sid)))
            try:
                s = session_codec.decode(fields)
            except session_codec.CodecError:
                continue
            if not self.is_idle(s):  # used on a replica that has not refreshed its score yet
                await self._call(self.redis.zadd(self._live, {sid: s.last_used}, xx=True, gt=True))
                continue
            gone.append(s)
            await self._expire(sid, s)
        for sid in [sid for sid, h in self._held.items() if h.session.last_used < low]:
            self._forget(sid)
        for sid in [sid for sid, (_, t) in self._seen.items() if t < low and sid not in self._held]:
            self._unsee(sid)
        return gone

    def local_count(self, key: str) -> int:
        return self._seen_per_model[key]  # every held session was seen

    async def list_page(
        self, offset: int, limit: int, visible: Callable[[str], bool] | None = None
    ) -> tuple[int, list[SessionBrief]]:
        """What `live` holds, most recently used first (as of the replicas' last sweeps): two round trips, and
        only each session's `meta` and `st` are read (a session this replica holds is described from its copy).
        With `visible`, every live session's `meta` is read first, for its owner (one round trip more)."""
        if visible is None:
            async with self.redis.pipeline(transaction=False) as p:
                p.zcard(self._live).zrevrange(self._live, offset, offset + limit - 1)
                total, raw_ids = await self._call(p.execute())
            ids = [raw.decode() for raw in raw_ids]
        else:
            ids = await self._visible_ids(visible)
            total, ids = len(ids), ids[offset : offset + limit]
        async with self.redis.pipeline(transaction=False) as p:
            for sid in ids:
                p.hmget(self._key(sid), "meta", "st")
            stored = await self._call(p.execute()) if ids else []
        out = []
        for sid, (meta, st) in zip(ids, stored, strict=True):
            held = self._held.get(sid)
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
        ids = [raw.decode() for raw in await self._call(self.redis.zrevrange(self._live, 0, -1))]
        async with self.redis.pipeline(transaction=False) as p:
            for sid in ids:
                p.hget(self._key(sid), "meta")
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
        raw = await self._call(self.redis.hgetall(self._models_key))
        return {k.decode(): orjson.loads(v) for k, v in raw.items()}

    async def save_model_state(self, name: str, entry: dict | None) -> None:
        """Save model `name`'s default version and canary (None: forget the model)."""
        if entry is None:
            await self._call(self.redis.hdel(self._models_key, name))
        else:
            await self._call(self.redis.hset(self._models_key, name, orjson.dumps(entry)))

    async def close(self) -> None:
        if self._fast is not None:
            self._fast.close()
        await self._client.aclose()


def _flat(fields: dict[str, bytes]) -> list:
    out: list = []
    for k, v in fields.items():
        out += [k, v]
    return out


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
