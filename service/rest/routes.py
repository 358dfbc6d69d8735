"""REST routes: convert JSON to core calls and back, nothing else."""

from __future__ import annotations

import asyncio
from typing import Annotated, Literal

import numpy as np
import orjson
from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from gmt.common.recording import COLUMNS
from gmt.service.core import Core
from gmt.service.rest import act as act_path
from gmt.service.rest import schemas as S
from gmt.service.rest.answers import SESSION_HEADER, session_header
from gmt.service.rest.media import require_json
from gmt.service.views import MAX_LIST_OFFSET, MAX_TIMELINE_PAGE

_ERRORS = {
    400: "Invalid argument",
    404: "Unknown or expired model or session",
    409: "Failed precondition (the act's step is not the session's), aborted (another replica changed the "
    "session: retry) or already_exists (a session_id taken by another request)",
    413: "Request body larger than --max-request-bytes",
    429: "The server holds --max-sessions live sessions",
    503: "Unavailable: no model loaded, shutting down, or the session store is unreachable (retry)",
}


def errors(*codes: int) -> dict:
    """The documented error answers of a route (401 is added by `openapi` when auth is on)."""
    return {c: {"model": S.ErrorOut, "description": _ERRORS[c]} for c in codes}


def get_core(request: Request) -> Core:
    """The core the app serves (set by the lifespan)."""
    return request.app.state.core


CoreDep = Annotated[Core, Depends(get_core)]


# Auth (with --auth-token) is checked by `app.AuthFirst` before anything reads a body; `openapi` declares it.
public = APIRouter(tags=["health"])
api = APIRouter(dependencies=[Depends(require_json)])  # bodies must be declared JSON (415 otherwise)


@public.get("/healthz", response_model=S.Health)
async def healthz() -> S.Health:
    """Liveness: the process answers."""
    return S.Health(status="ok")


@public.get("/readyz", response_model=S.Readiness, responses={503: {"model": S.Readiness}})
async def readyz(core: CoreDep) -> JSONResponse:
    """Readiness: at least one model is loaded and the server is not shutting down."""
    r = core.readiness()
    return JSONResponse(S.Readiness(**r).model_dump(), status_code=200 if r["ready"] else 503)


@api.get("/metrics", tags=["health"], response_class=Response)
async def metrics(core: CoreDep) -> Response:
    """Prometheus metrics."""
    body, content_type = core.metrics.render()
    return Response(body, media_type=content_type)


@api.get("/models", response_model=S.ModelList, tags=["models"])
async def list_models(core: CoreDep) -> S.ModelList:
    """Every loaded model."""
    return S.ModelList(
        models=[S.summary(v) for v in core.list_models()], model_state=core.model_state.where.split()[0]
    )


@api.get("/models/{name}", response_model=S.ModelOut, tags=["models"], responses=errors(404))
async def get_model(name: str, core: CoreDep, request: Request) -> S.ModelOut:
    """A model's spaces, goal table, context length and an example observation."""
    view = core.get_model(name)
    return S.ModelOut.of(view, getattr(request.app.state, "examples", {}).get(view.name))


@api.post(
    "/sessions",
    response_model=S.SessionOut,
    status_code=201,
    tags=["sessions"],
    responses=errors(400, 404, 409, 413, 429, 503),
)
async def create_session(body: S.CreateSession, core: CoreDep, response: Response) -> S.SessionOut:
    """Create a session on a model with a goal id, goal name, or target statistic value."""
    v = await core.create_session(
        body.model,
        body.goal,
        body.target,
        body.seed,
        body.action_mode,
        body.session_id,
        body.version,
        body.record,
    )
    response.headers[SESSION_HEADER] = v.session_id
    return S.SessionOut.of(v)


@api.get("/sessions/{session_id}", response_model=S.SessionOut, tags=["sessions"], responses=errors(404, 503))
async def get_session(session_id: str, core: CoreDep, response: Response) -> S.SessionOut:
    """A session's state (does not reset its idle timer)."""
    response.headers.update(session_header(session_id))
    return S.SessionOut.of(await core.get_session(session_id))


def _raw_body(model: type) -> dict:
    """The documented request body of a route that reads its raw bytes (`act_path.FastAct`'s): the model's
    component, which `openapi.build` adds (FastAPI collects none from `openapi_extra`)."""
    schema = {"$ref": f"#/components/schemas/{model.__name__}"}
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": schema}}}}


@api.post(
    "/sessions/{session_id}/act",
    response_model=S.ActOut,
    tags=["sessions"],
    openapi_extra=_raw_body(S.Act),
    responses=errors(400, 404, 409, 413, 503),
)
async def act(session_id: str, request: Request, core: CoreDep) -> Response:
    """One step: the observation in, the action out."""
    # Answered by `act_path.FastAct` below FastAPI's routing; this route documents it, with the same implementation.
    body = await request.body()
    status, answer, headers = await act_path.answer(
        core, session_id, body, request.headers.get("content-type")
    )
    return Response(answer, status, headers, media_type="application/json")


@api.post(
    "/act",
    response_model=S.ActManyOut,
    response_model_exclude_none=True,
    tags=["sessions"],
    openapi_extra=_raw_body(S.ActMany),
    responses=errors(400, 413, 503),
)
async def act_many(request: Request, core: CoreDep) -> Response:
    """One step for each of many sessions in one forward pass; results in request order, a bad item fails alone
    (HTTP 200 for the call). A session may appear once per call."""
    # Answered by `act_path.FastAct` below FastAPI's routing; this route documents it, with the same implementation.
    body = await request.body()
    status, answer, headers = await act_path.answer_many(core, body, request.headers.get("content-type"))
    return Response(answer, status, headers, media_type="application/json")


@api.put(
    "/sessions/{session_id}/goal",
    response_model=S.SetGoalOut,
    tags=["sessions"],
    responses=errors(400, 404, 409, 413, 503),
)
async def set_goal(session_id: str, body: S.SetGoal, core: CoreDep, response: Response) -> S.SetGoalOut:
    """Change the goal from the next step on (`effective_step`), optionally blended over `blend_steps` steps.
    Repeating the last change before the next act changes nothing."""
    response.headers.update(session_header(session_id))
    return S.SetGoalOut.of(
        await core.set_goal(session_id, body.goal, body.target, body.blend_steps, by="rest")
    )


@api.get(
    "/sessions/{session_id}/timeline",
    response_model=S.TimelineOut,
    tags=["records"],
    responses=errors(400, 404, 503),
)
async def timeline(
    session_id: str,
    core: CoreDep,
    response: Response,
    offset: int = Query(0, ge=0, le=MAX_LIST_OFFSET, description="Entries to skip."),
    limit: int = Query(
        MAX_TIMELINE_PAGE, ge=1, le=MAX_TIMELINE_PAGE, description="Entries to list at most (one page)."
    ),
) -> S.TimelineOut:
    """Every goal the session had, from the step of the first act that used it, a page at a time (`offset`,
    `limit`; `entries` counts them all); does not reset the idle timer."""
    response.headers.update(session_header(session_id))
    return S.TimelineOut.of(await core.timeline(session_id, offset, limit))


@api.get(
    "/sessions/{session_id}/recording",
    response_model=S.RecordingOut,
    tags=["records"],
    responses={
        200: {
            "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
            "description": "The recording: JSON, or with `format=npz` a NumPy .npz of the same columns plus "
            "`meta` (docs/records.md).",
        },
        **errors(400, 404, 503),
    },
)
async def recording(
    session_id: str,
    core: CoreDep,
    format: Annotated[
        Literal["json", "npz"], Query(description="json (lists) or npz (NumPy arrays, `np.load`).")
    ] = "json",
) -> Response:
    """The session's recording so far (a session created with `record`); does not reset the idle timer."""
    rec = await core.recording(session_id)  # assembled in a worker thread
    headers = session_header(session_id)
    if format == "npz":  # encoded in a worker thread too: up to --record-max-steps rows
        headers["Content-Disposition"] = f'attachment; filename="{rec.meta["session_id"]}.npz"'
        return Response(
            await asyncio.to_thread(rec.npz_bytes), media_type="application/octet-stream", headers=headers
        )
    return Response(
        await asyncio.to_thread(recording_json, rec), media_type="application/json", headers=headers
    )


_META = (
    "session_id",
    "model",
    "model_version",
    "fingerprint",
    "env_id",
    "action_mode",
    "seed",
    "created_at",
    "max_steps",
    "stopped",
)


def recording_json(rec) -> bytes:
    """A recording as `S.RecordingOut` JSON (NaN, a value not reported, becomes null). Float32 values are written
    as the act answers write them (their exact float64 value), so that both compare equal."""
    a = {k: v.astype(np.float64) if v.dtype == np.float32 else v for k, v in rec.arrays.items()}
    body = {k: rec.meta.get(k) for k in _META}
    body["steps"] = rec.steps
    for k in COLUMNS:  # the recording's own columns, in its order
        body[k] = a[k]
    body["infos"] = {k: a["info." + k] for k in rec.info_keys}
    body["timeline"] = rec.meta["timeline"]
    return orjson.dumps(body, option=orjson.OPT_SERIALIZE_NUMPY)


@api.post(
    "/sessions/{session_id}/reset",
    response_model=S.SessionOut,
    tags=["sessions"],
    responses=errors(400, 404, 409, 413, 503),
)
async def reset_session(
    session_id: str, core: CoreDep, response: Response, body: S.ResetSession | None = None
) -> S.SessionOut:
    """Start a new episode, keeping the goal unless one is given."""
    body = body or S.ResetSession()
    response.headers.update(session_header(session_id))
    return S.SessionOut.of(await core.reset(session_id, body.goal, body.target))


@api.delete(
    "/sessions/{session_id}",
    status_code=204,
    tags=["sessions"],
    response_class=Response,
    responses=errors(404, 503),
)
async def close_session(session_id: str, core: CoreDep) -> Response:
    """Close the session."""
    await core.close_session(session_id)
    return Response(status_code=204, headers=session_header(session_id))
