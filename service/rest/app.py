"""The FastAPI application: lifespan (models load here, never at import), error envelope, body limit, metrics."""

from __future__ import annotations

import asyncio
import logging
import re
import sys
import time
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from gmt.service import admin, examples, keys
from gmt.service.core import Core
from gmt.service.errors import PayloadTooLarge, ServiceError, Unauthenticated, Unavailable
from gmt.service.rest import console, docs, media, openapi
from gmt.service.rest.act import FastAct
from gmt.service.rest.answers import error_response, session_header, validation_message
from gmt.service.rest.methods import KnownMethods
from gmt.service.rest.models_admin import admin_api
from gmt.service.rest.routes import api, public
from gmt.service.settings import Settings

log = logging.getLogger("gmt.rest")
HTTP_CODES = {
    400: "invalid_argument",  # e.g. a body FastAPI could not parse (nesting too deep for its JSON parser)
    404: "not_found",
    405: "method_not_allowed",
    413: "payload_too_large",
    415: "unsupported_media_type",
}


def _session_header(request: Request) -> dict:
    return session_header(request.path_params.get("session_id"))


async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
    headers = _session_header(request)
    if exc.http_status == 401:
        headers["WWW-Authenticate"] = "Bearer"
    return error_response(exc.http_status, exc.code, exc.message, headers)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return error_response(400, "invalid_argument", validation_message(exc.errors()), _session_header(request))


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    code = HTTP_CODES.get(exc.status_code, "http_error")
    headers = getattr(exc, "headers", None)
    if exc.status_code == 404:
        msg = f"no route {request.method} {request.url.path}; see /docs"
    elif exc.status_code == 405:
        msg = f"method {request.method} is not allowed on {request.url.path}"
        allowed = _allowed_methods(request)
        if allowed:
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
    elif exc.status_code == 400 and exc.__cause__ is not None:  # FastAPI could not parse a JSON body
        msg = _unparsable_body(exc.__cause__)
    else:
        msg = str(exc.detail)
    return error_response(exc.status_code, code, msg, headers)


def _unparsable_body(cause: BaseException) -> str:
    """What broke a body that Python's json module (FastAPI's routes) could not read, in the words the act
    route's parser uses for the same bodies."""
    if isinstance(cause, RecursionError):
        return (
            "request body is not valid JSON: recursion limit exceeded (arrays or objects nested too deeply)"
        )
    if isinstance(cause, ValueError) and "digits" in str(cause):
        limit = sys.get_int_max_str_digits()
        return f"request body is not valid JSON: number out of range (an integer of more than {limit} digits)"
    return f"request body is not valid JSON: {type(cause).__name__}"


def _allowed_methods(request: Request) -> list[str]:
    """Every method the API documents on this path (Starlette's 405 names only the first matching route's)."""
    path = request.scope["path"]
    for template, item in request.app.openapi()["paths"].items():
        if re.fullmatch(re.sub(r"\\{[^/]+?\\}", "[^/]+", re.escape(template)), path):
            return sorted(m.upper() for m in item)
    return []


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error", extra={"path": request.url.path})
    return error_response(500, "internal", f"internal error: {type(exc).__name__}")


class BodyLimit:
    """Reads the whole body first and answers 413 (error envelope) once it exceeds `limit` bytes."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def _too_large(self, scope: Scope, receive: Receive, send: Send) -> None:
        e = PayloadTooLarge(f"request body is larger than the limit of {self.limit} bytes")
        await error_response(e.http_status, e.code, e.message, {"Connection": "close"})(scope, receive, send)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        try:
            body = await media.read_body(scope, receive, self.limit)
        except ClientDisconnect:
            return
        if body is None:
            return await self._too_large(scope, receive, send)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class AuthFirst:
    """Refuses a request that may not be answered before anything reads its body, and runs the others as their
    caller (`gmt.service.keys`: the key whose bearer token they carry).

    Model management paths follow `gmt.service.admin` (the admin token, else the bearer token, else loopback
    only). With auth on, health checks, the API docs (their pages and assets) and the console's page and assets
    (no data: the page sends the token on every call it makes) stay open; every other path (unknown ones
    included) needs one of the keys (or the admin token, which sees every session).
    """

    OPEN = frozenset({"/healthz", "/readyz", "/openapi.json"}) | docs.PATHS | console.PATHS
    HOW = "'Authorization: Bearer <token>'"

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings
        self.keyring = keys.Keyring.of(settings)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and admin.is_management_path(scope.get("path", "")):
            return await self._management(scope, receive, send)
        if not self.keyring or scope["type"] != "http" or scope.get("path") in self.OPEN:
            return await self.app(scope, receive, send)
        auth = next((v for k, v in scope["headers"] if k == b"authorization"), None)
        try:
            caller = self.keyring.identify(auth, self.HOW)
        except Unauthenticated as e:
            headers = {"WWW-Authenticate": "Bearer", **session_header(_path_session(scope.get("path", "")))}
            return await error_response(e.http_status, e.code, e.message, headers)(scope, receive, send)
        with keys.acting_as(caller):
            await self.app(scope, receive, send)

    async def _management(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        client = scope.get("client")
        try:
            admin.authorize(
                self.settings,
                headers.get("authorization"),
                client[0] if client else None,
                any(h in headers for h in admin.PROXY_HEADERS),
                web=headers,
            )
        except ServiceError as e:
            extra = {"WWW-Authenticate": "Bearer"} if e.http_status == 401 else {}
            return await error_response(e.http_status, e.code, e.message, extra)(scope, receive, send)
        await self.app(scope, receive, send)


def _path_session(path: str) -> str | None:
    """The session id of a `/sessions/{id}...` path (ASGI's `path` is already percent-decoded: never again)."""
    parts = path.split("/")
    return parts[2] if len(parts) > 2 and parts[1] == "sessions" and parts[2] else None


class ServedBy:
    """Adds `X-Served-By: <replica id>` to every HTTP response, errors and unknown routes included.

    It wraps the whole middleware stack (see `_App`), so even the 500 of Starlette's outermost error handler
    carries it.
    """

    def __init__(self, app: ASGIApp, replica_id: str) -> None:
        self.app = app
        self.header = (b"x-served-by", replica_id.encode("ascii"))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_header(message: Message) -> None:
            if message["type"] == "http.response.start":
                message["headers"] = [*message.get("headers", ()), self.header]
            await send(message)

        await self.app(scope, receive, send_with_header)


class PlainBodies:
    """A compressed request body (a Content-Encoding other than identity) answers 415 before any route reads it,
    `FastAct`'s included: the routes would parse the compressed bytes as JSON."""

    _SESSION = re.compile(r"^/sessions/([^/]+)")

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] in ("POST", "PUT", "PATCH"):
            encoding = next((v for k, v in scope["headers"] if k == b"content-encoding"), None)
            refusal = None if encoding is None else media.encoding_refusal(encoding.decode("latin-1"))
            if refusal is not None:
                m = self._SESSION.match(scope.get("path", ""))
                headers = session_header(m.group(1)) if m else None
                response = error_response(refusal.http_status, refusal.code, refusal.message, headers)
                return await response(scope, receive, send)
        await self.app(scope, receive, send)


class AnswerCutOff:
    """A request still running when the shutdown grace period ends is cancelled by uvicorn, which would answer
    500; during shutdown this answers it `503 unavailable` instead (retryable: with the act's `step`, a retry
    never steps twice), unless its answer had started."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = False

        async def send_started(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, send_started)
        except asyncio.CancelledError:
            core = getattr(scope["app"].state, "core", None)
            if started or core is None or not core.closing:
                raise
            asyncio.current_task().uncancel()
            e = Unavailable("server shut down before this request was answered; retry it")
            headers = {"Connection": "close", **session_header(_path_session(scope.get("path", "")))}
            await error_response(e.http_status, e.code, e.message, headers)(scope, receive, send)


class _App(FastAPI):
    """FastAPI whose middleware stack, Starlette's own error handling included, is wrapped in `ServedBy`."""

    replica_id = ""

    settings: Settings | None = None

    def build_middleware_stack(self) -> ASGIApp:
        inner = PlainBodies(FastAct(super().build_middleware_stack(), self.settings))
        authed = AuthFirst(inner, self.settings)
        return ServedBy(AnswerCutOff(KnownMethods(authed, self.router.routes)), self.replica_id)

    def openapi(self) -> dict:
        """The document for the loaded models and the auth setting (`gmt.service.rest.openapi`), built once the
        models are loaded."""
        if self.openapi_schema is None:
            core = getattr(self.state, "core", None)
            doc = openapi.build(self, core)
            if core is None or not core.started:
                return doc
            self.openapi_schema = doc
        return self.openapi_schema


class RequestMetrics:
    """Observes each request's latency by endpoint name and status."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0, status = time.perf_counter(), 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        core = getattr(scope["app"].state, "core", None) if "app" in scope else None
        path = scope["path"]
        counted = path != "/metrics" and not path.endswith(
            "/events"
        )  # a scrape; an event stream (long-lived)
        in_flight = core.metrics.in_flight_rest if core is not None and counted else None
        if in_flight is not None:
            in_flight.inc()
        try:
            await self.app(scope, receive, send_status)
        finally:
            if in_flight is not None:
                in_flight.dec()
            endpoint = scope.get("endpoint")
            name = getattr(endpoint, "__name__", "unmatched")
            if core is not None:
                core.metrics.observe_request("rest", name, str(status), time.perf_counter() - t0)


def create_app(settings: Settings | None = None, core: Core | None = None) -> FastAPI:
    """The REST app over `core` (default: a new one from `settings`).

    The lifespan loads the models (starts the core) unless the core already runs, and closes the core on
    shutdown only if it created it; whoever passes a core closes it.
    """
    settings = settings or (core.settings if core else Settings())

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        c = core or Core(settings)
        if not c.started:
            await c.start()  # models load here, never at import time
        # No local keeps the checkpoints: this frame lives as long as the app, and an unloaded version must go.
        app.state.examples = await asyncio.to_thread(
            examples.examples_of,
            {n: m.checkpoint for n, m in (c.registry.models if c.registry else {}).items()},
        )
        app.state.core = c
        try:
            yield
        finally:
            if core is None:
                await c.close()

    app = _App(
        title="GMT controllable-policy service",
        version="1",
        description="Drive an agent with a Goal-Masked Transformer and change its goal mid-episode.",
        lifespan=lifespan,
        # The service has its own metrics (/metrics) and logs; FastAPI's OpenTelemetry hooks looked up the global
        # providers on every request (3.2 us each here, ~1.5% of a REST act under load) to find them unconfigured.
        telemetry={"tracing": False, "metrics": False, "logs": False},
        # No trailing-slash redirects: Starlette builds their Location from the Host header.
        redirect_slashes=False,
        docs_url=None,  # `docs` serves /docs and /redoc with their assets from the package, not a CDN
        redoc_url=None,
    )
    app.replica_id, app.settings = settings.replica_id, settings
    app.include_router(public)
    app.include_router(api)
    app.include_router(admin_api)
    app.include_router(console.router)
    docs.add_docs(app)
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected)
    app.add_middleware(RequestMetrics)
    app.add_middleware(BodyLimit, limit=settings.max_request_bytes)
    return app
