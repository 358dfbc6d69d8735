"""`POST /sessions/{id}/act` and `POST /act`, the hot paths: one implementation of each (`answer`, `answer_many`),
which the documented routes in `routes.py` and the fast path `FastAct` both call.

The fast path answers them below FastAPI's routing and middleware: measured with py-spy, FastAPI's stack was most
of the server's time per act (docs/performance.md, "Throughput at 256 sessions"), and half of a one-session
`POST /act`'s (0.78 against 0.42 ms, "Small calls on the loop").
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Awaitable, Callable

import orjson
from pydantic import ValidationError
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Receive, Scope, Send

from gmt.service.core import Core
from gmt.service.errors import PayloadTooLarge, ServiceError
from gmt.service.ids import echoed_id
from gmt.service.observations import decode_base64, decode_tensor
from gmt.service.records import Report, check_report
from gmt.service.rest import media
from gmt.service.rest import schemas as S
from gmt.service.rest.answers import error_bytes, session_header, validation_message
from gmt.service.settings import Settings
from gmt.service.views import ActResult

log = logging.getLogger("gmt.rest")


def report(body: S.Act) -> Report | None:
    """The client's report on its previous action, checked (`records.check_report`)."""
    return check_report(body.reward, body.terminated, body.truncated, body.info)


def observation(body: S.Act) -> object:
    """The observation a body carries, a tensor decoded (`gmt.service.observations`)."""
    obs = body.observation
    if isinstance(obs, S.Tensor):
        obs = decode_tensor(decode_base64(obs.data), obs.dtype, obs.shape)
    return obs


async def act_answer(core: Core, session_id: str, raw: bytes) -> bytes:
    """The JSON answer of one act, from the raw body (validated from bytes by pydantic-core, written by orjson).

    Raises:
        ValidationError: the body does not match `S.Act`.
        ServiceError: the core refused the act.
    """
    body = S.Act.model_validate_json(raw)
    r = await core.act(session_id, observation(body), body.step, report(body))
    return orjson.dumps(act_fields(r))


def act_fields(r: ActResult) -> dict:
    """One act's answer (`S.ActOut`): the action (a list for Box spaces, an int for Discrete ones), step, goal, id."""
    action = r.action if r.action is not None else r.discrete_action
    return {"action": action, "step": r.step, "goal": r.goal, "session_id": r.session_id}


def many_answer(ids: list[str], results: list[ActResult | ServiceError]) -> bytes:
    """`POST /act`'s JSON answer (`S.ActManyOut`, None fields left out), written by orjson in one pass: per item
    the act's answer or its error (an id too long to name a session is answered as "")."""
    return orjson.dumps(
        {
            "results": [
                {"session_id": echoed_id(sid), "error": {"code": r.code, "message": r.message}}
                if isinstance(r, ServiceError)
                else act_fields(r)
                for sid, r in zip(ids, results, strict=True)
            ]
        }
    )


async def acts_answer(core: Core, raw: bytes) -> bytes:
    """`POST /act`'s JSON answer from the raw body (validated from bytes by pydantic-core): a bad observation,
    tensor or report fails its item alone.

    Raises:
        ValidationError: the body does not match `S.ActMany`.
        ServiceError: the core refused the whole call (too many items, shutting down).
    """
    body = S.ActMany.model_validate_json(raw)
    items = []
    for r in body.requests:
        rep = None
        try:
            obs, rep = observation(r), report(r)
        except ServiceError as e:  # an undecodable tensor or a bad report fails its item alone
            obs = e
        items.append((r.session_id, obs, r.step, rep))
    out = await core.act_many(items)
    return many_answer([r.session_id for r in body.requests], out)


async def answer(core: Core, sid: str, raw: bytes, content_type: str | None) -> tuple[int, bytes, dict]:
    """(status, JSON body, headers) of one act from its raw body: the content-type rule (`media`), the body checked,
    the core's answer or its error in the one envelope.

    Raises:
        Exception: anything but a refusal (a bug): the caller answers 500.
    """
    return await _answered(lambda: act_answer(core, sid, raw), raw, content_type, session_header(sid))


async def answer_many(core: Core, raw: bytes, content_type: str | None) -> tuple[int, bytes, dict]:
    """`answer` for `POST /act` (`acts_answer`): 200 with every item's answer or error, or the whole call's error.

    Raises:
        Exception: anything but a refusal (a bug): the caller answers 500.
    """
    return await _answered(lambda: acts_answer(core, raw), raw, content_type, {})


async def _answered(
    work: Callable[[], Awaitable[bytes]], raw: bytes, content_type: str | None, headers: dict
) -> tuple[int, bytes, dict]:
    """`work()`'s answer to the body unless the body is empty or not JSON, or its refusal, in the one error
    envelope."""
    try:
        if not raw:
            return 400, error_bytes("invalid_argument", "request body is required: a JSON object"), headers
        refusal = media.refusal(content_type)
        if refusal is not None:
            return refusal.http_status, error_bytes(refusal.code, refusal.message), headers
        try:
            return 200, await work(), headers
        except ValidationError as e:
            return (
                400,
                error_bytes("invalid_argument", validation_message(e.errors(include_url=False))),
                headers,
            )
    except ServiceError as e:
        return e.http_status, error_bytes(e.code, e.message), headers


class FastAct:
    """`POST /sessions/{id}/act` and `POST /act` answered below FastAPI's routing and middleware (`answer`,
    `answer_many`; the body limit as every route has it, request metrics under the documented routes' names, a 413
    and the time reading the body included; `AuthFirst` and `ServedBy` still wrap it). A client that goes away before
    its body arrived is neither answered nor counted. Any other request passes through untouched."""

    _PATH = re.compile(r"^/sessions/([^/]+)/act$|^/act$")

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.limit = settings.max_request_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        m = self._PATH.match(scope.get("path", "")) if scope["type"] == "http" else None
        if m is None or scope["method"] != "POST":
            return await self.app(scope, receive, send)
        core = scope["app"].state.core
        t0 = time.perf_counter()
        # `path` is decoded once by the server, as for every route: never decode it again. None: POST /act.
        sid = m.group(1)
        in_flight = core.metrics.in_flight_rest
        in_flight.inc()
        try:
            answered = await self._answer(core, scope, receive, sid)
            if answered is None:  # the client went away before its body arrived: nothing to answer or count
                return
            status, body, headers = answered
            raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
            raw += [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in headers.items()]
            await send({"type": "http.response.start", "status": status, "headers": raw})
            await send({"type": "http.response.body", "body": body})
        finally:
            in_flight.dec()
        core.metrics.observe_request(
            "rest", "act" if sid is not None else "act_many", str(status), time.perf_counter() - t0
        )

    async def _answer(
        self, core: Core, scope: Scope, receive: Receive, sid: str | None
    ) -> tuple[int, bytes, dict] | None:
        try:
            try:
                raw = await media.read_body(scope, receive, self.limit)
            except ClientDisconnect:
                return None
            if raw is None:
                e = PayloadTooLarge(f"request body is larger than the limit of {self.limit} bytes")
                return e.http_status, error_bytes(e.code, e.message), {"Connection": "close"}
            content_type = next((v for k, v in scope["headers"] if k == b"content-type"), None)
            ct = None if content_type is None else content_type.decode("latin-1")
            return await (answer(core, sid, raw, ct) if sid is not None else answer_many(core, raw, ct))
        except Exception as e:  # noqa: BLE001 - the error envelope, never a dropped connection
            log.exception("unhandled error", extra={"path": scope.get("path")})
            return 500, error_bytes("internal", f"internal error: {type(e).__name__}"), {}
