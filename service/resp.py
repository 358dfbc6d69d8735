"""A minimal pipelined Redis connection (RESP2) for the session store's hot path.

redis-py spends ~60 us of Python per call on this machine (pool checkout, command packing, response parsing)
against ~27 us for the round trip itself; an act's write is on the path of every answer, so the store sends it
over this one connection instead: commands are written in order and their replies read in order by one reader
task, so any number of writes are in flight at once. Everything else (reads, creates, sweeps, Sentinel) stays
with redis-py.
"""

from __future__ import annotations

import asyncio
import collections


class RespError(Exception):
    """An error reply from Redis (`-ERR ...`), or a reply this parser does not read."""


class ConnectionLost(ConnectionError):
    """The connection broke or timed out; every command still waiting for its reply fails with this."""


def encode(*commands: list) -> bytes:
    """Commands (lists of bytes / str / int / float arguments) as RESP arrays of bulk strings."""
    out: list[bytes] = []
    for args in commands:
        out.append(b"*%d\r\n" % len(args))
        for a in args:
            if not isinstance(a, bytes):
                a = str(a).encode()
            out.append(b"$%d\r\n" % len(a))
            out.append(a)
            out.append(b"\r\n")
    return b"".join(out)


class RespConnection:
    """One TCP connection to a Redis server, pipelined.

    Args:
        host: Server host.
        port: Server port.
        username: ACL user (None: the default user).
        password: Password (None: none).
        db: Database number.
        timeout_s: Longest wait for a connection, or for a reply once sent.
    """

    def __init__(
        self,
        host: str,
        port: int,
        *,
        username: str | None = None,
        password: str | None = None,
        db: int = 0,
        timeout_s: float = 5.0,
    ) -> None:
        self.address = (host, port)
        self._auth = (username, password)
        self._db = db
        self.timeout_s = timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._waiting: collections.deque[asyncio.Future] = collections.deque()
        self._task: asyncio.Task | None = None
        self.closed = False

    async def open(self) -> None:
        """Connect, authenticate and select the database.

        Raises:
            ConnectionLost: the server cannot be reached in time, or refused the handshake.
        """
        try:
            self._reader, self._writer = await asyncio.wait_for(
                asyncio.open_connection(*self.address), self.timeout_s
            )
        except (OSError, TimeoutError) as e:
            self.closed = True
            raise ConnectionLost(
                f"cannot connect to Redis at {self.address[0]}:{self.address[1]}: {e}"
            ) from e
        self._task = asyncio.get_running_loop().create_task(self._read_forever())
        setup = []
        user, password = self._auth
        if password is not None:
            setup.append(["AUTH", user, password] if user else ["AUTH", password])
        if self._db:
            setup.append(["SELECT", self._db])
        if setup:
            for reply in await self.call(*setup):
                if isinstance(reply, RespError):
                    self.close(ConnectionLost(f"Redis refused the connection's setup: {reply}"))
                    raise ConnectionLost(f"Redis refused the connection's setup: {reply}")

    def send(self, *commands: list) -> list[asyncio.Future]:
        """Write `commands` now; one future per command for its reply (an error reply is a `RespError` result).

        If the last reply is not in within `timeout_s`, the connection is closed and every future still waiting
        fails with ConnectionLost (a late reply could not be matched to its command any more).

        Raises:
            ConnectionLost: the connection is closed.
        """
        if self.closed or self._writer is None:
            raise ConnectionLost("the connection is closed")
        loop = asyncio.get_running_loop()
        futures = [loop.create_future() for _ in commands]
        self._waiting.extend(futures)
        self._writer.write(encode(*commands))
        timer = loop.call_later(self.timeout_s, self._late, futures[-1])
        futures[-1].add_done_callback(lambda _: timer.cancel())
        return futures

    def _late(self, last: asyncio.Future) -> None:
        if not last.done():
            self.close(ConnectionLost(f"no reply from Redis within {self.timeout_s:g} s"))

    async def call(self, *commands: list) -> list:
        """Send `commands` at once and return their replies (an error reply is a `RespError` in its place).

        Raises:
            ConnectionLost: the connection broke, or a reply took longer than `timeout_s`.
        """
        return [await f for f in self.send(*commands)]

    def close(self, error: BaseException | None = None) -> None:
        """Close the connection; every command still waiting fails with `error` (default ConnectionLost)."""
        self.closed = True
        error = error or ConnectionLost("the connection was closed")
        while self._waiting:
            f = self._waiting.popleft()
            if not f.done():
                f.set_exception(error)
        if self._writer is not None:
            self._writer.close()
        if self._task is not None and self._task is not asyncio.current_task():
            self._task.cancel()

    async def _read_forever(self) -> None:
        try:
            while True:
                reply = await self._reply()
                if not self._waiting:
                    raise RespError("a reply came that no command waits for")
                f = self._waiting.popleft()
                if not f.done():
                    f.set_result(reply)
        except asyncio.CancelledError:
            raise
        except (OSError, EOFError, asyncio.IncompleteReadError, RespError, ValueError) as e:
            self.close(ConnectionLost(f"the connection to Redis broke: {e!r}"))

    async def _reply(self):
        line = await self._reader.readuntil(b"\r\n")
        kind, rest = line[:1], line[1:-2]
        if kind == b":":
            return int(rest)
        if kind == b"*":
            n = int(rest)
            return None if n < 0 else [await self._reply() for _ in range(n)]
        if kind == b"$":
            n = int(rest)
            return None if n < 0 else (await self._reader.readexactly(n + 2))[:-2]
        if kind == b"+":
            return rest
        if kind == b"-":
            return RespError(rest.decode(errors="replace"))
        raise RespError(f"unexpected reply {line[:40]!r}")
