"""A seeded fuzz of every gRPC method with malformed messages, sent as raw bytes over a generic channel.

- bytes that are not a valid protobuf message (random, truncated, bad UTF-8, overlong varints, unterminated
  groups) answer INVALID_ARGUMENT on every unary method, and in-band `invalid_argument` on the Control stream,
  which stays open;
- valid messages with wrong contents (shapes, dtypes, NaN, huge dimensions, unknown sessions, models and goals,
  out-of-range numbers) answer a status naming the problem;
- never UNKNOWN or INTERNAL, every status comes from the server (its `x-served-by` trailer), the server stays
  up, and the session that received all the bad input then acts exactly like a twin that never saw it.
"""

from __future__ import annotations

import math
import random

import grpc
import numpy as np
import pytest
from google.protobuf.message import DecodeError
from grpc_health.v1 import health_pb2, health_pb2_grpc
from service_harness import OBS_DIM

from gmt.service.ids import echoed_id
from gmt.v1 import policy_pb2 as pb

SERVICE = pb.DESCRIPTOR.services_by_name["PolicyService"]
MODEL = "tiny-gmt"
GOALS = 3
ROUNDS = 40  # per kind of bad input and method
ANSWERED = {  # every status a malformed or wrong request may get
    grpc.StatusCode.OK,
    grpc.StatusCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.FAILED_PRECONDITION,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
}
REFUSED = ANSWERED - {grpc.StatusCode.OK}


class Raw:
    """Calls by method name with raw request bytes; answers are (code, details, response bytes or None)."""

    def __init__(self, channel: grpc.Channel) -> None:
        self.channel = channel
        self.calls: list[tuple[str, grpc.StatusCode]] = []

    def unary(
        self, method: str, payload: bytes, served: bool = True
    ) -> tuple[grpc.StatusCode, str, bytes | None]:
        call = self.channel.unary_unary(
            f"/{SERVICE.full_name}/{method}", request_serializer=None, response_deserializer=None
        )
        try:
            response, c = call.with_call(payload, timeout=30)
            code, details, trailers = grpc.StatusCode.OK, "", c.trailing_metadata()
        except grpc.RpcError as e:
            code, details, trailers, response = e.code(), e.details() or "", e.trailing_metadata(), None
        assert code in ANSWERED, (method, payload[:64], code, details)
        if served:  # the servicer answered it, not the transport
            assert "x-served-by" in dict(trailers or ()), (method, code, details)
        self.calls.append((method, code))
        return code, details, response

    def control(self, messages: list[bytes]) -> list[pb.ControlResponse]:
        call = self.channel.stream_stream(
            f"/{SERVICE.full_name}/Control", request_serializer=None, response_deserializer=None
        )
        self.calls.append(("Control", grpc.StatusCode.OK))
        return [pb.ControlResponse.FromString(r) for r in call(iter(messages), timeout=30)]


def parses(request_type, payload: bytes) -> bool:
    try:
        request_type.FromString(payload)
    except DecodeError:
        return False
    return True


# ----- bytes that are not protobuf --------------------------------------------------------------------------------
def varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def undecodable(rng: random.Random, request_type, valid: bytes) -> bytes:
    """Wire bytes that are not a valid `request_type` message (derived from `valid`, a valid one)."""
    while True:
        payload = _garbage(rng, valid)
        if not parses(request_type, payload):
            return payload


def _garbage(rng: random.Random, valid: bytes) -> bytes:
    kind = rng.randrange(7)
    if kind == 0:
        return rng.randbytes(rng.randrange(1, 48))
    if kind == 1 and len(valid) > 1:  # a valid message cut short
        return valid[: rng.randrange(1, len(valid))]
    if kind == 2:  # a string field with bytes that are not UTF-8
        bad = rng.choice([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80"])
        return b"\x0a" + varint(len(bad)) + bad
    if kind == 3:  # a varint longer than 10 bytes
        return bytes([rng.randrange(1, 16) << 3]) + b"\xff" * rng.randrange(10, 20)
    if kind == 4:  # a group that is never closed, or nested past the recursion limit
        return bytes([(rng.randrange(1, 16) << 3) | 3]) * rng.randrange(1, 300)
    if kind == 5:  # a length-delimited field longer than the message
        return b"\x0a" + varint(rng.randrange(100, 2**31)) + rng.randbytes(rng.randrange(0, 8))
    return valid + b"\x0a\x05ab"  # trailing truncated field


# ----- valid messages with wrong contents --------------------------------------------------------------------------
DTYPES = [
    "float32",
    "float64",
    "uint8",
    "int64",
    "bool",
    "complex64",
    "object",
    "",
    "f4",
    "<U3",
    "V8",
    "float128",
]


def bad_observation(rng: random.Random) -> dict:
    """ActRequest fields whose observation the server must refuse for tiny-gmt (17 float values)."""
    kind = rng.randrange(7)
    if kind == 0:  # wrong size
        n = rng.choice([0, 1, OBS_DIM - 1, OBS_DIM + 1, 1000])
        return {"values": pb.FloatVector(values=[rng.uniform(-1, 1) for _ in range(n)])}
    if kind == 1:  # NaN / Inf somewhere
        v = [rng.uniform(-1, 1) for _ in range(OBS_DIM)]
        v[rng.randrange(OBS_DIM)] = rng.choice([float("nan"), float("inf"), float("-inf")])
        return {"values": pb.FloatVector(values=v)}
    if kind == 2:  # finite, but outside +-1e9
        v = [0.0] * OBS_DIM
        v[rng.randrange(OBS_DIM)] = rng.choice([-1, 1]) * 10.0 ** rng.uniform(9.5, 38)
        return {"values": pb.FloatVector(values=v)}
    if kind == 3:  # huge, negative or too many dimensions
        shape = rng.choice(
            [[2**62, 2**62], [0, 2**62], [2**63 - 1], [-1, OBS_DIM], [1] * rng.randrange(9, 70), [OBS_DIM, 0]]
        )
        return {"tensor": pb.Tensor(data=rng.randbytes(rng.randrange(0, 80)), dtype="float32", shape=shape)}
    if kind == 4:  # a dtype that is not a supported NumPy name, or bytes that do not fill the shape
        dtype = rng.choice(DTYPES)
        n = rng.choice(
            [m for m in range(0, 200) if m not in (OBS_DIM, 2 * OBS_DIM, 4 * OBS_DIM, 8 * OBS_DIM)]
        )
        return {"tensor": pb.Tensor(data=rng.randbytes(n), dtype=dtype, shape=[OBS_DIM])}
    if kind == 5:  # a tensor of the right size with non-finite or huge bytes
        x = np.zeros(OBS_DIM, np.float32)
        x[rng.randrange(OBS_DIM)] = rng.choice([np.nan, np.inf, 3e38])
        return {"tensor": pb.Tensor(data=x.tobytes(), dtype="float32", shape=[OBS_DIM])}
    return {}  # no observation at all


def bad_goal(rng: random.Random) -> pb.GoalSelector | None:
    kind = rng.randrange(5)
    if kind == 0:
        return pb.GoalSelector(id=rng.choice([-1, GOALS, GOALS + 1, 2**31 - 1, -(2**31)]))
    if kind == 1:
        return pb.GoalSelector(name=rng.choice(["", "fastest", "LOW", "low ", "\u4f4e", "\x00", "x" * 5000]))
    if kind == 2:
        return pb.GoalSelector(target=rng.choice([float("nan"), float("inf"), float("-inf")]))
    if kind == 3:
        return pb.GoalSelector()  # a selector with nothing set
    return None


def strange_id(rng: random.Random) -> str:
    return rng.choice(
        [
            "",
            "nope",
            "s\u00e9ance-\u4f1a\u8bdd",
            "\x00",
            "a/b",
            "../..",
            "x" * 10_000,
            "\U0001f600",
            " ",
            "%2F",
        ]
    )


# ----- fixtures ----------------------------------------------------------------------------------------------------
@pytest.fixture
def channel(server):
    with grpc.insecure_channel(server.target) as ch:
        yield ch


@pytest.fixture
def twins(channel, observations):
    """(victim, twin) sessions of tiny-gmt, goal 1, that both acted once with the same observation."""
    raw = Raw(channel)
    sids = []
    for _ in range(2):
        req = pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=1))
        code, _, out = raw.unary("CreateSession", req.SerializeToString())
        assert code == grpc.StatusCode.OK
        sids.append(pb.SessionInfo.FromString(out).session_id)
        act = pb.ActRequest(session_id=sids[-1], values=pb.FloatVector(values=observations[0]))
        assert raw.unary("Act", act.SerializeToString())[0] == grpc.StatusCode.OK
    return sids


def act(raw: Raw, sid: str, obs) -> pb.ActResponse:
    code, details, out = raw.unary(
        "Act", pb.ActRequest(session_id=sid, values=pb.FloatVector(values=obs)).SerializeToString()
    )
    assert code == grpc.StatusCode.OK, details
    return pb.ActResponse.FromString(out)


def assert_twins(raw: Raw, victim: str, twin: str, observations) -> None:
    """The victim's state and its next acts equal the twin's."""
    infos = []
    for sid in (victim, twin):
        code, _, out = raw.unary("GetSession", pb.GetSessionRequest(session_id=sid).SerializeToString())
        assert code == grpc.StatusCode.OK
        info = pb.SessionInfo.FromString(out)
        infos.append((info.step, info.goal, info.blend_remaining, info.blend_from, list(info.context_goals)))
    assert infos[0] == infos[1]
    for o in observations:
        a, b = act(raw, victim, o), act(raw, twin, o)
        assert list(a.action) == list(b.action) and a.step == b.step and a.goal == b.goal
        assert np.isfinite(a.action).all()


# ----- the tests ---------------------------------------------------------------------------------------------------
def test_every_method_refuses_undecodable_bytes(channel, twins, observations):
    rng = random.Random(1201)
    raw = Raw(channel)
    victim, twin = twins
    valid = {
        "ListModels": pb.ListModelsRequest(),
        "GetModel": pb.GetModelRequest(name=MODEL),
        "CreateSession": pb.CreateSessionRequest(model=MODEL, goal=pb.GoalSelector(id=0)),
        "GetSession": pb.GetSessionRequest(session_id=victim),
        "Act": pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[1])),
        "SetGoal": pb.SetGoalRequest(session_id=victim, goal=pb.GoalSelector(id=2), blend_steps=3),
        "ResetSession": pb.ResetSessionRequest(session_id=victim, goal=pb.GoalSelector(id=0)),
        "CloseSession": pb.CloseSessionRequest(session_id=victim),
        "ActBatch": pb.ActBatchRequest(requests=[pb.ActRequest(session_id=victim)]),
        "GetTimeline": pb.GetTimelineRequest(session_id=victim),
    }
    streaming = {m.name for m in SERVICE.methods if m.client_streaming}
    assert set(valid) == {m.name for m in SERVICE.methods} - streaming  # every unary method is fuzzed here
    assert streaming == {"Control"}  # ... and the stream below
    for method, message in valid.items():
        request_type = type(message)
        for _ in range(ROUNDS):
            payload = undecodable(rng, request_type, message.SerializeToString())
            code, details, _ = raw.unary(method, payload)
            assert code == grpc.StatusCode.INVALID_ARGUMENT, (method, payload[:32], code, details)
            assert f"request is not a valid {request_type.DESCRIPTOR.full_name} message" in details
    assert_twins(raw, victim, twin, observations[1:4])


def test_valid_messages_with_wrong_contents_answer_a_status_and_harm_nothing(channel, twins, observations):
    rng = random.Random(1202)
    raw = Raw(channel)
    victim, twin = twins

    def refused(method: str, message) -> str:
        code, details, _ = raw.unary(method, message.SerializeToString())
        assert code in REFUSED, (method, message, code, details)
        return details

    for _ in range(ROUNDS):
        # Everything the victim gets is wrong: nothing may change it.
        obs = bad_observation(rng)
        step = rng.choice([None, -1, 2, 5, 2**62, -(2**63)])  # the victim's next step is 1 (0 repeats)
        req = pb.ActRequest(session_id=victim, **obs)
        if step is not None:
            req.step = step
        if not obs:
            assert "observation is required" in refused("Act", req)
        else:
            refused("Act", req)
        if step is not None:  # a wrong step alone, with a good observation
            good = pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[1]), step=step)
            message = refused("Act", good)
            assert "is at step 1" in message if step >= 0 else "step must be an integer >= 0" in message
        goal = bad_goal(rng)
        blend = rng.choice([0, -1, 100_001, 2**31 - 1, -(2**31)])
        set_goal = pb.SetGoalRequest(session_id=victim, blend_steps=blend)
        if goal is not None:
            set_goal.goal.CopyFrom(goal)
        refused("SetGoal", set_goal)
        if goal is not None and goal.WhichOneof("kind") is not None:
            refused("ResetSession", pb.ResetSessionRequest(session_id=victim, goal=goal))
        items = [pb.ActRequest(session_id=victim, **bad_observation(rng))]
        items += [pb.ActRequest(session_id=strange_id(rng), **bad_observation(rng)) for _ in range(3)]
        # the victim again, with a good observation: refused, a session may appear once per call
        items.append(pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[1])))
        code, details, out = raw.unary("ActBatch", pb.ActBatchRequest(requests=items).SerializeToString())
        assert code == grpc.StatusCode.OK, details
        results = pb.ActBatchResponse.FromString(out).results
        # Each item names its session, but never an id longer than the limit (its error names its index instead).
        assert [r.session_id for r in results] == [echoed_id(r.session_id) for r in items]
        assert [r.WhichOneof("outcome") for r in results] == ["error"] * len(items), results
        assert "appears more than once" in results[-1].error.message

        # A report on the previous action that is no finite number, or an info no server keeps.
        report = rng.choice(
            [
                {"reward": rng.choice([math.nan, math.inf, -math.inf, 1e13, -1e300])},
                {"info": {rng.choice(["", "a b", "é", "k" * 65]): 1.0}},
                {"info": {"x": rng.choice([math.nan, math.inf, 2e12])}},
                {"info": {f"k{i}": 1.0 for i in range(33)}},
            ]
        )
        message = refused(
            "Act", pb.ActRequest(session_id=victim, values=pb.FloatVector(values=observations[1]), **report)
        )
        assert "reward" in message or "info" in message, message

        # Unknown things, and numbers out of range, anywhere.
        refused("GetModel", pb.GetModelRequest(name=strange_id(rng)))
        refused("GetSession", pb.GetSessionRequest(session_id=strange_id(rng)))
        refused("GetTimeline", pb.GetTimelineRequest(session_id=strange_id(rng)))
        refused("CloseSession", pb.CloseSessionRequest(session_id=strange_id(rng)))
        refused(
            "Act", pb.ActRequest(session_id=strange_id(rng), values=pb.FloatVector(values=observations[1]))
        )
        create = pb.CreateSessionRequest(
            model=rng.choice([MODEL, "", "nope", strange_id(rng)]),
            action_mode=rng.choice(["", "mean", "greedy"]),
        )
        if create.model == MODEL and not create.action_mode == "greedy":
            create.seed = rng.choice([-1, -(2**63)])  # otherwise a valid request: make it wrong
        goal = bad_goal(rng)
        if goal is not None:
            create.goal.CopyFrom(goal)
        refused("CreateSession", create)

    too_many = pb.ActBatchRequest(requests=[pb.ActRequest() for _ in range(4097)])
    assert "at most 4096" in refused("ActBatch", too_many)
    too_big = pb.ActRequest(
        session_id=victim, tensor=pb.Tensor(data=bytes(100_000), dtype="uint8", shape=[1])
    )
    code, details, _ = raw.unary("Act", too_big.SerializeToString(), served=False)  # refused by gRPC itself
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert_twins(raw, victim, twin, observations[2:5])


def test_control_stream_answers_garbage_in_band_and_goes_on(channel, twins, observations):
    rng = random.Random(1203)
    raw = Raw(channel)
    victim, twin = twins

    def command(**kw) -> bytes:
        return pb.ControlRequest(**kw).SerializeToString()

    good = [observations[i] for i in range(1, 5)]

    def garbage(valid: bytes) -> bytes:
        return undecodable(rng, pb.ControlRequest, valid)

    messages: list[bytes] = [garbage(command(act=pb.ActRequest(session_id=victim)))]  # before any session
    expected: list[str] = ["bad"]
    messages.append(command(act=pb.ActRequest(session_id=victim, values=pb.FloatVector(values=good[0]))))
    expected.append("act")
    for o in good[1:]:
        for _ in range(ROUNDS // 4):
            kind = rng.randrange(4)
            if kind == 0:
                messages.append(garbage(command(act=pb.ActRequest(values=pb.FloatVector(values=o)))))
            elif kind == 1:
                messages.append(command(act=pb.ActRequest(**bad_observation(rng))))
            elif kind == 2:
                goal = bad_goal(rng) or pb.GoalSelector(id=-5)
                messages.append(
                    command(set_goal=pb.SetGoalRequest(goal=goal, blend_steps=rng.choice([0, -3])))
                )
            else:
                other = rng.choice(["someone-else", twin, strange_id(rng) or "x"])
                messages.append(command(act=pb.ActRequest(session_id=other, values=pb.FloatVector(values=o))))
            expected.append("bad")
        messages.append(command(act=pb.ActRequest(values=pb.FloatVector(values=o))))
        expected.append("act")
    messages.append(b"")  # an empty message is a valid, empty command: in-band "empty command"
    expected.append("bad")
    answers = raw.control(messages)
    assert len(answers) == len(messages)  # one answer per message, in order: the stream never broke
    for msg, want, got in zip(messages, expected, answers, strict=True):
        if want == "act":
            assert got.WhichOneof("result") == "act", got
            continue
        assert got.WhichOneof("result") == "error" and got.error.code == "invalid_argument", (msg, got)
        if not parses(pb.ControlRequest, msg):
            assert "request is not a valid gmt.v1.ControlRequest message" in got.error.message
    acts = [a.act for a in answers if a.WhichOneof("result") == "act"]
    twin_acts = [act(raw, twin, o) for o in good]
    assert [list(a.action) for a in acts] == [list(b.action) for b in twin_acts]
    assert [a.step for a in acts] == [b.step for b in twin_acts] == [1, 2, 3, 4]
    assert_twins(raw, victim, twin, observations[5:7])


def test_no_status_was_unknown_or_internal_and_the_server_is_up(channel, server):
    health = health_pb2_grpc.HealthStub(channel)
    assert health.Check(health_pb2.HealthCheckRequest()).status == health_pb2.HealthCheckResponse.SERVING
    raw = Raw(channel)
    assert raw.unary("ListModels", b"")[0] == grpc.StatusCode.OK
    metrics = server.core.metrics.registry
    codes = {
        s.labels["code"]
        for m in metrics.collect()
        if m.name == "gmt_request_duration_seconds"
        for s in m.samples
        if s.labels.get("transport") == "grpc"
    }
    assert codes and not codes & {"UNKNOWN", "INTERNAL"}, codes


def test_undecodable_bytes_without_a_token_are_unauthenticated(make_server):
    server = make_server(auth_token="fuzz")
    with grpc.insecure_channel(server.target) as ch:
        call = ch.unary_unary(
            f"/{SERVICE.full_name}/Act", request_serializer=None, response_deserializer=None
        )
        with pytest.raises(grpc.RpcError) as e:
            call(b"\xff\xff\xff", timeout=10)
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED  # auth before the body is decoded
        with pytest.raises(grpc.RpcError) as e:
            call(b"\xff\xff\xff", timeout=10, metadata=(("authorization", "Bearer fuzz"),))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_health_and_reflection_refuse_undecodable_bytes_too(channel):
    for path in ("/grpc.health.v1.Health/Check", "/grpc.health.v1.Health/Watch"):
        kind = "unary_stream" if path.endswith("Watch") else "unary_unary"
        call = getattr(channel, kind)(path, request_serializer=None, response_deserializer=None)
        with pytest.raises(grpc.RpcError) as e:
            r = call(b"\x0a\x01\xff", timeout=10)
            list(r) if kind == "unary_stream" else r
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, path
    reflection = channel.stream_stream(
        "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
        request_serializer=None,
        response_deserializer=None,
    )
    with pytest.raises(grpc.RpcError) as e:
        list(reflection(iter([b"\xff\xff"]), timeout=10))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
