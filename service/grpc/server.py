"""The grpc.aio server: PolicyService, ModelAdmin, standard health checking, server reflection, optional bearer
auth."""

from __future__ import annotations

import inspect

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from gmt.service import admin, keys
from gmt.service.core import Core
from gmt.service.errors import Unauthenticated
from gmt.service.grpc.admin_servicer import ModelAdminServicer
from gmt.service.grpc.servicer import PolicyServicer, Undecodable
from gmt.service.limits import connection_caps
from gmt.service.settings import Settings
from gmt.v1 import admin_pb2, admin_pb2_grpc, policy_pb2, policy_pb2_grpc

POLICY_SERVICE = policy_pb2.DESCRIPTOR.services_by_name["PolicyService"].full_name
ADMIN_SERVICE = admin_pb2.DESCRIPTOR.services_by_name["ModelAdmin"].full_name
OPEN_PREFIXES = ("/grpc.health.v1.Health/", "/grpc.reflection.")


SERVED_BY = "x-served-by"


class ServedBy(grpc.aio.ServerInterceptor):
    """Sends `x-served-by: <replica id>` as initial metadata at the start of every call (of every service,
    refused ones included), so routing can be checked from any answer, and in the trailers of every status this
    server answers, which tells clients a status of this server (nothing applied) from a broken connection."""

    def __init__(self, replica_id: str) -> None:
        self._metadata = ((SERVED_BY, replica_id),)

    async def intercept_service(self, continuation, handler_call_details):
        handler = await continuation(handler_call_details)
        if handler is None:
            return None
        md = self._metadata
        if handler.response_streaming:
            behavior = handler.unary_stream or handler.stream_stream

            async def wrapped(request_or_iterator, context):
                context.set_trailing_metadata(md)
                await context.send_initial_metadata(md)
                out = behavior(request_or_iterator, context)
                if inspect.isasyncgen(out):
                    async for message in out:
                        yield message
                elif inspect.isawaitable(out):  # writes with context.write
                    await out
                else:
                    for message in out:
                        yield message

        else:
            behavior = handler.unary_unary or handler.stream_unary

            async def wrapped(request_or_iterator, context):
                context.set_trailing_metadata(md)
                await context.send_initial_metadata(md)
                out = behavior(request_or_iterator, context)
                return await out if inspect.isawaitable(out) else out

        make = {
            (False, False): grpc.unary_unary_rpc_method_handler,
            (False, True): grpc.unary_stream_rpc_method_handler,
            (True, False): grpc.stream_unary_rpc_method_handler,
            (True, True): grpc.stream_stream_rpc_method_handler,
        }[(handler.request_streaming, handler.response_streaming)]
        return make(wrapped, handler.request_deserializer, handler.response_serializer)


_MAKE_HANDLER = {
    (False, False): grpc.unary_unary_rpc_method_handler,
    (False, True): grpc.unary_stream_rpc_method_handler,
    (True, False): grpc.stream_unary_rpc_method_handler,
    (True, True): grpc.stream_stream_rpc_method_handler,
}
IN_BAND_UNDECODABLE = frozenset({f"/{POLICY_SERVICE}/Control"})  # answers undecodable messages in-band


def _tolerant(deserialize):
    """`deserialize`, returning an `Undecodable` instead of raising (grpcio answers UNKNOWN for that)."""
    owner = getattr(deserialize, "__self__", None)
    descriptor = getattr(owner, "DESCRIPTOR", None)
    type_name = getattr(descriptor, "full_name", None) or "request"

    def tolerant(data: bytes):
        try:
            return deserialize(data)
        except Exception as e:  # noqa: BLE001 - protobuf's DecodeError, or whatever a foreign deserializer raises
            return Undecodable(type_name, e)

    return tolerant


class RefuseUndecodable(grpc.aio.ServerInterceptor):
    """A request whose bytes are not a valid message of the method's type answers INVALID_ARGUMENT, on every
    service (grpcio itself answers UNKNOWN); on the Control stream the servicer answers it in-band and the
    stream goes on. It is the innermost interceptor, so that auth is still checked first."""

    def __init__(self) -> None:
        self._wrapped: dict[str, tuple] = {}  # method -> (its handler, the tolerant handler built for it)

    async def intercept_service(self, continuation, handler_call_details):
        handler = await continuation(handler_call_details)
        if handler is None or handler.request_deserializer is None:
            return handler
        method = handler_call_details.method
        cached = self._wrapped.get(method)
        if cached is not None and cached[0] is handler:  # built once per method, not once per call
            return cached[1]
        wrapped_handler = self._wrap(handler, method)
        self._wrapped[method] = (handler, wrapped_handler)
        return wrapped_handler

    @staticmethod
    def _wrap(handler, method: str):
        deserialize = _tolerant(handler.request_deserializer)
        kind = (handler.request_streaming, handler.response_streaming)
        behavior = (
            handler.unary_unary or handler.unary_stream or handler.stream_unary or handler.stream_stream
        )
        if method in IN_BAND_UNDECODABLE:
            wrapped = behavior
        elif not handler.request_streaming:

            async def refuse(request, context):
                if isinstance(request, Undecodable):
                    await context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)

            if handler.response_streaming:

                async def wrapped(request, context):
                    await refuse(request, context)
                    async for message in _responses(behavior(request, context)):
                        yield message

            else:

                async def wrapped(request, context):
                    await refuse(request, context)
                    out = behavior(request, context)
                    return await out if inspect.isawaitable(out) else out

        else:

            async def checked(requests, context):
                async for message in requests:
                    if isinstance(message, Undecodable):
                        await context.abort(grpc.StatusCode.INVALID_ARGUMENT, message.message)
                    yield message

            if handler.response_streaming:

                async def wrapped(requests, context):
                    async for message in _responses(behavior(checked(requests, context), context)):
                        yield message

            else:

                async def wrapped(requests, context):
                    out = behavior(checked(requests, context), context)
                    return await out if inspect.isawaitable(out) else out

        return _MAKE_HANDLER[kind](wrapped, deserialize, handler.response_serializer)


async def _responses(out):
    """The messages of a response-streaming behaviour (an async generator, a coroutine that writes with
    `context.write`, or a plain iterable)."""
    if inspect.isasyncgen(out):
        async for message in out:
            yield message
    elif inspect.isawaitable(out):
        await out
    else:
        for message in out:
            yield message


class BearerAuth(grpc.aio.ServerInterceptor):
    """Requires `authorization: Bearer <token>` metadata of one of the keys (`gmt.service.keys`) on every call
    except health, reflection and ModelAdmin's (which `gmt.service.admin` authorises per call), and runs the call
    as the key's caller."""

    HOW = "metadata 'authorization: Bearer <token>'"

    def __init__(self, keyring: keys.Keyring) -> None:
        self._keyring = keyring

    async def intercept_service(self, continuation, handler_call_details):
        handler = await continuation(handler_call_details)
        if handler is None or handler_call_details.method.startswith((*OPEN_PREFIXES, admin.GRPC_SERVICE)):
            return handler
        auth = next(
            (v for k, v in handler_call_details.invocation_metadata or () if k == "authorization"), None
        )
        try:
            behavior = _as_caller(self._keyring.identify(auth, self.HOW), handler)
        except Unauthenticated as e:
            behavior = _deny(e)
        kind = (handler.request_streaming, handler.response_streaming)
        return _MAKE_HANDLER[kind](behavior, handler.request_deserializer, handler.response_serializer)


def _deny(err: Unauthenticated):
    """A behaviour that refuses the call with `err`."""

    async def deny(request_or_iterator, context):
        await context.abort(grpc.StatusCode[err.grpc_code], err.message)

    return deny


def _as_caller(caller: keys.Caller, handler):
    """The handler's behaviour run as `caller` (PolicyService's are coroutines: Control writes its answers with
    `context.write`)."""
    behavior = handler.unary_unary or handler.unary_stream or handler.stream_unary or handler.stream_stream

    if inspect.isasyncgenfunction(behavior):

        async def streamed(request_or_iterator, context):
            with keys.acting_as(caller):
                async for message in behavior(request_or_iterator, context):
                    yield message

        return streamed

    async def called(request_or_iterator, context):
        with keys.acting_as(caller):
            out = behavior(request_or_iterator, context)
            return await out if inspect.isawaitable(out) else out

    return called


def server_options(settings: Settings, max_connections: int) -> list[tuple[str, int]]:
    """grpcio channel arguments bounding what clients can make the server hold (docs/reliability.md, "Control
    streams that never read"); each one's effect was checked against grpcio 1.85."""
    limit = settings.max_request_bytes
    return [
        ("grpc.max_receive_message_length", limit),
        ("grpc.max_send_message_length", 4 * limit),
        # With BDP probing on, gRPC raised every stream's window (SETTINGS_INITIAL_WINDOW_SIZE) to 64-128 MiB
        # on loopback, and buffered that much per stream that its handler had not read. Off, the window is
        # lookahead_bytes; a larger message still arrives (gRPC opens the window for the message it reads).
        ("grpc.http2.bdp_probe", 0),
        ("grpc.http2.lookahead_bytes", settings.grpc_window_bytes),
        ("grpc.max_concurrent_streams", settings.grpc_max_streams_per_connection),
        ("grpc.max_allowed_incoming_connections", max_connections),
        ("grpc.server_handshake_timeout_ms", int(settings.grpc_handshake_timeout_s * 1000)),
        # gRPC binds with SO_REUSEPORT by default: a second `gmt serve` on a taken port would share it silently.
        ("grpc.so_reuseport", 0),
    ]


class GrpcServer:
    """The gRPC side of a server process.

    Args:
        core: The started core.
        host: Interface to bind.
        port: Port (0 = any free port; the bound one is in `port` after `start`).
    """

    def __init__(self, core: Core, host: str, port: int) -> None:
        s = core.settings
        self.core = core
        # ServedBy first: it wraps whatever the others answer, a refused call included; auth before decoding.
        interceptors = [
            ServedBy(s.replica_id),
            *([BearerAuth(core.keyring)] if core.keyring else []),
            RefuseUndecodable(),
        ]
        self.server = grpc.aio.server(
            interceptors=interceptors,
            options=server_options(s, connection_caps(s).grpc),
            maximum_concurrent_rpcs=s.grpc_max_concurrent_rpcs,  # one more answers RESOURCE_EXHAUSTED
        )
        self.servicer = PolicyServicer(core)
        policy_pb2_grpc.add_PolicyServiceServicer_to_server(self.servicer, self.server)
        admin_pb2_grpc.add_ModelAdminServicer_to_server(ModelAdminServicer(core, self.servicer), self.server)
        self.health = health.aio.HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        names = (POLICY_SERVICE, ADMIN_SERVICE, health.SERVICE_NAME, reflection.SERVICE_NAME)
        reflection.enable_server_reflection(names, self.server)
        address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self.port = self.server.add_insecure_port(address)
        if not self.port:
            raise OSError(f"gRPC could not bind {address}")

    async def start(self) -> None:
        """Start serving and publish readiness through the health service."""
        await self.server.start()
        status = (
            health_pb2.HealthCheckResponse.SERVING
            if self.core.ready
            else health_pb2.HealthCheckResponse.NOT_SERVING
        )
        for name in ("", POLICY_SERVICE):
            await self.health.set(name, status)

    async def stop(self, grace: float) -> None:
        """Report NOT_SERVING, refuse new calls, end Control streams once their command in flight is answered
        (UNAVAILABLE: reopen elsewhere) and give in-flight calls `grace` seconds."""
        await self.health.enter_graceful_shutdown()
        self.servicer.stop_streams()
        await self.server.stop(grace)
        self.servicer.trimmer.cancel()
