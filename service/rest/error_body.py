"""The one error body of the REST adapter: `{"error": {"code", "message"}}` (codes and statuses from
`gmt.service.errors`)."""

from __future__ import annotations

import orjson
from fastapi.responses import JSONResponse


def error_response(status: int, code: str, message: str, headers: dict | None = None) -> JSONResponse:
    """The one error body: `{"error": {"code", "message"}}`."""
    return JSONResponse({"error": {"code": code, "message": message}}, status_code=status, headers=headers)


def error_bytes(code: str, message: str) -> bytes:
    """The same body, encoded, for an answer written below FastAPI (`app.FastAct`)."""
    return orjson.dumps({"error": {"code": code, "message": message}})
