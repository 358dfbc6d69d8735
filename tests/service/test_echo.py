"""No id longer than the server's limit comes back (docs/reliability.md, "Echo"): a 200,000-character session id
in a many-session act (`POST /act`, gRPC ActBatch) fails its item, which names its index instead of the id; the
single-session routes refuse it without quoting it either."""

from __future__ import annotations

import grpc
import pytest

from gmt.service.ids import MAX_ID_LENGTH
from gmt.v1 import policy_pb2 as pb

HUGE = "a" * 200_000


@pytest.fixture
def big_server(make_server):
    return make_server(max_request_bytes=4 * 1024 * 1024)


def test_act_many_does_not_echo_a_huge_id(big_server, observations):
    import httpx

    with httpx.Client(base_url=big_server.url, timeout=30) as http:
        good = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
        obs = observations[0].tolist()
        r = http.post(
            "/act",
            json={
                "requests": [
                    {"session_id": good, "observation": obs},
                    {"session_id": HUGE, "observation": obs},
                ]
            },
        )
        assert r.status_code == 200, r.text
        assert len(r.content) < 4096, f"{len(r.content)} bytes answered"
        ok, bad = r.json()["results"]
        assert ok["session_id"] == good and "action" in ok
        assert bad["session_id"] == ""
        assert bad["error"]["code"] == "not_found"
        assert "item 1" in bad["error"]["message"]
        # The single-session route answers without the id, in the body or the headers (an id as long as a
        # client sends in a URL).
        r = http.post(f"/sessions/{HUGE[:8000]}/act", json={"observation": obs})
        assert r.status_code == 404, r.status_code
        assert len(r.content) + sum(len(v) for v in r.headers.values()) < 4096


def test_act_batch_does_not_echo_a_huge_id(big_server, observations):
    options = [("grpc.max_send_message_length", 4 * 1024 * 1024)]
    with grpc.insecure_channel(big_server.target, options=options) as ch:
        from gmt.v1 import policy_pb2_grpc

        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        good = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0))
        ).session_id
        obs = pb.FloatVector(values=observations[0].tolist())
        items = [pb.ActRequest(session_id=good, values=obs), pb.ActRequest(session_id=HUGE, values=obs)]
        out = stub.ActBatch(pb.ActBatchRequest(requests=items))
        assert out.ByteSize() < 4096, f"{out.ByteSize()} bytes answered"
        ok, bad = out.results
        assert ok.session_id == good and ok.HasField("action")
        assert bad.session_id == ""
        assert bad.error.code == "not_found" and "item 1" in bad.error.message
        assert str(MAX_ID_LENGTH) in bad.error.message
