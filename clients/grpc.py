"""gRPC client (grpcio) for `gmt.v1.PolicyService`, with an optional ordered `Control` stream per session."""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Sequence
from typing import Any

import grpc
import numpy as np
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc as pb_grpc

from clients.base import (
    DEFAULT_BACKOFF_S,
    DEFAULT_RETRIES,
    DEFAULT_TIMEOUT_S,
    ActResult,
    GoalInfo,
    ModelInfo,
    PolicyClient,
    Session,
    SessionInfo,
    as_observation,
    goal_selector,
    with_retries,
)
from clients.errors import DeadlineExceeded, ProtocolError, ServiceError, error_for

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


def _error(e: grpc.RpcError) -> ServiceError:
    code = e.code()
    return error_for(code.name.lower(), e.details() or code.name, code.name)


# ----- messages <-> values ------------------------------------------------------------------------------------
def space_from_proto(s: pb.Space) -> dict:
    """A space dict in the shape of `model.spaces.space_to_dict` (infinite or absent bounds are None)."""
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
    return ModelInfo(
        name=m.name,
        env_id=m.env_id,
        observation_space=space_from_proto(m.observation_space),
        action_space=space_from_proto(m.action_space),
        context_length=m.context_length,
        statistic=m.statistic,
        goals=[GoalInfo(g.id, g.name, g.mean, g.std, g.min, g.max, g.count) for g in m.goals],
    )


def session_from_proto(s: pb.SessionInfo) -> SessionInfo:
    """A `SessionInfo` from the gRPC message."""
    return SessionInfo(
        session_id=s.session_id,
        model=s.model,
        goal=s.goal,
        goal_name=s.goal_name,
        step=s.step,
        context_size=s.context_size,
        blend_remaining=s.blend_remaining,
        blend_from=s.blend_from,
        idle_timeout_s=s.idle_timeout_s,
        expires_in_s=s.expires_in_s,
        action_mode=s.action_mode,
        context_goals=tuple(s.context_goals),
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


def act_request(session_id: str, observation: Any) -> pb.ActRequest:
    """Float observations as float32 values; other dtypes (images) as a raw little-endian tensor."""
    x = as_observation(observation)
    if x.dtype == np.float32:
        return pb.ActRequest(session_id=session_id, values=pb.FloatVector(values=x.ravel()))
    x = np.ascontiguousarray(x, dtype=x.dtype.newbyteorder("<"))
    tensor = pb.Tensor(data=x.tobytes(), shape=list(x.shape), dtype=x.dtype.name)
    return pb.ActRequest(session_id=session_id, tensor=tensor)


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
        retries: Extra attempts when the server cannot be connected to (never after it answered).
        backoff_s: First retry delay; doubles with each retry.
        token: Bearer token, when the server requires one.
        stream: Sessions send act / set_goal / reset over one ordered `Control` stream instead of unary calls.
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
        self.timeout_s, self.retries, self.backoff_s, self.stream = timeout_s, retries, backoff_s, stream
        self.metadata = (("authorization", f"Bearer {token}"),) if token else ()
        self._channel = grpc.insecure_channel(self.target)
        self.stub = pb_grpc.PolicyServiceStub(self._channel)

    def _call(self, method: str, request: Any) -> Any:
        rpc = getattr(self.stub, method)

        def send() -> Any:
            return rpc(request, timeout=self.timeout_s, metadata=self.metadata)

        try:
            return with_retries(send, _is_connection_error, self.retries, self.backoff_s, self.target)
        except grpc.RpcError as e:
            raise _error(e) from None

    # ----- models -------------------------------------------------------------------------------------------
    def list_models(self) -> list[ModelInfo]:
        return [model_from_proto(m) for m in self._call("ListModels", pb.ListModelsRequest()).models]

    def get_model(self, name: str) -> ModelInfo:
        return model_from_proto(self._call("GetModel", pb.GetModelRequest(name=name)))

    # ----- sessions -----------------------------------------------------------------------------------------
    def create_session(
        self,
        model: str | None = None,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        seed: int | None = None,
        action_mode: str | None = None,
    ) -> Session:
        req = pb.CreateSessionRequest(
            model=model or "", goal=goal_proto(goal, target), action_mode=action_mode or ""
        )
        if seed is not None:
            req.seed = seed
        info = session_from_proto(self._call("CreateSession", req))
        return StreamSession(self, info) if self.stream else Session(self, info)

    def get_session(self, session_id: str) -> SessionInfo:
        return session_from_proto(self._call("GetSession", pb.GetSessionRequest(session_id=session_id)))

    def act(self, session_id: str, observation: Any) -> ActResult:
        return act_from_proto(self._call("Act", act_request(session_id, observation)))

    def act_many(self, items: Sequence[tuple[str, Any]]) -> list[ActResult | ServiceError]:
        req = pb.ActBatchRequest(requests=[act_request(sid, o) for sid, o in items])
        results = self._call("ActBatch", req).results
        if len(results) != len(items):
            raise ProtocolError(f"ActBatch answered {len(results)} results for {len(items)} requests")
        return [act_batch_item_from_proto(r) for r in results]

    def set_goal(
        self,
        session_id: str,
        goal: int | str | None = None,
        *,
        target: float | None = None,
        blend_steps: int = 0,
    ) -> SessionInfo:
        req = set_goal_request(session_id, goal, target, blend_steps)
        return session_from_proto(self._call("SetGoal", req))

    def reset(
        self, session_id: str, goal: int | str | None = None, *, target: float | None = None
    ) -> SessionInfo:
        req = pb.ResetSessionRequest(session_id=session_id, goal=goal_proto(goal, target))
        return session_from_proto(self._call("ResetSession", req))

    def close_session(self, session_id: str) -> None:
        self._call("CloseSession", pb.CloseSessionRequest(session_id=session_id))

    def close(self) -> None:
        self._channel.close()


class ControlStream:
    """One `Control` stream: each command is sent and its answer awaited before the next (strict order).

    A reader thread moves answers into a queue so that each wait has the client's timeout. A stream that
    fails to connect before its first answer is reopened (bounded retries); once the server has answered, a
    broken or silent stream is an error, never silently resent.
    """

    _END = object()

    def __init__(self, client: GrpcClient) -> None:
        self._client = client
        self._call: Any = None
        self._requests: queue.SimpleQueue = queue.SimpleQueue()
        self._answers: queue.SimpleQueue = queue.SimpleQueue()
        self._answered = False

    def _open(self) -> None:
        self._requests, self._answers = queue.SimpleQueue(), queue.SimpleQueue()
        self._call = self._client.stub.Control(iter(self._requests.get, None), metadata=self._client.metadata)
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
        return answer

    def call(self, request: pb.ControlRequest) -> pb.ControlResponse:
        """Send one command and return its answer; in-band errors are raised as `ServiceError`s."""

        def is_retryable(e: BaseException) -> bool:
            return not self._answered and _is_connection_error(e)

        try:
            response = with_retries(
                lambda: self._send(request),
                is_retryable,
                self._client.retries,
                self._client.backoff_s,
                self._client.target,
            )
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
        self._stream = ControlStream(client)

    def act(self, observation: Any) -> ActResult:
        r = self._stream.call(pb.ControlRequest(act=act_request(self.id, observation)))
        if r.WhichOneof("result") != "act":
            raise ProtocolError(f"Control answered an act with {r.WhichOneof('result')!r}")
        return act_from_proto(r.act)

    def set_goal(
        self, goal: int | str | None = None, *, target: float | None = None, blend_steps: int = 0
    ) -> SessionInfo:
        req = set_goal_request(self.id, goal, target, blend_steps)
        self.info = self._session_answer(pb.ControlRequest(set_goal=req), "set_goal")
        return self.info

    def reset(self, goal: int | str | None = None, *, target: float | None = None) -> SessionInfo:
        req = pb.ResetSessionRequest(session_id=self.id, goal=goal_proto(goal, target))
        self.info = self._session_answer(pb.ControlRequest(reset=req), "reset")
        return self.info

    def _session_answer(self, request: pb.ControlRequest, what: str) -> SessionInfo:
        r = self._stream.call(request)
        if r.WhichOneof("result") != "session":
            raise ProtocolError(f"Control answered a {what} with {r.WhichOneof('result')!r}")
        return session_from_proto(r.session)

    def close(self) -> None:
        self._stream.close()
        super().close()
