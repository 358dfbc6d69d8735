"""A session's timeline is read a page at a time, off the event loop (docs/reliability.md, "Timeline"):

- a session with 5,000 timeline entries (put straight into its in-memory ledger, as 100,000 goal changes over a
  Control stream would leave) answers at most 1,000 of them per read, over REST and gRPC, and the pages
  (`offset`/`limit`) together list every entry once, in order;
- while a timeline page is decoded, another session's act is served: the decoding runs in a worker thread (it is
  held here until that act is answered; on the event loop it would hold the act too);
- goal changes that no act separates are limited per step: past the limit a change fails with
  resource_exhausted (429 / RESOURCE_EXHAUSTED) naming the step, and after an act changes work again.
"""

from __future__ import annotations

import threading

import grpc
import httpx
import orjson
import pytest

import gmt.service.core_recordings as core_module
import gmt.service.rest.routes as routes_module
from gmt.common.recording import Recording
from gmt.service.records import MAX_GOALS_PER_STEP
from gmt.service.views import MAX_TIMELINE_PAGE
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

ENTRIES = 5000


def _create(http: httpx.Client) -> str:
    r = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0})
    assert r.status_code == 201, r.text
    return r.json()["session_id"]


def _entry(i: int) -> dict:
    """The i-th filled entry, as a timeline read lists it."""
    return {
        "step": 0,
        "episode": 0,
        "goal": i % 3,
        "given": {"goal": i % 3},
        "blend_steps": 0,
        "by": "stream",
        "at": 1.0,
    }


def _fill(server, sid: str, n: int) -> None:
    """Give the in-memory session `n` more timeline entries, as goal changes at step 0 would have."""
    s = server.core.store._sessions[sid]
    base = s.ledger.entries
    s.ledger.timeline += [orjson.dumps(_entry(i) | {"n": base + i}) for i in range(n)]
    s.ledger.entries += n


@pytest.fixture
def big(make_server):
    server = make_server()
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = _create(http)
        _fill(server, sid, ENTRIES - 1)
        yield server, http, sid


def test_a_timeline_read_answers_one_page_and_the_pages_list_every_entry(big):
    server, http, sid = big
    first = http.get(f"/sessions/{sid}/timeline")
    assert first.status_code == 200, first.text
    body = first.json()
    assert body["entries"] == ENTRIES and body["offset"] == 0
    assert len(body["goals"]) == MAX_TIMELINE_PAGE
    seen = []
    offset = 0
    while True:
        page = http.get(f"/sessions/{sid}/timeline", params={"offset": offset, "limit": 700}).json()
        assert len(page["goals"]) <= 700
        if not page["goals"]:
            break
        seen += page["goals"]
        offset += len(page["goals"])
    assert len(seen) == ENTRIES and seen[0]["by"] == "create"
    assert seen[1:] == [_entry(i) for i in range(ENTRIES - 1)]
    for bad in ({"limit": 0}, {"limit": MAX_TIMELINE_PAGE + 1}, {"offset": -1}):
        r = http.get(f"/sessions/{sid}/timeline", params=bad)
        assert r.status_code == 400, (bad, r.text)
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        t = stub.GetTimeline(pb.GetTimelineRequest(session_id=sid))
        assert (t.entries, t.offset, len(t.goals)) == (ENTRIES, 0, MAX_TIMELINE_PAGE)
        t = stub.GetTimeline(pb.GetTimelineRequest(session_id=sid, offset=4990, limit=50))
        assert (t.offset, len(t.goals), t.goals[-1].goal) == (4990, 10, (ENTRIES - 2) % 3)


def _act_served_while_held(monkeypatch, module, name: str, server, read_path: str, other: str, obs) -> None:
    """Hold `module.name` (a function a read calls) until another session's act is answered, while `read_path`
    is read: the act is answered only if the held function runs off the event loop."""
    entered, acted = threading.Event(), threading.Event()
    real = getattr(module, name)

    def held(*args):
        entered.set()
        assert acted.wait(30), f"the act was not served while {name} ran"
        return real(*args)

    monkeypatch.setattr(module, name, held)
    answers = {}
    with httpx.Client(base_url=server.url, timeout=60) as reading:
        reader = threading.Thread(target=lambda: answers.update(r=reading.get(read_path)))
        reader.start()
        try:
            assert entered.wait(30)
            with httpx.Client(base_url=server.url, timeout=10) as fresh:
                r = fresh.post(f"/sessions/{other}/act", json={"observation": obs.tolist()})
            assert r.status_code == 200, r.text
        finally:
            acted.set()
            reader.join(60)
    assert answers["r"].status_code == 200, answers["r"].text


def test_another_sessions_act_is_served_while_a_timeline_is_decoded(big, monkeypatch, observations):
    server, http, sid = big
    other = _create(http)
    path = f"/sessions/{sid}/timeline"
    _act_served_while_held(monkeypatch, core_module, "decode_timeline", server, path, other, observations[0])


def test_another_sessions_act_is_served_while_a_recording_is_encoded(
    make_server, tmp_path, monkeypatch, observations
):
    server = make_server(record_dir=tmp_path)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        r = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0, "record": True})
        sid, other = r.json()["session_id"], _create(http)
        assert (
            http.post(f"/sessions/{sid}/act", json={"observation": observations[1].tolist()}).status_code
            == 200
        )
    for fmt, name in (("json", "recording_json"), ("npz", "Recording.npz_bytes")):
        module, attr = (routes_module, name) if "." not in name else (Recording, name.split(".")[1])
        path = f"/sessions/{sid}/recording?format={fmt}"
        _act_served_while_held(monkeypatch, module, attr, server, path, other, observations[0])


def test_goal_changes_without_an_act_are_limited_per_step(make_server, observations):
    server = make_server()
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = _create(http)
        for i in range(MAX_GOALS_PER_STEP):
            r = http.put(f"/sessions/{sid}/goal", json={"goal": (i + 1) % 3})
            assert r.status_code == 200, r.text
        r = http.put(f"/sessions/{sid}/goal", json={"goal": (MAX_GOALS_PER_STEP + 1) % 3})
        assert r.status_code == 429, r.text
        assert r.json()["error"]["code"] == "resource_exhausted"
        assert "step 0" in r.json()["error"]["message"]
        again = http.put(f"/sessions/{sid}/goal", json={"goal": MAX_GOALS_PER_STEP % 3})
        assert again.status_code == 200, "a retry of the last change is still answered"
        assert (
            http.post(f"/sessions/{sid}/act", json={"observation": observations[0].tolist()}).status_code
            == 200
        )
        assert http.put(f"/sessions/{sid}/goal", json={"goal": 2}).status_code == 200
        assert http.get(f"/sessions/{sid}/timeline").json()["entries"] == MAX_GOALS_PER_STEP + 2
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        for i in range(MAX_GOALS_PER_STEP - 1):
            stub.SetGoal(pb.SetGoalRequest(session_id=sid, goal=pb.GoalSelector(id=i % 3)))
        with pytest.raises(grpc.RpcError) as e:
            stub.SetGoal(pb.SetGoalRequest(session_id=sid, goal=pb.GoalSelector(id=1)))
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


@pytest.mark.parametrize("transport", ["rest", "grpc"])
def test_the_python_clients_read_every_page(big, transport):
    from gmt.client.grpc import GrpcClient
    from gmt.client.rest import RestClient

    server, _, sid = big
    client = RestClient(server.url) if transport == "rest" else GrpcClient(server.target)
    try:
        t = client.get_timeline(sid)
    finally:
        client.close()
    assert t.entries == len(t.goals) == ENTRIES
    assert [g.goal for g in t.goals[1:]] == [i % 3 for i in range(ENTRIES - 1)]
