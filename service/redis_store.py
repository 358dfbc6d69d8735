"""Sessions in Redis, shared by replicas: any replica can continue any session exactly where it stopped.

Layout (prefix `gmt:` by default): `s:<id>` is a hash written by `session_codec.encode` after every step;
`live` is a sorted set of session ids scored by last use (the maximum-sessions count across replicas);
`x:<id>` marks an expired session for a day, so that it answers "expired" rather than "not found".
Expiry follows the store's clock; Redis key TTLs only collect sessions nobody touched for twice the timeout.
"""

from __future__ import annotations

import contextlib

from service import session_codec
from service.errors import Aborted, Internal, NotFound, ResourceExhausted, SessionExpired, Unavailable
from service.sessions import Clock, Session, SessionStore, expired_message, not_found_message
from service.settings import Settings

TOMBSTONE_TTL_S = 86_400

# KEYS: live, session hash. ARGV: now, idle timeout, max sessions, id, key TTL ms, then field/value pairs.
_CREATE = """
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', '(' .. (tonumber(ARGV[1]) - tonumber(ARGV[2])))
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
    """A `SessionStore` over Redis: one server, or a primary that Redis Sentinel watches (redis-py asyncio client).

    With `min_replicas`, a write that answers a client (create, and every save: an act, a goal change, a reset) is
    followed on the same connection by `WAIT min_replicas wait_timeout`, and answers `unavailable` unless that many
    replicas have it: a step is acknowledged only once a replica holds it, so a promoted replica has every
    acknowledged step (docs/reliability.md).

    Args:
        url: Redis URL, e.g. redis://localhost:6379/0 or redis+sentinel://h1:26379,h2:26379/mymaster
            (`service.redis_connect`).
        idle_timeout_s: Sessions unused for longer expire.
        max_sessions: Live sessions allowed at once, counted over all replicas.
        clock: Wall-clock seconds; replicas must agree, so use real time outside tests.
        prefix: Key prefix.
        min_replicas: Redis replicas that must hold a write before it is acknowledged (0: do not wait).
        wait_timeout_s: Longest wait for them.
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
    ) -> None:
        super().__init__(idle_timeout_s, max_sessions, clock)
        import redis.asyncio as aioredis  # optional dependency: only needed with --redis-url

        from service import redis_connect

        self._errors = (aioredis.RedisError, OSError)
        # A bounded pool that makes callers wait for a free connection: the default pool answers "Too many
        # connections" once 100 requests are in flight (seen at 256 concurrent sessions through nginx).
        # Socket timeouts bound a call to a paused or unreachable Redis: it answers `unavailable` (retryable).
        self._client = redis_connect.connect(url, max_connections=64, pool_timeout_s=10, socket_timeout_s=5)
        self.redis = self._client.redis
        self.prefix = prefix
        self.min_replicas = min_replicas
        self._wait_ms = max(1, round(wait_timeout_s * 1000))
        self._live = f"{prefix}live"
        self._create = self.redis.register_script(_CREATE)
        self._save = self.redis.register_script(_SAVE)
        self._seen: dict[str, tuple[str, float]] = {}  # id -> (model, last use here) of sessions touched here
        # Sessions whose last write here may not have reached `min_replicas` replicas: confirmed before use.
        self._unconfirmed: set[str] = set()

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
        """Raise Unavailable unless Redis answers."""
        await self._call(self.redis.ping())

    async def _write(self, script, keys: list[str], args: list) -> tuple[int, int | None]:
        """(the script's result, replicas holding the write): with `min_replicas`, the script and then WAIT in
        one pipeline, so on one connection (WAIT counts the writes of its own connection); else None replicas."""
        if not self.min_replicas:
            return await self._call(script(keys=keys, args=args)), None
        async with self.redis.pipeline(transaction=False) as p:
            # EVAL, not the script object's EVALSHA: in a pipeline that costs a SCRIPT EXISTS round trip first.
            p.eval(script.script, len(keys), *keys, *args).wait(self.min_replicas, self._wait_ms)
            n, acked = await self._call(p.execute())
        return n, acked

    def _not_replicated(self, acked: int | None) -> Unavailable | None:
        if acked is None or acked >= self.min_replicas:
            return None
        return Unavailable(
            f"session store: the write reached {acked} of the {self.min_replicas} Redis replica(s) required "
            f"within {self._wait_ms} ms, so it is not acknowledged; retry (an act with the same step is "
            "answered without stepping twice)"
        )

    async def create(self, session: Session) -> None:
        flat: list[bytes | str] = []
        for k, v in session_codec.encode(session).items():
            flat += [k, v]
        args = [repr(self.clock()), repr(self.idle_timeout_s), self.max_sessions, session.id, self._ttl_ms]
        n, acked = await self._write(self._create, [self._live, self._key(session.id)], args + flat)
        if n != -1:
            raise ResourceExhausted(
                f"server is full: {n} live sessions (maximum {self.max_sessions}); close a session or retry later"
            )
        if (e := self._not_replicated(acked)) is not None:
            # Nobody will learn this session's id (the client creates another): take it back if Redis still can.
            async with self.redis.pipeline(transaction=True) as p:
                p.delete(self._key(session.id)).zrem(self._live, session.id)
                with contextlib.suppress(*self._errors):
                    await p.execute()
            raise e
        self._seen[session.id] = (session.model, session.last_used)

    async def _expire(self, sid: str) -> None:
        async with self.redis.pipeline(transaction=True) as p:
            p.delete(self._key(sid)).zrem(self._live, sid).set(self._tomb(sid), b"1", ex=TOMBSTONE_TTL_S)
            await self._call(p.execute())
        self._forget(sid)

    def _forget(self, sid: str) -> None:
        self._unconfirmed.discard(sid)
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
        if sid in self._unconfirmed:
            fields = await self._confirmed_read(sid)
        else:
            fields = await self._call(self.redis.hgetall(self._key(sid)))
        if not fields:
            self._forget(sid)
            if await self._call(self.redis.exists(self._tomb(sid))):
                raise SessionExpired(expired_message(sid, self.idle_timeout_s))
            raise NotFound(not_found_message(sid))
        s = self._decode(sid, fields)
        if self.is_idle(s):
            await self._expire(sid)
            raise SessionExpired(expired_message(sid, self.idle_timeout_s))
        self._seen[sid] = (s.model, s.last_used)
        return s

    async def _confirmed_read(self, sid: str) -> dict:
        """The session's fields, once `min_replicas` replicas hold them (a retry after a write that was not
        acknowledged may be answered from that write: it must not be acknowledged before it is replicated).

        PEXPIRE (the key's TTL again) is a write, and WAIT after it covers every write before it, the session's
        last one included."""
        key = self._key(sid)
        async with self.redis.pipeline(transaction=False) as p:
            p.hgetall(key).pexpire(key, self._ttl_ms).wait(self.min_replicas, self._wait_ms)
            fields, _, acked = await self._call(p.execute())
        if fields and (e := self._not_replicated(acked)) is not None:
            raise e
        self._unconfirmed.discard(sid)
        return fields

    async def save(self, session: Session, read_version: int | None = None) -> None:
        flat: list[bytes | str] = []
        for k, v in session_codec.encode(session).items():
            flat += [k, v]
        expect = "" if read_version is None else str(read_version)
        args = [expect, repr(session.last_used), self._ttl_ms, session.id]
        try:
            n, acked = await self._write(self._save, [self._live, self._key(session.id)], args + flat)
        except Unavailable:
            if self.min_replicas:  # it may have been written, and not replicated
                self._unconfirmed.add(session.id)
            raise
        if (e := self._not_replicated(acked)) is not None and n == 0:
            self._unconfirmed.add(session.id)
            raise e
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
            p.delete(self._key(sid)).zrem(self._live, sid)
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
        await self._client.aclose()


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
    )
