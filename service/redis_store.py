"""Sessions in Redis, shared by replicas: any replica can continue any session exactly where it stopped.

Layout (prefix `gmt:` by default): `s:<id>` is a hash written by `session_codec.encode` after every step;
`live` is a sorted set of session ids scored by last use (the maximum-sessions count across replicas);
`x:<id>` marks an expired (`1`) or closed (`closed`) session for a day, so that it answers that rather than "not
found"; `epoch` is a random marker written once: when it is gone or changed, the store lost its data.
Expiry follows the store's clock; Redis key TTLs only collect sessions nobody touched for twice the timeout.
"""

from __future__ import annotations

import uuid

from service import session_codec
from service.errors import (
    Aborted,
    AlreadyExists,
    Internal,
    NotFound,
    ResourceExhausted,
    SessionExpired,
    Unavailable,
)
from service.sessions import Clock, Session, SessionStore, expired_message, not_found_message

TOMBSTONE_TTL_S = 86_400

# KEYS: live, session hash. ARGV: now, idle timeout, max sessions, id, key TTL ms, then field/value pairs.
# Returns -1 when created, -2 when a live session has the id, else the live count that made the store full.
_CREATE = """
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', '(' .. (tonumber(ARGV[1]) - tonumber(ARGV[2])))
if redis.call('ZSCORE', KEYS[1], ARGV[4]) then return -2 end
local n = redis.call('ZCARD', KEYS[1])
if n >= tonumber(ARGV[3]) then return n end
redis.call('ZADD', KEYS[1], ARGV[1], ARGV[4])
redis.call('DEL', KEYS[2])
redis.call('HSET', KEYS[2], unpack(ARGV, 6))
redis.call('PEXPIRE', KEYS[2], ARGV[5])
return -1
"""


# KEYS: live, session hash. ARGV: read version ('' = any), last use, key TTL ms, id, then field/value pairs.
# Returns 0 when written, -1 when the session is gone (never revived), -2 when another writer came first.
_SAVE = """
local cur = redis.call('HGET', KEYS[2], 'ver')
if not cur then return -1 end
if ARGV[1] ~= '' and cur ~= ARGV[1] then return -2 end
redis.call('DEL', KEYS[2])
redis.call('HSET', KEYS[2], unpack(ARGV, 5))
redis.call('PEXPIRE', KEYS[2], ARGV[3])
redis.call('ZADD', KEYS[1], ARGV[2], ARGV[4])
return 0
"""


class RedisSessionStore(SessionStore):
    """A `SessionStore` over a Redis server (redis-py asyncio client).

    Args:
        url: Redis URL, e.g. redis://localhost:6379/0.
        idle_timeout_s: Sessions unused for longer expire.
        max_sessions: Live sessions allowed at once, counted over all replicas.
        clock: Wall-clock seconds; replicas must agree, so use real time outside tests.
        prefix: Key prefix.
    """

    def __init__(
        self, url: str, idle_timeout_s: float, max_sessions: int, clock: Clock, prefix: str = "gmt:"
    ) -> None:
        super().__init__(idle_timeout_s, max_sessions, clock)
        import redis.asyncio as aioredis  # optional dependency: only needed with --redis-url

        self._errors = (aioredis.RedisError, OSError)
        # A bounded pool that makes callers wait for a free connection: the default pool answers "Too many
        # connections" once 100 requests are in flight (seen at 256 concurrent sessions through nginx).
        # Socket timeouts bound a call to a paused or unreachable Redis: it answers `unavailable` (retryable).
        pool = aioredis.BlockingConnectionPool.from_url(
            url, max_connections=64, timeout=10, socket_timeout=5, socket_connect_timeout=5
        )
        self.redis = aioredis.Redis(connection_pool=pool)
        self.prefix = prefix
        self._live = f"{prefix}live"
        self._create = self.redis.register_script(_CREATE)
        self._save = self.redis.register_script(_SAVE)
        self._seen: dict[str, tuple[str, float]] = {}  # id -> (model, last use here) of sessions touched here
        self._epoch_key = f"{prefix}epoch"
        self._epoch: bytes | None = None  # the store's epoch when this replica last checked (None: not yet)

    def _key(self, sid: str) -> str:
        return f"{self.prefix}s:{sid}"

    def _tomb(self, sid: str) -> str:
        return f"{self.prefix}x:{sid}"

    @property
    def _ttl_ms(self) -> int:
        return int((2 * self.idle_timeout_s + 60) * 1000)

    async def _call(self, coro):
        try:
            return await coro
        except self._errors as e:
            raise Unavailable(f"session store unreachable: {e}") from e

    async def ping(self) -> None:
        """Raise Unavailable unless Redis answers; learn the store's epoch (see `_lost_message`)."""
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
        return NotFound(not_found_message(sid) + "; or the session store lost its data")

    async def create(self, session: Session) -> None:
        flat: list[bytes | str] = []
        for k, v in session_codec.encode(session).items():
            flat += [k, v]
        args = [repr(self.clock()), repr(self.idle_timeout_s), self.max_sessions, session.id, self._ttl_ms]
        n = await self._call(self._create(keys=[self._live, self._key(session.id)], args=args + flat))
        if n == -2:
            raise AlreadyExists(f"session {session.id!r} exists")
        if n != -1:
            raise ResourceExhausted(
                f"server is full: {n} live sessions (maximum {self.max_sessions}); close a session or retry later"
            )
        self._seen[session.id] = (session.model, session.last_used)

    async def _expire(self, sid: str) -> None:
        async with self.redis.pipeline(transaction=True) as p:
            p.delete(self._key(sid)).zrem(self._live, sid).set(self._tomb(sid), b"1", ex=TOMBSTONE_TTL_S)
            await self._call(p.execute())
        self._forget(sid)

    def _forget(self, sid: str) -> None:
        seen = self._seen.pop(sid, None)
        if seen is not None:
            self.on_remove(sid, seen[0])

    @staticmethod
    def _decode(sid: str, fields: dict) -> Session:
        try:
            return session_codec.decode(fields)
        except session_codec.CodecError as e:
            raise Internal(f"session {sid!r} is stored in an unreadable form: {e}") from e

    async def get(self, sid: str) -> Session:
        fields = await self._call(self.redis.hgetall(self._key(sid)))
        if not fields:
            self._forget(sid)
            raise await self._missing(sid)
        s = self._decode(sid, fields)
        if self.is_idle(s):
            await self._expire(sid)
            raise SessionExpired(expired_message(sid, self.idle_timeout_s))
        self._seen[sid] = (s.model, s.last_used)
        return s

    async def save(self, session: Session, read_version: int | None = None) -> None:
        flat: list[bytes | str] = []
        for k, v in session_codec.encode(session).items():
            flat += [k, v]
        expect = "" if read_version is None else str(read_version)
        args = [expect, repr(session.last_used), self._ttl_ms, session.id]
        n = await self._call(self._save(keys=[self._live, self._key(session.id)], args=args + flat))
        if n == -1:
            self._forget(session.id)
            raise NotFound(f"session {session.id!r} was closed or expired while this request ran")
        if n == -2:
            raise Aborted(
                f"session {session.id!r} was changed by another replica while this request ran; "
                "retry the request (with the same step: a repeat is answered without stepping twice)"
            )
        self._seen[session.id] = (session.model, session.last_used)

    async def delete(self, sid: str) -> None:
        await self.get(sid)
        async with self.redis.pipeline(transaction=True) as p:
            p.delete(self._key(sid)).zrem(self._live, sid).set(self._tomb(sid), b"closed", ex=TOMBSTONE_TTL_S)
            await self._call(p.execute())
        self._forget(sid)

    async def count(self) -> int:
        low = self.clock() - self.idle_timeout_s
        return int(await self._call(self.redis.zcount(self._live, low, "+inf")))

    async def sweep(self) -> list[Session]:
        low = self.clock() - self.idle_timeout_s
        stale = await self._call(self.redis.zrangebyscore(self._live, "-inf", f"({low!r}"))
        gone = []
        for raw in stale:
            sid = raw.decode()
            fields = await self._call(self.redis.hgetall(self._key(sid)))
            if fields:
                s = self._decode(sid, fields)
                if not self.is_idle(s):
                    continue
                gone.append(s)
            await self._expire(sid)
        for k in [k for k, v in self._seen.items() if v[1] < low]:
            self._forget(k)
        return gone

    def local_count(self, model: str) -> int:
        return sum(1 for m, _ in self._seen.values() if m == model)

    async def close(self) -> None:
        await self.redis.aclose()
        await self.redis.connection_pool.disconnect()  # a pool passed in is not closed by the client
