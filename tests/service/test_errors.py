"""Every class of bad input, on both transports: the right status and message, and the session is unharmed.

Each case runs against a session that has already stepped once; afterwards it must act exactly like an untouched
twin session that saw the same observations.
"""

import base64
import gzip
import json
import shutil
import subprocess

import grpc
import numpy as np
import pytest

from gmt.v1 import policy_pb2 as pb

N = 17


def b64(a: np.ndarray) -> str:
    return base64.b64encode(a.tobytes()).decode()


def obs_json(values) -> str:
    return json.dumps({"observation": values})


# ----- REST ---------------------------------------------------------------------------------------------------
@pytest.fixture
def rest_twins(http, observations):
    """(victim, twin) sessions that both stepped once; `check()` steps both and compares."""
    sids = []
    for _ in range(2):
        sid = http.post("/sessions", json={"model": "tiny-gmt", "goal": 1}).json()["session_id"]
        assert (
            http.post(f"/sessions/{sid}/act", json={"observation": observations[0].tolist()}).status_code
            == 200
        )
        sids.append(sid)
    step = iter(observations[1:])

    def check():
        o = next(step).tolist()
        a, b = (http.post(f"/sessions/{s}/act", json={"observation": o}) for s in sids)
        assert a.status_code == b.status_code == 200
        assert a.json()["action"] == b.json()["action"] and a.json()["step"] == b.json()["step"]

    return sids[0], check


ACT_BODIES = [
    ("wrong size", obs_json([0.0] * 5), "observation has 5 values, expected 17"),
    ("wrong size nested", obs_json([[0.0] * N, [0.0] * N]), "observation has 34 values, expected 17"),
    ("ragged", obs_json([[0.0] * 16, [0.0]]), "observation is not a rectangular numeric array"),
    ("extra dimension", obs_json([[0.0] * N]), "observation has shape [1, 17], expected [17]"),
    ("booleans", obs_json([True] * N), "observation must hold numbers, got booleans"),
    ("huge", obs_json([3e38] * N), "observation value at index 0 is outside [-1e9, 1e9]"),
    ("huge integer", obs_json([0] * 16 + [10**10]), "observation value at index 16 is outside [-1e9, 1e9]"),
    (
        "integer past int64",
        obs_json([0] * 15 + [10**30, 0]),
        "observation value at index 15 is outside [-1e9, 1e9]",
    ),
    ("strings", obs_json(["a"] * N), "observation must be numeric"),
    ("nulls", obs_json([None] * N), "observation must be numeric"),
    ("not a list", obs_json("fast"), "observation: Value error, must be a list of numbers or an object"),
    ("missing", json.dumps({"obs": [0.0] * N}), "observation: Field required"),
    ("NaN", '{"observation": [NaN' + ", 0" * 16 + "]}", "non-finite value (NaN or Inf) at index 0"),
    (
        "Inf",
        '{"observation": [0, 0, 0, -Infinity' + ", 0" * 13 + "]}",
        "non-finite value (NaN or Inf) at index 3",
    ),
    (
        "float32 overflow",
        obs_json([0.0, 1e39] + [0.0] * 15),
        "observation value at index 1 is outside [-1e9, 1e9]",
    ),
    (
        "tensor dtype",
        obs_json({"data": b64(np.zeros(N, np.complex64)), "dtype": "complex64", "shape": [N]}),
        "observation dtype 'complex64' is not supported",
    ),
    (
        "tensor bytes",
        obs_json({"data": b64(np.zeros(16, np.float32)), "dtype": "float32", "shape": [N]}),
        "observation data has 64 bytes; shape [17] of float32 needs 68",
    ),
    (
        "tensor NaN",
        obs_json({"data": b64(np.full(N, np.nan, np.float32)), "dtype": "float32", "shape": [N]}),
        "non-finite value (NaN or Inf) at index 0",
    ),
    (
        "tensor base64",
        obs_json({"data": "%%%", "dtype": "uint8", "shape": [3]}),
        "observation.data is not valid base64",
    ),
    (
        "tensor shape",
        obs_json({"data": "", "dtype": "uint8", "shape": ["a"]}),
        "observation.shape.0: Input should be a valid integer",
    ),
    ("bad JSON", '{"observation": [1,', "request body is not valid JSON"),
    (
        "tensor shape overflow",
        obs_json({"data": "", "dtype": "float32", "shape": [4294967296, 4294967296]}),
        "observation data has 0 bytes; shape [4294967296, 4294967296] of float32 needs",
    ),
    (
        "tensor empty with a huge dimension",
        obs_json({"data": "", "dtype": "float32", "shape": [0, 2**62]}),
        "observation shape [0, 4611686018427387904] is too large",
    ),
    (
        "tensor 65 dimensions",
        obs_json({"data": "", "dtype": "float32", "shape": [1] * 65}),
        "observation shape has 65 dimensions; at most 8 are accepted",
    ),
    ("deep JSON", '{"observation": ' + "[" * 30_000 + "]" * 30_000 + "}", "request body is not valid JSON"),
    ("empty body", "", "request body is required: a JSON object"),
]


@pytest.mark.parametrize("body,message", [c[1:] for c in ACT_BODIES], ids=[c[0] for c in ACT_BODIES])
def test_rest_bad_observation(http, rest_twins, body, message):
    sid, check = rest_twins
    r = http.post(f"/sessions/{sid}/act", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400, r.text
    assert r.json()["error"]["code"] == "invalid_argument"
    assert message in r.json()["error"]["message"]
    assert r.headers["X-Session-Id"] == sid
    check()


GOAL_BODIES = [
    (
        "unknown goal id",
        {"goal": 7},
        "goal 7 is not a goal id of model 'tiny-gmt'; goals are 0=low, 1=medium, 2=high",
    ),
    ("unknown goal name", {"goal": "fastest"}, "unknown goal name 'fastest' for model 'tiny-gmt'"),
    (
        "goal as bool",
        {"goal": True},
        "goal: Input should be a valid integer or Input should be a valid string",
    ),
    ("goal and target", {"goal": 1, "target": 1.0}, "give either goal (an id or a name) or target, not both"),
    ("huge target", {"target": -1.5e9}, "target must be within [-1e9, 1e9], got -1500000000.0"),
    ("target as a string", {"target": "1.0"}, "target: Input should be a valid number"),
    ("no goal", {"blend_steps": 3}, "give a goal (an id or a name) or a target statistic value"),
    (
        "negative blend_steps",
        {"goal": 2, "blend_steps": -1},
        "blend_steps must be an integer in 0..100000, got -1",
    ),
    ("huge blend_steps", {"goal": 2, "blend_steps": 10**9}, "blend_steps must be an integer in 0..100000"),
    (
        "non-integer blend_steps",
        {"goal": 2, "blend_steps": 2.5},
        "blend_steps: Input should be a valid integer",
    ),
]


@pytest.mark.parametrize("body,message", [c[1:] for c in GOAL_BODIES], ids=[c[0] for c in GOAL_BODIES])
def test_rest_bad_set_goal(http, rest_twins, body, message):
    sid, check = rest_twins
    r = http.put(f"/sessions/{sid}/goal", json=body)
    assert r.status_code == 400, r.text
    assert r.json()["error"] == {"code": "invalid_argument", "message": r.json()["error"]["message"]}
    assert message in r.json()["error"]["message"]
    assert http.get(f"/sessions/{sid}").json()["goal"] == 1
    check()


def test_rest_non_finite_target(http, rest_twins):
    sid, check = rest_twins
    r = http.put(
        f"/sessions/{sid}/goal", content='{"target": NaN}', headers={"content-type": "application/json"}
    )
    assert r.status_code == 400 and "target must be a finite number, got nan" in r.json()["error"]["message"]
    check()


UNPARSABLE = [
    ("huge integer", '{"goal": 1' + "0" * 5000 + "}", "number out of range"),
    ("deep nesting", '{"goal": ' + "[" * 3000 + "]" * 3000 + "}", "recursion limit exceeded"),
]


@pytest.mark.parametrize("body,message", [c[1:] for c in UNPARSABLE], ids=[c[0] for c in UNPARSABLE])
@pytest.mark.parametrize("route", ["act", "goal", "reset", "create"])
def test_rest_bodies_json_cannot_hold_name_the_problem_on_every_route(http, rest_twins, body, message, route):
    """Python's json module (FastAPI's routes) and the act route's parser refuse these for different reasons;
    the answer says the same on every route (it was "There was an error parsing the body")."""
    sid, check = rest_twins
    method, path = {
        "act": ("POST", f"/sessions/{sid}/act"),
        "goal": ("PUT", f"/sessions/{sid}/goal"),
        "reset": ("POST", f"/sessions/{sid}/reset"),
        "create": ("POST", "/sessions"),
    }[route]
    r = http.request(method, path, content=body, headers={"content-type": "application/json"})
    assert r.status_code == 400 and r.json()["error"]["code"] == "invalid_argument", r.text
    assert "not valid JSON" in r.json()["error"]["message"], r.text
    assert message in r.json()["error"]["message"], r.text
    check()


def test_rest_body_too_large(http, rest_twins):
    sid, check = rest_twins
    body = obs_json([0.0] * 20_000)  # about 100 kB > the test server's 64 KiB limit
    r = http.post(f"/sessions/{sid}/act", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert r.json()["error"] == {
        "code": "payload_too_large",
        "message": "request body is larger than the limit of 65536 bytes",
    }
    check()


def test_rest_body_too_large_without_content_length(http, rest_twins):
    sid, check = rest_twins

    def chunks():
        yield b'{"observation": ['
        for _ in range(5000):
            yield b"0.0, 0.0, 0.0, 0.0, "
        yield b"0.0]}"

    r = http.post(f"/sessions/{sid}/act", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and r.json()["error"]["code"] == "payload_too_large"
    check()


JSON_ROUTES = [
    ("POST", "/sessions", {"model": "tiny-gmt", "goal": 0}),
    ("POST", "/sessions/{sid}/act", {"observation": [0.0] * N}),
    ("PUT", "/sessions/{sid}/goal", {"goal": 2}),
    ("POST", "/sessions/{sid}/reset", {"goal": 0}),
    ("POST", "/act", {"requests": [{"session_id": "{sid}", "observation": [0.0] * N}]}),
]


@pytest.mark.parametrize("method,path,body", JSON_ROUTES, ids=[f"{m} {p}" for m, p, _ in JSON_ROUTES])
@pytest.mark.parametrize(
    "content_type,named",
    [
        ("application/x-www-form-urlencoded", "Content-Type 'application/x-www-form-urlencoded'"),  # curl -d
        ("text/plain", "Content-Type 'text/plain'"),
        (None, "no Content-Type"),
    ],
)
def test_rest_body_not_declared_json_is_415_naming_both_types(
    http, rest_twins, method, path, body, content_type, named
):
    sid, check = rest_twins
    headers = {} if content_type is None else {"content-type": content_type}
    raw = json.dumps(body).replace("{sid}", sid)
    r = http.request(method, path.format(sid=sid), content=raw, headers=headers)
    assert r.status_code == 415, r.text
    error = r.json()["error"]
    assert error["code"] == "unsupported_media_type"
    assert named in error["message"] and "expected Content-Type: application/json" in error["message"]
    if "{sid}" in path:
        assert r.headers["x-session-id"] == sid
    check()  # nothing was applied


@pytest.mark.parametrize("method,path,body", JSON_ROUTES, ids=[f"{m} {p}" for m, p, _ in JSON_ROUTES])
def test_rest_compressed_body_is_415_naming_the_encoding(http, rest_twins, method, path, body):
    sid, check = rest_twins
    raw = gzip.compress(json.dumps(body).replace("{sid}", sid).encode())
    headers = {"content-type": "application/json", "content-encoding": "gzip"}
    r = http.request(method, path.format(sid=sid), content=raw, headers=headers)
    assert r.status_code == 415, r.text
    assert r.json()["error"]["code"] == "unsupported_media_type"
    assert "Content-Encoding 'gzip'" in r.json()["error"]["message"], r.text
    check()  # nothing was applied
    plain = json.dumps(body).replace("{sid}", sid)
    r = http.request(
        method, path.format(sid=sid), content=plain, headers={**headers, "content-encoding": "identity"}
    )
    assert r.status_code < 300, r.text


@pytest.mark.parametrize("content_type", ["application/json; charset=utf-8", "application/vnd.gmt+json"])
def test_rest_json_content_types_with_parameters_or_suffix_are_json(http, rest_twins, content_type):
    sid, _ = rest_twins
    raw = json.dumps({"observation": [0.0] * N})
    r = http.post(f"/sessions/{sid}/act", content=raw, headers={"content-type": content_type})
    assert r.status_code == 200, r.text
    r = http.put(f"/sessions/{sid}/goal", content='{"goal": 0}', headers={"content-type": content_type})
    assert r.status_code == 200, r.text


def test_openapi_documents_the_415_of_every_operation_with_a_body(http):
    doc = http.get("/openapi.json").json()
    ops = {(m.upper(), p): op for p, item in doc["paths"].items() for m, op in item.items()}
    with_body = {k for k, op in ops.items() if "requestBody" in op}
    management = {("POST", "/models/{name}/versions"), ("PUT", "/models/{name}/default")}
    assert with_body == {(m, p.replace("{sid}", "{session_id}")) for m, p, _ in JSON_ROUTES} | management
    assert {k for k, op in ops.items() if "415" in op["responses"]} == with_body


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_curl_data_without_a_json_header_is_told_how_to_send_json(server):
    out = subprocess.run(
        ["curl", "-s", "-X", "POST", f"{server.url}/sessions", "-d", '{"model": "tiny-gmt", "goal": 0}'],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    ).stdout
    message = json.loads(out)["error"]["message"]
    assert (
        "'application/x-www-form-urlencoded'" in message and "-H 'content-type: application/json'" in message
    )


@pytest.mark.parametrize(
    "method,path,body,status,code,message",
    [
        (
            "POST",
            "/sessions",
            {"model": "nope", "goal": 0},
            404,
            "not_found",
            "unknown model 'nope'; loaded models: tiny-cartpole, tiny-gmt",
        ),
        ("GET", "/models/nope", None, 404, "not_found", "unknown model 'nope'"),
        (
            "POST",
            "/sessions",
            {"goal": 0},
            400,
            "invalid_argument",
            "model is required: loaded models are tiny-cartpole, tiny-gmt",
        ),
        (
            "POST",
            "/sessions",
            {"model": "tiny-gmt", "goal": 3},
            400,
            "invalid_argument",
            "goal 3 is not a goal id",
        ),
        (
            "POST",
            "/sessions",
            {"model": "tiny-gmt", "goal": "Low"},
            400,
            "invalid_argument",
            "unknown goal name 'Low'",
        ),
        (
            "POST",
            "/sessions",
            {"model": "tiny-gmt", "goal": 0, "seed": -1},
            400,
            "invalid_argument",
            "seed must be an integer in [0, 2**63)",
        ),
        (
            "POST",
            "/sessions",
            {"model": "tiny-gmt", "goal": 0, "action_mode": "sample"},
            400,
            "invalid_argument",
            "action_mode 'sample' is not available for model 'tiny-gmt' (continuous actions); choose one of mean",
        ),
        (
            "POST",
            "/sessions",
            {"model": "tiny-gmt", "goal": 0, "action_mode": "greedy"},
            400,
            "invalid_argument",
            "action_mode: Input should be 'argmax', 'sample', 'expert' or 'mean'",
        ),
        (
            "POST",
            "/sessions/nope/act",
            {"observation": [0.0] * N},
            404,
            "not_found",
            "session 'nope' not found (never created, or closed)",
        ),
        ("GET", "/sessions/nope", None, 404, "not_found", "session 'nope' not found"),
        (
            "POST",
            "/sessions/s\u00e9ance-\u4f1a\u8bdd/act",
            {"observation": [0.0] * N},
            404,
            "not_found",
            "session 's\u00e9ance-\u4f1a\u8bdd' not found",
        ),
        ("PUT", "/sessions/nope/goal", {"goal": 0}, 404, "not_found", "session 'nope' not found"),
        ("POST", "/sessions/nope/reset", None, 404, "not_found", "session 'nope' not found"),
        ("DELETE", "/sessions/nope", None, 404, "not_found", "session 'nope' not found"),
        ("GET", "/nope", None, 404, "not_found", "no route GET /nope"),
        ("DELETE", "/models", None, 405, "method_not_allowed", "method DELETE is not allowed on /models"),
    ],
)
def test_rest_unknown_things(http, rest_twins, method, path, body, status, code, message):
    _, check = rest_twins
    r = http.request(method, path, json=body)
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code and message in r.json()["error"]["message"]
    check()


# ----- gRPC ---------------------------------------------------------------------------------------------------
@pytest.fixture
def grpc_twins(stub, observations):
    sids = []
    for _ in range(2):
        sid = stub.CreateSession(
            pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=1))
        ).session_id
        stub.Act(pb.ActRequest(session_id=sid, values=pb.FloatVector(values=observations[0])))
        sids.append(sid)
    step = iter(observations[1:])

    def check():
        o = next(step)
        a, b = (stub.Act(pb.ActRequest(session_id=s, values=pb.FloatVector(values=o))) for s in sids)
        assert list(a.action) == list(b.action) and a.step == b.step

    return sids[0], check


def _tensor(a: np.ndarray, dtype=None, shape=None) -> pb.Tensor:
    return pb.Tensor(
        data=a.tobytes(), dtype=dtype or str(a.dtype), shape=list(a.shape) if shape is None else shape
    )


GRPC_ACTS = [
    ("wrong size", dict(values=pb.FloatVector(values=[0.0] * 5)), "observation has 5 values, expected 17"),
    (
        "NaN",
        dict(values=pb.FloatVector(values=[0.0, 0.0, float("nan")] + [0.0] * 14)),
        "non-finite value (NaN or Inf) at index 2",
    ),
    (
        "Inf",
        dict(values=pb.FloatVector(values=[float("inf")] * N)),
        "non-finite value (NaN or Inf) at index 0",
    ),
    (
        "tensor dtype",
        dict(tensor=_tensor(np.zeros(N, np.float32), dtype="object")),
        "observation dtype 'object' is not supported",
    ),
    (
        "tensor bytes",
        dict(tensor=_tensor(np.zeros(N, np.float32), shape=[18])),
        "observation data has 68 bytes; shape [18] of float32 needs 72",
    ),
    (
        "tensor size",
        dict(tensor=_tensor(np.zeros((2, N), np.uint8))),
        "observation has 34 values, expected 17",
    ),
    ("no observation", dict(), "observation is required: set values or tensor"),
]


@pytest.mark.parametrize("fields,message", [c[1:] for c in GRPC_ACTS], ids=[c[0] for c in GRPC_ACTS])
def test_grpc_bad_observation(stub, grpc_twins, fields, message):
    sid, check = grpc_twins
    with pytest.raises(grpc.RpcError) as e:
        stub.Act(pb.ActRequest(session_id=sid, **fields))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in e.value.details()
    check()


GRPC_CALLS = [
    (
        "unknown model",
        "CreateSession",
        pb.CreateSessionRequest(model="nope", goal=pb.GoalSelector(id=0)),
        "NOT_FOUND",
        "unknown model 'nope'",
    ),
    ("unknown model info", "GetModel", pb.GetModelRequest(name="nope"), "NOT_FOUND", "unknown model 'nope'"),
    (
        "no model",
        "CreateSession",
        pb.CreateSessionRequest(goal=pb.GoalSelector(id=0)),
        "INVALID_ARGUMENT",
        "model is required",
    ),
    (
        "no goal",
        "CreateSession",
        pb.CreateSessionRequest(model="tiny-gmt"),
        "INVALID_ARGUMENT",
        "give a goal (an id or a name) or a target",
    ),
    (
        "unknown session",
        "Act",
        pb.ActRequest(session_id="nope", values=pb.FloatVector(values=[0.0] * N)),
        "NOT_FOUND",
        "session 'nope' not found",
    ),
    (
        "unknown session info",
        "GetSession",
        pb.GetSessionRequest(session_id="nope"),
        "NOT_FOUND",
        "session 'nope' not found",
    ),
    (
        "unknown session close",
        "CloseSession",
        pb.CloseSessionRequest(session_id="nope"),
        "NOT_FOUND",
        "session 'nope' not found",
    ),
]


@pytest.mark.parametrize(
    "method,request_,code,message", [c[1:] for c in GRPC_CALLS], ids=[c[0] for c in GRPC_CALLS]
)
def test_grpc_unknown_things(stub, grpc_twins, method, request_, code, message):
    _, check = grpc_twins
    with pytest.raises(grpc.RpcError) as e:
        getattr(stub, method)(request_)
    assert e.value.code() == grpc.StatusCode[code] and message in e.value.details()
    check()


GRPC_GOALS = [
    ("unknown goal id", dict(goal=pb.GoalSelector(id=9)), "goal 9 is not a goal id of model 'tiny-gmt'"),
    ("unknown goal name", dict(goal=pb.GoalSelector(name="fastest")), "unknown goal name 'fastest'"),
    ("no goal", dict(), "goal is required: set id, name or target"),
    ("NaN target", dict(goal=pb.GoalSelector(target=float("nan"))), "target must be a finite number"),
    (
        "negative blend_steps",
        dict(goal=pb.GoalSelector(id=2), blend_steps=-4),
        "blend_steps must be an integer in 0..100000, got -4",
    ),
]


@pytest.mark.parametrize("fields,message", [c[1:] for c in GRPC_GOALS], ids=[c[0] for c in GRPC_GOALS])
def test_grpc_bad_set_goal(stub, grpc_twins, fields, message):
    sid, check = grpc_twins
    with pytest.raises(grpc.RpcError) as e:
        stub.SetGoal(pb.SetGoalRequest(session_id=sid, **fields))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and message in e.value.details()
    assert stub.GetSession(pb.GetSessionRequest(session_id=sid)).goal == 1
    check()


def test_grpc_message_too_large(stub, grpc_twins):
    sid, check = grpc_twins
    big = pb.Tensor(data=bytes(100_000), dtype="uint8", shape=[100_000])  # > the test server's 64 KiB limit
    with pytest.raises(grpc.RpcError) as e:
        stub.Act(pb.ActRequest(session_id=sid, tensor=big))
    assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "larger than max" in e.value.details()
    check()


def test_control_stream_answers_errors_in_band_and_stays_open(stub, grpc_twins, observations):
    sid, _ = grpc_twins
    twin = stub.CreateSession(
        pb.CreateSessionRequest(model="tiny-gmt", goal=pb.GoalSelector(id=1))
    ).session_id
    stub.Act(pb.ActRequest(session_id=twin, values=pb.FloatVector(values=observations[0])))
    o = observations[1].tolist()
    reqs = [
        pb.ControlRequest(act=pb.ActRequest(session_id=sid, values=pb.FloatVector(values=[1.0] * 5))),
        pb.ControlRequest(set_goal=pb.SetGoalRequest(goal=pb.GoalSelector(name="fastest"))),
        pb.ControlRequest(set_goal=pb.SetGoalRequest(goal=pb.GoalSelector(id=0), blend_steps=-1)),
        pb.ControlRequest(act=pb.ActRequest(session_id="someone-else", values=pb.FloatVector(values=o))),
        pb.ControlRequest(),
        pb.ControlRequest(act=pb.ActRequest(values=pb.FloatVector(values=o))),
    ]
    out = list(stub.Control(iter(reqs)))
    assert [r.WhichOneof("result") for r in out] == ["error"] * 5 + ["act"]
    assert (
        out[0].error.code == "invalid_argument"
        and "observation has 5 values, expected 17" in out[0].error.message
    )
    assert "unknown goal name 'fastest'" in out[1].error.message
    assert "blend_steps must be an integer" in out[2].error.message
    assert f"this stream controls session '{sid}'; a command names another one" in out[3].error.message
    assert "empty command" in out[4].error.message
    want = stub.Act(pb.ActRequest(session_id=twin, values=pb.FloatVector(values=o)))
    assert list(out[5].act.action) == list(want.action) and out[5].act.step == want.step == 1


def test_control_stream_unknown_session_is_in_band(stub):
    reqs = [pb.ControlRequest(act=pb.ActRequest(session_id="nope", values=pb.FloatVector(values=[0.0] * N)))]
    (out,) = list(stub.Control(iter(reqs)))
    assert out.error.code == "not_found" and "session 'nope' not found" in out.error.message


def test_every_error_code_has_a_row_in_the_documented_table():
    """docs/serving.md's error table names every code the service answers, with its HTTP status."""
    from pathlib import Path

    from gmt.service import errors
    from gmt.service.rest.app import HTTP_CODES

    doc = (Path(__file__).parents[2] / "docs" / "serving.md").read_text()
    rows = {
        line.split("|")[1].strip(" `"): line.split("|")[2].strip()
        for line in doc.splitlines()
        if "| `" in line
    }
    classes = [c for c in vars(errors).values() if isinstance(c, type) and issubclass(c, errors.ServiceError)]
    answered = {c.code: c.http_status for c in classes if c.code != "internal"} | {
        code: status for status, code in HTTP_CODES.items()
    }
    # answered by the HTTP protocol itself (rest/protocol.py)
    answered |= {"request_timeout": 408, "request_header_fields_too_large": 431}
    wrong = {
        code: (status, rows.get(code)) for code, status in answered.items() if rows.get(code) != str(status)
    }
    assert not wrong, f"code: (HTTP status, documented) {wrong}"


@pytest.mark.parametrize("name", ["CreateSession", "SetGoal", "ResetSession", "Act", "ActItem", "ActMany"])
def test_openapi_request_bodies_rebuilt_from_the_models_keep_every_field(http, name):
    """The OpenAPI bodies are rewritten from the loaded models (`rest/openapi.py`): none may lose a field the
    server accepts, or Swagger and generated clients cannot send it."""
    from gmt.service.rest import schemas

    schema = http.get("/openapi.json").json()["components"]["schemas"][name]
    variants = [schema, *schema.get("oneOf", [])]
    documented = {p for v in variants for p in v.get("properties", {})}
    assert set(getattr(schemas, name).model_fields) <= documented
