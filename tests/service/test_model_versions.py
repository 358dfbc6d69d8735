"""Model versions on real servers (docs/models.md): load and promote a new version without a restart, sessions
pinned to the version they started on, canaries, draining that frees the old version, bad checkpoints refused,
management authorised, and a replica that adopts a session of a version it lacks."""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import threading
import time
import weakref
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest
from service_harness import OBS_DIM

from gmt.model.checkpoint import load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.model.fixtures import tiny_checkpoint
from gmt.service import core_versions as core_module
from gmt.service.model_state import STATE_FILE
from gmt.v1 import admin_pb2 as apb
from gmt.v1 import admin_pb2_grpc, policy_pb2_grpc
from gmt.v1 import policy_pb2 as pb

MODEL = "tiny-gmt"
N = 8


@pytest.fixture(scope="module")
def roots(tmp_path_factory):
    """checkpoints/ serving tiny-gmt v1 (calibrated: sampled actions), and releases of the same model with other
    weights one level down (not served at startup)."""
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / MODEL, calibrated=True, seed=0)
    tiny_checkpoint(root / "releases" / "v2", calibrated=True, seed=1)
    tiny_checkpoint(root / "releases" / "v3", calibrated=True, seed=2)
    return root


@pytest.fixture(autouse=True)
def fresh_state(roots):
    """Each test starts from the versions under the roots: forget what an earlier test promoted (a restart keeps
    it: test_model_state.py)."""
    (roots / STATE_FILE).unlink(missing_ok=True)


@pytest.fixture(scope="module")
def versions(roots):
    return {
        "v1": load_checkpoint(roots / MODEL).version,
        "v2": load_checkpoint(roots / "releases" / "v2").version,
        "v3": load_checkpoint(roots / "releases" / "v3").version,
    }


def wait_for(condition, what: str, timeout_s: float = 30.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = condition()
        if got:
            return got
        time.sleep(0.02)
    raise AssertionError(f"{what}: not within {timeout_s} s")


def create(http, seed: int, **kw) -> dict:
    r = http.post("/sessions", json={"model": MODEL, "goal": seed % 3, "seed": seed, **kw})
    assert r.status_code == 201, r.text
    return r.json()


def act(http, sid: str, obs, step: int) -> list[float]:
    r = http.post(f"/sessions/{sid}/act", json={"observation": np.asarray(obs).tolist(), "step": step})
    assert r.status_code == 200, r.text
    return r.json()["action"]


def versions_of(http) -> dict:
    (m,) = [m for m in http.get("/models").json()["models"] if m["name"] == MODEL]
    return m


def test_v2_rolls_in_while_v1_sessions_continue_exactly_and_v1_is_freed(make_server, roots, versions):
    """8 sessions on v1, v2 loaded and promoted, 8 new sessions on v2, the old 8 go on with the actions of twins on
    a server that only ever had v1; v1 drained is unloaded (its engine freed) when its last session closes."""
    live, twin = make_server(checkpoints=[roots]), make_server(checkpoints=[roots])
    rng = np.random.default_rng(11)
    obs = rng.normal(size=(2 * N, 10, OBS_DIM)).astype(np.float32)
    with (
        httpx.Client(base_url=live.url, timeout=30) as http,
        httpx.Client(base_url=twin.url, timeout=30) as ref,
    ):
        old = [create(http, seed=i) for i in range(N)]
        twins = [create(ref, seed=i) for i in range(N)]
        assert {s["model_version"] for s in old + twins} == {versions["v1"]}
        got = {
            s["session_id"]: [act(http, s["session_id"], obs[i, t], t) for t in range(5)]
            for i, s in enumerate(old)
        }

        r = http.post(f"/models/{MODEL}/versions", json={"path": "releases/v2"})
        assert r.status_code == 201, r.text
        assert r.json()["version"] == versions["v2"] and r.json()["state"] == "serving"
        r = http.put(f"/models/{MODEL}/default", json={"version": versions["v2"]})
        assert r.status_code == 200, r.text
        assert r.json()["default_version"] == versions["v2"]

        new = [create(http, seed=i) for i in range(N)]
        assert {s["model_version"] for s in new} == {versions["v2"]}
        v2_engine = PolicyEngine(load_checkpoint(roots / "releases" / "v2"))
        for i, s in enumerate(new):
            ctx = v2_engine.new_context(i % 3, seed=i)
            for t in range(5):
                want = v2_engine.act([ctx], [obs[N + i, t]])[0]
                np.testing.assert_array_equal(np.float32(act(http, s["session_id"], obs[N + i, t], t)), want)
        for i, s in enumerate(old):
            got[s["session_id"]] += [act(http, s["session_id"], obs[i, t], t) for t in range(5, 10)]
        for i, (s, t) in enumerate(zip(old, twins, strict=True)):
            want = [act(ref, t["session_id"], obs[i, k], k) for k in range(10)]
            assert got[s["session_id"]] == want, f"session {i} left its version"
        # The two versions answer differently: a session that had moved to v2 would show.
        ctx = v2_engine.new_context(0, seed=0)
        on_v2 = [v2_engine.act([ctx], [obs[0, t]])[0].tolist() for t in range(5)]
        assert not np.allclose(got[old[0]["session_id"]][:5], on_v2)

        m = versions_of(http)
        table = {v["version"]: (v["state"], v["sessions"]) for v in m["versions"]}
        assert table == {versions["v1"]: ("serving", N), versions["v2"]: ("serving", N)}

        v1 = live.core.registry.version(MODEL, versions["v1"])
        engine, weights = weakref.ref(v1.engine), weakref.ref(v1.checkpoint.model)
        del v1
        r = http.post(f"/models/{MODEL}/versions/{versions['v1']}/drain")
        assert r.status_code == 200, r.text
        assert {v["version"]: v["state"] for v in r.json()["versions"]}[versions["v1"]] == "draining"
        r = http.post("/sessions", json={"model": MODEL, "goal": 0, "version": versions["v1"]})
        assert r.status_code == 409 and "draining" in r.json()["error"]["message"]
        for s in old[:-1]:
            assert http.delete(f"/sessions/{s['session_id']}").status_code == 204
        assert act(http, old[-1]["session_id"], obs[N - 1, 0], 10)  # the last one still acts on v1
        assert versions["v1"] in [v["version"] for v in versions_of(http)["versions"]]
        assert http.delete(f"/sessions/{old[-1]['session_id']}").status_code == 204
        wait_for(
            lambda: versions["v1"] not in [v["version"] for v in versions_of(http)["versions"]], "v1 unloaded"
        )

        def freed() -> bool:
            live.run(_collect())
            return engine() is None and weights() is None

        wait_for(freed, "v1's engine and weights freed")
        assert [
            s["model_version"] for s in [http.get(f"/sessions/{n['session_id']}").json() for n in new]
        ] == [versions["v2"]] * N
        metrics = http.get("/metrics").text
        assert f'gmt_batch_size_count{{model="{MODEL}",version="{versions["v2"]}"}}' in metrics
        assert "gmt_model_versions_loaded 1.0" in metrics


async def _collect() -> None:
    gc.collect()


def test_a_canary_gets_its_share_of_new_sessions(make_server, roots, versions, record_property):
    """share 0.25: a hash of the session id (and the canary version) decides, so the same id always gets the same
    version, on any replica; 400 ids give 25% +- 5%."""
    server = make_server(checkpoints=[roots])
    with httpx.Client(base_url=server.url, timeout=30) as http:
        assert http.post(f"/models/{MODEL}/versions", json={"path": "releases/v2"}).status_code == 201
        r = http.put(f"/models/{MODEL}/default", json={"version": versions["v2"], "share": 0.25})
        assert r.status_code == 200, r.text
        assert r.json()["canary"] == {"version": versions["v2"], "share": 0.25}
        assert r.json()["default_version"] == versions["v1"]
        got = [create(http, seed=0, session_id=f"canary-{i}")["model_version"] for i in range(400)]
        share = got.count(versions["v2"]) / len(got)
        record_property("canary_share", share)
        print(f"canary share measured: {share:.4f} of 400 sessions")
        assert 0.20 <= share <= 0.30, share
        assert set(got) == {versions["v1"], versions["v2"]}
        again = create(
            http, seed=0, session_id="canary-7"
        )  # a retried create: the same session, same version
        assert again["model_version"] == got[7]
        # Over gRPC too: the version table, and a session naming its version.
        with grpc.insecure_channel(server.target) as ch:
            stub = policy_pb2_grpc.PolicyServiceStub(ch)
            info = stub.GetModel(pb.GetModelRequest(name=MODEL))
            assert info.default_version == versions["v1"]
            assert (info.canary.version, info.canary.share) == (versions["v2"], 0.25)
            assert {v.version: v.sessions for v in info.versions} == {
                versions["v1"]: got.count(versions["v1"]),
                versions["v2"]: got.count(versions["v2"]),
            }
            s = stub.CreateSession(
                pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=0), version=versions["v1"])
            )
            assert s.model_version == versions["v1"]
        # Promoting the default again (share 1) ends the canary.
        r = http.put(f"/models/{MODEL}/default", json={"version": versions["v1"]})
        assert r.json()["canary"] is None
        assert create(http, seed=0, session_id="canary-after")["model_version"] == versions["v1"]


def _corrupt(root, name: str, how: str) -> str:
    d = root / "bad" / name
    tiny_checkpoint(d, calibrated=True, seed=5)
    meta = json.loads((d / "gmt.json").read_text())
    if how == "missing":
        (d / "model.safetensors").unlink()
    elif how == "pickle":
        (d / "model.safetensors").write_bytes(b"\x80\x04\x95" + b"\0" * 64)
    elif how == "shapes":
        meta["model"]["n_embd"] = 64
        (d / "gmt.json").write_text(json.dumps(meta))
    elif how == "metadata":
        (d / "gmt.json").write_text('{"format": "gmt-checkpoint", "format_version": 1, "model": ')
    elif how == "fields":
        del meta["env"]
        (d / "gmt.json").write_text(json.dumps(meta))
    elif how == "goals":
        meta["goals"] = []
        (d / "gmt.json").write_text(json.dumps(meta))
    elif how == "mode":  # a discrete mode for continuous actions (was a 500: the engine's ValueError)
        meta["default_action_mode"] = "argmax"
        (d / "gmt.json").write_text(json.dumps(meta))
    return f"bad/{name}"


def test_bad_checkpoints_are_refused_and_leave_the_served_versions_alone(
    make_server, roots, versions, tmp_path
):
    server = make_server(checkpoints=[roots])
    cases = [
        ("missing", 400, "has no model.safetensors"),
        ("pickle", 400, "pickle stream"),
        ("shapes", 400, "wrong tensor shapes"),
        ("metadata", 400, "not valid JSON"),
        ("fields", 400, "missing field 'env'"),
        ("goals", 400, "0 goals listed for a model of 3"),
        ("mode", 400, "default_action_mode 'argmax' is not one of"),
    ]
    with httpx.Client(base_url=server.url, timeout=30) as http:
        before = http.get("/models").json()
        sid = create(http, seed=3)["session_id"]
        obs = np.zeros(OBS_DIM, np.float32)
        for i, (how, status, words) in enumerate(cases):
            r = http.post(f"/models/{MODEL}/versions", json={"path": _corrupt(roots, how, how)})
            assert r.status_code == status and words in r.json()["error"]["message"], (how, r.text)
            assert r.json()["error"]["code"] == "invalid_argument"
            act(http, sid, obs, i)  # the served version answers meanwhile
        pt = roots / "bad" / "weights.pt"
        pt.write_bytes(b"\x80\x04")
        r = http.post(f"/models/{MODEL}/versions", json={"path": "bad/weights.pt"})
        assert (
            r.status_code == 400 and "pickle-based formats are not accepted" in r.json()["error"]["message"]
        )
        r = http.post(f"/models/{MODEL}/versions", json={"path": "releases/v2", "fingerprint": "0" * 12})
        assert r.status_code == 400 and f"not the expected {'0' * 12}" in r.json()["error"]["message"]
        # A checkpoint that names a version already loaded from other weights.
        d = roots / "bad" / "same-name"
        tiny_checkpoint(d, calibrated=True, seed=9)
        meta = json.loads((d / "gmt.json").read_text())
        (d / "gmt.json").write_text(json.dumps({**meta, "version": versions["v1"]}))
        r = http.post(f"/models/{MODEL}/versions", json={"path": "bad/same-name"})
        assert r.status_code == 409 and "already loaded with fingerprint" in r.json()["error"]["message"]
        cartpole = roots / "bad" / "cartpole"
        tiny_checkpoint(cartpole, env_id="CartPole-v1")
        r = http.post(f"/models/{MODEL}/versions", json={"path": "bad/cartpole"})
        assert r.status_code == 400 and "env_id differs" in r.json()["error"]["message"]
        outside = tmp_path / "elsewhere"
        tiny_checkpoint(outside)
        for path in (str(outside), "../" * 12 + str(outside), "/etc"):
            r = http.post(f"/models/{MODEL}/versions", json={"path": path})
            assert r.status_code == 403 and "not under the checkpoint roots" in r.json()["error"]["message"]
        r = http.post(f"/models/{MODEL}/versions", json={})
        assert r.status_code == 400 and "path" in r.json()["error"]["message"]
        # A name longer than the file system allows (was a 500: the OSError of Path.exists), a path past PATH_MAX.
        r = http.post(f"/models/{MODEL}/versions", json={"path": "y" * 300})
        assert r.status_code == 400 and "cannot name a checkpoint directory" in r.json()["error"]["message"]
        r = http.post(f"/models/{MODEL}/versions", json={"path": "y/" * 3000})
        assert r.status_code == 400 and "at most 4096" in r.json()["error"]["message"]
        r = http.post(f"/models/{MODEL}/versions", json={"path": "releases/nope"})  # nowhere at all
        assert r.status_code == 400 and "no checkpoint 'releases/nope' under" in r.json()["error"]["message"]
        assert http.get("/models").json() == {
            **before,
            "models": [
                {**m, "versions": [{**v, "sessions": 1} for v in m["versions"]]} for m in before["models"]
            ],
        }
        with grpc.insecure_channel(server.target) as ch:
            admin = admin_pb2_grpc.ModelAdminStub(ch)
            with pytest.raises(grpc.RpcError) as e:
                admin.LoadVersion(
                    apb.LoadVersionRequest(name=MODEL, path=_corrupt(roots, "g-shapes", "shapes"))
                )
            assert (
                e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
                and "wrong tensor shapes" in e.value.details()
            )
            with pytest.raises(grpc.RpcError) as e:
                admin.LoadVersion(apb.LoadVersionRequest(name=MODEL, path="/etc"))
            assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED
            with pytest.raises(grpc.RpcError) as e:
                admin.LoadVersion(apb.LoadVersionRequest(name=MODEL, path="y" * 300))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "cannot name" in e.value.details()
            # Names an HTTP client rewrites in a path (GET /models/.. is GET /): the model would be unreachable.
            for name in (".", ".."):
                with pytest.raises(grpc.RpcError) as e:
                    admin.LoadVersion(apb.LoadVersionRequest(name=name, path="releases/v2"))
                assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "rewrite" in e.value.details()


def test_management_over_grpc_and_unload_rules(make_server, roots, versions):
    server = make_server(checkpoints=[roots])
    with httpx.Client(base_url=server.url, timeout=30) as http, grpc.insecure_channel(server.target) as ch:
        admin = admin_pb2_grpc.ModelAdminStub(ch)
        loaded = admin.LoadVersion(apb.LoadVersionRequest(name=MODEL, path="releases/v3"))
        assert loaded.version.version == versions["v3"] and loaded.version.state == "serving"
        again = admin.LoadVersion(apb.LoadVersionRequest(name=MODEL, path="releases/v3"))  # idempotent
        assert again.version.fingerprint == loaded.version.fingerprint
        sid = create(http, seed=1, version=versions["v3"])["session_id"]
        with pytest.raises(grpc.RpcError) as e:
            admin.Unload(apb.UnloadRequest(name=MODEL, version=versions["v3"]))
        assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "1 session(s)" in e.value.details()
        with pytest.raises(grpc.RpcError) as e:
            admin.Drain(apb.DrainRequest(name=MODEL, version=versions["v1"]))
        assert "promote another version" in e.value.details()
        info = admin.Promote(apb.PromoteRequest(name=MODEL, version=versions["v3"], share=0.5))
        assert (info.canary.version, info.default_version) == (versions["v3"], versions["v1"])
        info = admin.Unload(apb.UnloadRequest(name=MODEL, version=versions["v3"], force=True))
        assert [v.version for v in info.versions] == [versions["v1"]] and not info.HasField("canary")
        r = http.post(f"/sessions/{sid}/act", json={"observation": [0.0] * OBS_DIM})
        assert r.status_code == 409 and versions["v3"] in r.json()["error"]["message"]
        assert "unloaded from this server" in r.json()["error"]["message"]
        r = http.delete(f"/models/{MODEL}/versions/nope")
        assert r.status_code == 404 and "has no version 'nope'" in r.json()["error"]["message"]
        r = http.put(f"/models/{MODEL}/default", json={"version": versions["v1"], "share": 1.5})
        assert r.status_code == 400 and "share" in r.json()["error"]["message"]
        body = json.dumps({"version": versions["v1"], "share": 0.5}).replace("0.5", "NaN")
        r = http.put(f"/models/{MODEL}/default", content=body, headers={"content-type": "application/json"})
        assert (
            r.status_code == 400 and "share: Input should be a finite number" in r.json()["error"]["message"]
        )


def test_a_version_unloaded_with_force_and_loaded_again_continues_its_sessions_exactly(
    make_server, roots, versions
):
    """A session whose version was unloaded with force fails meanwhile (409); once the version is loaded again it
    continues exactly where it stopped, on its own history, beside a session created on the reloaded engine (which
    may hold the same slot index in its new pool)."""
    server = make_server(checkpoints=[roots])
    engine = PolicyEngine(load_checkpoint(roots / "releases" / "v3"))
    obs = np.random.default_rng(13).normal(size=(2, 6, OBS_DIM)).astype(np.float32)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        assert http.post(f"/models/{MODEL}/versions", json={"path": "releases/v3"}).status_code == 201
        old, ref_old = (
            create(http, seed=1, version=versions["v3"])["session_id"],
            engine.new_context(1, seed=1),
        )
        for t in range(3):
            want = engine.act([ref_old], [obs[0, t]])[0]
            np.testing.assert_array_equal(np.float32(act(http, old, obs[0, t], t)), want)
        r = http.delete(f"/models/{MODEL}/versions/{versions['v3']}", params={"force": "true"})
        assert r.status_code == 200, r.text
        r = http.post(f"/sessions/{old}/act", json={"observation": obs[0, 3].tolist(), "step": 3})
        assert r.status_code == 409 and "unloaded from this server" in r.json()["error"]["message"]
        assert http.post(f"/models/{MODEL}/versions", json={"path": "releases/v3"}).status_code == 201
        new, ref_new = (
            create(http, seed=2, version=versions["v3"])["session_id"],
            engine.new_context(2, seed=2),
        )
        for t in range(3):
            for sid, ref, o, step in ((new, ref_new, obs[1, t], t), (old, ref_old, obs[0, 3 + t], 3 + t)):
                want = engine.act([ref], [o])[0]
                np.testing.assert_array_equal(np.float32(act(http, sid, o, step)), want)


def test_management_is_authorised(make_server, roots):
    body = {"path": "releases/v2"}
    open_server = make_server(checkpoints=[roots])
    with httpx.Client(base_url=open_server.url, timeout=30) as http:
        # No token at all: this machine only, never through a proxy.
        r = http.post(f"/models/{MODEL}/versions", json=body, headers={"X-Forwarded-For": "203.0.113.9"})
        assert r.status_code == 403 and "--admin-token" in r.json()["error"]["message"]
        assert http.post(f"/models/{MODEL}/versions", json=body).status_code == 201
    with grpc.insecure_channel(open_server.target) as ch:
        admin = admin_pb2_grpc.ModelAdminStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            admin.Drain(
                apb.DrainRequest(name=MODEL, version="x"), metadata=(("x-forwarded-for", "203.0.113.9"),)
            )
        assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED

    bearer = make_server(checkpoints=[roots], auth_token="user")
    with httpx.Client(base_url=bearer.url, timeout=30) as http:
        assert http.post(f"/models/{MODEL}/versions", json=body).status_code == 401
        r = http.post(f"/models/{MODEL}/versions", json=body, headers={"Authorization": "Bearer user"})
        assert r.status_code == 201

    both = make_server(checkpoints=[roots], auth_token="user", admin_token="root")
    user, root = {"Authorization": "Bearer user"}, {"Authorization": "Bearer root"}
    with httpx.Client(base_url=both.url, timeout=30) as http:
        r = http.post(f"/models/{MODEL}/versions", json=body, headers=user)
        assert r.status_code == 401 and "admin token" in r.json()["error"]["message"]
        assert http.post(f"/models/{MODEL}/versions", json=body, headers=root).status_code == 201
        assert (
            http.get("/models", headers=root).status_code == 200
        )  # the admin key: every session (test_keys)
        assert http.get("/models", headers=user).status_code == 200
    with grpc.insecure_channel(both.target) as ch:
        admin = admin_pb2_grpc.ModelAdminStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            admin.Drain(
                apb.DrainRequest(name=MODEL, version="x"), metadata=(("authorization", "Bearer user"),)
            )
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        with pytest.raises(grpc.RpcError) as e:
            admin.Drain(
                apb.DrainRequest(name=MODEL, version="x"), metadata=(("authorization", "Bearer root"),)
            )
        assert e.value.code() == grpc.StatusCode.NOT_FOUND  # authorised: the version does not exist


def test_tokenless_management_refuses_web_pages(make_server, roots, versions):
    """DNS rebinding: a page of another site, its name rebound to 127.0.0.1, sends its own Host; a cross-origin
    page sends its Origin / Referer. Without a token both are refused (403 naming the header); a loopback Host
    without an Origin still manages, and a token makes the headers irrelevant."""
    body = {"path": "releases/v2"}
    server = make_server(checkpoints=[roots])
    port = server.url.rsplit(":", 1)[1]
    promote = {"version": versions["v1"]}
    with httpx.Client(base_url=server.url, timeout=30) as http:
        refused = [
            ({"Host": f"attacker.example:{port}"}, "Host 'attacker.example:"),
            (
                {"Host": f"attacker.example:{port}", "Origin": f"http://attacker.example:{port}"},
                "DNS rebinding",
            ),
            ({"Origin": "http://attacker.example"}, "Origin 'http://attacker.example'"),
            ({"Origin": "null"}, "Origin 'null'"),
            ({"Referer": "http://attacker.example/page"}, "Referer"),
            ({"Origin": "http://localhost:1"}, "another origin"),  # another port: another origin
        ]
        for headers, named in refused:
            for r in (
                http.post(f"/models/{MODEL}/versions", json=body, headers=headers),
                http.put(f"/models/{MODEL}/default", json=promote, headers=headers),
                http.delete(f"/models/{MODEL}/versions/{versions['v2']}", headers=headers),
            ):
                assert r.status_code == 403, (headers, r.text)
                assert (
                    r.json()["error"]["code"] == "permission_denied" and named in r.json()["error"]["message"]
                )
        assert [v["version"] for v in versions_of(http)["versions"]] == [versions["v1"]]  # nothing loaded
        for host in (f"localhost:{port}", f"127.0.0.1:{port}", "localhost", f"[::1]:{port}"):
            r = http.put(f"/models/{MODEL}/default", json=promote, headers={"Host": host})
            assert r.status_code == 200, (host, r.text)
        same_origin = {"Origin": server.url, "Referer": f"{server.url}/docs"}
        assert http.post(f"/models/{MODEL}/versions", json=body, headers=same_origin).status_code == 201
    with_token = make_server(checkpoints=[roots], admin_token="root")
    with httpx.Client(base_url=with_token.url, timeout=30) as http:
        foreign = {
            "Host": "attacker.example",
            "Origin": "http://attacker.example",
            "Authorization": "Bearer root",
        }
        assert http.put(f"/models/{MODEL}/default", json=promote, headers=foreign).status_code == 200


def test_acts_are_answered_while_a_version_loads(make_server, roots, monkeypatch):
    """The load runs in a thread: held inside it, the server still answers acts."""
    server = make_server(checkpoints=[roots])
    inside, release = threading.Event(), threading.Event()
    load_model = core_module.load_model

    def slow_load(*args, **kw):
        inside.set()
        assert release.wait(30), "the test never released the load"
        return load_model(*args, **kw)

    monkeypatch.setattr(core_module, "load_model", slow_load)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        sid = create(http, seed=2)["session_id"]
        out = {}
        loader = threading.Thread(
            target=lambda: out.update(r=http.post(f"/models/{MODEL}/versions", json={"path": "releases/v2"}))
        )
        loader.start()
        assert inside.wait(30)
        with httpx.Client(base_url=server.url, timeout=5) as other:
            for t in range(20):
                act(other, sid, np.zeros(OBS_DIM), t)
        assert loader.is_alive()  # the load was still running while those 20 acts were answered
        release.set()
        loader.join(30)
        assert out["r"].status_code == 201, out["r"].text


def test_a_replica_adopts_a_session_of_a_version_it_lacks(
    make_server, roots, versions, redis_clean, tmp_path
):
    """Two replicas share Redis; one loads v2 and starts sessions on it, the other (which never loaded v2) continues
    them exactly, loading v2 from its checkpoint roots by fingerprint. A replica without the checkpoint says which
    version it lacks."""
    a = make_server(checkpoints=[roots], redis_url=redis_clean)
    b = make_server(checkpoints=[roots], redis_url=redis_clean)
    bare_root = tmp_path / "only-v1"
    tiny_checkpoint(bare_root / MODEL, calibrated=True, seed=0)
    c = make_server(checkpoints=[bare_root], redis_url=redis_clean)
    obs = np.random.default_rng(5).normal(size=(6, OBS_DIM)).astype(np.float32)
    engine = PolicyEngine(load_checkpoint(roots / "releases" / "v2"))
    with (
        httpx.Client(base_url=a.url, timeout=30) as ha,
        httpx.Client(base_url=b.url, timeout=30) as hb,
        httpx.Client(base_url=c.url, timeout=30) as hc,
    ):
        assert ha.post(f"/models/{MODEL}/versions", json={"path": "releases/v2"}).status_code == 201
        sid = create(ha, seed=4, version=versions["v2"])["session_id"]
        ctx = engine.new_context(1, seed=4)
        want = [engine.act([ctx], [o])[0] for o in obs]
        got = [act(ha, sid, obs[t], t) for t in range(3)] + [act(hb, sid, obs[t], t) for t in range(3, 6)]
        np.testing.assert_array_equal(np.float32(got), np.float32(want))
        assert hb.get(f"/sessions/{sid}").json()["model_version"] == versions["v2"]
        b_table = {v["version"]: v["state"] for v in versions_of(hb)["versions"]}
        assert b_table == {
            versions["v1"]: "serving",
            versions["v2"]: "draining",
        }  # adopted: for its sessions only
        r = hc.post(f"/sessions/{sid}/act", json={"observation": obs[0].tolist(), "step": 6})
        assert r.status_code == 409 and r.json()["error"]["code"] == "failed_precondition"
        assert f"version {versions['v2']!r} of model {MODEL!r} is not loaded" in r.json()["error"]["message"]


def test_load_and_unload_under_256_sessions_give_no_errors(
    make_server, roots, versions, tmp_path, record_property
):
    """256 sessions act without pause from another process while versions are loaded, promoted, run as a canary,
    unloaded and drained: every act is answered, and v1 goes once the load loop closes its sessions."""
    server = make_server(checkpoints=[roots], max_sessions=1024)
    stop = tmp_path / "stop"
    loop = subprocess.Popen(
        [
            sys.executable,
            str(Path(__file__).with_name("load_loop.py")),
            server.url,
            MODEL,
            "256",
            str(stop),
            "120",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert loop.stdout.readline().strip() == "ready"
        with httpx.Client(base_url=server.url, timeout=60) as http:
            calls = [
                ("POST", f"/models/{MODEL}/versions", {"path": "releases/v2"}),
                ("PUT", f"/models/{MODEL}/default", {"version": versions["v2"]}),
                ("POST", f"/models/{MODEL}/versions", {"path": "releases/v3"}),
                ("PUT", f"/models/{MODEL}/default", {"version": versions["v3"], "share": 0.5}),
                ("DELETE", f"/models/{MODEL}/versions/{versions['v3']}", None),
                ("POST", f"/models/{MODEL}/versions/{versions['v1']}/drain", None),
            ]
            before = acts_answered(http)
            for method, path, body in calls:
                r = http.request(method, path, json=body)
                assert r.status_code in (200, 201), r.text
                # The load goes on after each change: the server answers more acts before the next call. This
                # waits on the counter, not on time: on a busy 2-core machine six quick calls can all land
                # between two acts of the load process.
                seen = acts_answered(http)
                wait_for(lambda seen=seen: acts_answered(http) > seen, f"acts answered after {method} {path}")
            during = acts_answered(http) - before
            sessions = {v["version"]: v["sessions"] for v in versions_of(http)["versions"]}
            assert sessions == {versions["v1"]: 256, versions["v2"]: 0}
            stop.touch()
            out, _ = loop.communicate(timeout=120)
            report = json.loads(out.strip().splitlines()[-1])
            wait_for(
                lambda: [v["version"] for v in versions_of(http)["versions"]] == [versions["v2"]],
                "v1 unloaded",
            )
    finally:
        stop.touch()
        if loop.poll() is None:
            loop.kill()
            loop.wait(30)
    record_property("load_report", report)
    print(
        f"256 sessions under load and unload: {report}; acts answered during the 6 management calls: {during}"
    )
    assert report["errors"] == {} and report["versions"] == [versions["v1"]]
    assert during > 0  # the load went on while the versions changed


def acts_answered(http) -> float:
    """Acts the server answered 200 (its request metrics)."""
    line = 'gmt_request_duration_seconds_count{code="200",method="act",transport="rest"} '
    return float(next(x for x in http.get("/metrics").text.splitlines() if x.startswith(line)).split()[-1])


def test_the_only_version_a_server_serves_is_not_unloaded(make_server, roots, versions):
    """A fuzzer with management rights once unloaded the only model (`?force=true`): the server then answered
    nothing. Now that unload answers 409 and the version goes on serving."""
    s = make_server(checkpoints=[roots / MODEL])
    with httpx.Client(base_url=s.url, timeout=30) as http:
        r = http.delete(f"/models/{MODEL}/versions/{versions['v1']}", params={"force": "true"})
        assert r.status_code == 409, r.text
        assert "only version this server serves" in r.json()["error"]["message"]
        assert http.get("/readyz").status_code == 200
        create(http, seed=1)
