"""gRPC client (grpcio) for `gmt.v1.PolicyService`, with an optional ordered `Control` stream per session."""

from __future__ import annotations

import json
import math
import queue
import threading
from collections.abc import Mapping, Sequence
from dataclasses import fields
from typing import Any

import grpc
import numpy as np

from gmt.client.base import (
    DEFAULT_BACKOFF_S,
    DEFAULT_RETRIES,
    DEFAULT_TIMEOUT_S,
    TIMELINE_PAGE,
    ActResult,
    PolicyClient,
    Session,
    SessionInfo,
    Timeline,
    TimelineEntry,
    as_observation,
    batch_routing_key,
    goal_selector,
    new_session_id,
    report_fields,
    whole_timeline,
    with_retries,
)
from gmt.client.errors import DeadlineExceeded, ProtocolError, ServiceError, error_for
from gmt.common.spec import GoalInfo, ModelInfo
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc as pb_grpc

DEFAULT_PORT = 50051  # gmt serve's --grpc-port default: the port of a target given as a bare host

# gRPC reports a server it never reached as UNAVAILABLE, like a server that answers "unavailable"; these
# phrases of gRPC core mark the former (the request was not sent, so retrying it is safe).
_CONNECT_FAILURES = (
    "failed to connect to all addresses",
    "connections to all backends failing",
    "dns resolution failed",
    "errors resolving",
)


def _is_connection_error(e: BaseException) -> bool:
    if not isinstance(e, grpc.RpcError) or e.code() != grpc.StatusCode.UNAVAILABLE:
        return False
    details = (e.details() or "").lower()
    return any(p in details for p in _CONNECT_FAILURES)


SESSION_METADATA = (
    "x-session-id"  # what a proxy routes on (cluster/nginx.conf): session ids are in the messages
)
SERVED_BY = "x-served-by"  # the replica that answered: initial metadata, and trailing metadata of its status


def _answered_by_replica(e: grpc.RpcError) -> bool:
    """The status came from a replica (it sends `x-served-by` in the trailers of every status it answers), not
    from a broken connection or a proxy."""
    trailers = getattr(e, "trailing_metadata", None)
    try:
        md = trailers() if callable(trailers) else None
    except Exception:  # noqa: BLE001 - a call without trailers
        md = None
    return any(k == SERVED_BY for k, _ in md or ())


def _is_retryable(e: BaseException, safe: bool) -> bool:
    """ABORTED, and UNAVAILABLE answered by a replica, applied nothing: retry. A call that may have been applied
    (UNAVAILABLE from the transport or a proxy; a stream reset, which gRPC reports as INTERNAL "RST_STREAM",
    e.g. when nginx loses the replica mid-call) is repeated only when `safe`."""
    if not isinstance(e, grpc.RpcError):
        return False
    code = e.code()
    if code == grpc.StatusCode.ABORTED:
        return True
    if code == grpc.StatusCode.UNAVAILABLE:
        return safe or _answered_by_replica(e)
    if code == grpc.StatusCode.INTERNAL and "RST_STREAM" in (e.details() or ""):
        return safe and not _answered_by_replica(e)
    return False


def _error(e: grpc.RpcError) -> ServiceError:
    code = e.code()
    return error_for(code.name.lower(), e.details() or code.name, code.name)


# ----- messages <-> values ------------------------------------------------------------------------------------
def space_from_proto(s: pb.Space) -> dict:
    """A space dict in the shape of `gmt.common.spaces.space_to_dict` (infinite or absent bounds are None)."""
    if s.type == "discrete":
        return {"type": "discrete", "n": int(s.n), "shape": list(s.shape), "dtype": s.dtype or "int64"}

    def bounds(v) -> list | None:
        return [float(x) if math.isfinite(x) else None for x in v] if len(v) else None

    return {
        "type": s.type,
        "shape": list(s.shape),
        "dtype": s.dtype,
        "low": bounds(s.low),
        "high": bounds(s.high),
    }


def model_from_proto(m: pb.ModelInfo) -> ModelInfo:
    """A `ModelInfo` from the gRPC message."""
    values = {f.name: getattr(m, f.name) for f in fields(ModelInfo) if f.name != "preprocessing"}
    return ModelInfo(
        **values
        | {
            "observation_space": space_from_proto(m.observation_space),
            "action_space": space_from_proto(m.action_space),
            "goals": [GoalInfo(**{f.name: getattr(g, f.name) for f in fields(GoalInfo)}) for g in m.goals],
            "preprocessing": json.loads(m.preprocessing_json) if m.preprocessing_json else None,
            "action_modes": list(m.action_modes),
        }
    )


def session_from_proto(s: pb.SessionInfo) -> SessionInfo:
    """A `SessionInfo` from the gRPC message."""
    values = {f.name: getattr(s, f.name) for f in fields(SessionInfo)}
    values["context_goals"] = tuple(s.context_goals)
    values["effective_step"] = s.effective_step if s.HasField("effective_step") else None
    return SessionInfo(**values)


def timeline_from_proto(t: pb.Timeline) -> Timeline:
    """A `Timeline` from the gRPC message (`given` as the REST body spells it)."""

    def given(sel: pb.GoalSelector) -> dict:
        kind = sel.WhichOneof("kind")
        return {} if kind is None else {"target" if kind == "target" else "goal": getattr(sel, kind)}

    return Timeline(
        session_id=t.session_id,
        model=t.model,
        fingerprint=t.fingerprint or None,
        step=t.step,
        episode=t.episode,
        entries=t.entries,
        goals=[
            TimelineEntry(e.step, e.episode, e.goal, given(e.given), e.blend_steps, e.by, e.at)
            for e in t.goals
        ],
    )


def act_from_proto(r: pb.ActResponse) -> ActResult:
    """An `ActResult` from the gRPC message (float32 actions, or an int for discrete ones)."""
    action = int(r.discrete_action) if r.is_discrete else np.asarray(r.action, dtype=np.float32)
    return ActResult(action=action, step=int(r.step), goal=int(r.goal))


def act_batch_item_from_proto(r: pb.ActBatchResult) -> ActResult | ServiceError:
    """One item of an `ActBatchResponse`: an `ActResult`, or the `ServiceError` that failed the item."""
    if r.WhichOneof("outcome") == "error":
        return error_for(r.error.code, r.error.message)
    if r.WhichOneof("outcome") != "action":
        raise ProtocolError(f"ActBatch result for session {r.session_id!r} has neither action nor error")
    return act_from_proto(r.action)


def goal_proto(goal: int | str | None, target: float | None) -> pb.GoalSelector | None:
    """The `GoalSelector` for a goal id, name or target (None when neither is given)."""
    sel = goal_selector(goal, target)
    if sel is None:
        return None
    kind, value = sel
    return pb.GoalSelector(**{kind: value})


def act_request(
    session_id: str, observation: Any, step: int | None = None, report: Mapping[str, Any] | None = None
) -> pb.ActRequest:
    """Vector float observations as float32 values; others (images, or a shape the server should check) as a
    raw little-endian tensor with its shape; `step` is the
    step the act is for (None: not checked); `report` the outcome of the previous action (`report_fields`)."""
    x = as_observation(observation)
    if x.dtype == np.float32 and x.ndim == 1:
        req = pb.ActRequest(session_id=session_id, values=pb.FloatVector(values=x))
    else:
        x = np.ascontiguousarray(x, dtype=x.dtype.newbyteorder("<"))
        tensor = pb.Tensor(data=x.tobytes(), shape=list(x.shape), dtype=x.dtype.name)
        req = pb.ActRequest(session_id=session_id, tensor=tensor)
    if step is not None:
        req.step = step
    for k, v in (report or {}).items():
        if k == "info":
            req.info.update(v)
        else:
            setattr(req, k, v)
    return req


def set_goal_request(
    session_id: str, goal: int | str | None, target: float | None, blend_steps: int
) -> pb.SetGoalRequest:
    """A `SetGoalRequest`; a goal or a target is required."""
    sel = goal_proto(goal, target)
    if sel is None:
        raise ValueError("set_goal needs a goal (id or name) or a target")
    return pb.SetGoalRequest(session_id=session_id, goal=sel, blend_steps=blend_steps)


class GrpcClient(PolicyClient):
    """The service over gRPC.

    Args:
        target: "host:port" of the gRPC server.
        timeout_s: Deadline of each unary call, and the longest wait for each answer on a Control stream.
        retries: Extra attempts after a failure that a retry cannot make worse (see `gmt.client.base`).
        backoff_s: First retry delay; doubles with each retry.
        token: Bearer token, when the server requires one.
        stream: Sessions send act / set_goal / reset over one ordered `Control` stream instead of unary calls.

    Every call about one session carries its id as `x-session-id` metadata, so that a proxy routes all of a
    session's calls (and its Control stream) to one replica.
    """

    def __init__(
        self,
        target: str = "localhost:50051",
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        backoff_s: float = DEFAULT_BACKOFF_S,
        token: str | None = None,
        stream: bool = False,
    ) -> None:
        self.target = target.removeprefix("grpc://")
        if ":" not in self.target:  # a bare host: gmt serve's default port, not gRPC's TLS default of 443
            self.target += f":{DEFAULT_PORT}"
        self.timeout_s, self.retries, self.backoff_s, self.stream = timeout_s, retries, backoff_s, stream
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self._channel = grpc.insecure_channel(self.target)
        self.stub = pb_grpc.PolicyServiceStub(self._channel)

    def session_metadata(self, session_id: str | None) -> tuple[tuple[str, str], ...]:
        """The metadata of a call about `session_id`: the token, and the id for a routing proxy."""
        return (*self.metadata, (SESSION_METADATA, session_id)) if session_id else self.metadata

    def _call(
        self,
        method: str,
        request: Any,
        *,
        session_id: str | None = None,
        safe: bool = False,
        gone_ok_on_retry: bool = False,
    ) -> Any:
        """One unary call; `safe` and `gone_ok_on_retry` as in `RestClient._request`."""
        rpc = getattr(self.stub, method)
        metadata = self.session_metadata(session_id)
        maybe_applied = False

        def send() -> Any:
            return rpc(request, timeout=self.timeout_s, metadata=metadata)

        def retryable(e: BaseException) -> bool:
            nonlocal maybe_applied
            if not _is_retryable(e, safe):
                return False
            maybe_applied |= e.code() != grpc.StatusCode.ABORTED and not _answered_by_replica(e)
            return True

        try:
            return with_retries(
                send, _is_connection_error, self.retries, self.backoff_s, self.target, retryable
            )
        except grpc.RpcError as e:
            if gone_ok_on_retry and maybe_applied and e.code() == grpc.StatusCode.NOT_FOUND:
                return None
            raise _error(e) from None

    # ----- models -------------------------------------------------------------------------------------------
    def list_models(self) -> list[ModelInfo]:
        models = self._call("ListModels", pb.ListModelsRequest(), safe=True).models
        return [model_from_proto(m) for m in models]

    def get_model(self, name: str) -> ModelInfo:
        return model_from_proto(self._call("GetModel", pb.GetModelRequest(name=name), safe=True))

    # ----- sessions -----------------------------------------------------------------------------------------
    def create_session(
        self,
        model: str | None = None,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        seed: int | None = None,
        action_mode: str | None = None,
        session_id: str | None = None,
        record: bool | None = None,
    ) -> Session:
        req = pb.CreateSessionRequest(
            model=model or "",
            goal=goal_proto(goal, target),
            action_mode=action_mode or "",
            session_id=session_id or new_session_id(),
        )
        if seed is not None:
            req.seed = seed
        if record is not None:
            req.record = record
        info = self._seen_session(session_from_proto(self._call("CreateSession", req, safe=True)))
        return StreamSession(self, info) if self.stream else Session(self, info)

    def get_session(self, session_id: str) -> SessionInfo:
        req = pb.GetSessionRequest(session_id=session_id)
        return self._seen_session(
            session_from_proto(self._call("GetSession", req, session_id=session_id, safe=True))
        )

    def act(
        self,
        session_id: str,
        observation: Any,
        *,
        reward: float | None = None,
        terminated: bool | None = None,
        truncated: bool | None = None,
        info: Mapping[str, float] | None = None,
    ) -> ActResult:
        step = self.expected_step(session_id)
        req = act_request(session_id, observation, step, report_fields(reward, terminated, truncated, info))
        try:
            result = act_from_proto(self._call("Act", req, session_id=session_id, safe=step is not None))
        except ServiceError as e:
            self._seen_act(session_id, e)
            raise
        self._seen_act(session_id, result)
        return result

    def act_many(self, items: Sequence[tuple]) -> list[ActResult | ServiceError]:
        steps = [self.expected_step(sid) for sid, *_ in items]
        req = pb.ActBatchRequest(
            requests=[
                act_request(sid, o, t, report_fields(**rep[0]) if rep and rep[0] else None)
                for (sid, o, *rep), t in zip(items, steps, strict=True)
            ]
        )
        try:
            key = batch_routing_key([sid for sid, *_ in items]) if items else None  # as `RestClient.act_many`
            results = self._call(
                "ActBatch", req, session_id=key, safe=all(t is not None for t in steps)
            ).results
        except ServiceError as e:
            for sid, *_ in items:
                self._seen_act(sid, e)
            raise
        if len(results) != len(items):
            raise ProtocolError(f"ActBatch answered {len(results)} results for {len(items)} requests")
        out = [act_batch_item_from_proto(r) for r in results]
        for (sid, *_), r in zip(items, out, strict=True):
            self._seen_act(sid, r)
        return out

    def set_goal(
        self,
        session_id: str,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        blend_steps: int = 0,
    ) -> SessionInfo:
        req = set_goal_request(session_id, goal, target, blend_steps)
        # Setting a goal again is harmless, unless a blend would restart.
        answer = self._call("SetGoal", req, session_id=session_id, safe=not blend_steps)
        return self._seen_session(session_from_proto(answer))

    def reset(
        self, session_id: str, goal: int | str | None = None, *, target: float | None = None
    ) -> SessionInfo:
        req = pb.ResetSessionRequest(session_id=session_id, goal=goal_proto(goal, target))
        answer = self._call("ResetSession", req, session_id=session_id, safe=True)
        return self._seen_session(session_from_proto(answer))

    def get_timeline(self, session_id: str) -> Timeline:
        def page(offset: int) -> Timeline:
            req = pb.GetTimelineRequest(session_id=session_id, offset=offset, limit=TIMELINE_PAGE)
            return timeline_from_proto(self._call("GetTimeline", req, session_id=session_id, safe=True))

        return whole_timeline(page)

    def close_session(self, session_id: str) -> None:
        self._forget(session_id)
        req = pb.CloseSessionRequest(session_id=session_id)
        self._call("CloseSession", req, session_id=session_id, safe=True, gone_ok_on_retry=True)

    def close(self) -> None:
        self._channel.close()


class _InBandRetry(Exception):
    """An in-band `aborted` / `unavailable` answer on a Control stream (nothing applied; worth another try)."""

    def __init__(self, response: pb.ControlResponse) -> None:
        super().__init__(response.error.code)
        self.response = response


class ControlStream:
    """One session's `Control` stream: each command is sent and its answer awaited before the next (strict order).

    A reader thread moves answers into a queue so that each wait has the client's timeout. The stream carries
    the session's id as `x-session-id` metadata, so that a proxy routes it to the session's replica. When a
    command fails, the stream is reopened (a new call, which the proxy may route to another replica) and the
    command resent, under the rules of `gmt.client.base`: always when the stream never reached a server or the
    server answered `aborted` / `unavailable` in-band; after a broken stream (e.g. its replica died) only when
    the command is `safe` to repeat (an act carrying its step, reset, set_goal without a blend). A silent stream
    (no answer within the timeout) is an error, never resent.
    """

    _END = object()

    def __init__(self, client: GrpcClient, session_id: str) -> None:
        self._client = client
        self._metadata = client.session_metadata(session_id)
        self._call: Any = None
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._answers: queue.SimpleQueue = queue.SimpleQueue()
        self._answered = False

    def _open(self) -> None:
        self._requests, self._answers = queue.SimpleQueue(), queue.SimpleQueue()
        self._call = self._client.stub.Control(iter(self._requests.get, None), metadata=self._metadata)
        self._answered = False
        threading.Thread(
            target=self._read, args=(self._call, self._answers), name="gmt-control-reader", daemon=True
        ).start()

    @classmethod
    def _read(cls, call: Any, answers: queue.SimpleQueue) -> None:
        try:
            for response in call:
                answers.put(response)
            answers.put(cls._END)
        except grpc.RpcError as e:  # includes the CANCELLED of our own close
            answers.put(e)

    def _send(self, request: pb.ControlRequest) -> pb.ControlResponse:
        if self._call is None:
            self._open()
        self._requests.put(request)
        try:
            answer = self._answers.get(timeout=self._client.timeout_s)
        except queue.Empty:
            self.close()
            raise DeadlineExceeded(
                f"no answer on the Control stream to {self._client.target} within {self._client.timeout_s} s"
            ) from None
        if isinstance(answer, grpc.RpcError):
            self.close()
            raise answer
        if answer is self._END:
            self.close()
            raise ProtocolError("the server closed the Control stream")
        self._answered = True
        if answer.WhichOneof("result") == "error" and answer.error.code in ("aborted", "unavailable"):
            if answer.error.code == "unavailable":
                self.close()  # a new stream may reach a replica that can serve
            raise _InBandRetry(answer)
        return answer

    def call(self, request: pb.ControlRequest, safe: bool = False) -> pb.ControlResponse:
        """Send one command and return its answer; in-band errors are raised as `ServiceError`s.

        Args:
            safe: Applying the command twice is the same as once (see the class docstring).
        """

        def is_connection_error(e: BaseException) -> bool:
            return not self._answered and _is_connection_error(e)

        def is_retryable(e: BaseException) -> bool:
            return isinstance(e, _InBandRetry) or _is_retryable(e, safe)

        try:
            response = with_retries(
                lambda: self._send(request),
                is_connection_error,
                self._client.retries,
                self._client.backoff_s,
                self._client.target,
                is_retryable,
            )
        except _InBandRetry as e:
            response = e.response
        except grpc.RpcError as e:
            raise _error(e) from None
        if response.WhichOneof("result") == "error":
            raise error_for(response.error.code, response.error.message, "control_stream")
        return response

    def close(self) -> None:
        """End the stream (half-close, then cancel anything outstanding)."""
        if self._call is not None:
            self._requests.put(None)
            self._call.cancel()
            self._call = None


class StreamSession(Session):
    """A session whose act / set_goal / reset travel over one ordered `Control` stream."""

    def __init__(self, client: GrpcClient, info: SessionInfo) -> None:
        super().__init__(client, info)
        self._stream = ControlStream(client, info.session_id)

    def act(self, observation: Any, **report: Any) -> ActResult:
        client = self._client
        step = client.expected_step(self.id)
        request = pb.ControlRequest(act=act_request(self.id, observation, step, report_fields(**report)))
        try:
            r = self._stream.call(request, safe=step is not None)
        except ServiceError as e:
            client._seen_act(self.id, e)
            raise
        if r.WhichOneof("result") != "act":
            raise ProtocolError(f"Control answered an act with {r.WhichOneof('result')!r}")
        result = act_from_proto(r.act)
        client._seen_act(self.id, result)
        return result

    def set_goal(
        self, goal: int | str | None = None, *, target: float | None = None, blend_steps: int = 0
    ) -> SessionInfo:
        req = set_goal_request(self.id, goal, target, blend_steps)
        self.info = self._session_answer(pb.ControlRequest(set_goal=req), "set_goal", not blend_steps)
        return self.info

    def reset(self, goal: int | str | None = None, *, target: float | None = None) -> SessionInfo:
        req = pb.ResetSessionRequest(session_id=self.id, goal=goal_proto(goal, target))
        self.info = self._session_answer(pb.ControlRequest(reset=req), "reset", True)
        return self.info

    def _session_answer(self, request: pb.ControlRequest, what: str, safe: bool) -> SessionInfo:
        r = self._stream.call(request, safe)
        if r.WhichOneof("result") != "session":
            raise ProtocolError(f"Control answered a {what} with {r.WhichOneof('result')!r}")
        return self._client._seen_session(session_from_proto(r.session))

    def close(self) -> None:
        self._stream.close()
        super().close()
