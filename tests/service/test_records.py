"""Sessions as records (issue 39): the goal timeline and recorded sessions, over REST (curl-style JSON) and gRPC,
with sessions in memory and in Redis, on real in-process servers.

What must hold: a goal change answers `effective_step`, the step of the first act that used the new goal; the
timeline lists every goal once (a retried act or an identical goal change adds nothing); a recording holds every
answered step exactly once, with the client's report on each action moved onto that action's step; it stops at
--record-max-steps while the acts go on; a hostile request gets a clear 4xx and changes nothing; at close and at
expiry the recording is written to the recordings directory as `<id>.npz` + `<id>.json`.
"""

from __future__ import annotations

import grpc
import httpx
import numpy as np
import pytest

from gmt.common.recording import Recording, read_recording
from gmt.service.records import record_drawn
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

MODEL = "tiny-sampled"  # continuous actions, sampled by default: the session's seed matters
OBS = np.random.default_rng(39).normal(size=(40, 17)).astype(np.float32)


@pytest.fixture(params=["memory", "redis"])
def store(request):
    """Sessions in memory, or in a real Redis (skipped where redis-server is missing)."""
    return None if request.param == "memory" else request.getfixturevalue("redis_clean")


@pytest.fixture
def recorder(make_server, store, tmp_path):
    """A server that records, over sessions in `store`; its recordings directory is `tmp_path / "rec"`."""
    return make_server(redis_url=store, record_dir=tmp_path / "rec", max_request_bytes=64 * 1024)


def _create(http: httpx.Client, **body) -> str:
    r = http.post("/sessions", json={"model": MODEL, "goal": 0, "seed": 5, "record": True, **body})
    assert r.status_code == 201, r.text
    assert r.json()["recording"] is body.get("record", True)
    return r.json()["session_id"]


def _act(http: httpx.Client, sid: str, t: int, **report) -> dict:
    r = http.post(f"/sessions/{sid}/act", json={"observation": OBS[t].tolist(), "step": t, **report})
    assert r.status_code == 200, r.text
    return r.json()


def test_rest_session_records_every_step_once_with_its_goal_timeline(recorder):
    with httpx.Client(base_url=recorder.url, timeout=30) as http:
        sid = _create(http)
        answers = [_act(http, sid, 0)]
        for t in range(1, 12):
            if t == 4:  # a goal change by name, and its retry: the same answer, no second entry
                first = http.put(f"/sessions/{sid}/goal", json={"goal": "high"})
                again = http.put(f"/sessions/{sid}/goal", json={"goal": "high"})
                assert first.status_code == again.status_code == 200, first.text
                assert first.json()["effective_step"] == again.json()["effective_step"] == 4
            if t == 8:  # a blended change by target value
                r = http.put(f"/sessions/{sid}/goal", json={"target": 1.1, "blend_steps": 2})
                assert r.json()["effective_step"] == 8 and r.json()["blend_remaining"] == 2
            answers.append(_act(http, sid, t, reward=0.5 * t, info={"x_velocity": float(t), "cost": -t}))
            if t == 6:  # a retried act (its answer was lost): answered again, not stepped, not recorded twice
                assert _act(http, sid, 6, reward=3.0, info={"x_velocity": 6.0, "cost": -6}) == answers[-1]
        # The first act that used each new goal is its effective step.
        assert [a["goal"] for a in answers] == [0] * 4 + [2] * 4 + [1] * 4
        tl = http.get(f"/sessions/{sid}/timeline")
        assert tl.status_code == 200 and tl.headers["x-session-id"] == sid
        body = tl.json()
        assert body["step"] == 12 and body["episode"] == 0 and body["entries"] == 3
        session = http.get(f"/sessions/{sid}").json()  # the timeline names the version the session runs
        version = next(v for v in http.get("/models").json()["models"] if v["name"] == session["model"])[
            "versions"
        ]
        fingerprints = {v["version"]: v["fingerprint"] for v in version}
        assert body["model_version"] == session["model_version"]
        assert body["fingerprint"] == fingerprints[session["model_version"]]
        assert [(e["step"], e["goal"], e["given"], e["blend_steps"], e["by"]) for e in body["goals"]] == [
            (0, 0, {"goal": 0}, 0, "create"),
            (4, 2, {"goal": "high"}, 0, "rest"),
            (8, 1, {"target": 1.1}, 2, "rest"),
        ]

        rec = http.get(f"/sessions/{sid}/recording").json()
        assert (rec["model_version"], rec["fingerprint"]) == (body["model_version"], body["fingerprint"])
        assert rec["steps"] == 12 and rec["t"] == list(range(12)) and rec["episode"] == [0] * 12
        assert rec["actions"] == [a["action"] for a in answers]
        np.testing.assert_array_equal(np.asarray(rec["observations"], np.float32), OBS[:12])
        assert rec["goals"] == [a["goal"] for a in answers]
        assert rec["goal_tokens"][8:11] == [2, 2, 1] and rec["blend_w"][8] == 0.5  # the blend's tokens
        # The report sent with act t describes the action of step t - 1.
        assert rec["rewards"] == [0.5 * t for t in range(1, 12)] + [None]
        assert rec["infos"] == {
            "cost": [float(-t) for t in range(1, 12)] + [None],
            "x_velocity": [*range(1, 12), None],
        }
        assert rec["reported"] == [True] * 11 + [False] and rec["stopped"] is None
        assert rec["timeline"] == body["goals"] and rec["seed"] == 5 and rec["action_mode"] == "sample"

        npz = http.get(f"/sessions/{sid}/recording", params={"format": "npz"})
        assert npz.headers["content-type"] == "application/octet-stream"
        arrays = Recording.from_npz(npz.content)
        np.testing.assert_array_equal(arrays.arrays["actions"], np.asarray(rec["actions"], np.float32))
        assert arrays.meta["timeline"] == rec["timeline"]

        assert http.delete(f"/sessions/{sid}").status_code == 204
        written = read_recording(recorder.settings.record_dir / f"{sid}.json")
        assert written.meta["ended_by"] == "close" and written.meta["env_id"] == "HalfCheetah-v5"
        np.testing.assert_array_equal(written.arrays["actions"], arrays.arrays["actions"])
        (ep,) = written.episodes()
        assert len(ep) == 11 and ep.truncated and not ep.terminated  # the last action's outcome never came
        np.testing.assert_array_equal(ep.final_observation, OBS[11])
        assert http.get(f"/sessions/{sid}/recording").status_code == 404  # closed: the file is what is left


def test_reset_starts_a_new_episode_and_a_terminal_report_ends_one(recorder):
    with httpx.Client(base_url=recorder.url, timeout=30) as http:
        sid = _create(http)
        for t in range(3):
            _act(http, sid, t, **({"reward": 1.0} if t else {}))
        _act(http, sid, 3, reward=2.0, terminated=True)  # carries the final observation of episode 0
        for _ in range(2):  # the reset and its retry: one new episode
            r = http.post(f"/sessions/{sid}/reset", json={"goal": 1})
            assert r.status_code == 200 and r.json()["step"] == 0
        for t in range(2):
            _act(http, sid, t, **({"reward": 5.0} if t else {}))
        goals = http.get(f"/sessions/{sid}/timeline").json()["goals"]
        assert [(e["episode"], e["step"], e["goal"], e["by"]) for e in goals] == [
            (0, 0, 0, "create"),
            (1, 0, 1, "reset"),
        ]
        rec = Recording.from_npz(http.get(f"/sessions/{sid}/recording?format=npz").content)
        e0, e1 = rec.episodes()
        assert len(e0) == 3 and e0.terminated and not e0.truncated
        assert e0.rewards.tolist() == [1.0, 1.0, 2.0]
        np.testing.assert_array_equal(e0.final_observation, OBS[3])
        assert len(e1) == 1 and e1.goals.tolist() == [1] and e1.rewards.tolist() == [5.0]


def test_grpc_session_records_with_goal_changes_from_unary_calls_and_the_stream(recorder):
    with (
        grpc.insecure_channel(recorder.target) as ch,
        httpx.Client(base_url=recorder.url, timeout=30) as http,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        info = stub.CreateSession(
            pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=1), seed=9, record=True)
        )
        assert info.recording
        sid, answers = info.session_id, []

        def act(t: int, **report) -> pb.ActResponse:
            return stub.Act(
                pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[t]), step=t, **report)
            )

        answers.append(act(0))
        answers.append(act(1, reward=1.5, info={"x_velocity": 0.25}))
        changed = stub.SetGoal(pb.SetGoalRequest(session_id=sid, goal=pb.GoalSelector(name="high")))
        assert changed.HasField("effective_step") and changed.effective_step == 2
        answers.append(act(2, reward=-2.0, terminated=False, truncated=False))

        def stream():
            yield pb.ControlRequest(set_goal=pb.SetGoalRequest(session_id=sid, goal=pb.GoalSelector(id=0)))
            for t in (3, 4):
                yield pb.ControlRequest(
                    act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[t]), step=t, reward=t)
                )

        out = list(stub.Control(stream(), metadata=(("x-session-id", sid),)))
        assert out[0].session.effective_step == 3
        answers += [o.act for o in out[1:]]
        assert [a.goal for a in answers] == [1, 1, 2, 0, 0]

        tl = stub.GetTimeline(pb.GetTimelineRequest(session_id=sid))
        assert (tl.step, tl.entries) == (5, 3) and tl.fingerprint
        assert [(e.step, e.goal, e.given.WhichOneof("kind"), e.by) for e in tl.goals] == [
            (0, 1, "id", "create"),
            (2, 2, "name", "grpc"),
            (3, 0, "id", "stream"),
        ]
        rec = http.get(f"/sessions/{sid}/recording").json()
        assert rec["steps"] == 5 and rec["goals"] == [1, 1, 2, 0, 0]
        np.testing.assert_allclose(rec["actions"], [list(a.action) for a in answers], rtol=0, atol=0)
        assert rec["rewards"] == [1.5, -2.0, 3.0, 4.0, None] and rec["infos"]["x_velocity"][0] == 0.25
        with pytest.raises(grpc.RpcError) as e:
            stub.GetTimeline(pb.GetTimelineRequest(session_id="no-such-session"))
        assert e.value.code() == grpc.StatusCode.NOT_FOUND
        stub.CloseSession(pb.CloseSessionRequest(session_id=sid))
        assert read_recording(recorder.settings.record_dir / f"{sid}.npz").steps == 5


def test_hostile_record_requests_get_a_clear_4xx_and_lose_nothing(recorder, make_server, stub):
    with httpx.Client(base_url=recorder.url, timeout=30) as http:
        sid = _create(http)
        _act(http, sid, 0)
        _act(http, sid, 1, reward=1.0)
        before = http.get(f"/sessions/{sid}/recording").json()
        bad = [
            ({"reward": "1"}, 400, "reward"),
            ({"reward": 1e13}, 400, "finite number within +-1e12"),
            ({"terminated": 1}, 400, "terminated"),
            ({"info": {"x": [1.0]}}, 400, "info"),
            ({"info": {"x y": 1.0}}, 400, "info key 'x y'"),
            ({"info": {"k" * 65: 1.0}}, 400, "info key given"),
            ({"info": {f"k{i}": 1.0 for i in range(33)}}, 400, "info has 33 keys; at most 32"),
        ]
        for extra, status, words in bad:
            r = http.post(f"/sessions/{sid}/act", json={"observation": OBS[2].tolist(), "step": 2, **extra})
            assert r.status_code == status and words in r.json()["error"]["message"], (extra, r.text)
        for raw in (b'"reward": NaN', b'"info": {"x": Infinity}'):  # not JSON, yet some parsers take them
            r = http.post(
                f"/sessions/{sid}/act",
                content=b'{"observation": %s, "step": 2, %s}' % (str(OBS[2].tolist()).encode(), raw),
                headers={"content-type": "application/json"},
            )
            assert r.status_code == 400 and raw[1:5].decode() in r.json()["error"]["message"], r.text
        # In POST /act the bad item fails alone; the good one steps and is recorded.
        other = _create(http, seed=6)
        _act(http, other, 0)
        r = http.post(
            "/act",
            json={
                "requests": [
                    {"session_id": sid, "observation": OBS[2].tolist(), "step": 2, "reward": 1e99},
                    {"session_id": other, "observation": OBS[1].tolist(), "step": 1, "reward": 7.0},
                ]
            },
        )
        assert r.status_code == 200
        bad_item, good_item = r.json()["results"]
        assert bad_item["error"]["code"] == "invalid_argument" and good_item["step"] == 1
        assert http.get(f"/sessions/{other}/recording").json()["rewards"] == [7.0, None]
        # A report with an episode's first act has no action to describe.
        fresh = _create(http, seed=7)
        r = http.post(f"/sessions/{fresh}/act", json={"observation": OBS[0].tolist(), "reward": 1.0})
        assert r.status_code == 409 and "first act of an episode" in r.json()["error"]["message"]
        assert http.get(f"/sessions/{fresh}").json()["step"] == 0
        # Unknown sessions, unknown formats, a recording a session does not keep, a body over the limit.
        for path in ("/sessions/no-such/recording", "/sessions/no-such/timeline"):
            r = http.get(path)
            assert r.status_code == 404 and "not found" in r.json()["error"]["message"], path
        r = http.get(f"/sessions/{sid}/recording", params={"format": "hdf5"})
        assert r.status_code == 400 and "format" in r.json()["error"]["message"]
        plain = _create(http, record=False)
        r = http.get(f"/sessions/{plain}/recording")
        assert r.status_code == 404 and "has no recording" in r.json()["error"]["message"]
        r = http.post(
            f"/sessions/{sid}/act", json={"observation": OBS[2].tolist(), "info": {"x": "1" * 70_000}}
        )
        assert r.status_code == 413
        # Nothing above changed the session or its recording.
        assert http.get(f"/sessions/{sid}").json()["step"] == 2
        assert http.get(f"/sessions/{sid}/recording").json() == before
    # gRPC: the same rule, and a server without a recordings directory refuses to record.
    with pytest.raises(grpc.RpcError) as e:
        stub.CreateSession(pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=0), record=True))
    assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "--record-dir" in e.value.details()
    with grpc.insecure_channel(recorder.target) as ch:
        s = policy_pb2_grpc.PolicyServiceStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            s.Act(
                pb.ActRequest(
                    session_id=sid, values=pb.FloatVector(values=OBS[2]), step=2, reward=float("nan")
                )
            )
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "reward" in e.value.details()
        with pytest.raises(grpc.RpcError) as e:
            s.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=OBS[2]), step=2, info={"": 1.0}))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "info key" in e.value.details()


def test_a_recording_stops_at_its_maximum_and_the_session_goes_on(make_server, store, tmp_path):
    server = make_server(redis_url=store, record_dir=tmp_path, record_max_steps=3)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = _create(http)
        answers = [_act(http, sid, t, **({"reward": float(t)} if t else {})) for t in range(6)]
        assert [a["step"] for a in answers] == list(range(6))
        rec = http.get(f"/sessions/{sid}/recording").json()
        assert rec["steps"] == 3 and rec["max_steps"] == 3
        assert "maximum of 3 steps" in rec["stopped"] and "--record-max-steps" in rec["stopped"]
        assert rec["actions"] == [a["action"] for a in answers[:3]]
        assert rec["rewards"] == [1.0, 2.0, None]  # the report on step 2's action came with a step not kept


def test_expiry_and_shutdown_write_the_recordings(make_server, store, clock, tmp_path):
    server = make_server(clock=clock, redis_url=store, record_dir=tmp_path, idle_timeout_s=60)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = _create(http)
        _act(http, sid, 0)
        _act(http, sid, 1, reward=4.0)
        clock.advance(61)
        assert server.run(server.core.sweep()) == 1
        # The sweep's write finishes before it answers with a Redis store; in memory it runs beside: wait for it.
        server.run(_drained(server.core))
        rec = read_recording(tmp_path / f"{sid}.json")
        assert rec.meta["ended_by"] == "expiry" and rec.steps == 2 and rec.arrays["rewards"][0] == 4.0
        kept = _create(http, seed=8)
        _act(http, kept, 0)
    server.stop()
    if store is None:  # sessions in memory end with the process: their recordings are written
        assert read_recording(tmp_path / f"{kept}.json").meta["ended_by"] == "shutdown"
    else:  # Redis keeps them for another replica
        assert not (tmp_path / f"{kept}.json").exists()


async def _drained(core) -> None:
    import asyncio

    await asyncio.gather(*core._archives)


def test_record_share_draws_sessions_by_their_id(make_server, tmp_path):
    server = make_server(record_dir=tmp_path, record_share=0.5)
    ids = [f"share-{i}" for i in range(24)]
    with httpx.Client(base_url=server.url, timeout=30) as http:
        got = []
        for sid in ids:
            r = http.post("/sessions", json={"model": MODEL, "goal": 0, "session_id": sid})
            again = http.post("/sessions", json={"model": MODEL, "goal": 0, "session_id": sid})
            assert r.status_code == 201 and again.json()["recording"] == r.json()["recording"]
            got.append(r.json()["recording"])
        assert got == [record_drawn(sid, 0.5) for sid in ids] and 0 < sum(got) < len(ids)
        r = http.post(
            "/sessions", json={"model": MODEL, "goal": 0, "record": False, "session_id": ids[got.index(True)]}
        )
        assert r.status_code == 409  # the id is taken by a session created otherwise (recorded)


@pytest.mark.parametrize("transport", ["rest", "grpc", "stream"])
def test_python_clients_record_report_and_read_the_timeline(make_server, tmp_path, transport):
    from gmt.client.grpc import GrpcClient
    from gmt.client.rest import RestClient

    server = make_server(record_dir=tmp_path)
    if transport == "rest":
        client = RestClient(server.url)
    else:
        client = GrpcClient(server.target, stream=transport == "stream")
    with client, httpx.Client(base_url=server.url, timeout=30) as http:
        s = client.create_session(MODEL, "low", seed=2, record=True)
        other = client.create_session(MODEL, 0, seed=3, record=True)
        assert s.info.recording and other.info.recording
        s.act(OBS[0])
        s.act(OBS[1], reward=0.5, terminated=False, info={"x_velocity": 0.25})
        assert s.set_goal("high", blend_steps=3).effective_step == 2
        s.act(OBS[2], reward=0.75)
        tl = s.timeline()
        assert (tl.step, tl.entries) == (3, 2)
        assert [(e.step, e.goal, e.given, e.blend_steps) for e in tl.goals] == [
            (0, 0, {"goal": "low"}, 0),
            (2, 2, {"goal": "high"}, 3),
        ]
        assert tl.goals[1].by == {"rest": "rest", "grpc": "grpc", "stream": "stream"}[transport]
        out = client.act_many(
            [(other.id, OBS[0]), (s.id, OBS[3], {"reward": 1.0, "info": {"x_velocity": 2.0}})]
        )
        assert [r.step for r in out] == [0, 3]
        rec = http.get(f"/sessions/{s.id}/recording").json()
        assert rec["rewards"] == [0.5, 0.75, 1.0, None] and rec["infos"]["x_velocity"] == [
            0.25,
            None,
            2.0,
            None,
        ]
        if transport == "rest":
            assert client.get_recording(s.id).steps == 4
        s.close()
        other.close()
    assert {p.name for p in tmp_path.glob("*.json")} == {f"{s.id}.json", f"{other.id}.json"}


def test_recordings_are_named_by_the_whole_id_and_never_overwritten(make_server, tmp_path):
    """Ids that differ after their last dot get their own files (`Path.with_suffix` once cut both to `bot-7`), a
    re-created id gets a new file beside the first one's, and `gmt data import-sessions` reads them all."""
    from gmt.common.recording import find_recordings
    from gmt.model.data.served import import_sessions

    rec_dir = tmp_path / "rec"
    server = make_server(record_dir=rec_dir)
    plan = [("bot-7.episode-12", 3), ("bot-7.episode-13", 4), ("bot-7.episode-12", 2), (".hidden", 2)]
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for sid, steps in plan:
            assert _create(http, session_id=sid) == sid
            for t in range(steps):
                _act(http, sid, t)
            assert http.delete(f"/sessions/{sid}").status_code == 204
    files = find_recordings([rec_dir])
    got = sorted((read_recording(p).meta["session_id"], read_recording(p).steps) for p in files)
    assert got == sorted(plan), [p.name for p in files]
    assert (rec_dir / "bot-7.episode-12.json").is_file() and (rec_dir / "bot-7.episode-13.json").is_file()
    done = import_sessions([rec_dir], "gmt/halfcheetah/served-v0", tmp_path / "minari")
    assert (done.recordings, done.episodes, done.transitions) == (4, 4, sum(n for _, n in plan) - 4)


def test_a_rewritten_recording_of_one_session_replaces_its_own_file(tmp_path):
    """A retried close writes the same session again (same id and creation time): it replaces its own file, so
    an import never counts its steps twice; another session with that id gets the next name."""
    from gmt.common.recording import COLUMNS, FORMAT, VERSION, find_recordings

    def rec(created_at: float, steps: int) -> Recording:
        arrays = {c: np.zeros(steps) for c in COLUMNS}
        return Recording(
            {"format": FORMAT, "version": VERSION, "session_id": "a.b", "created_at": created_at}, arrays
        )

    first = rec(1.0, 2).write(tmp_path)
    assert rec(1.0, 3).write(tmp_path) == first == tmp_path / "a.b.json"
    assert rec(2.0, 1).write(tmp_path) == tmp_path / "a.b@2.json"
    got = sorted(
        (read_recording(p).meta["created_at"], read_recording(p).steps) for p in find_recordings([tmp_path])
    )
    assert got == [(1.0, 3), (2.0, 1)]
