"""Redis URLs of the session store and the asyncio clients they open: one Redis server, or a primary that Redis
Sentinel watches (and replaces by a promoted replica when it fails).

Accepted forms:
- `redis://[[user]:password@]host:port/db`, `rediss://...` (TLS), `unix:///path.sock?db=0`: one server, parsed by
  redis-py (`redis.asyncio.BlockingConnectionPool.from_url`);
- `redis+sentinel://[[user]:password@]host1[:port1],host2[:port2],.../<service-name>[/db]`: the primary that the
  sentinels at host1, host2, ... know as `<service-name>` (`sentinel monitor <service-name> ...`); a port left out
  is Sentinel's 26379, the password is the Redis servers' (the sentinels are asked without one). redis-py has no
  URL form for Sentinel; this is the one Redis-Sentinel-Url defined and LangChain, RedisVL and others adopted.
  The client asks the sentinels for the primary's address whenever it opens a connection, so it follows a
  promoted replica without a restart (redis-py's `redis.asyncio.sentinel.Sentinel.master_for`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import unquote, urlsplit

SENTINEL_SCHEME = "redis+sentinel"
SENTINEL_PORT = 26379
DIRECT_SCHEMES = ("redis", "rediss", "unix")
_HOST = re.compile(r"^(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9._-]+))(?::(?P<port>[^:]*))?$")
_SERVICE = re.compile(r"^[A-Za-z0-9._-]+$")  # sentinel.conf's master names: no spaces, no slashes


@dataclass(frozen=True)
class SentinelURL:
    """A parsed `redis+sentinel://` URL.

    Attributes:
        sentinels: (host, port) of each sentinel, in the URL's order.
        service: The name the sentinels monitor the primary under.
        db: Database number on the Redis servers.
        username: Redis ACL user of the servers (None: default user).
        password: Password of the servers (None: none).
    """

    sentinels: tuple[tuple[str, int], ...]
    service: str
    db: int = 0
    username: str | None = None
    password: str | None = field(default=None, repr=False)


def parse_redis_url(url: str) -> SentinelURL | None:
    """Check a store URL; the parts of a sentinel URL, None for a one-server URL (which redis-py parses).

    Raises:
        ValueError: the URL is malformed; the message names the problem.
    """
    scheme, sep, _ = url.partition("://")
    scheme = scheme.lower()
    if not sep or scheme not in (*DIRECT_SCHEMES, SENTINEL_SCHEME):
        raise ValueError(
            f"redis URL {redacted(url)!r} must start with redis://, rediss://, unix:// or {SENTINEL_SCHEME}:// "
            f"(e.g. redis://127.0.0.1:6379/0 or {SENTINEL_SCHEME}://127.0.0.1:26379,127.0.0.1:26380/mymaster)"
        )
    if scheme in DIRECT_SCHEMES:
        try:
            from redis.connection import parse_url
        except ImportError:  # the serve extra is missing: opening the store will say so
            return None
        try:
            parse_url(url)
        except ValueError as e:
            raise ValueError(f"redis URL {redacted(url)!r}: {e}") from None
        return None
    return _parse_sentinel(url)


def _parse_sentinel(url: str) -> SentinelURL:
    where = f"sentinel URL {redacted(url)!r}"
    form = f"{SENTINEL_SCHEME}://[:password@]host1:port1,host2:port2,.../<service-name>[/db]"
    parts = urlsplit(url)
    if parts.query or parts.fragment:
        raise ValueError(f"{where}: takes no ?options or #fragment; the form is {form}")
    userinfo, at, hosts = parts.netloc.rpartition("@")
    username = password = None
    if at:
        user, colon, pw = userinfo.partition(":")
        username, password = (unquote(user) or None), (unquote(pw) if colon else None)
        if not colon:  # "user@" alone: redis-py reads a lone userinfo as the password; say which is meant
            raise ValueError(f"{where}: write the password as ':password@' (or 'user:password@')")
    if not hosts:
        raise ValueError(f"{where}: names no sentinel; the form is {form}")
    sentinels = []
    for item in hosts.split(","):
        m = _HOST.match(item)
        if not m:
            raise ValueError(f"{where}: {item!r} is not host[:port] (IPv6 addresses in brackets)")
        port_text = m.group("port")
        if port_text is None:
            port = SENTINEL_PORT
        elif port_text.isdigit() and 1 <= int(port_text) <= 65535:
            port = int(port_text)
        else:
            raise ValueError(f"{where}: port {port_text!r} of {item!r} is not a number in 1..65535")
        sentinels.append((m.group("v6") or m.group("name"), port))
    if len(set(sentinels)) != len(sentinels):
        raise ValueError(f"{where}: names a sentinel twice")
    path = [unquote(p) for p in parts.path.split("/")[1:]]
    if not path or not path[0]:
        raise ValueError(
            f"{where}: names no service (the primary's name in sentinel.conf); the form is {form}"
        )
    if len(path) > 2 or (len(path) == 2 and not path[1].isdigit()):
        raise ValueError(
            f"{where}: after the service name only a database number may follow; the form is {form}"
        )
    if not _SERVICE.match(path[0]):
        raise ValueError(f"{where}: service name {path[0]!r} may hold only letters, digits, '.', '_' and '-'")
    db = int(path[1]) if len(path) == 2 else 0
    return SentinelURL(tuple(sentinels), path[0], db, username, password)


def redacted(url: str) -> str:
    """The URL with its password replaced by `***` (for messages and logs)."""
    return re.sub(r"(://[^/@]*?:)[^/@]*@", r"\1***@", url)


class RedisClient:
    """An asyncio Redis client of the store and what it owns (its pool, and the sentinels' clients).

    Attributes:
        redis: The client; with a sentinel URL it always talks to the current primary.
        sentinel: The Sentinel manager (None for a one-server URL).
        url: The URL, password redacted.
    """

    def __init__(self, redis: Any, sentinel: Any, url: str, service: str | None = None) -> None:
        self.redis, self.sentinel, self.url, self.service = redis, sentinel, url, service

    async def primary(self) -> dict | None:
        """Where the current primary is, for a plain connection of our own: host, port (or path, for a Unix
        socket), username, password, db (asking the sentinels with a sentinel URL); None where the URL is TLS.

        Raises:
            redis.RedisError: no sentinel names a primary.
        """
        pool = self.redis.connection_pool
        kw = pool.connection_kwargs
        who = {"username": kw.get("username"), "password": kw.get("password"), "db": int(kw.get("db") or 0)}
        if self.sentinel is not None:
            host, port = await self.sentinel.discover_master(self.service)
            return {"host": host, "port": int(port), **who}
        from redis.asyncio.connection import Connection, UnixDomainSocketConnection

        if pool.connection_class is UnixDomainSocketConnection:
            return {"host": None, "port": None, "path": kw["path"], **who}
        if pool.connection_class is not Connection:  # TLS: leave it to redis-py
            return None
        return {"host": kw.get("host", "localhost"), "port": int(kw.get("port", 6379)), **who}

    async def aclose(self) -> None:
        """Close the client, its pool, and the sentinel clients."""
        await self.redis.aclose()
        await self.redis.connection_pool.disconnect()  # a pool passed in is not closed by the client
        if self.sentinel is not None:
            await self.sentinel.aclose()


def connect(
    url: str,
    *,
    max_connections: int = 64,
    pool_timeout_s: float = 10.0,
    socket_timeout_s: float = 5.0,
    sentinel_timeout_s: float = 1.0,
) -> RedisClient:
    """A client for `url` over a bounded pool that makes callers wait for a free connection.

    Args:
        url: A store URL (see the module docstring).
        max_connections: Connections to Redis at most.
        pool_timeout_s: Longest wait for a free connection.
        socket_timeout_s: Longest wait for a connection or an answer from a Redis server.
        sentinel_timeout_s: The same for a sentinel (a silent one is skipped for the next one).

    Raises:
        ValueError: a malformed URL.
    """
    import redis.asyncio as aioredis

    target = parse_redis_url(url)
    from redis.asyncio.retry import Retry
    from redis.backoff import NoBackoff
    from redis.exceptions import ConnectionError as RedisConnectionError

    # Once more on a broken connection (a pooled one that Redis closed by restarting): a fresh one answers.
    # Never on a timeout: a paused Redis must answer `unavailable` after one socket timeout, not several.
    once = Retry(NoBackoff(), 1, supported_errors=(RedisConnectionError,))
    timeouts = {"socket_timeout": socket_timeout_s, "socket_connect_timeout": socket_timeout_s, "retry": once}
    if target is None:
        pool = aioredis.BlockingConnectionPool.from_url(
            url, max_connections=max_connections, timeout=pool_timeout_s, **timeouts
        )
        return RedisClient(aioredis.Redis(connection_pool=pool), None, redacted(url))

    from redis.asyncio.sentinel import Sentinel, SentinelConnectionPool

    class BlockingSentinelPool(SentinelConnectionPool, aioredis.BlockingConnectionPool):
        """Sentinel's pool (each new connection asks for the primary) with the blocking pool's wait."""

    sentinel = Sentinel(
        list(target.sentinels),
        # No retries: a sentinel that does not answer is skipped for the next one at once.
        sentinel_kwargs={
            "socket_timeout": sentinel_timeout_s,
            "socket_connect_timeout": sentinel_timeout_s,
            "retry": None,
        },
    )
    client = sentinel.master_for(
        target.service,
        connection_pool_class=BlockingSentinelPool,
        max_connections=max_connections,
        timeout=pool_timeout_s,
        db=target.db,
        username=target.username,
        password=target.password,
        **timeouts,
    )
    return RedisClient(client, sentinel, redacted(url), target.service)
