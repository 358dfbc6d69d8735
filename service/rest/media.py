"""The content-type rule of the JSON endpoints: a request body is read only when its Content-Type says JSON.

`application/json` (with parameters, e.g. `; charset=utf-8`) and any `application/*+json` are JSON. Anything else
answers 415 unsupported_media_type naming the type received and the one expected, before the body is parsed, and
so does a body without a Content-Type: curl's `-d` sends `application/x-www-form-urlencoded` anyway, so accepting
a missing header would help no curl user, while a web page can make a browser send a body without a Content-Type,
and without a CORS preflight, to a server on localhost (FastAPI refuses to parse such bodies for that reason). A
request without a body is not concerned. `FastAct` applies the rule to `POST /sessions/{id}/act` and `POST /act`,
`require_json` (a dependency of every API route) to the others; `openapi` documents the 415. A compressed body (a
Content-Encoding other than identity) answers 415 too (`encoding_refusal`, applied to every route by `app.PlainBodies`). A body is
read whole, up to the request-size limit, by `read_body` (`app.BodyLimit` and `act.FastAct`).
"""

from __future__ import annotations

from fastapi import Request
from starlette.requests import ClientDisconnect
from starlette.types import Receive, Scope

from gmt.service.errors import UnsupportedMediaType

JSON = "application/json"
_SHOWN = 100  # longest Content-Type quoted back


def is_json(content_type: str) -> bool:
    """Whether a Content-Type value declares JSON (`application/json` or `application/*+json`)."""
    media = content_type.split(";", 1)[0].strip().lower()
    return media == JSON or (media.startswith("application/") and media.endswith("+json"))


def encoding_refusal(content_encoding: str) -> UnsupportedMediaType | None:
    """The 415 for a body sent with a Content-Encoding other than identity (RFC 7694): this server decodes none."""
    if content_encoding.strip().lower() in ("", "identity"):
        return None
    return UnsupportedMediaType(
        f"request body sent with Content-Encoding {content_encoding.strip()[:_SHOWN]!r}; this server reads "
        "uncompressed bodies only: send the JSON without Content-Encoding"
    )


def refusal(content_type: str | None) -> UnsupportedMediaType | None:
    """The 415 for a body sent with `content_type` (None: no header), or None when it is JSON."""
    if content_type is not None and is_json(content_type):
        return None
    got = "no Content-Type" if content_type is None else f"Content-Type {content_type.strip()[:_SHOWN]!r}"
    return UnsupportedMediaType(
        f"request body sent with {got}; expected Content-Type: {JSON} "
        "(curl: add -H 'content-type: application/json', or use --json instead of -d)"
    )


async def require_json(request: Request) -> None:
    """FastAPI dependency: a POST / PUT / PATCH body whose Content-Type is not JSON answers 415.

    Raises:
        UnsupportedMediaType: the request has a body that is not declared JSON.
    """
    if request.method in ("POST", "PUT", "PATCH") and await request.body():
        error = refusal(request.headers.get("content-type"))
        if error is not None:
            raise error


async def read_body(scope: Scope, receive: Receive, limit: int) -> bytes | None:
    """The whole request body, or None once it is over `limit` bytes (a Content-Length over it is refused unread).

    Raises:
        ClientDisconnect: the client left before the body ended.
    """
    for k, v in scope["headers"]:
        if k == b"content-length" and v.isdigit() and int(v) > limit:
            return None
    chunks, size = [], 0
    while True:
        msg = await receive()
        if msg["type"] != "http.request":
            raise ClientDisconnect
        chunks.append(msg.get("body", b""))
        size += len(chunks[-1])
        if size > limit:
            return None
        if not msg.get("more_body", False):
            return b"".join(chunks)
