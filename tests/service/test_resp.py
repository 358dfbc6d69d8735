"""The store's own pipelined Redis connection against a real redis-server: replies in order, errors in place,
authentication and database, and a broken connection failing every command that waits."""

from __future__ import annotations

import asyncio
import shutil
import subprocess

import pytest

from gmt.cluster.supervisor import free_port
from gmt.service import resp

pytestmark = pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server is not installed")


@pytest.fixture
def server(tmp_path):
    """A redis-server with a password on a free port: (port, process)."""
    port = free_port()
    proc = subprocess.Popen(
        ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--requirepass", "pw"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stdout:
        if "Ready to accept connections" in line:
            break
    yield port, proc
    proc.kill()
    proc.wait(10)


def test_encode_writes_bulk_strings():
    assert resp.encode(["SET", "k", b"v\r\n", 12], ["PING"]) == (
        b"*4\r\n$3\r\nSET\r\n$1\r\nk\r\n$3\r\nv\r\n\r\n$2\r\n12\r\n*1\r\n$4\r\nPING\r\n"
    )


def test_replies_come_back_in_order_with_errors_in_place(server):
    port, _ = server

    async def scenario():
        c = resp.RespConnection("127.0.0.1", port, password="pw", db=3)
        await c.open()
        script = "return {1, -2, redis.call('GET', KEYS[1]) and 1 or 0}"
        replies = await c.call(
            ["SET", "k", b"\x00bytes\r\n"],
            ["GET", "k"],
            ["EVAL", script, 1, "k"],
            ["NOSUCHCOMMAND"],
            ["GET", "nope"],
        )
        assert replies[:3] == [b"OK", b"\x00bytes\r\n", [1, -2, 1]]
        assert isinstance(replies[3], resp.RespError) and "unknown command" in str(replies[3])
        assert replies[4] is None
        # Many calls in flight at once on one connection, each answered its own reply.
        got = await asyncio.gather(*(c.call(["ECHO", str(i)]) for i in range(200)))
        assert got == [[str(i).encode()] for i in range(200)]
        c.close()
        other = resp.RespConnection("127.0.0.1", port, password="pw")  # database 0 does not have "k"
        await other.open()
        assert await other.call(["EXISTS", "k"]) == [0]
        other.close()

    asyncio.run(scenario())


def test_a_wrong_password_or_a_dead_server_is_connection_lost(server):
    port, proc = server

    async def scenario():
        with pytest.raises(resp.ConnectionLost, match="refused the connection's setup"):
            await resp.RespConnection("127.0.0.1", port, password="wrong").open()
        c = resp.RespConnection("127.0.0.1", port, password="pw", timeout_s=2)
        await c.open()
        blocked = asyncio.ensure_future(c.call(["BLPOP", "never", 0]))  # waits until the server goes away
        await asyncio.sleep(0)
        proc.kill()
        with pytest.raises(resp.ConnectionLost):
            await blocked
        assert c.closed
        with pytest.raises(resp.ConnectionLost, match="closed"):
            await c.call(["PING"])
        proc.wait(10)
        with pytest.raises(resp.ConnectionLost, match="cannot connect"):
            await resp.RespConnection("127.0.0.1", port, timeout_s=1).open()

    asyncio.run(scenario())


def test_a_reply_later_than_the_timeout_closes_the_connection(server):
    port, _ = server

    async def scenario():
        c = resp.RespConnection("127.0.0.1", port, password="pw", timeout_s=0.3)
        await c.open()
        with pytest.raises(resp.ConnectionLost, match="no reply from Redis within 0.3 s"):
            await c.call(["BLPOP", "never", 0])
        assert c.closed  # a late reply could no longer be matched to its command

    asyncio.run(scenario())


def test_replies_split_anywhere_are_parsed_whole():
    """The bytes of several replies, cut at every position, parse to the same replies once complete."""
    wire = b":-2\r\n$5\r\nab\r\nc\r\n*3\r\n:1\r\n$-1\r\n*1\r\n+OK\r\n-ERR bad\r\n$0\r\n\r\n"
    want = [-2, b"ab\r\nc", [1, None, [b"OK"]], "ERR bad", b""]
    for cut in range(len(wire) + 1):
        got, buf = [], bytearray()
        for chunk in (wire[:cut], wire[cut:]):
            buf += chunk
            pos = 0
            while True:
                try:
                    reply, pos = resp.parse(buf, pos)
                except resp._Incomplete:
                    break
                got.append(str(reply) if isinstance(reply, resp.RespError) else reply)
            del buf[:pos]
        assert got == want, cut
    with pytest.raises(resp.RespError):
        resp.parse(b"?what\r\n")


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
def test_a_lone_command_polled_for_is_answered_before_send_returns(server, loop):
    """With `spin_s`, the only commands in flight get their replies read right there; a reply that takes longer
    than the poll comes through the event loop as usual, and later commands still get their own replies."""
    port, _ = server

    async def scenario():
        c = resp.RespConnection("127.0.0.1", port, password="pw")
        await c.open()
        got = []
        c.send(
            got.append, ["SET", "k", "v"], ["GET", "k"], spin_s=5.0
        )  # bounded, not slept: Redis answers first
        assert got == [[b"OK", b"v"]]
        c.send(got.append, ["ECHO", "no poll"])  # without spin_s the reply waits for the loop
        assert len(got) == 1
        assert await c.call(["ECHO", "after"]) == [b"after"] and got[1] == [b"no poll"]
        # A reply slower than the poll (BLPOP times out after 0.2 s): read by the transport, in order.
        c.send(got.append, ["BLPOP", "never", "0.2"], spin_s=0.001)
        assert len(got) == 2
        assert await c.call(["ECHO", "next"]) == [b"next"] and got[2] == [None]
        # Not polled while another command waits: its reply must not be read out from under it.
        c.send(got.append, ["BLPOP", "never", "0.2"])
        c.send(got.append, ["PING"], spin_s=5.0)
        assert len(got) == 3
        assert await c.call(["ECHO", "last"]) == [b"last"] and got[3:] == [[None], [b"PONG"]]
        c.close()

    if loop == "uvloop":  # what `gmt serve` runs on: its transport's socket is read the same way
        import uvloop

        uvloop.run(scenario())
    else:
        asyncio.run(scenario())
