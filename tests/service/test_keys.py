"""Keys with ownership (`gmt.service.keys`): two named keys on real servers, over REST and gRPC, in memory and with
Redis. Each key gets 404 / NOT_FOUND on the other's sessions (never 403: an id's existence is not revealed), and the
listing (`GET /sessions`, the console's), the event feed and batches show only its own; the admin token sees
all; metrics carry the key's name; the owner survives the Redis store."""

from __future__ import annotations

import json

import grpc
import httpx
import numpy as np
import pytest
from pydantic import ValidationError
from service_harness import OBS_DIM, ServeProcess

from gmt.model.context import Context
from gmt.service import keys, session_codec
from gmt.service.sessions import Session
from gmt.service.settings import Settings
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

KEY_FILE = """# two teams
alice:alice-token-1
bob : bob-token-2

"""
OBS = [0.0] * OBS_DIM


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "keys.txt"
    path.write_text(KEY_FILE)
    return path


def bearer(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def md(token: str) -> tuple:
    return (("authorization", f"Bearer {token}"),)


def listed(http: httpx.Client, token: str) -> tuple[int, set[str]]:
    r = http.get("/sessions", headers=bearer(token))
    assert r.status_code == 200, r.text
    return r.json()["total"], {row["session_id"] for row in r.json()["sessions"]}


def assert_hidden_over_rest(http: httpx.Client, token: str, sid: str) -> None:
    """Every route of session `sid` answers `token` exactly as for an id that never existed."""
    h = bearer(token)
    calls = [
        ("GET", f"/sessions/{sid}", None),
        ("POST", f"/sessions/{sid}/act", {"observation": OBS}),
        ("PUT", f"/sessions/{sid}/goal", {"goal": 1}),
        ("POST", f"/sessions/{sid}/reset", {}),
        ("GET", f"/sessions/{sid}/timeline", None),
        ("GET", f"/sessions/{sid}/recording", None),
        ("GET", f"/sessions/{sid}/events", None),
        ("DELETE", f"/sessions/{sid}", None),
    ]
    for method, path, body in calls:
        r = http.request(method, path, json=body, headers=h)
        unknown = http.request(method, path.replace(sid, "never-created"), json=body, headers=h)
        assert r.status_code == 404, (method, path, r.status_code, r.text)
        assert r.json() == {
            "error": {
                "code": "not_found",
                "message": unknown.json()["error"]["message"].replace("never-created", sid),
            }
        }, (method, path)
    r = http.post("/act", json={"requests": [{"session_id": sid, "observation": OBS}]}, headers=h)
    assert r.status_code == 200 and r.json()["results"][0]["error"]["code"] == "not_found", r.text


def assert_hidden_over_grpc(stub, token: str, sid: str) -> None:
    """Every PolicyService call on session `sid` answers `token` NOT_FOUND (in-band on Control and ActBatch)."""
    m = md(token)
    calls = [
        lambda: stub.GetSession(pb.GetSessionRequest(session_id=sid), metadata=m),
        lambda: stub.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS)), metadata=m),
        lambda: stub.SetGoal(pb.SetGoalRequest(session_id=sid, goal=pb.GoalSelector(id=1)), metadata=m),
        lambda: stub.ResetSession(pb.ResetSessionRequest(session_id=sid), metadata=m),
        lambda: stub.GetTimeline(pb.GetTimelineRequest(session_id=sid), metadata=m),
        lambda: stub.CloseSession(pb.CloseSessionRequest(session_id=sid), metadata=m),
    ]
    for call in calls:
        with pytest.raises(grpc.RpcError) as e:
            call()
        assert e.value.code() == grpc.StatusCode.NOT_FOUND and "not found" in e.value.details()
    batch = stub.ActBatch(
        pb.ActBatchRequest(requests=[pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS))]),
        metadata=m,
    )
    assert batch.results[0].error.code == "not_found"
    commands = [
        pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS))),
        pb.ControlRequest(set_goal=pb.SetGoalRequest(goal=pb.GoalSelector(id=1))),
    ]
    answers = list(stub.Control(iter(commands), metadata=m))
    assert [a.error.code for a in answers] == ["not_found", "not_found"]


@pytest.mark.parametrize("store", ["memory", "redis"])
def test_each_key_sees_and_acts_on_only_its_own_sessions(make_server, key_file, store, request):
    redis_url = request.getfixturevalue("redis_clean") if store == "redis" else None
    server = make_server(auth_tokens=key_file, admin_token="root-token", redis_url=redis_url)
    with httpx.Client(base_url=server.url, timeout=30) as http, grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        # alice creates over REST, bob over gRPC; each acts on its own session.
        r = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=bearer("alice-token-1"))
        assert r.status_code == 201, r.text
        a = r.json()["session_id"]
        b = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=0)), metadata=md("bob-token-2")
        ).session_id
        assert http.post(
            f"/sessions/{a}/act", json={"observation": OBS}, headers=bearer("alice-token-1")
        ).is_success
        stub.Act(pb.ActRequest(session_id=b, values=pb.FloatVector(values=OBS)), metadata=md("bob-token-2"))

        assert_hidden_over_rest(http, "bob-token-2", a)
        assert_hidden_over_rest(http, "alice-token-1", b)
        assert_hidden_over_grpc(stub, "bob-token-2", a)
        assert_hidden_over_grpc(stub, "alice-token-1", b)
        # A named create cannot take over another key's live id (409, as for other parameters).
        r = http.post(
            "/sessions",
            json={"model": "tiny-gmt", "goal": 0, "session_id": b},
            headers=bearer("alice-token-1"),
        )
        assert r.status_code == 409 and r.json()["error"]["code"] == "already_exists"

        # The listing (what /ui shows) and the batches: only one's own; the admin token: everything.
        assert listed(http, "alice-token-1") == (1, {a})
        assert listed(http, "bob-token-2") == (1, {b})
        assert listed(http, "root-token") == (2, {a, b})
        for sid in (a, b):
            assert http.get(f"/sessions/{sid}", headers=bearer("root-token")).status_code == 200
            got = stub.GetSession(pb.GetSessionRequest(session_id=sid), metadata=md("root-token"))
            assert got.step == 1  # nothing the other key tried changed the session
        items = {"requests": [{"session_id": a, "observation": OBS}, {"session_id": b, "observation": OBS}]}
        res = http.post("/act", json=items, headers=bearer("alice-token-1")).json()["results"]
        assert [("action" in x, x.get("error", {}).get("code")) for x in res] == [
            (True, None),
            (False, "not_found"),
        ]
        res = http.post("/act", json=items, headers=bearer("root-token")).json()["results"]
        assert all("action" in x for x in res)

        # The owner's own calls, Control and ActBatch included, run as its key.
        answers = list(
            stub.Control(
                iter([pb.ControlRequest(act=pb.ActRequest(session_id=b, values=pb.FloatVector(values=OBS)))]),
                metadata=md("bob-token-2"),
            )
        )
        assert answers[0].WhichOneof("result") == "act", answers[0]
        own = stub.ActBatch(
            pb.ActBatchRequest(requests=[pb.ActRequest(session_id=b, values=pb.FloatVector(values=OBS))]),
            metadata=md("bob-token-2"),
        )
        assert own.results[0].WhichOneof("outcome") == "action", own

        # The event feed: the owner's opens (its first event is the session), the other key's is a 404 above.
        with http.stream("GET", f"/sessions/{a}/events", headers=bearer("alice-token-1")) as feed:
            assert feed.status_code == 200
            first = next(feed.iter_lines())
            assert first == "event: session"

        # Metrics carry the key's name (never its token).
        text = http.get("/metrics", headers=bearer("root-token")).text
        assert 'gmt_key_sessions_created_total{key="alice"} 1.0' in text
        assert 'gmt_key_sessions_created_total{key="bob"} 1.0' in text
        assert 'gmt_key_requests_total{code="OK",key="bob",transport="grpc"}' in text
        assert 'gmt_key_requests_total{code="404",key="bob",transport="rest"}' in text
        assert not any(t in text for t in ("alice-token-1", "bob-token-2", "root-token"))

        # Owners close their own; an unknown token is refused before anything.
        assert http.get("/sessions", headers=bearer("mallory")).status_code == 401
        assert http.delete(f"/sessions/{a}", headers=bearer("alice-token-1")).status_code == 204
        stub.CloseSession(pb.CloseSessionRequest(session_id=b), metadata=md("root-token"))
        assert listed(http, "root-token") == (0, set())


def test_the_owner_survives_the_redis_store(make_server, key_file, redis_clean):
    """Two replicas on one Redis: a session created on one keeps its owner on the other."""
    one = make_server(auth_tokens=key_file, redis_url=redis_clean)
    two = make_server(auth_tokens=key_file, redis_url=redis_clean)
    with httpx.Client(base_url=one.url, timeout=30) as h1, httpx.Client(base_url=two.url, timeout=30) as h2:
        r = h1.post("/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=bearer("alice-token-1"))
        sid = r.json()["session_id"]
        assert (
            h2.post(
                f"/sessions/{sid}/act", json={"observation": OBS}, headers=bearer("bob-token-2")
            ).status_code
            == 404
        )
        r = h2.post(f"/sessions/{sid}/act", json={"observation": OBS}, headers=bearer("alice-token-1"))
        assert r.status_code == 200, r.text
        assert listed(h2, "bob-token-2") == (0, set())
        assert listed(h2, "alice-token-1") == (1, {sid})


def test_gmt_serve_logs_the_key_names_and_never_a_token(ckpt_root, key_file):
    p = ServeProcess(
        "--checkpoints", str(ckpt_root), "--auth-tokens", str(key_file), "--admin-token", "root-token"
    )
    try:
        serving = p.wait_serving()
        assert serving["auth"] is True and serving["keys"] == ["alice", "bob"]
        with httpx.Client(base_url=p.url, timeout=30) as http:
            assert http.get("/sessions").status_code == 401
            assert listed(http, "bob-token-2") == (0, set())
            made = http.post(
                "/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=bearer("bob-token-2")
            )
            assert made.status_code == 201, made.text
    finally:
        p.kill()
    assert not any(t in json.dumps(p.lines) for t in ("alice-token-1", "bob-token-2", "root-token"))
    created = [rec for rec in p.lines if rec.get("msg") == "session created"]
    assert [rec.get("key") for rec in created] == ["bob"]  # the log names the key that created it


def test_a_stored_session_without_owner_is_read_as_anyones(engine):
    ctx = engine.new_context(0, None, 1, key="s")
    assert isinstance(ctx, Context)
    s = Session("s", "tiny-gmt", ctx, 1.0, 1.0)
    fields = session_codec.create_fields(s)
    assert b"owner" not in fields["meta"]  # a record as written before keys were
    assert session_codec.decode(fields).owner == ""
    assert keys.visible("", keys.Caller("bob"))
    s.owner = "alice"
    back = session_codec.decode(session_codec.create_fields(s))
    assert back.owner == "alice" and not keys.visible(back.owner, keys.Caller("bob"))
    engine.forget("s")


def test_auth_token_is_one_key_beside_the_file(make_server, key_file):
    server = make_server(auth_tokens=key_file, auth_token="plain-token")
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = http.post(
            "/sessions", json={"model": "tiny-gmt", "goal": 0}, headers=bearer("plain-token")
        ).json()["session_id"]
        assert listed(http, "plain-token") == (1, {sid})
        assert listed(http, "alice-token-1") == (0, set())
        assert http.get(f"/sessions/{sid}", headers=bearer("alice-token-1")).status_code == 404


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("alice\n", "line 1: expected 'name:token'"),
        ("# c\nal ice:t1\n", "line 2: a key name is 1 to 64"),
        ("admin:t1\n", "line 1: the name 'admin' is the admin token's"),
        ("a:secret one\n", "line 1: a token is 1 to 4096 printable ASCII"),
        ("a:secret1\na:secret2\n", "line 2: the key 'a' is named twice"),
        ("a:secret1\nb:secret1\n", "line 2: the key 'b' has the token of an earlier key"),
        ("# nothing\n", "holds no key"),
    ],
)
def test_a_bad_key_file_is_refused_without_quoting_a_token(tmp_path, text, problem):
    path = tmp_path / "keys.txt"
    path.write_text(text)
    with pytest.raises(ValidationError) as e:
        Settings(auth_tokens=path)
    assert problem in str(e.value)
    assert "secret" not in str(e.value.errors(include_input=False))


def test_keys_come_from_the_environment_too(tmp_path, key_file, monkeypatch):
    monkeypatch.setenv("GMT_AUTH_TOKENS", str(key_file))
    assert Settings().keys == {"alice": "alice-token-1", "bob": "bob-token-2"}
    with pytest.raises(ValidationError, match="rename it"):
        (tmp_path / "k").write_text("default:x1\n")
        Settings(auth_tokens=tmp_path / "k", auth_token="y")
    with pytest.raises(ValidationError, match="cannot read the key file"):
        Settings(auth_tokens=tmp_path / "missing")


def test_a_server_without_keys_lets_anyone_see_everything(http):
    sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 0}).json()["session_id"]
    assert sid in {
        row["session_id"] for row in http.get("/sessions", params={"limit": 500}).json()["sessions"]
    }
    assert keys.current(keyed=False).sees_all and not keys.current(keyed=True).sees_all
    assert np.isfinite(http.post(f"/sessions/{sid}/act", json={"observation": OBS}).json()["action"]).all()
    http.delete(f"/sessions/{sid}")
