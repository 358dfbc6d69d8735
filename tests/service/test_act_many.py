"""Many sessions in one call (`POST /act`, gRPC `ActBatch`): the same actions as one-by-one `act`, per-item
errors that leave every other item (and the failed session) alone, and one forward pass per call."""

import asyncio
import base64
import threading
import time

import grpc
import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from service_harness import make_settings

from gmt.model.checkpoint import load_checkpoint
from gmt.service.batcher import SPLIT_FROM
from gmt.service.core import Core
from gmt.service.redis_store import store_for
from gmt.service.views import MAX_ACT_ITEMS
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

# (model, goal, seed, observation size) of the sessions each parity test steps together: a calibrated
# (sampled, seeded) model, a deterministic one and a discrete one, all in one call.
SESSIONS = [
    ("tiny-sampled", 0, 11, 17),
    ("tiny-sampled", 2, 12, 17),
    ("tiny-sampled", 2, 13, 17),
    ("tiny-gmt", 1, 14, 17),
    ("tiny-gmt", 2, 15, 17),
    ("tiny-cartpole", 0, 16, 4),
]
STEPS = 4


def observations_for(sizes, steps, seed=5) -> list[list[np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [[rng.normal(size=n).astype(np.float32) for n in sizes] for _ in range(steps)]


def rest_create(http, model="tiny-gmt", goal=0, seed=None) -> str:
    body = {"model": model, "goal": goal} | ({} if seed is None else {"seed": seed})
    r = http.post("/sessions", json=body)
    assert r.status_code == 201, r.text
    return r.json()["session_id"]


def rest_act(http, sid, obs) -> httpx.Response:
    return http.post(f"/sessions/{sid}/act", json={"observation": np.asarray(obs).tolist()})


def rest_act_many(http, items) -> httpx.Response:
    body = {"requests": [{"session_id": s, "observation": np.asarray(o).tolist()} for s, o in items]}
    return http.post("/act", json=body)


def grpc_create(stub, model="tiny-gmt", goal=0, seed=None) -> str:
    req = pb.CreateSessionRequest(model=model, goal=pb.GoalSelector(id=goal))
    if seed is not None:
        req.seed = seed
    return stub.CreateSession(req).session_id


def grpc_request(sid, obs) -> pb.ActRequest:
    return pb.ActRequest(session_id=sid, values=pb.FloatVector(values=np.asarray(obs).tolist()))


def metric_samples(http, name: str) -> dict:
    """{(sample name, labels as a sorted tuple): value} of one metric family from GET /metrics."""
    out = {}
    for fam in text_string_to_metric_families(http.get("/metrics").text):
        if fam.name == name:
            for s in fam.samples:
                out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


# ----- the same actions as one-by-one act ----------------------------------------------------------------------
def test_rest_act_many_matches_single_acts_of_twin_sessions(http):
    many = [rest_create(http, m, g, seed) for m, g, seed, _ in SESSIONS]
    single = [rest_create(http, m, g, seed) for m, g, seed, _ in SESSIONS]
    for t, obs in enumerate(observations_for([n for *_, n in SESSIONS], STEPS)):
        if t == 2:  # a goal change shows up in both paths from the next step on
            for sid in (many[0], single[0]):
                assert http.put(f"/sessions/{sid}/goal", json={"goal": 1}).status_code == 200
        r = rest_act_many(http, zip(many, obs, strict=True))
        assert r.status_code == 200, r.text
        results = r.json()["results"]
        assert [x["session_id"] for x in results] == many  # request order
        for sid, o, got in zip(single, obs, results, strict=True):
            want = rest_act(http, sid, o)
            assert want.status_code == 200, want.text
            want = want.json()
            assert set(got) == {"session_id", "action", "step", "goal"}
            assert (got["action"], got["step"], got["goal"]) == (want["action"], want["step"], want["goal"])
            assert got["step"] == t
        assert results[0]["goal"] == (1 if t >= 2 else 0)
        assert isinstance(results[-1]["action"], int)  # the discrete model answers an action index
        # every session's action is its own: sampled twins with different seeds differ
        assert results[1]["action"] != results[2]["action"]


def test_grpc_act_batch_matches_single_acts_of_twin_sessions(stub):
    many = [grpc_create(stub, m, g, seed) for m, g, seed, _ in SESSIONS]
    single = [grpc_create(stub, m, g, seed) for m, g, seed, _ in SESSIONS]
    for t, obs in enumerate(observations_for([n for *_, n in SESSIONS], STEPS, seed=6)):
        r = stub.ActBatch(
            pb.ActBatchRequest(requests=[grpc_request(s, o) for s, o in zip(many, obs, strict=True)])
        )
        assert [x.session_id for x in r.results] == many
        for sid, o, got in zip(single, obs, r.results, strict=True):
            assert got.WhichOneof("outcome") == "action"
            want = stub.Act(grpc_request(sid, o))
            want.session_id = got.session_id
            assert got.action == want and got.action.step == t
        assert r.results[-1].action.is_discrete


def test_tensor_observations_in_one_call(http, stub):
    (o,) = observations_for([17], 1, seed=8)[0]
    sids = [rest_create(http, seed=1) for _ in range(3)]
    tensor = {"data": base64.b64encode(o.tobytes()).decode(), "dtype": "float32", "shape": [17]}
    r = http.post(
        "/act",
        json={
            "requests": [
                {"session_id": sids[0], "observation": tensor},
                {"session_id": sids[1], "observation": o.tolist()},
            ]
        },
    )
    assert r.status_code == 200, r.text
    a, b = r.json()["results"]
    g = stub.ActBatch(
        pb.ActBatchRequest(
            requests=[
                pb.ActRequest(
                    session_id=sids[2],
                    tensor=pb.Tensor(data=o.astype(np.float64).tobytes(), dtype="float64", shape=[17]),
                )
            ]
        )
    ).results[0]
    assert a["action"] == b["action"] == list(g.action.action)


def test_an_empty_call_answers_no_results(http, stub):
    r = http.post("/act", json={"requests": []})
    assert r.status_code == 200 and r.json() == {"results": []}
    assert len(stub.ActBatch(pb.ActBatchRequest()).results) == 0


# ----- a bad item fails alone -----------------------------------------------------------------------------------
def _bad_item_setup(create, n=4):
    """Sessions that each stepped once, and their twins."""
    return [create() for _ in range(n)], [create() for _ in range(n)]


def test_rest_bad_items_fail_alone_and_leave_their_sessions_unchanged(http):
    obs = observations_for([17] * 4, 3, seed=9)
    many, twins = _bad_item_setup(lambda: rest_create(http, "tiny-sampled", 1, seed=21))
    for sid, o in zip(many + twins, obs[0] + obs[0], strict=True):
        assert rest_act(http, sid, o).status_code == 200
    bad_tensor = {"data": "%%%", "dtype": "uint8", "shape": [3]}
    body = {
        "requests": [
            {"session_id": many[0], "observation": obs[1][0].tolist()},
            {"session_id": many[1], "observation": [0.0] * 5},  # wrong size
            {"session_id": "no-such-session", "observation": obs[1][2].tolist()},
            {"session_id": many[2], "observation": obs[1][2].tolist()},
            {"session_id": many[2], "observation": obs[1][2].tolist()},  # repeated in the call
            {"session_id": many[3], "observation": bad_tensor},
        ]
    }
    r = http.post("/act", json=body)
    assert r.status_code == 200, r.text
    res = r.json()["results"]
    assert [x["session_id"] for x in res] == [i["session_id"] for i in body["requests"]]
    # each failure carries the code and message the single act answers for the same input
    single_errors = [
        rest_act(http, twins[1], [0.0] * 5),
        rest_act(http, "no-such-session", obs[1][2]),
        http.post(f"/sessions/{twins[3]}/act", json={"observation": bad_tensor}),
    ]
    assert [e.status_code for e in single_errors] == [400, 404, 400]
    assert [res[i] for i in (1, 2, 5)] == [
        {"session_id": s, **e.json()}
        for s, e in zip((many[1], "no-such-session", many[3]), single_errors, strict=True)
    ]
    assert res[1]["error"]["message"].startswith("observation has 5 values, expected 17")
    assert res[2]["error"]["code"] == "not_found"
    assert res[5]["error"]["message"].startswith("observation.data is not valid base64")
    assert res[4] == {
        "session_id": many[2],
        "error": {
            "code": "invalid_argument",
            "message": f"session '{many[2]}' appears more than once in this call",
        },
    }
    # the good items (sessions 0 and 2) acted exactly like their twins acting one by one
    for i, item in ((0, res[0]), (2, res[3])):
        want = rest_act(http, twins[i], obs[1][i]).json()
        assert (item["action"], item["step"]) == (want["action"], want["step"]) == (want["action"], 1)
    # the failed sessions (1 and 3) are unchanged: their next act equals their twins', which never saw the step
    for i, step in ((0, 2), (1, 1), (2, 2), (3, 1)):
        got, want = (rest_act(http, s, obs[2][i]).json() for s in (many[i], twins[i]))
        assert (got["action"], got["step"]) == (want["action"], want["step"]) == (want["action"], step)


def test_grpc_bad_items_fail_alone_and_leave_their_sessions_unchanged(stub):
    obs = observations_for([17] * 4, 3, seed=10)
    many, twins = _bad_item_setup(lambda: grpc_create(stub, "tiny-sampled", 2, seed=22))
    for sid, o in zip(many + twins, obs[0] + obs[0], strict=True):
        stub.Act(grpc_request(sid, o))
    bad_tensor = pb.Tensor(data=b"\0" * 64, dtype="float32", shape=[17])
    requests = [
        grpc_request(many[0], obs[1][0]),
        grpc_request(many[1], [0.0] * 5),
        grpc_request("no-such-session", obs[1][2]),
        grpc_request(many[2], obs[1][2]),
        grpc_request(many[2], obs[1][2]),
        pb.ActRequest(session_id=many[3], tensor=bad_tensor),
        pb.ActRequest(session_id=many[3]),  # a repeat (whatever the first item's fate) and no observation
    ]
    res = stub.ActBatch(pb.ActBatchRequest(requests=requests)).results
    assert [x.session_id for x in res] == [r.session_id for r in requests]
    assert [x.WhichOneof("outcome") for x in res] == [
        "action",
        "error",
        "error",
        "action",
        "error",
        "error",
        "error",
    ]
    single = []
    for req in (
        grpc_request(twins[1], [0.0] * 5),
        requests[2],
        pb.ActRequest(session_id=twins[3], tensor=bad_tensor),
    ):
        with pytest.raises(grpc.RpcError) as e:
            stub.Act(req)
        single.append(e.value)
    for i, e in zip((1, 2, 5), single, strict=True):
        assert (res[i].error.code.upper(), res[i].error.message) == (e.code().name, e.details())
    assert res[1].error.message.startswith("observation has 5 values, expected 17")
    assert res[2].error.code == "not_found"
    assert res[5].error.message == "observation data has 64 bytes; shape [17] of float32 needs 68"
    assert (res[6].error.code, res[6].error.message) == (
        "invalid_argument",
        f"session '{many[3]}' appears more than once in this call",
    )
    assert (res[4].error.code, res[4].error.message) == (
        "invalid_argument",
        f"session '{many[2]}' appears more than once in this call",
    )
    for i, item in ((0, res[0]), (2, res[3])):
        want = stub.Act(grpc_request(twins[i], obs[1][i]))
        assert list(item.action.action) == list(want.action) and item.action.step == want.step == 1
    for i, step in ((0, 2), (1, 1), (2, 2), (3, 1)):
        got, want = (stub.Act(grpc_request(s, obs[2][i])) for s in (many[i], twins[i]))
        assert list(got.action) == list(want.action) and got.step == want.step == step


def test_rest_repeat_fails_even_when_the_first_item_did_not_decode(http, observations):
    victim, twin = rest_create(http, goal=1), rest_create(http, goal=1)
    for sid in (victim, twin):
        assert rest_act(http, sid, observations[0]).status_code == 200
    body = {
        "requests": [
            {"session_id": victim, "observation": {"data": "%%%", "dtype": "float32", "shape": [17]}},
            {"session_id": victim, "observation": observations[1].tolist()},
        ]
    }
    r = http.post("/act", json=body)
    assert r.status_code == 200, r.text
    first, second = r.json()["results"]
    assert "observation.data is not valid base64" in first["error"]["message"]
    assert second["error"] == {
        "code": "invalid_argument",
        "message": f"session '{victim}' appears more than once in this call",
    }
    got, want = (rest_act(http, sid, observations[1]).json() for sid in (victim, twin))
    assert (got["action"], got["step"]) == (want["action"], want["step"]) == (want["action"], 1)


# ----- a malformed or oversized call fails as a whole -----------------------------------------------------------
MALFORMED = [
    ("no requests", {}, "requests: Field required"),
    ("requests not an array", {"requests": "all"}, "requests: Input should be a valid array"),
    ("no session id", {"requests": [{"observation": [0.0]}]}, "requests.0.session_id: Field required"),
    (
        "session id not a string",
        {"requests": [{"session_id": 3, "observation": [0.0]}]},
        "requests.0.session_id: Input should be a valid string",
    ),
    (
        "observation not a list",
        {"requests": [{"session_id": "s", "observation": "fast"}]},
        "requests.0.observation: Value error, must be a list of numbers or an object",
    ),
]


@pytest.mark.parametrize("body,message", [c[1:] for c in MALFORMED], ids=[c[0] for c in MALFORMED])
def test_rest_malformed_body_fails_the_call(http, body, message):
    r = http.post("/act", json=body)
    assert r.status_code == 400, r.text
    assert r.json()["error"]["code"] == "invalid_argument"
    assert message in r.json()["error"]["message"]


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "request body is required: a JSON object"),
        (b'{"requests": [', "request body is not valid JSON"),
        (b"null", "body: Input should be an object"),
    ],
    ids=["empty", "broken JSON", "not an object"],
)
def test_rest_unreadable_body_fails_the_call(http, content, message):
    r = http.post("/act", content=content, headers={"content-type": "application/json"})
    assert r.status_code == 400, r.text
    error = r.json()["error"]
    assert set(error) == {"code", "message"} and error["code"] == "invalid_argument"
    assert message in error["message"]


def test_too_many_items_fail_the_call_on_both_transports(make_server):
    server = make_server()
    n = MAX_ACT_ITEMS + 1
    message = f"a call may act for at most {MAX_ACT_ITEMS} sessions, got {n} requests"
    with httpx.Client(base_url=server.url) as http:
        sid = rest_create(http)
        r = http.post("/act", json={"requests": [{"session_id": sid, "observation": [0.0]}] * n})
        assert r.status_code == 400
        assert r.json() == {"error": {"code": "invalid_argument", "message": message}}
        assert http.get(f"/sessions/{sid}").json()["step"] == 0
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            stub.ActBatch(pb.ActBatchRequest(requests=[pb.ActRequest(session_id=sid)] * n))
        assert (e.value.code(), e.value.details()) == (grpc.StatusCode.INVALID_ARGUMENT, message)


def test_act_many_requires_the_token(make_server):
    server = make_server(auth_token="s3cret")
    with httpx.Client(base_url=server.url) as http:
        r = http.post("/act", json={"requests": []})
        assert r.status_code == 401 and r.json()["error"]["code"] == "unauthenticated"
        ok = http.post("/act", json={"requests": []}, headers={"Authorization": "Bearer s3cret"})
        assert ok.status_code == 200
    with grpc.insecure_channel(server.target) as ch:
        stub = policy_pb2_grpc.PolicyServiceStub(ch)
        with pytest.raises(grpc.RpcError) as e:
            stub.ActBatch(pb.ActBatchRequest())
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        stub.ActBatch(pb.ActBatchRequest(), metadata=(("authorization", "Bearer s3cret"),))


# ----- one forward pass per call ----------------------------------------------------------------------------------
def test_one_call_is_one_forward_pass_even_beyond_max_batch(make_server, ckpt_root):
    server = make_server(max_batch=4)
    n = 8
    obs = observations_for([17] * n, 2, seed=12)
    version = load_checkpoint(ckpt_root / "tiny-gmt").version
    key = (("model", "tiny-gmt"), ("version", version))
    with httpx.Client(base_url=server.url) as http:
        sids = [rest_create(http, goal=i % 3, seed=i) for i in range(n)]
        r = rest_act_many(http, zip(sids, obs[0], strict=True))
        assert r.status_code == 200 and all("action" in x for x in r.json()["results"])
        batches = metric_samples(http, "gmt_batch_size")
        assert batches[("gmt_batch_size_count", key)] == 1
        assert batches[("gmt_batch_size_sum", key)] == n
        with grpc.insecure_channel(server.target) as ch:
            stub = policy_pb2_grpc.PolicyServiceStub(ch)
            res = stub.ActBatch(
                pb.ActBatchRequest(requests=[grpc_request(s, o) for s, o in zip(sids, obs[1], strict=True)])
            )
        assert [x.action.step for x in res.results] == [1] * n
        batches = metric_samples(http, "gmt_batch_size")
    assert batches[("gmt_batch_size_count", key)] == 2
    assert batches[("gmt_batch_size_sum", key)] == 2 * n
    assert (
        batches[("gmt_batch_size_bucket", (("le", "4.0"), ("model", "tiny-gmt"), ("version", version)))] == 0
    )


def test_a_large_call_runs_in_two_passes_with_the_answers_of_one_by_one_acts(make_server, ckpt_root):
    """From `SPLIT_FROM` sessions of one model a call goes in two passes (its first half is answered and written
    while the engine runs the second), each answer still that of its session acting alone."""
    server = make_server()
    n = SPLIT_FROM + 1
    obs = observations_for([17] * n, 2, seed=21)
    version = load_checkpoint(ckpt_root / "tiny-sampled").version
    key = (("model", "tiny-sampled"), ("version", version))
    with httpx.Client(base_url=server.url) as http:
        many = [rest_create(http, "tiny-sampled", i % 3, seed=i) for i in range(n)]
        single = [rest_create(http, "tiny-sampled", i % 3, seed=i) for i in range(n)]
        for t in range(2):
            before = metric_samples(http, "gmt_batch_size")
            r = rest_act_many(http, zip(many, obs[t], strict=True))
            assert r.status_code == 200, r.text
            after = metric_samples(http, "gmt_batch_size")
            passes = after[("gmt_batch_size_count", key)] - before.get(("gmt_batch_size_count", key), 0)
            sizes = after[("gmt_batch_size_sum", key)] - before.get(("gmt_batch_size_sum", key), 0)
            assert (passes, sizes) == (2, n)  # one pass would be (1, n)
            results = r.json()["results"]
            for sid, o, got in zip(single, obs[t], results, strict=True):
                want = rest_act(http, sid, o).json()
                assert (got["action"], got["step"], got["goal"]) == (
                    want["action"],
                    want["step"],
                    want["goal"],
                )


class _GatedEngine:
    """An engine whose first pass waits at a gate (so the batcher holds what is queued behind it); counts passes."""

    def __init__(self, engine) -> None:
        self._engine, self.passes = engine, 0
        self.gate, self.entered = threading.Event(), threading.Event()

    def __getattr__(self, name):
        return getattr(self._engine, name)

    def act(self, *args, **kw):
        self.passes += 1
        self.entered.set()
        self.gate.wait(30)
        return self._engine.act(*args, **kw)


def test_a_split_call_cancelled_before_its_passes_start_runs_neither_part(ckpt_root):
    """A call in two parts can be cancelled only while neither part's pass has started (`gmt.service.units`): then
    neither runs later, and no session of it steps."""

    async def main():
        settings = make_settings(checkpoints=[ckpt_root / "tiny-gmt"])
        core = Core(settings, store=store_for(settings, time.time), clock=time.time)
        await core.start()
        try:
            sids = [
                (await core.create_session("tiny-gmt", goal=0, seed=i)).session_id
                for i in range(SPLIT_FROM + 1)
            ]
            (batcher,) = core._batchers.values()
            batcher.inline_alone = False  # the first act goes through the batcher, to be held there
            batcher.engine = gated = _GatedEngine(batcher.engine)
            obs = np.zeros(17, dtype=np.float32)
            held = asyncio.ensure_future(core.act(sids[0], obs))
            assert await asyncio.to_thread(gated.entered.wait, 10)
            call = asyncio.ensure_future(core.act_many([(sid, obs) for sid in sids[1:]]))
            while batcher.queued < SPLIT_FROM:  # both parts wait behind the held pass
                await asyncio.sleep(0)
            call.cancel()
            with pytest.raises(asyncio.CancelledError):
                await call
            gated.gate.set()
            assert (await held).step == 0
            while not batcher.idle:
                await asyncio.sleep(0.001)
            return gated.passes, [(await core.get_session(sid)).step for sid in sids]
        finally:
            await core.close()

    passes, steps = asyncio.run(main())
    assert passes == 1 and steps == [1] + [0] * SPLIT_FROM


class _HeldFirstWrite:
    """A session store whose first `save_many` waits at a gate (a write not yet acknowledged); counts the calls."""

    def __init__(self, store) -> None:
        self._store, self.sizes = store, []
        self.gate, self.second = asyncio.Event(), asyncio.Event()

    def __getattr__(self, name):
        return getattr(self._store, name)

    async def save_many(self, items):
        self.sizes.append(len(items))
        if len(self.sizes) == 1:
            await self.gate.wait()
        else:
            self.second.set()
        return await self._store.save_many(items)


def test_a_split_calls_second_write_goes_while_the_first_is_unacknowledged(ckpt_root):
    """The second part of a call in two is written as soon as its pass is done, not after the first part's write
    is acknowledged (a replicated store's WAIT would otherwise stand between them); the call answers once both
    are, every session stepped once."""

    async def main():
        settings = make_settings(checkpoints=[ckpt_root / "tiny-gmt"])
        core = Core(settings, store=store_for(settings, time.time), clock=time.time)
        await core.start()
        try:
            n = SPLIT_FROM + 1
            sids = [(await core.create_session("tiny-gmt", goal=0, seed=i)).session_id for i in range(n)]
            core.store = held = _HeldFirstWrite(core.store)
            call = asyncio.ensure_future(core.act_many([(sid, np.zeros(17, np.float32)) for sid in sids]))
            await asyncio.wait_for(held.second.wait(), 30)  # the first write is still held
            assert not call.done()
            held.gate.set()
            results = await call
            return held.sizes, [r.step for r in results], [(await core.get_session(s)).step for s in sids]
        finally:
            await core.close()

    sizes, answered, steps = asyncio.run(main())
    assert sizes == [(SPLIT_FROM + 2) // 2, (SPLIT_FROM + 1) // 2]
    assert answered == [0] * (SPLIT_FROM + 1) and steps == [1] * (SPLIT_FROM + 1)
