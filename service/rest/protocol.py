"""uvicorn's HTTP/1.1 protocol (httptools) with read deadlines and a connection cap (docs/reliability.md,
"Slowloris").

uvicorn times only idle keep-alive connections: a client that sends a request's headers one byte at a time, or
never finishes its body, holds its connection (and a file descriptor) for as long as it likes, and enough of them
exhaust the process's descriptors, for gRPC and Redis too. Here:

- a request's headers must arrive within `header_timeout_s` of its first byte (of the connection's opening, for
  its first request), else the server answers 408 and closes the connection;
- its body must arrive within `body_timeout_s` of its headers, and average at least `body_min_rate` bytes a second
  after its first second, else the same;
- a request line and headers larger than `MAX_HEAD_BYTES` answer 431 and the connection closes (httptools has no
  limit of its own), and a request that is not valid HTTP/1.1 answers 400; both in the error envelope of every
  other answer, `{"error": {"code", "message"}}` (uvicorn answers plain text);
- at most `max_connections` connections are open. A new one past it closes, in this order: the oldest connection
  not being answered (one still sending its headers or body, or an idle keep-alive one) of a client address
  holding more than `per_peer` connections; else the oldest one without a request in progress (sending its
  headers, or idle); else the oldest one still sending its body (its application reads a disconnect); else, when
  every connection is being answered, the new one is closed. A new connection whose address already holds
  `per_peer` connections of a full server makes room with its own address's connections only (the same order),
  else it is closed: one address (a proxy) alone behaves as without the share. The cap is kept below the descriptor limit
  (`gmt.service.limits`), so that accept() never fails for lack of descriptors.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from typing import Any, Literal

import orjson
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from gmt.service.metrics import Metrics

log = logging.getLogger("gmt.rest")
Phase = Literal["idle", "headers", "body", "busy"]
MAX_HEAD_BYTES = 64 * 1024  # a request's line and headers at most (nginx's default allows 32 KiB)


class _HeadTooLarge(Exception):
    """Raised in a parser callback: httptools stops and uvicorn calls `send_400_response`."""


_on_url, _on_header = HttpToolsProtocol.on_url, HttpToolsProtocol.on_header


class ConnectionGuard:
    """What the connections of one REST server share: the cap, the deadlines, the connections that may be closed
    to make room (oldest first).

    Args:
        max_connections: Open connections at most.
        header_timeout_s: Longest time a request's headers may take.
        body_timeout_s: Longest time a request's body may take after its headers.
        replica_id: Sent as `X-Served-By` with the 408 answers.
        metrics: Where `gmt_rest_connections` and `gmt_connections_closed` are counted.
        body_min_rate: Bytes per second a body must average after its first second (0: no minimum).
        per_peer: Connections one client address may hold while the server is full.
    """

    def __init__(
        self,
        max_connections: int,
        header_timeout_s: float,
        body_timeout_s: float,
        replica_id: str,
        metrics: Metrics,
        body_min_rate: int = 0,
        per_peer: int = 0,
    ) -> None:
        self.max_connections = max_connections
        self.header_timeout_s = header_timeout_s
        self.body_timeout_s = body_timeout_s
        self.body_min_rate = body_min_rate
        self.per_peer = per_peer or max_connections
        self.served_by = replica_id.encode("ascii")
        self.metrics = metrics
        self.open = 0
        self._evictable: dict[GuardedHttpProtocol, None] = {}  # no request in progress; oldest first
        self._reading: dict[GuardedHttpProtocol, None] = {}  # sending a body, not answered yet; oldest first
        self._peers: Counter[str | None] = Counter()  # counted connections by client address
        metrics.rest_connections.set_function(lambda: self.open)

    def admit(self, conn: GuardedHttpProtocol) -> bool:
        """Count a new connection; past the cap, close another one for it (see the module docstring), or refuse
        this one (False)."""
        if self.open >= self.max_connections:
            victim = self._victim(conn.peer)
            if victim is None:
                self.metrics.closed("rest", "over_limit")
                return False
            self.leave(victim)
            victim.drop()
            self.metrics.closed("rest", "evicted")
        self.open += 1
        self._peers[conn.peer] += 1
        return True

    def _victim(self, peer: str | None) -> GuardedHttpProtocol | None:
        """The connection to close for a new one from `peer`, None when there is none to close."""
        # A body's answer may have started since the connection joined `_reading` (an early refusal): not it.
        idle = list(self._evictable)
        reading = [c for c in self._reading if c.reading()]
        if self._peers[peer] >= self.per_peer:  # at its share: it makes room with its own connections only
            return next((c for c in idle + reading if c.peer == peer), None)
        hog, held = max(self._peers.items(), key=lambda kv: kv[1])
        if held > self.per_peer:
            for conn in idle + reading:
                if conn.peer == hog:
                    return conn
        return next(iter(idle + reading), None)

    def leave(self, conn: GuardedHttpProtocol) -> None:
        """Stop counting a connection (closed, or being closed)."""
        if conn.counted:
            conn.counted = False
            self.open -= 1
            self._peers[conn.peer] -= 1
            if not self._peers[conn.peer]:
                del self._peers[conn.peer]
        self._evictable.pop(conn, None)
        self._reading.pop(conn, None)

    def update(self, conn: GuardedHttpProtocol) -> None:
        """Record whether `conn` may be closed to make room, and how readily; one that just became so goes last."""
        evictable, reading = conn.counted and conn.evictable(), conn.counted and conn.reading()
        for group, member in ((self._evictable, evictable), (self._reading, reading)):
            if member:
                group.setdefault(conn, None)
            else:
                group.pop(conn, None)


class GuardedHttpProtocol(HttpToolsProtocol):
    """`HttpToolsProtocol` with a header deadline, a body deadline and a `ConnectionGuard`; build it with
    `functools.partial(GuardedHttpProtocol, guard=...)` as `uvicorn.Config(http=...)`.

    Deadline timers are started only when a read leaves a request incomplete, so a request that arrives whole
    (the usual case) costs no timer.
    """

    def __init__(self, *args: Any, guard: ConnectionGuard, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.guard = guard
        self.counted = False
        self.peer: str | None = None
        self.phase: Phase = "idle"
        self._deadline: asyncio.TimerHandle | None = None
        self._rate_check: asyncio.TimerHandle | None = None
        self._head_bytes = 0
        self._head_too_large = False
        self._body_start = 0.0
        self._body_bytes = 0

    # Connection

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        peer = transport.get_extra_info("peername")
        self.peer = peer[0] if isinstance(peer, tuple) and peer else None
        if not self.guard.admit(self):
            transport.abort()
            return
        self.counted = True
        self.guard.update(self)
        self._arm(self.guard.header_timeout_s, "header_timeout")  # the first request's headers

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self._stop_rate_check()
        self.guard.leave(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._deadline is None and not self.transport.is_closing():
            if self.phase == "headers":
                self._arm(self.guard.header_timeout_s, "header_timeout")
            elif self.phase == "body":
                self._arm(self.guard.body_timeout_s, "body_timeout")
                if self.guard.body_min_rate and self._rate_check is None:
                    self._rate_check = self.loop.call_at(self._body_start + 2.0, self._check_rate)

    def evictable(self) -> bool:
        """No request in progress: waiting for one, or still receiving one's headers."""
        return (
            self.phase in ("idle", "headers")
            and (self.cycle is None or self.cycle.response_complete)
            and not self.pipeline
        )

    def reading(self) -> bool:
        """Receiving a request's body, and nothing of its answer sent yet."""
        return self.phase == "body" and self.cycle is not None and not self.cycle.response_started

    def drop(self) -> None:
        """Close the connection to make room for another; a request whose body it was reading reads a
        disconnect."""
        self._disarm()
        self._stop_rate_check()
        cycle = self.cycle
        if cycle is not None and not cycle.response_complete:
            cycle.disconnected = True
            cycle.message_event.set()
        self.transport.close()

    # Parser callbacks and the response

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.phase = "headers"
        self._head_bytes = 0
        self.guard.update(self)

    # Every header of every request passes here: counted inline, then uvicorn's own callback (no super() lookup).
    def on_url(self, url: bytes) -> None:
        self._head_bytes += len(url)
        if self._head_bytes > MAX_HEAD_BYTES:
            self._head_too_large = True
            raise _HeadTooLarge
        _on_url(self, url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._head_bytes += len(name) + len(value) + 4  # ": " and CRLF
        if self._head_bytes > MAX_HEAD_BYTES:
            self._head_too_large = True
            raise _HeadTooLarge
        _on_header(self, name, value)

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to bytes its parser refused (plain text there), in the error envelope."""
        if self._head_too_large:
            status, code = b"431 Request Header Fields Too Large", "request_header_fields_too_large"
            message = f"the request line and headers exceed {MAX_HEAD_BYTES} bytes"
        else:
            status, code = b"400 Bad Request", "invalid_argument"
            message = (
                "malformed HTTP request: the request line, a header, or the body's framing "
                "(Content-Length / Transfer-Encoding) is not valid HTTP/1.1"
            )
        self._answer_and_close(status, code, message)

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()
        self.phase = "body"
        self._body_start, self._body_bytes = self.loop.time(), 0
        self.guard.update(self)

    def on_body(self, body: bytes) -> None:
        self._body_bytes += len(body)
        super().on_body(body)

    def on_message_complete(self) -> None:
        self._disarm()
        self._stop_rate_check()
        super().on_message_complete()
        self.phase = "busy"
        self.guard.update(self)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if self.phase == "busy" and not self.pipeline:
            self.phase = "idle"  # uvicorn's keep-alive timeout runs from here
        self.guard.update(self)

    # Deadlines

    def _arm(self, seconds: float, reason: str) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(seconds, self._expired, reason, seconds)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _stop_rate_check(self) -> None:
        if self._rate_check is not None:
            self._rate_check.cancel()
            self._rate_check = None

    def _check_rate(self) -> None:
        """Each second from the body's second second: its bytes so far must average `body_min_rate` a second
        over the time after its first second."""
        self._rate_check = None
        if self.phase != "body" or self.transport.is_closing():
            return
        rate = self.guard.body_min_rate
        if self._body_bytes >= rate * (self.loop.time() - self._body_start - 1.0):
            self._rate_check = self.loop.call_later(1.0, self._check_rate)
            return
        self._disarm()
        self._expired("body_rate", 0.0)

    def _expired(self, reason: str, seconds: float) -> None:
        self._deadline = None
        if self.transport.is_closing():
            return
        self.guard.metrics.closed("rest", reason)
        cycle = self.cycle
        if cycle is not None and not cycle.response_complete and self.phase != "body":
            # A pipelined request stalled behind one being answered: close once that answer is sent.
            cycle.keep_alive = False
            self.flow.pause_reading()
            return
        if cycle is not None and not cycle.response_complete:
            if cycle.response_started:
                self.transport.close()
                return
            # The application waits for the rest of the body: it reads a disconnect, and anything it sends
            # is dropped (as when the client goes away).
            cycle.disconnected = True
            cycle.message_event.set()
        if reason == "body_rate":
            message = f"the request's body arrived at under {self.guard.body_min_rate} bytes/s"
        else:
            what = "headers" if reason == "header_timeout" else "body"
            message = f"the request's {what} did not arrive within {seconds:g} s"
        self._answer_and_close(b"408 Request Timeout", "request_timeout", message)

    def _answer_and_close(self, status: bytes, code: str, message: str) -> None:
        """Answer `status` in the error envelope, outside the application, and close the connection."""
        body = orjson.dumps({"error": {"code": code, "message": message}})
        self.transport.write(
            b"HTTP/1.1 %s\r\ncontent-type: application/json\r\n"
            b"content-length: %d\r\nconnection: close\r\nx-served-by: %s\r\n\r\n%s"
            % (status, len(body), self.guard.served_by, body)
        )
        self.transport.close()
        self.guard.leave(self)
