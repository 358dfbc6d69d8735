"""Both clients against a real server: the same answers, the server's errors as typed exceptions, and retries
only when the server cannot be reached."""

from __future__ import annotations

import socket

import grpc
import httpx
import numpy as np
import pytest

from gmt.client import base
from gmt.client.base import PolicyClient
from gmt.client.errors import (
    AlreadyExists,
    ConnectionFailed,
    DeadlineExceeded,
    InvalidArgument,
    NotFound,
    ProtocolError,
    ResourceExhausted,
    ServiceError,
    Unavailable,
)
from gmt.client.grpc import GrpcClient, StreamSession
from gmt.client.rest import RestClient
from gmt.service.views import MAX_ACT_ITEMS

TRANSPORTS = ["rest", "grpc", "grpc-stream"]
OBS = np.linspace(-1, 1, 17)


def make_client(kind: str, server, **kw) -> PolicyClient:
    if kind == "rest":
        return RestClient(server.rest_url, **kw)
    return GrpcClient(server.grpc_target, stream=kind == "grpc-stream", **kw)


@pytest.fixture(params=TRANSPORTS)
def client(request, live_server):
    with make_client(request.param, live_server) as c:
        yield c


def free_port() -> int:
    """A loopback port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def no_sleep(monkeypatch):
    """Record retry back-off delays instead of sleeping."""
    delays: list[float] = []
    monkeypatch.setattr(base.time, "sleep", delays.append)
    return delays


def test_model_spec_is_the_same_over_both_transports(live_server):
    with RestClient(live_server.rest_url) as r, GrpcClient(live_server.grpc_target) as g:
        rm, gm = r.get_model("tiny-gmt"), g.get_model("tiny-gmt")
        assert [m.name for m in r.list_models()] == [m.name for m in g.list_models()] == ["tiny-gmt"]
    assert rm.goals == gm.goals
    assert [x.name for x in rm.goals] == ["low", "medium", "high"]
    assert (rm.env_id, rm.context_length, rm.statistic) == (gm.env_id, gm.context_length, gm.statistic)
    assert (rm.env_id, rm.context_length, rm.statistic) == ("HalfCheetah-v5", 5, "mean_x_velocity")
    for a, b in ((rm.observation_space, gm.observation_space), (rm.action_space, gm.action_space)):
        assert (a["type"], a["shape"], a["dtype"]) == (b["type"], b["shape"], b["dtype"])
        assert a["low"] == b["low"] and a["high"] == b["high"]
    assert rm.observation_space["shape"] == [17] and rm.action_space["shape"] == [6]
    assert rm.action_space["low"] == [-1.0] * 6


def test_session_lifecycle(client):
    with client.create_session("tiny-gmt", "medium", seed=3) as s:
        assert s.info.goal == 1 and s.info.goal_name == "medium" and s.info.model == "tiny-gmt"
        r0, r1 = s.act(OBS), s.act(OBS)
        assert (r0.step, r1.step, r0.goal) == (0, 1, 1)
        assert isinstance(r0.action, np.ndarray) and r0.action.dtype == np.float32 and r0.action.shape == (6,)
        assert np.all(np.abs(r0.action) <= 1.0)
        assert s.set_goal(target=1.9).goal == 2
        assert s.act(OBS).goal == 2
        blending = s.set_goal(0, blend_steps=4)
        assert (blending.blend_remaining, blending.blend_from, blending.goal) == (4, 2, 0)
        info = s.refresh()
        assert (info.step, info.goal, info.context_size, info.context_goals) == (3, 0, 3, (1, 1, 2))
        assert 0 < info.expires_in_s <= info.idle_timeout_s
        reset = s.reset("high")
        assert (reset.step, reset.goal) == (0, 2)
        assert s.act(OBS).step == 0
    with pytest.raises(NotFound):  # the context manager closed it
        client.get_session(s.id)


def test_unknown_session_is_not_found_with_the_servers_message(client, live_server):
    raw = httpx.post(
        f"{live_server.rest_url}/sessions/no-such-session/act", json={"observation": OBS.tolist()}
    )
    assert raw.status_code == 404
    session = base.Session(client, base.SessionInfo(session_id="no-such-session", model="tiny-gmt", goal=0))
    with pytest.raises(NotFound) as e:
        session.act(OBS)
    assert e.value.code == "not_found"
    assert e.value.message == raw.json()["error"]["message"] and "no-such-session" in e.value.message
    with pytest.raises(NotFound, match="no-such-session"):
        session.set_goal(1)


def test_bad_observation_and_goal_are_invalid_arguments(client):
    with client.create_session("tiny-gmt", 0) as s:
        with pytest.raises(InvalidArgument) as e:
            s.act(np.zeros(5))
        assert e.value.code == "invalid_argument"
        assert "5 values" in e.value.message and "17" in e.value.message
        with pytest.raises(InvalidArgument, match="fastest"):
            s.set_goal("fastest")
        assert s.act(OBS).step == 0  # the bad observation left the session as it was


def test_non_finite_values_and_wrong_shapes_are_invalid_arguments_on_every_transport(client):
    """The same mistake raises the same error whichever transport carries it: REST could not write NaN as JSON
    (a bare ValueError) and gRPC flattened a [1, 17] observation and stepped."""
    with client.create_session("tiny-gmt", 0) as s:
        for bad in (np.full(17, np.nan), np.full(17, np.inf), np.full(17, 1e39)):  # 1e39 overflows float32
            with pytest.raises(InvalidArgument):
                s.act(bad)
        with pytest.raises(InvalidArgument, match=r"\[1, 17\]"):
            s.act(OBS[None, :])
        with pytest.raises(InvalidArgument):
            s.set_goal(target=float("nan"))
        assert s.act(OBS).step == 0  # nothing reached the session


def test_leaving_a_session_that_expired_meanwhile_is_quiet(client):
    """`with` closes the session; one the server already dropped is closed, not an error."""
    s = client.create_session("tiny-gmt", 0)
    with s:
        client.close_session(s.id)  # gone behind this handle's back (as an idle timeout would)
    assert s.closed
    with pytest.raises(NotFound):
        client.close_session(s.id)  # closing it by hand still says it is gone


def test_unknown_model_is_not_found(client):
    with pytest.raises(NotFound, match="nope"):
        client.get_model("nope")
    with pytest.raises(NotFound, match="nope"):
        client.create_session("nope", 0)


def test_full_server_is_resource_exhausted(ckpt_root, start_server):
    srv = start_server(ckpt_root, max_sessions=1)
    for kind in ("rest", "grpc"):
        with make_client(kind, srv) as c, c.create_session(goal=0):
            with pytest.raises(ResourceExhausted) as e:
                c.create_session(goal=0)
            assert e.value.code == "resource_exhausted" and e.value.message


@pytest.mark.parametrize("kind", TRANSPORTS)
def test_unreachable_server_is_retried_then_fails_clearly(kind, no_sleep):
    port = free_port()
    c = (
        RestClient(f"http://127.0.0.1:{port}", retries=2, backoff_s=0.1)
        if kind == "rest"
        else GrpcClient(f"127.0.0.1:{port}", retries=2, backoff_s=0.1, stream=kind == "grpc-stream")
    )
    with c:
        with pytest.raises(ConnectionFailed) as e:
            if kind == "grpc-stream":
                StreamSession(c, base.SessionInfo("s", "tiny-gmt", 0)).act(OBS)
            else:
                c.list_models()
    assert no_sleep == [0.1, 0.2]  # two retries, exponential back-off, then give up
    assert f"127.0.0.1:{port}" in str(e.value) and "3 attempt(s)" in str(e.value)
    assert isinstance(e.value, Unavailable) and e.value.code == "unavailable"
    assert "\n" not in str(e.value) and "Rpc" not in str(e.value)  # one line, not gRPC's error dump
    assert "Connection refused" in str(e.value) or "Errno 111" in str(e.value)


class CountingTransport(httpx.HTTPTransport):
    """Counts requests; the first `fail` ones raise `error` (default: a refused connection)."""

    def __init__(self, fail: int = 0, error: type[httpx.TransportError] = httpx.ConnectError) -> None:
        super().__init__()
        self.calls, self.fail, self.error = 0, fail, error

    def handle_request(self, request):
        self.calls += 1
        if self.calls <= self.fail:
            raise self.error("simulated", request=request)
        return super().handle_request(request)


def test_rest_retries_connection_errors_only(live_server, no_sleep):
    flaky = CountingTransport(fail=2)
    with RestClient(live_server.rest_url, retries=3, transport=flaky) as c:
        assert c.get_model("tiny-gmt").name == "tiny-gmt"
    assert flaky.calls == 3 and len(no_sleep) == 2

    counting = CountingTransport()
    with RestClient(live_server.rest_url, retries=3, transport=counting) as c:
        with pytest.raises(NotFound):
            c.get_session("missing")
        with pytest.raises(InvalidArgument):
            c.create_session(goal=99)
    assert counting.calls == 2 and len(no_sleep) == 2  # answers (4xx) are never retried


def test_rest_resends_after_a_broken_connection_only_what_cannot_apply_twice(live_server, no_sleep):
    """The server may have applied a request whose answer was lost: a read is sent again, an act on a session
    whose step the client does not know is not (it could step twice)."""
    broken = CountingTransport(fail=1, error=httpx.ReadError)
    with RestClient(live_server.rest_url, retries=3, transport=broken) as c:
        assert c.get_model("tiny-gmt").name == "tiny-gmt"
    assert broken.calls == 2 and no_sleep == [0.2]

    with RestClient(live_server.rest_url) as owner:
        sid = owner.create_session(goal=0).id
    broken = CountingTransport(fail=1, error=httpx.ReadError)
    with RestClient(live_server.rest_url, retries=3, transport=broken) as c:
        assert c.expected_step(sid) is None
        with pytest.raises(Unavailable) as e:  # as gRPC reports a broken stream (was an undocumented code)
            c.act(sid, OBS)
    assert broken.calls == 1 and no_sleep == [0.2]
    assert e.value.code == "unavailable" and "ReadError" in e.value.message
    assert "may have been applied" in e.value.message


class LosesAnswers(httpx.HTTPTransport):
    """Sends every request; the answers to the ones numbered in `lose` are lost (ReadError) after the server
    applied them, and answers in `replace` are swapped for a canned response (status, JSON body)."""

    def __init__(self, lose=(), replace=None) -> None:
        super().__init__()
        self.calls, self.lose, self.replace, self.bodies = 0, set(lose), replace or {}, []

    def handle_request(self, request):
        self.calls += 1
        self.bodies.append(request.content)
        if self.calls in self.replace:
            status, body = self.replace[self.calls]
            return httpx.Response(status, json=body, request=request)
        response = super().handle_request(request)
        if self.calls in self.lose:
            response.read()
            raise httpx.ReadError("answer lost (simulated)", request=request)
        return response


def test_rest_act_lost_after_it_stepped_is_resent_with_its_step_and_never_steps_twice(live_server, no_sleep):
    rng = np.random.default_rng(3)
    obs = rng.normal(size=(4, 17)).astype(np.float32)
    lossy = LosesAnswers(lose={3})  # 1: create, 2: act step 0, 3: act step 1 (applied, answer lost)
    with RestClient(live_server.rest_url, transport=lossy) as c, RestClient(live_server.rest_url) as twin_c:
        s, twin = c.create_session(goal=1, seed=4), twin_c.create_session(goal=1, seed=4)
        assert c.expected_step(s.id) == 0
        got = [s.act(o) for o in obs]
        want = [twin.act(o) for o in obs]
        assert [r.step for r in got] == [0, 1, 2, 3] and c.expected_step(s.id) == 4
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g.action, w.action)
        assert c.get_session(s.id).step == 4  # the lost act was applied once, not twice
    assert lossy.calls == 7 and no_sleep == [0.2]
    assert [b'"step":1' in b.replace(b" ", b"") for b in lossy.bodies[2:4]] == [True, True]


def test_rest_retries_aborted_and_unavailable_answers_and_a_lost_create_answers_its_session(
    live_server, no_sleep
):
    aborted = {"error": {"code": "aborted", "message": "session changed meanwhile (simulated)"}}
    unavailable = {"error": {"code": "unavailable", "message": "no replica answered (simulated)"}}
    flaky = LosesAnswers(replace={2: (409, aborted), 3: (503, unavailable)})
    with RestClient(live_server.rest_url, transport=flaky) as c:
        s = c.create_session(goal=0)
        assert s.act(OBS).step == 0 and flaky.calls == 4 and no_sleep == [0.2, 0.4]
    lossy = LosesAnswers(lose={1})  # the server created the session; its answer was lost
    with RestClient(live_server.rest_url, transport=lossy) as c:
        s = c.create_session(goal=0, seed=5)  # the client named it: the retry answers the same session
        assert lossy.calls == 2 and lossy.bodies[0] == lossy.bodies[1]
        assert s.id in lossy.bodies[0].decode() and c.get_session(s.id).step == 0
        with pytest.raises(AlreadyExists, match="other parameters"):  # the same id, another goal: not a retry
            c.create_session(goal=1, seed=5, session_id=s.id)


class Unreachable(grpc.RpcError):
    """What grpcio raises for a call that could not be sent or whose connection broke."""

    def __init__(self, details: str) -> None:
        self._details = details

    def code(self):
        return grpc.StatusCode.UNAVAILABLE

    def details(self):
        return self._details


REFUSED = "failed to connect to all addresses; last error: Connection refused (simulated)"


class CountingStub:
    """Wraps a PolicyService stub: counts unary calls; the first `fail` ones raise Unreachable(details)."""

    def __init__(self, stub, fail: int = 0, details: str = REFUSED) -> None:
        self.stub, self.fail, self.details, self.calls = stub, fail, details, 0

    def __getattr__(self, name):
        rpc = getattr(self.stub, name)

        def call(*args, **kw):
            self.calls += 1
            if self.calls <= self.fail:
                raise Unreachable(self.details)
            return rpc(*args, **kw)

        return call


def test_grpc_retries_connection_errors_and_repeats_only_what_cannot_apply_twice(live_server, no_sleep):
    with GrpcClient(live_server.grpc_target, retries=3) as c:
        c.stub = stub = CountingStub(c.stub, fail=1)
        assert c.get_model("tiny-gmt").name == "tiny-gmt"
        assert stub.calls == 2 and len(no_sleep) == 1
        with pytest.raises(NotFound):
            c.get_session("missing")
        assert stub.calls == 3 and len(no_sleep) == 1

        c.stub = stub = CountingStub(stub.stub, fail=1, details="Socket closed")  # broke mid-call
        assert c.get_model("tiny-gmt").name == "tiny-gmt"  # a read: sent again
        assert stub.calls == 2 and len(no_sleep) == 2

        sid = c.create_session(goal=0).id
        c._forget(sid)  # as if another client had created it: the step is unknown, so an act is not repeated
        c.stub = stub = CountingStub(stub.stub, fail=1, details="Socket closed")
        with pytest.raises(Unavailable, match="Socket closed") as e:
            c.act(sid, OBS)
        assert stub.calls == 1 and len(no_sleep) == 2 and not isinstance(e.value, ConnectionFailed)


def test_server_side_unavailable_is_retried_then_reported(tmp_path, start_server, no_sleep):
    """A server with no model answers UNAVAILABLE itself: nothing was applied, so even a create is tried again
    (a few times), and the server's own message is what the caller finally sees."""
    srv = start_server(tmp_path)
    for kind in ("rest", "grpc"):
        with make_client(kind, srv, retries=2) as c:
            with pytest.raises(Unavailable) as e:
                c.create_session(goal=0)
        assert not isinstance(e.value, ConnectionFailed)
        assert "no model is loaded" in e.value.message
    assert no_sleep == [0.2, 0.4, 0.2, 0.4]


def test_service_error_str_names_code_and_message():
    err = NotFound("session 'x' does not exist")
    assert str(err) == "not_found: session 'x' does not exist"
    assert isinstance(err, ServiceError)


@pytest.fixture
def silent_grpc_server():
    """A PolicyService that takes calls and never answers in time (until the test ends)."""
    from concurrent.futures import ThreadPoolExecutor
    from threading import Event

    from gmt.v1 import policy_pb2 as pb
    from gmt.v1 import policy_pb2_grpc as pb_grpc

    release = Event()

    class Silent(pb_grpc.PolicyServiceServicer):
        def Act(self, request, context):
            release.wait(30)
            return pb.ActResponse()

        def Control(self, request_iterator, context):
            for _ in request_iterator:
                release.wait(30)
                yield pb.ControlResponse()

    server = grpc.server(ThreadPoolExecutor(4))
    pb_grpc.add_PolicyServiceServicer_to_server(Silent(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    yield f"127.0.0.1:{port}"
    release.set()
    server.stop(0)


@pytest.mark.parametrize("stream", [False, True], ids=["unary", "stream"])
def test_grpc_call_without_an_answer_times_out(silent_grpc_server, stream, no_sleep):
    with GrpcClient(silent_grpc_server, timeout_s=0.2, stream=stream) as c:
        session = (StreamSession if stream else base.Session)(c, base.SessionInfo("s", "tiny-gmt", 0))
        with pytest.raises(DeadlineExceeded) as e:
            session.act(OBS)
    assert e.value.code == "deadline_exceeded" and no_sleep == []


def test_rest_request_without_an_answer_times_out(no_sleep):
    with socket.socket() as listener:  # accepts connections (backlog) but never answers
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        url = f"http://127.0.0.1:{listener.getsockname()[1]}"
        with RestClient(url, timeout_s=0.2) as c, pytest.raises(DeadlineExceeded) as e:
            c.act("s", OBS)
    assert e.value.code == "deadline_exceeded" and "/sessions/s/act" in e.value.message and no_sleep == []


# ----- many sessions in one call -------------------------------------------------------------------------------
def test_act_many_answers_what_act_answers(client):
    rng = np.random.default_rng(4)
    goals, seeds = (0, 2, 2, 1), (1, 2, 3, 4)
    many = [client.create_session("tiny-gmt", g, seed=s) for g, s in zip(goals, seeds, strict=True)]
    twins = [client.create_session("tiny-gmt", g, seed=s) for g, s in zip(goals, seeds, strict=True)]
    try:
        for t in range(3):
            obs = rng.normal(size=(len(many), 17))
            got = client.act_many([(s.id, o) for s, o in zip(many, obs, strict=True)])
            assert len(got) == len(many)
            for r, twin, o, g in zip(got, twins, obs, goals, strict=True):
                want = twin.act(o)
                assert isinstance(r, base.ActResult) and r.action.dtype == np.float32
                np.testing.assert_array_equal(r.action, want.action)
                assert (r.step, r.goal) == (want.step, want.goal) == (t, g)
            # same goal, different observations: each session acted on its own
            assert not np.array_equal(got[1].action, got[2].action)
    finally:
        for s in many + twins:
            s.close()


def test_act_many_returns_per_item_errors_and_raises_whole_call_errors(client):
    with client.create_session("tiny-gmt", 1, seed=7) as a, client.create_session("tiny-gmt", 1, seed=7) as b:
        got = client.act_many([(a.id, OBS), (b.id, np.zeros(5)), ("no-such-session", OBS), (a.id, OBS)])
        assert isinstance(got[0], base.ActResult) and got[0].step == 0
        assert [type(e) for e in got[1:]] == [InvalidArgument, NotFound, InvalidArgument]
        with pytest.raises(InvalidArgument) as single:
            b.act(np.zeros(5))
        assert (got[1].code, got[1].message) == ("invalid_argument", single.value.message)
        with pytest.raises(NotFound) as single:
            client.act("no-such-session", OBS)
        assert (got[2].code, got[2].message) == ("not_found", single.value.message)
        assert got[3].message == f"session {a.id!r} appears more than once in this call"
        r = b.act(OBS)  # the failed item left b as it was: it acts like a did on its first step
        np.testing.assert_array_equal(r.action, got[0].action)
        assert r.step == 0
        with pytest.raises(
            InvalidArgument, match=f"at most {MAX_ACT_ITEMS} sessions, got {MAX_ACT_ITEMS + 1} requests"
        ):
            client.act_many([(a.id, [0.0])] * (MAX_ACT_ITEMS + 1))
        assert client.act_many([]) == []
        assert a.act(OBS).step == 1


def test_act_many_is_the_same_over_both_transports(live_server):
    rng = np.random.default_rng(5)
    with RestClient(live_server.rest_url) as r, GrpcClient(live_server.grpc_target) as g:
        rs = [r.create_session("tiny-gmt", i % 3, seed=i) for i in range(5)]
        gs = [g.create_session("tiny-gmt", i % 3, seed=i) for i in range(5)]
        for _ in range(2):
            obs = rng.normal(size=(5, 17))
            a = r.act_many([(s.id, o) for s, o in zip(rs, obs, strict=True)])
            b = g.act_many([(s.id, o) for s, o in zip(gs, obs, strict=True)])
            for x, y in zip(a, b, strict=True):
                np.testing.assert_array_equal(x.action, y.action)
                assert (x.step, x.goal) == (y.step, y.goal)
        for s in rs + gs:
            s.close()


# ----- routing metadata, expected steps and retries over gRPC --------------------------------------------------
@pytest.fixture
def recording_grpc_server():
    """A PolicyService that records each call's (method, x-session-id, expected step) and answers minimally;
    `aborts` holds, per method, how many calls to abort with ABORTED first (in-band on the Control stream)."""
    from concurrent.futures import ThreadPoolExecutor

    from gmt.v1 import policy_pb2 as pb
    from gmt.v1 import policy_pb2_grpc as pb_grpc

    calls: list[tuple[str, str | None, int | None]] = []
    aborts: dict[str, int] = {}

    def note(method, context, step=None):
        sid = dict(context.invocation_metadata()).get("x-session-id")
        calls.append((method, sid, step))
        if aborts.get(method, 0) > 0:
            aborts[method] -= 1
            return True
        return False

    def act(req):
        return pb.ActResponse(
            session_id=req.session_id, action=[0.0] * 6, step=req.step if req.HasField("step") else 7
        )

    class Recording(pb_grpc.PolicyServiceServicer):
        def CreateSession(self, request, context):
            note("CreateSession", context)
            return pb.SessionInfo(session_id="s-1", model="tiny-gmt", step=0)

        def GetSession(self, request, context):
            note("GetSession", context)
            return pb.SessionInfo(session_id=request.session_id, step=5)

        def Act(self, request, context):
            if note("Act", context, request.step if request.HasField("step") else None):
                context.abort(grpc.StatusCode.ABORTED, "changed meanwhile (simulated)")
            return act(request)

        def SetGoal(self, request, context):
            note("SetGoal", context)
            return pb.SessionInfo(session_id=request.session_id, step=2)

        def ResetSession(self, request, context):
            note("ResetSession", context)
            return pb.SessionInfo(session_id=request.session_id, step=0)

        def CloseSession(self, request, context):
            note("CloseSession", context)
            return pb.CloseSessionResponse(session_id=request.session_id)

        def Control(self, request_iterator, context):
            for req in request_iterator:
                cmd = req.act
                if note("Control.act", context, cmd.step if cmd.HasField("step") else None):
                    yield pb.ControlResponse(error=pb.ControlError(code="aborted", message="simulated"))
                else:
                    yield pb.ControlResponse(act=act(cmd))

    server = grpc.server(ThreadPoolExecutor(4))
    pb_grpc.add_PolicyServiceServicer_to_server(Recording(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    yield f"127.0.0.1:{port}", calls, aborts
    server.stop(0)


def test_grpc_client_sends_the_session_id_and_the_expected_step(recording_grpc_server, no_sleep):
    target, calls, aborts = recording_grpc_server
    with GrpcClient(target) as c:
        s = c.create_session(goal=0)
        s.act(OBS)
        aborts["Act"] = 1  # ABORTED applied nothing: sent again, with the same step
        s.act(OBS)
        s.set_goal(1)
        assert c.expected_step("s-1") == 2  # the server's answer wins
        s.act(OBS)
        s.reset()
        s.act(OBS)
        c.get_session("s-1")
        s.close()
    assert calls == [
        ("CreateSession", None, None),
        ("Act", "s-1", 0),
        ("Act", "s-1", 1),
        ("Act", "s-1", 1),
        ("SetGoal", "s-1", None),
        ("Act", "s-1", 2),
        ("ResetSession", "s-1", None),
        ("Act", "s-1", 0),
        ("GetSession", "s-1", None),
        ("CloseSession", "s-1", None),
    ]
    assert no_sleep == [0.2]

    calls.clear()
    with GrpcClient(target, stream=True) as c:
        s = c.create_session(goal=0)
        assert [s.act(OBS).step for _ in range(2)] == [0, 1]
        aborts["Control.act"] = 2  # in-band aborted: sent again, with the same step
        assert s.act(OBS).step == 2
        s.close()
    assert calls == [
        ("CreateSession", None, None),
        ("Control.act", "s-1", 0),
        ("Control.act", "s-1", 1),
        ("Control.act", "s-1", 2),
        ("Control.act", "s-1", 2),
        ("Control.act", "s-1", 2),
        ("CloseSession", "s-1", None),
    ]


class Headers(httpx.HTTPTransport):
    """Records each request's (path, X-Session-Id header)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[str, str | None]] = []

    def handle_request(self, request):
        self.seen.append((request.url.path, request.headers.get("x-session-id")))
        return super().handle_request(request)


class Metadata:
    """Wraps a PolicyService stub: records each call's x-session-id metadata."""

    def __init__(self, stub) -> None:
        self.stub, self.seen = stub, []

    def __getattr__(self, name):
        rpc = getattr(self.stub, name)

        def call(request, **kw):
            self.seen.append((name, dict(kw.get("metadata") or ()).get("x-session-id")))
            return rpc(request, **kw)

        return call


def test_many_session_calls_carry_one_routing_key_whatever_the_order(live_server):
    """A proxy hashing on the session id sends every tick of the same sessions to one replica (which then holds
    them): `act_many` names the smallest of its session ids, on both transports."""
    obs = np.zeros(17, np.float32)
    headers = Headers()
    with (
        RestClient(live_server.rest_url, transport=headers) as rest,
        GrpcClient(live_server.grpc_target) as g,
    ):
        g.stub = meta = Metadata(g.stub)
        for client, seen in ((rest, headers.seen), (g, meta.seen)):
            ids = [client.create_session(goal=0).id for _ in range(3)]
            client.act_many([(s, obs) for s in ids])
            client.act_many([(s, obs) for s in reversed(ids)])
            keys = [key for what, key in seen if what in ("/act", "ActBatch")]
            assert keys == [min(ids), min(ids)]


def test_a_rest_client_aimed_at_the_grpc_port_says_so(live_server):
    """The gRPC port answers an HTTP/1.1 request with HTTP/2 frames: named as a gRPC port, not as a broken
    connection whose request 'may have been applied'."""
    with RestClient(f"http://{live_server.grpc_target}", retries=0) as c:
        with pytest.raises(
            ProtocolError, match="looks like a gRPC port; this REST client needs the server's REST"
        ):
            c.create_session("tiny-gmt", 0)


def test_session_id_is_an_alias_of_id(live_server):
    with RestClient(live_server.rest_url) as c, c.create_session("tiny-gmt", 0) as s:
        assert s.session_id == s.id == s.info.session_id and len(s.id) == 32
