"""A minimal pipelined Redis connection (RESP2) for the session store's hot path.

redis-py spends ~60 us of Python per call on this machine (pool checkout, command packing, response parsing, a
reader coroutine) against ~27 us for the round trip itself; an act's write is on the path of every answer, so the
store sends it over this one connection instead: commands are written in order, and the replies, parsed as the
bytes arrive (an `asyncio.Protocol`, no reader task), answer them in order, so any number of writes are in flight
at once; the caller's callback runs as the last reply is parsed, without waiting for another turn of the loop.
Everything else (reads, creates, sweeps, Sentinel) stays with redis-py.
"""

from __future__ import annotations

import asyncio
import collections
import os
import time


class RespError(Exception):
    """An error reply from Redis (`-ERR ...`), or a reply this parser does not read."""


class ConnectionLost(ConnectionError):
    """The connection broke or timed out; every command still waiting for its reply fails with this."""


class _Incomplete(Exception):
    """The buffer ends inside a reply."""


class Encoded(bytes):
    """A whole command already in RESP form (`command`): `encode` writes it as it is."""


def bulk(args: list) -> bytes:
    """Arguments (bytes / str / int / float) as RESP bulk strings, without the array's header."""
    out: list[bytes] = []
    for a in args:
        if a.__class__ is not bytes:
            a = str(a).encode()
        out.append(b"$%d\r\n%b\r\n" % (len(a), a))
    return b"".join(out)


def pairs(fields: dict[str, bytes]) -> bytes:
    """Field / value pairs (str names, bytes values) as RESP bulk strings (`bulk` of the flattened pairs, one
    format per pair)."""
    out: list[bytes] = []
    for k, v in fields.items():
        out.append(b"$%d\r\n%s\r\n$%d\r\n%b\r\n" % (len(k), k.encode(), len(v), v))
    return b"".join(out)


def command(count: int, *parts: bytes) -> Encoded:
    """One command of `count` arguments whose bulk strings (`bulk`) are `parts`, in order."""
    return Encoded(b"*%d\r\n%b" % (count, b"".join(parts)))


def encode(*commands: list | Encoded) -> bytes:
    """Commands (lists of bytes / str / int / float arguments, or `Encoded`) as RESP arrays of bulk strings."""
    return b"".join(c if isinstance(c, Encoded) else b"*%d\r\n%b" % (len(c), bulk(c)) for c in commands)


def parse(buf: bytes | bytearray, pos: int = 0) -> tuple[object, int]:
    """The reply that starts at `pos` and where the next one starts.

    Raises:
        _Incomplete: the buffer ends inside the reply.
        RespError: not a RESP2 reply.
    """
    end = buf.find(b"\r\n", pos)
    if end < 0:
        raise _Incomplete
    kind, rest = buf[pos : pos + 1], bytes(buf[pos + 1 : end])
    pos = end + 2
    if kind == b":":
        return int(rest), pos
    if kind == b"$":
        n = int(rest)
        if n < 0:
            return None, pos
        if len(buf) < pos + n + 2:
            raise _Incomplete
        return bytes(buf[pos : pos + n]), pos + n + 2
    if kind == b"*":
        n = int(rest)
        if n < 0:
            return None, pos
        items = []
        for _ in range(n):
            item, pos = parse(buf, pos)
            items.append(item)
        return items, pos
    if kind == b"+":
        return rest, pos
    if kind == b"-":
        return RespError(rest.decode(errors="replace")), pos
    raise RespError(f"unexpected reply {bytes(buf[pos - len(rest) - 3 : pos])[:40]!r}")


class _Replies:
    """The replies of one `send`, collected as they arrive; the callback gets them all (or the failure) once."""

    __slots__ = ("callback", "got", "n", "timer")

    def __init__(self, n: int, callback, timer: asyncio.TimerHandle) -> None:
        self.n, self.got, self.callback, self.timer = n, [], callback, timer

    def add(self, reply: object) -> None:
        self.got.append(reply)
        if len(self.got) == self.n:
            self._done(self.got)

    def fail(self, error: BaseException) -> None:
        self._done(error)

    def _done(self, result: list | BaseException) -> None:
        callback, self.callback = self.callback, None
        if callback is not None:
            self.timer.cancel()
            try:
                callback(result)
            except Exception as e:  # noqa: BLE001 - the reader goes on for the other commands' replies
                asyncio.get_running_loop().call_exception_handler(
                    {"message": "a Redis reply callback failed", "exception": e}
                )


class _Protocol(asyncio.Protocol):
    def __init__(self, owner: RespConnection) -> None:
        self.owner = owner
        self.buf = bytearray()

    def data_received(self, data: bytes) -> None:
        self.buf += data
        pos = 0
        waiting = self.owner._waiting
        try:
            while pos < len(self.buf):
                reply, pos = parse(self.buf, pos)
                if not waiting:
                    raise RespError("a reply came that no command waits for")
                waiting.popleft().add(reply)  # the callback runs here: no extra turn of the loop
        except _Incomplete:
            pass
        except (RespError, ValueError) as e:
            self.owner.close(ConnectionLost(f"unreadable reply from Redis: {e}"))
            return
        del self.buf[:pos]

    def connection_lost(self, exc: Exception | None) -> None:
        self.owner.close(ConnectionLost(f"the connection to Redis broke: {exc or 'closed by the server'}"))


class RespConnection:
    """One connection to a Redis server (TCP, or a Unix socket for a co-located server), pipelined.

    Args:
        host: Server host (ignored with `path`).
        port: Server port (ignored with `path`).
        path: A Unix socket path instead of TCP, for a Redis on the same machine (a bare PING took 42-46 us
            against 60-96 us over loopback TCP here; end to end the difference was within noise,
            docs/performance.md).
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
        path: str | None = None,
        username: str | None = None,
        password: str | None = None,
        db: int = 0,
        timeout_s: float = 5.0,
    ) -> None:
        self.address = (host, port)
        self.path = path
        self.where = f"unix:{path}" if path else f"{host}:{port}"
        self._auth = (username, password)
        self._db = db
        self.timeout_s = timeout_s
        self._transport: asyncio.Transport | None = None
        self._protocol: _Protocol | None = None
        self._fd = -1
        self._waiting: collections.deque[_Replies] = collections.deque()  # one entry per command
        self.closed = False

    async def open(self) -> None:
        """Connect, authenticate and select the database.

        Raises:
            ConnectionLost: the server cannot be reached in time, or refused the handshake.
        """
        loop = asyncio.get_running_loop()
        try:
            if self.path:
                connecting = loop.create_unix_connection(lambda: _Protocol(self), self.path)
            else:
                connecting = loop.create_connection(lambda: _Protocol(self), *self.address)
            self._transport, self._protocol = await asyncio.wait_for(connecting, self.timeout_s)
            self._fd = self._transport.get_extra_info("socket").fileno()
        except (OSError, TimeoutError) as e:
            self.closed = True
            raise ConnectionLost(f"cannot connect to Redis at {self.where}: {e}") from e
        setup = []
        user, password = self._auth
        if password is not None:
            setup.append(["AUTH", user, password] if user else ["AUTH", password])
        if self._db:
            setup.append(["SELECT", self._db])
        for reply in await self.call(*setup) if setup else ():
            if isinstance(reply, RespError):
                self.close(ConnectionLost(f"Redis refused the connection's setup: {reply}"))
                raise ConnectionLost(f"Redis refused the connection's setup: {reply}")

    def send(self, callback, *commands: list, spin_s: float = 0.0) -> None:
        """Write `commands` now; `callback` is called once, from the connection's reader, with the list of their
        replies when the last one arrives (an error reply is a `RespError` in its place), or with a
        ConnectionLost when the connection fails first.

        If the last reply is not in within `timeout_s`, the connection is closed and every command still waiting
        fails with ConnectionLost (a late reply could not be matched to its command any more).

        Args:
            callback: Gets the replies, or the failure.
            commands: The commands.
            spin_s: When these are the only commands in flight, read their replies here, polling the socket for up
                to this long, instead of sleeping in the event loop until they come (`_spin`).

        Raises:
            ConnectionLost: the connection is closed.
        """
        if self.closed or self._transport is None:
            raise ConnectionLost("the connection is closed")
        replies = _Replies(
            len(commands), callback, asyncio.get_running_loop().call_later(self.timeout_s, self._late)
        )
        self._waiting.extend([replies] * len(commands))
        self._transport.write(encode(*commands))
        if spin_s > 0 and len(self._waiting) == len(commands) and not self._transport.get_write_buffer_size():
            self._spin(replies, spin_s)

    def _spin(self, replies: _Replies, spin_s: float) -> None:
        """Read the socket here until `replies` are in or `spin_s` has passed, handing what comes to the reader.

        Sleeping until the reply costs a wake-up on this 2-core VM, whose idle vCPUs halt at once: a bare round
        trip took 58 us sleeping and 21-27 us polling here, an act ~0.06 ms less (docs/performance.md). The
        event loop is not polling meanwhile, so the bytes read here are bytes its transport would have read next;
        what has not come by the deadline, the transport reads as usual. Errors and end of file are left for the
        transport to find.
        """
        deadline = time.perf_counter() + spin_s
        while replies.callback is not None and not self.closed:
            try:
                data = os.read(self._fd, 65536)
            except BlockingIOError:
                if time.perf_counter() > deadline:
                    return
                continue
            except OSError:
                return
            if not data:
                return
            self._protocol.data_received(data)

    def _late(self) -> None:
        self.close(ConnectionLost(f"no reply from Redis within {self.timeout_s:g} s"))

    async def call(self, *commands: list) -> list:
        """Send `commands` at once and return their replies (an error reply is a `RespError` in its place).

        Raises:
            ConnectionLost: the connection broke, or a reply took longer than `timeout_s`.
        """
        fut = asyncio.get_running_loop().create_future()

        def answer(result: list | BaseException) -> None:
            if fut.done():
                return
            if isinstance(result, BaseException):
                fut.set_exception(result)
            else:
                fut.set_result(result)

        self.send(answer, *commands)
        return await fut

    def close(self, error: BaseException | None = None) -> None:
        """Close the connection; every command still waiting fails with `error` (default ConnectionLost)."""
        self.closed = True
        error = error or ConnectionLost("the connection was closed")
        while self._waiting:
            self._waiting.popleft().fail(error)
        if self._transport is not None:
            self._transport.close()
