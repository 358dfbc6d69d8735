"""uvicorn's HTTP/1.1 protocol (httptools) with read deadlines and a connection cap (docs/reliability.md,
"Slowloris").

uvicorn times only idle keep-alive connections: a client that sends a request's headers one byte at a time, or
never finishes its body, holds its connection (and a file descriptor) for as long as it likes, and enough of them
exhaust the process's descriptors, for gRPC and Redis too. Here:

- a request's headers must arrive within `header_timeout_s` of its first byte (of the connection's opening, for
  its first request), else the server answers 408 and closes the connection;
- its body must arrive within `body_timeout_s` of its headers, else the same;
- a request line and headers larger than `MAX_HEAD_BYTES` answer 431 and the connection closes (httptools has no
  limit of its own), and a request that is not valid HTTP/1.1 answers 400; both in the error envelope of every
  other answer, `{"error": {"code", "message"}}` (uvicorn answers plain text);
- at most `max_connections` connections are open: a new one past it closes the oldest connection that has no
  request in progress (one still sending its headers, or an idle keep-alive one), or, when every connection has a
  request in progress, the new one. The cap is kept below the descriptor limit (`gmt.service.limits`), so that
  accept() never fails for lack of descriptors.
"""

from __future__ import annotations

import asyncio
import logging
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
    """

    def __init__(
        self,
        max_connections: int,
        header_timeout_s: float,
        body_timeout_s: float,
        replica_id: str,
        metrics: Metrics,
    ) -> None:
        self.max_connections = max_connections
        self.header_timeout_s = header_timeout_s
        self.body_timeout_s = body_timeout_s
        self.served_by = replica_id.encode("ascii")
        self.metrics = metrics
        self.open = 0
        self._evictable: dict[GuardedHttpProtocol, None] = {}  # no request in progress; oldest first
        metrics.rest_connections.set_function(lambda: self.open)

    def admit(self, conn: GuardedHttpProtocol) -> bool:
        """Count a new connection; past the cap, close the oldest evictable one, or refuse this one (False)."""
        if self.open >= self.max_connections:
            victim = next(iter(self._evictable), None)
            if victim is None:
                self.metrics.closed("rest", "over_limit")
                return False
            self.leave(victim)
            victim.transport.close()
            self.metrics.closed("rest", "evicted")
        self.open += 1
        return True

    def leave(self, conn: GuardedHttpProtocol) -> None:
        """Stop counting a connection (closed, or being closed)."""
        if conn.counted:
            conn.counted = False
            self.open -= 1
        self._evictable.pop(conn, None)

    def update(self, conn: GuardedHttpProtocol) -> None:
        """Record whether `conn` may be closed to make room; one that just became so goes last."""
        if conn.counted and conn.evictable():
            self._evictable.setdefault(conn, None)
        else:
            self._evictable.pop(conn, None)


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
        self.phase: Phase = "idle"
        self._deadline: asyncio.TimerHandle | None = None
        self._head_bytes = 0
        self._head_too_large = False

    # Connection

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if not self.guard.admit(self):
            transport.abort()
            return
        self.counted = True
        self.guard.update(self)
        self._arm(self.guard.header_timeout_s, "header_timeout")  # the first request's headers

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self.guard.leave(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self._deadline is None and not self.transport.is_closing():
            if self.phase == "headers":
                self._arm(self.guard.header_timeout_s, "header_timeout")
            elif self.phase == "body":
                self._arm(self.guard.body_timeout_s, "body_timeout")

    def evictable(self) -> bool:
        """No request in progress: waiting for one, or still receiving one's headers."""
        return (
            self.phase in ("idle", "headers")
            and (self.cycle is None or self.cycle.response_complete)
            and not self.pipeline
        )

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
        self.guard.update(self)

    def on_message_complete(self) -> None:
        self._disarm()
        super().on_message_complete()
        self.phase = "busy"

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
