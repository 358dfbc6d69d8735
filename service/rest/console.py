"""REST routes of the console: `GET /sessions` (the listing), `GET /sessions/{id}/events` (server-sent events) and
the page itself, `GET /ui` and `GET /ui/<asset>` (static files shipped in the package, no CDN).

Auth: the page and its assets hold no data and are served without a token (a browser cannot send a header on a
page load); the page asks for the token, keeps it in the tab's `sessionStorage`, and sends it as `Authorization:
Bearer` on every call it makes, the event stream included (read with `fetch`, not `EventSource`, which cannot set
headers), so no token ever appears in a URL. `app.AuthFirst` leaves `PATHS` open and guards everything else.
"""

from __future__ import annotations

import asyncio
import functools
from pathlib import Path

import orjson
from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, Field
from starlette.types import Receive, Scope, Send

from gmt.service.core import Core
from gmt.service.errors import NotFound, ServiceError
from gmt.service.events import Subscription
from gmt.service.rest import schemas as S
from gmt.service.rest.answers import session_header
from gmt.service.rest.routes import CoreDep, errors
from gmt.service.views import MAX_LIST_OFFSET, MAX_LIST_SESSIONS

STATIC = (
    Path(__file__).resolve().parent.parent / "console" / "static"
)  # the page's files (`gmt.service.console`)
ASSETS = {  # every file the page loads: nothing else is served from /ui
    "console.js": "text/javascript; charset=utf-8",
    "console.css": "text/css; charset=utf-8",
}
PATHS = frozenset({"/ui", *(f"/ui/{name}" for name in ASSETS)})
"""The page and its assets: open without a token (see `app.AuthFirst`)."""
PAGE_HEADERS = {
    # Only this origin: the page can load nothing from elsewhere and send nothing elsewhere.
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
    "img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}
KEEPALIVE_S = (
    15.0  # a comment line this often on an idle stream (proxies keep it open; a gone session is noticed)
)
FLUSH_EVERY_S = 0.05  # events are written at most this often per stream, in batches

EVENT_KINDS = ("session", "act", "goal", "reset", "dropped", "closed", "expired")

router = APIRouter()


class SessionRowOut(BaseModel):
    """One live session of the listing."""

    session_id: str
    model: str
    goal: int
    goal_name: str
    step: int = Field(description="Steps acted in the current episode.")
    idle_s: float = Field(description="Seconds since its last act, goal change or reset.")
    acts_per_s: float | None = Field(
        description="Acts per second over the last few seconds (null before any)."
    )
    last_latency_ms: float | None = Field(description="The last act's time in the server (null before any).")
    served_by: str | None = Field(
        description="Replica id that served its last act (null when unknown: a shared store's session that no "
        "replica has acted for)."
    )


class SessionListOut(BaseModel):
    """`GET /sessions`: a page of the live sessions, newest first."""

    sessions: list[SessionRowOut]
    total: int = Field(description="Live sessions in the store (all replicas, for a shared store).")
    offset: int
    limit: int
    replica: str = Field(description="The replica that answered.")


@router.get(
    "/sessions",
    response_model=SessionListOut,
    tags=["sessions"],
    responses=errors(400, 503),
)
async def list_sessions(
    core: CoreDep,
    offset: int = Query(0, ge=0, le=MAX_LIST_OFFSET, description="Sessions to skip."),
    limit: int = Query(50, ge=1, le=MAX_LIST_SESSIONS, description="Sessions to list at most."),
) -> SessionListOut:
    """Live sessions, newest first (memory store: by creation; Redis: by last use as of the replicas' last
    sweeps), a page at a time, with each one's goal, step, acts/s, last latency and serving replica."""
    total, rows = await core.list_sessions(offset, limit)
    return SessionListOut(
        sessions=[SessionRowOut(**vars(r)) for r in rows],
        total=total,
        offset=offset,
        limit=limit,
        replica=core.settings.replica_id,
    )


_EVENTS_DOC = {
    200: {
        "description": "`text/event-stream`: `session` (the state at subscription), then `act` (`step`, `goal`, "
        "`action`, `latency_ms`), `goal` (`goal`, `goal_name`, `step` of the first act that uses it, `given`, "
        "`blend_steps`), `reset`, `dropped` (`count`: events a slow reader lost), and last `closed` or "
        "`expired`. Acts served by another replica are not seen here (a proxy routes a session's calls, this "
        "one included, to one replica).",
        "content": {
            "text/event-stream": {
                "schema": {
                    "type": "object",
                    "description": "One event: its kind, and its data as JSON.",
                    "properties": {"event": {"enum": list(EVENT_KINDS)}, "data": {"type": "string"}},
                    "required": ["event", "data"],
                }
            }
        },
    },
    **errors(404, 503),
    429: {"model": S.ErrorOut, "description": "Too many event streams (per session or per replica)"},
}


@router.get(
    "/sessions/{session_id}/events",
    tags=["sessions"],
    response_class=Response,
    responses=_EVENTS_DOC,
)
async def session_events(session_id: str, core: CoreDep) -> Response:
    """Server-sent events of the session on this replica, as they happen (the console's live charts)."""
    view = await core.get_session(session_id)
    sub = core.events.subscribe(session_id)
    first = _encode("session", {k: v for k, v in vars(view).items() if k != "context_goals"})
    return EventStream(core, sub, first, session_header(session_id))


def _encode(kind: str, data: dict) -> bytes:
    return b"event: " + kind.encode() + b"\ndata: " + orjson.dumps(data) + b"\n\n"


class EventStream(Response):
    """A response that writes a subscription's events until it closes or the client leaves.

    A client that leaves is noticed at once (its disconnect ends the subscription); a session closed on another
    replica, at the next keep-alive.
    """

    media_type = "text/event-stream"

    def __init__(self, core: Core, sub: Subscription, first: bytes, headers: dict) -> None:
        self.core, self.sub, self.first = core, sub, first
        self.status_code, self.background = 200, None
        # no-store: never cached; X-Accel-Buffering: nginx passes each event on at once
        self.init_headers({"Cache-Control": "no-store", "X-Accel-Buffering": "no", **headers})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        sub, hub = self.sub, self.core.events
        listener = asyncio.get_running_loop().create_task(self._until_disconnect(receive))
        try:
            await send({"type": "http.response.start", "status": 200, "headers": self.raw_headers})
            await send({"type": "http.response.body", "body": self.first, "more_body": True})
            while True:
                await sub.wait(KEEPALIVE_S)
                closed = sub.closed  # read first: every event queued before the close is then taken below
                events, dropped = sub.take()
                chunk = b"".join(_encode(kind, data) for kind, data in events)
                if dropped:
                    chunk = _encode("dropped", {"count": dropped}) + chunk
                if not events and not closed:
                    chunk = b": keep-alive\n\n" + await self._gone()
                if chunk:
                    await send({"type": "http.response.body", "body": chunk, "more_body": True})
                if closed:
                    break
                await asyncio.sleep(FLUSH_EVERY_S)  # batch what comes meanwhile into the next write
            await send({"type": "http.response.body", "body": b"", "more_body": False})
        except OSError:
            pass  # the client left mid-write
        finally:
            listener.cancel()
            hub.unsubscribe(sub)

    async def _until_disconnect(self, receive: Receive) -> None:
        while (await receive())["type"] != "http.disconnect":
            pass
        self.sub.close()

    async def _gone(self) -> bytes:
        """A `closed` event (and the feed's end) when the session no longer exists, else nothing."""
        try:
            await self.core.get_session(self.sub.session_id)
        except NotFound:
            self.sub.close()
            return _encode("closed", {"session_id": self.sub.session_id})
        except ServiceError:
            pass  # the store is unreachable for now: keep the stream
        return b""


@functools.cache
def _asset(name: str) -> bytes:
    return (STATIC / name).read_bytes()


@router.get("/ui", include_in_schema=False)
async def console_page() -> Response:
    """The console page."""
    return Response(_asset("index.html"), media_type="text/html; charset=utf-8", headers=PAGE_HEADERS)


@router.get("/ui/{name}", include_in_schema=False)
async def console_asset(name: str) -> Response:
    """One of the page's static files."""
    if name not in ASSETS:
        raise NotFound(f"no console asset {name!r}; the console is at /ui")
    return Response(_asset(name), media_type=ASSETS[name], headers=PAGE_HEADERS)
