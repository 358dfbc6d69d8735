"""A create whose caller is gone leaves no session behind (docs/reliability.md, "Orphans"): an unnamed gRPC
CreateSession whose real deadline expires after the session was stored is rolled back (the client never learnt
its id, so nobody could use or close it, and it held a --max-sessions slot for the idle timeout); a named one
stays, so that the client's retry with the same id is answered that session.

The store's create is held (an asyncio event the test releases once the client saw DEADLINE_EXCEEDED), so the
deadline passes after the point of no return whatever the machine's speed."""

from __future__ import annotations

import asyncio
import time

import grpc
import pytest

from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc


def _hold_creates(server) -> asyncio.Event:
    """Make the server's store hold every create, once stored, until the returned event is set."""
    release = server.run(_event())
    store = server.core.store
    create = store.create

    async def held(s):
        await create(s)
        await release.wait()

    store.create = held
    return release


async def _event() -> asyncio.Event:
    return asyncio.Event()


def _live(server) -> int:
    return server.run(server.core.store.count())


def _settled(server, want: int, within_s: float = 20.0) -> int:
    """The live session count once it is `want`, or what it is after `within_s`."""
    end = time.monotonic() + within_s
    while (n := _live(server)) != want and time.monotonic() < end:
        time.sleep(0.05)
    return n


@pytest.mark.parametrize("named", [False, True])
def test_a_create_whose_deadline_expired_is_rolled_back_unless_named(make_server, named):
    server = make_server()
    release = _hold_creates(server)
    req = pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0))
    if named:
        req.session_id = "retry-me"
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            stub.CreateSession(req, timeout=0.5)
        assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        server.loop.call_soon_threadsafe(release.set)
        if not named:
            assert _settled(server, 0) == 0, "the unnamed session the client never learnt of is still live"
            return
        assert _settled(server, 1) == 1
        again = stub.CreateSession(req, timeout=10)  # the retry is answered the session the first call made
        assert again.session_id == "retry-me"
        assert _live(server) == 1
