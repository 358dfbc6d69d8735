"""gmt.v1.PolicyService: convert messages, call the core, map errors to status codes (or in-band errors)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import TypeVar

import grpc

from gmt.service.core import Core
from gmt.service.errors import DeadlineExceeded, InvalidArgument, ServiceError
from gmt.service.grpc import convert
from gmt.service.memory import Trimmer
from gmt.service.views import MAX_TIMELINE_PAGE, ActResult
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

T = TypeVar("T")
log = logging.getLogger("gmt.grpc")
SHUTTING_DOWN = "server is shutting down: open the stream again (a proxy sends it to another replica)"
UNWRITTEN = "the last answer could not be written"


class Undecodable:
    """What a request deserializes to when its bytes are not a valid message of the method's type (see
    `server.RefuseUndecodable`): unary calls answer INVALID_ARGUMENT, the Control stream answers in-band."""

    __slots__ = ("message",)

    def __init__(self, type_name: str, error: Exception) -> None:
        self.message = f"request is not a valid {type_name} message: {error}"


async def within_deadline(context: grpc.aio.ServicerContext, work: Awaitable[T]) -> T:
    """Await `work`, giving up with DeadlineExceeded when the caller's deadline passes."""
    remaining = context.time_remaining()
    if remaining is None:
        return await work
    try:
        async with asyncio.timeout(max(remaining, 0.0)):
            return await work
    except TimeoutError:
        raise DeadlineExceeded(f"deadline exceeded after {remaining:.3f} s") from None


class PolicyServicer(policy_pb2_grpc.PolicyServiceServicer):
    """The PolicyService over one core."""

    def __init__(self, core: Core) -> None:
        self.core = core
        self.write_timeout_s = core.settings.grpc_write_timeout_s
        self.trimmer = Trimmer()
        self._stopping = False
        self._idle_streams: set[asyncio.Task] = set()  # Control streams waiting for their next command
        self._woken: dict[
            asyncio.Task, str
        ] = {}  # ... of which these were cancelled: why (SHUTTING_DOWN, UNWRITTEN)

    def stop_streams(self) -> None:
        """Shutting down: every Control stream ends with UNAVAILABLE once its command in flight is answered
        (at once when it waits for a command), instead of holding the server for the whole grace period."""
        self._stopping = True
        for task in list(self._idle_streams):
            self._woken[task] = SHUTTING_DOWN
            task.cancel()

    async def _unary(
        self, method: str, context: grpc.aio.ServicerContext, call: Callable[[], Awaitable[T]]
    ) -> T:
        t0, code = time.perf_counter(), "OK"
        in_flight = self.core.metrics.in_flight_grpc
        in_flight.inc()
        try:
            return await within_deadline(context, call())
        except ServiceError as e:
            code = e.grpc_code
            await context.abort(grpc.StatusCode[e.grpc_code], e.message)
        except asyncio.CancelledError:
            # gRPC itself ended the call: its deadline passed (a race with `within_deadline`'s own timer, which
            # answers the same status) or the client cancelled it.
            remaining = context.time_remaining()
            code = "DEADLINE_EXCEEDED" if remaining is not None and remaining <= 0 else "CANCELLED"
            raise
        finally:
            in_flight.dec()
            self.core.metrics.observe_request("grpc", method, code, time.perf_counter() - t0)

    async def ListModels(self, request: pb.ListModelsRequest, context) -> pb.ListModelsResponse:
        async def call():
            return pb.ListModelsResponse(models=[convert.model_info(v) for v in self.core.list_models()])

        return await self._unary("ListModels", context, call)

    async def GetModel(self, request: pb.GetModelRequest, context) -> pb.ModelInfo:
        async def call():
            return convert.model_info(self.core.get_model(request.name))

        return await self._unary("GetModel", context, call)

    async def CreateSession(self, request: pb.CreateSessionRequest, context) -> pb.SessionInfo:
        async def call():
            goal, target = convert.goal(request.goal if request.HasField("goal") else None)
            seed = request.seed if request.HasField("seed") else None
            sid = request.session_id if request.HasField("session_id") else None
            record = request.record if request.HasField("record") else None
            v = await self.core.create_session(
                request.model or None,
                goal,
                target,
                seed,
                request.action_mode or None,
                sid,
                request.version or None,
                record,
            )
            return convert.session_info(v)

        return await self._unary("CreateSession", context, call)

    async def GetSession(self, request: pb.GetSessionRequest, context) -> pb.SessionInfo:
        async def call():
            return convert.session_info(await self.core.get_session(request.session_id))

        return await self._unary("GetSession", context, call)

    async def _act(self, request: pb.ActRequest) -> pb.ActResponse:
        return convert.act_response(await self._core_act(request))

    async def _core_act(self, request: pb.ActRequest) -> ActResult:
        step = request.step if request.HasField("step") else None
        obs, report = convert.observation(request), convert.report(request)
        return await self.core.act(request.session_id, obs, step, report)

    async def _act_batch(self, request: pb.ActBatchRequest) -> pb.ActBatchResponse:
        items = []
        for r in request.requests:
            report = None
            try:
                obs, report = convert.observation(r), convert.report(r)
            except ServiceError as e:  # an undecodable observation or a bad report fails its item alone
                obs = e
            items.append((r.session_id, obs, r.step if r.HasField("step") else None, report))
        out = await self.core.act_many(items)
        answer = pb.ActBatchResponse()
        for (sid, *_), o in zip(items, out, strict=True):
            convert.add_act_batch_result(answer, sid, o)
        return answer

    async def _set_goal(self, request: pb.SetGoalRequest, by: str = "grpc") -> pb.SessionInfo:
        if not request.HasField("goal"):
            raise InvalidArgument("goal is required: set id, name or target")
        goal, target = convert.goal(request.goal)
        return convert.session_info(
            await self.core.set_goal(request.session_id, goal, target, request.blend_steps, by=by)
        )

    async def _reset(self, request: pb.ResetSessionRequest) -> pb.SessionInfo:
        goal, target = convert.goal(request.goal if request.HasField("goal") else None)
        return convert.session_info(await self.core.reset(request.session_id, goal, target))

    async def Act(self, request: pb.ActRequest, context) -> pb.ActResponse:
        return await self._unary("Act", context, lambda: self._act(request))

    async def ActBatch(self, request: pb.ActBatchRequest, context) -> pb.ActBatchResponse:
        return await self._unary("ActBatch", context, lambda: self._act_batch(request))

    async def SetGoal(self, request: pb.SetGoalRequest, context) -> pb.SessionInfo:
        return await self._unary("SetGoal", context, lambda: self._set_goal(request))

    async def ResetSession(self, request: pb.ResetSessionRequest, context) -> pb.SessionInfo:
        return await self._unary("ResetSession", context, lambda: self._reset(request))

    async def GetTimeline(self, request: pb.GetTimelineRequest, context) -> pb.Timeline:
        async def call():
            limit = request.limit or MAX_TIMELINE_PAGE
            return convert.timeline(await self.core.timeline(request.session_id, request.offset, limit))

        return await self._unary("GetTimeline", context, call)

    async def CloseSession(self, request: pb.CloseSessionRequest, context) -> pb.CloseSessionResponse:
        async def call():
            await self.core.close_session(request.session_id)
            return pb.CloseSessionResponse(session_id=request.session_id)

        return await self._unary("CloseSession", context, call)

    async def Control(self, request_iterator: AsyncIterator[pb.ControlRequest], context) -> None:
        """Apply one session's commands in order; errors answer in-band and the stream stays open.

        A message that is not a valid ControlRequest is an in-band invalid_argument too. When the server shuts
        down, the stream ends with UNAVAILABLE after answering the command in flight; when the client takes no
        answer for `grpc_write_timeout_s`, with RESOURCE_EXHAUSTED.
        """
        try:
            await self._control(request_iterator, context)
        finally:
            self.trimmer.soon()  # what the stream held is freed now: hand it back to the OS

    async def _control(self, request_iterator: AsyncIterator, context) -> None:
        # Each answer is written while the next command is read: its write's completion (a hop through gRPC's
        # poller thread) overlaps the client's turn instead of delaying the next read. A command still runs only
        # once the answer before it is written.
        bound: str | None = None
        handler = asyncio.current_task()
        commands = request_iterator.__aiter__()
        in_flight = self.core.metrics.in_flight_grpc
        writing: asyncio.Task | None = None
        try:
            while True:
                req = await self._next_command(commands)
                if writing is not None:
                    await writing
                    writing = None
                if req is None:
                    return
                if req is SHUTTING_DOWN:
                    await context.abort(grpc.StatusCode.UNAVAILABLE, SHUTTING_DOWN)
                undecodable = isinstance(req, Undecodable)
                kind = "undecodable" if undecodable else req.WhichOneof("command")
                t0, code = time.perf_counter(), "OK"
                out = pb.ControlResponse()
                in_flight.inc()
                try:
                    if undecodable:
                        raise InvalidArgument(req.message)
                    if kind is None:
                        raise InvalidArgument("empty command: set act, set_goal or reset")
                    cmd = getattr(req, kind)
                    sid = cmd.session_id or bound
                    if not sid:
                        raise InvalidArgument("session_id is required in the first command of a stream")
                    if bound is not None and sid != bound:
                        raise InvalidArgument(
                            f"this stream controls session {bound!r}; a command names another one"
                        )
                    bound = cmd.session_id = sid
                    if kind == "act":
                        convert.fill_act_response(
                            out.act, await within_deadline(context, self._core_act(cmd))
                        )
                    elif kind == "set_goal":
                        out.session.CopyFrom(await within_deadline(context, self._set_goal(cmd, by="stream")))
                    else:
                        out.session.CopyFrom(await within_deadline(context, self._reset(cmd)))
                except ServiceError as e:
                    code = e.grpc_code
                    out = pb.ControlResponse(error=pb.ControlError(code=e.code, message=e.message))
                finally:
                    in_flight.dec()
                self.core.metrics.observe_request("grpc", f"Control.{kind}", code, time.perf_counter() - t0)
                writing = asyncio.ensure_future(self._answer(context, out, bound))
                writing.add_done_callback(self._woken_by(handler))
        finally:
            if (
                writing is not None and not writing.done()
            ):  # the stream ended meanwhile (the client went away)
                writing.cancel()
                await asyncio.gather(writing, return_exceptions=True)

    def _woken_by(self, handler: asyncio.Task) -> Callable[[asyncio.Task], None]:
        """A write's done callback: a failed write (the client took no answer) wakes its stream's handler when it
        waits for the next command, so that the stream ends now, not at the client's next command."""

        def done(write: asyncio.Task) -> None:
            if not write.cancelled() and write.exception() is not None and handler in self._idle_streams:
                self._woken.setdefault(handler, UNWRITTEN)
                handler.cancel()

        return done

    async def _answer(self, context, answer: pb.ControlResponse, session_id: str | None) -> None:
        """Write one Control answer. The write waits for the client's flow-control window: a client that takes no
        answer for `write_timeout_s` ends the stream with RESOURCE_EXHAUSTED (which it reads after the answers
        still queued; gRPC keeps the stream, at most its window of unread requests, until then or until the
        client goes)."""
        try:
            async with asyncio.timeout(self.write_timeout_s):
                await context.write(answer)
        except TimeoutError:
            log.warning(
                "Control stream ended: its client took no answer",
                extra={"session_id": session_id, "write_timeout_s": self.write_timeout_s},
            )
            self.core.metrics.closed("grpc", "write_timeout")
            try:
                await context.abort(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"the client took no answer of this stream for {self.write_timeout_s:g} s: read the answers",
                )
            except grpc.aio.AbortError:
                raise
            except Exception:  # noqa: BLE001 - gRPC's ExecuteBatchError: the client went away meanwhile
                pass  # the call is over; gRPC ends it as aborted

    async def _next_command(self, commands: AsyncIterator) -> pb.ControlRequest | Undecodable | str | None:
        """The stream's next message; None once the client closed its side; SHUTTING_DOWN when the server is
        shutting down (also while waiting), UNWRITTEN when the answer before failed to be written meanwhile."""
        if self._stopping:
            return SHUTTING_DOWN
        task = asyncio.current_task()
        self._idle_streams.add(task)
        try:
            return await commands.__anext__()
        except StopAsyncIteration:
            return None
        except asyncio.CancelledError:
            why = self._woken.get(task)
            if why is None:
                raise  # the client went away
            task.uncancel()
            return why
        finally:
            self._idle_streams.discard(task)
            self._woken.pop(task, None)
