"""What every REST answer shares: the one error body `{"error": {"code", "message"}}` (codes and statuses from
`gmt.service.errors`), the message naming what a request body got wrong, and the `X-Session-Id` header."""

from __future__ import annotations

import re

import orjson
from fastapi.responses import JSONResponse

from gmt.service.ids import MAX_ID_LENGTH

SESSION_HEADER = "X-Session-Id"


def error_response(status: int, code: str, message: str, headers: dict | None = None) -> JSONResponse:
    """The one error body: `{"error": {"code", "message"}}`."""
    return JSONResponse({"error": {"code": code, "message": message}}, status_code=status, headers=headers)


def error_bytes(code: str, message: str) -> bytes:
    """The same body, encoded, for an answer written below FastAPI (`act.FastAct`)."""
    return orjson.dumps({"error": {"code": code, "message": message}})


def session_header(sid: str | None) -> dict:
    """`X-Session-Id` for a response, when the id can be a session's (printable ASCII, at most 128 characters);
    else none: a hostile id is never echoed."""
    ok = sid and len(sid) <= MAX_ID_LENGTH and sid.isascii() and sid.isprintable()
    return {SESSION_HEADER: sid} if ok else {}


_UNION_TAG = re.compile(r"^(int|str|float|bool|none|list\[.*\]|dict\[.*\]|function-.*|[A-Z]\w*)$")


def _field(loc: tuple) -> str:
    parts = [str(p) for p in loc]
    if parts and parts[0] in ("body", "query", "path", "header"):
        parts = parts[1:]
    # union branches (goal.int / goal.str, observation.list[any] / observation.Tensor) name the same field
    return ".".join(p for p in parts if not _UNION_TAG.match(p)) or "body"


def validation_message(errors) -> str:
    """One message naming every field a body got wrong (or where its JSON broke)."""
    if any(e.get("type") == "json_invalid" for e in errors):
        e = next(e for e in errors if e.get("type") == "json_invalid")
        detail = (e.get("ctx") or {}).get("error", "invalid")
        loc = e.get("loc", ())
        where = f" at character {loc[1]}" if len(loc) > 1 else ""
        msg = f"request body is not valid JSON: {detail}{where}"
    else:
        by_field: dict[str, list[str]] = {}
        for e in errors:
            by_field.setdefault(_field(tuple(e.get("loc", ()))), []).append(e.get("msg", "invalid"))
        msg = "; ".join(f"{f}: {' or '.join(dict.fromkeys(m))}" for f, m in by_field.items())
    return msg
