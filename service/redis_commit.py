"""Group commit for the Redis session store: the writes of one event-loop turn go to Redis as one script call.

Each change is answered once the call that carried it is acknowledged (an answered step is a stored step). The
call goes over the store's own pipelined connection to the primary (`gmt.service.resp`; redis-py's pipeline where
the URL is TLS). With a minimum number of replicas, `WAIT` follows on the same connection, one at a time: the
writes sent while one is in flight share the next, so a change is acknowledged only once that many Redis replicas
hold it (docs/reliability.md).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from gmt.service import resp
from gmt.service.errors import Internal, ServiceError, Unavailable
from gmt.service.redis_connect import RedisClient
from gmt.service.redis_scripts import save_command

log = logging.getLogger("gmt.store")


class GroupCommit:
    """The write queue of one store and the connection it is sent on.

    Args:
        client: The store's redis-py client (where the primary is; the TLS fallback).
        errors: The exceptions that mean Redis cannot be reached.
        socket_timeout_s: Longest wait for a connection, or for a reply once sent.
        min_replicas: Redis replicas that must hold a write before it is acknowledged (0: do not wait).
        wait_ms: Longest wait for them.
        ttl_ms: The session keys' TTL (the save script's first argument).
        spin_s: How long a lone session's write polls for its reply (0: never).
        lone: Whether this replica serves one session at most (the only case where a write polls).
        encode: The save script's entries (keys, encoded arguments, their count) of a turn's changes, in order
            (`RedisSessionStore._encode`): called once per write, with every change queued for it.
    """

    def __init__(
        self,
        client: RedisClient,
        errors: tuple[type[BaseException], ...],
        socket_timeout_s: float,
        *,
        min_replicas: int,
        wait_ms: int,
        ttl_ms: int,
        spin_s: float,
        lone: Callable[[], bool],
        encode: Callable[[list[Any]], list[tuple[list, bytes, int]]],
    ) -> None:
        self._client = client
        self._errors = errors
        self._socket_timeout_s = socket_timeout_s
        self.min_replicas = min_replicas
        self.wait_ms = wait_ms
        self._ttl_ms = ttl_ms
        self.spin_s = spin_s
        self._lone = lone
        self._encode = encode
        self.fast: resp.RespConnection | None = None  # the hot path's own connection (`send`)
        self._fast_lock = asyncio.Lock()
        self._queue: list[
            tuple[list, asyncio.Future]
        ] = []  # (changes, their caller) waiting for this turn's write
        self._flushes: set[asyncio.Task] = set()
        # The fast connection a WAIT is in flight on, and the writes sent on it since, each with the list its
        # script's replies arrive in: the next WAIT covers them all.
        self.waiting_on: resp.RespConnection | None = None
        self.uncovered: list[tuple[list, list]] = []

    def not_replicated(self, acked: int | None) -> Unavailable | None:
        """The error for a write that `acked` replicas hold (None: it is acknowledged)."""
        if acked is None or acked >= self.min_replicas:
            return None
        return Unavailable(
            f"session store: the write reached {acked} of the {self.min_replicas} Redis replica(s) required "
            f"within {self.wait_ms} ms, so it is not acknowledged; retry (an act with the same step is "
            "answered without stepping twice)"
        )

    def enqueue(self, changes: list[Any]) -> asyncio.Future:
        """Queue changes (`RedisSessionStore._change`, encoded when the write is sent) for this turn's write; the
        future answers, per change, the script's result for it or the error that failed it (one future per caller,
        not per session)."""
        loop = asyncio.get_running_loop()
        fut = loop.create_future()
        first = not self._queue
        self._queue.append((changes, fut))
        if first:
            if self.spin_s > 0 and self._lone() and self.fast is not None and not self.fast.closed:
                # A lone session's write (the only session served here): sent now, its reply polled for, so the
                # future is answered before the caller awaits it.
                self._flush(self.spin_s)
            else:
                loop.call_soon(self._flush)
        return fut

    def _flush(self, spin_s: float = 0.0) -> None:
        """Encode the turn's changes (`_encoded`) and send them as one script call (then WAIT on the same
        connection when replicas must hold them, one WAIT in flight at a time: the writes sent while one is in
        flight share the next, `_waited`): at once on the open fast connection (polling for the reply up to
        `spin_s`, `RespConnection.send`), else from a task that connects first."""
        queue, self._queue = self._queue, []
        queue, entries = self._encoded(queue)
        if not queue:
            return
        commands = [save_command(entries, self._ttl_ms)]
        conn = self.fast
        if conn is not None and not conn.closed:
            if not self.min_replicas:
                conn.send(lambda replies: self._answer(queue, conn, replies), *commands, spin_s=spin_s)
            elif self.waiting_on is conn:
                # A WAIT is in flight on this connection (Redis holds the connection's later commands until it is
                # answered). The write goes now; one WAIT for every write sent meanwhile follows once that one is
                # answered (`_waited`).
                got: list = []
                self.uncovered.append((queue, got))
                conn.send(got.append, *commands)
            else:
                self.waiting_on = conn
                wait = ["WAIT", self.min_replicas, self.wait_ms]
                conn.send(
                    lambda replies: self._waited(conn, [(queue, None)], replies),
                    *commands,
                    wait,
                    spin_s=spin_s,
                )
            return
        if self.min_replicas:
            commands.append(["WAIT", self.min_replicas, self.wait_ms])
        task = asyncio.get_running_loop().create_task(self._flush_slowly(queue, commands))
        self._flushes.add(task)  # the loop holds tasks weakly
        task.add_done_callback(self._flushes.discard)

    def _encoded(
        self, queue: list[tuple[list, asyncio.Future]]
    ) -> tuple[list, list[tuple[list, bytes, int]]]:
        """The turn's writers that can be written and their changes' script entries, encoded together; if that
        fails, each writer's changes are encoded alone and only a writer whose changes cannot be is failed
        (`internal`, the cause logged), never left waiting."""
        try:
            return queue, self._encode([c for changes, _ in queue for c in changes])
        except Exception:  # noqa: BLE001 - found below, writer by writer
            pass
        ok: list[tuple[list, asyncio.Future]] = []
        entries: list[tuple[list, bytes, int]] = []
        for changes, fut in queue:
            try:
                mine = self._encode(changes)
            except Exception:  # noqa: BLE001 - a change that cannot be encoded fails its writer alone
                log.exception("a session change could not be encoded for the store")
                if not fut.done():
                    fut.set_exception(Internal("the session store could not encode this request's write"))
                continue
            ok.append((changes, fut))
            entries += mine
        return ok, entries

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
        if self.waiting_on is not conn:
            return
        uncovered, self.uncovered = self.uncovered, []
        if not uncovered:
            self.waiting_on = None
            return
        try:
            conn.send(lambda r: self._waited(conn, uncovered, r), ["WAIT", self.min_replicas, self.wait_ms])
        except resp.ConnectionLost as e:
            self.waiting_on = None
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
        short = self.not_replicated(acked[0] if acked else None)
        at = 0
        for entries, fut in queue:
            mine, at = results[at : at + len(entries)], at + len(entries)
            if not fut.done():
                # A change written on the primary only is not acknowledged (the store marks it unconfirmed).
                fut.set_result([short if short is not None and int(r) == 0 else int(r) for r in mine])

    async def _send(self, commands: list[list]) -> list:
        """The replies to `commands`, sent together on the store's own pipelined connection to the primary
        (`gmt.service.resp`, over TCP or a Unix socket; redis-py's pipeline where the URL is TLS).

        Raises:
            Unavailable: Redis cannot be reached, or answered an error.
        """
        conn = await self._connection()
        if conn is None:
            async with self._client.redis.pipeline(transaction=False) as p:
                for c in commands:
                    p.execute_command(*(resp.parse(c)[0] if isinstance(c, resp.Encoded) else c))
                try:
                    return await p.execute()
                except self._errors as e:
                    raise Unavailable(f"session store unreachable: {e}") from e
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
        if self.fast is not None and not self.fast.closed:
            return self.fast
        async with self._fast_lock:
            if self.fast is not None and not self.fast.closed:
                return self.fast
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
            self.fast = conn
            return conn

    def close(self) -> None:
        """Close the fast connection."""
        if self.fast is not None:
            self.fast.close()
