"""Errors a client raises: one class per server error code, the same for REST and gRPC.

The server answers REST errors as `{"error": {"code", "message"}}` with an HTTP status and gRPC errors with a
status code and details; both become a `ServiceError` subclass carrying the server's own message.
"""

from __future__ import annotations


class ServiceError(Exception):
    """An error answered by the server (or the failure to reach it).

    Attributes:
        code: Snake_case error code, e.g. "not_found" (the REST body's code, or the gRPC status name lowercased).
        message: The server's message.
        status: HTTP status (REST), gRPC status name, or "control_stream" for an error the `Control` stream
            answered in-band (its `code` is the server's), when there was an answer.
    """

    code = "unknown"

    def __init__(self, message: str, code: str | None = None, status: int | str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.status = status
        if code is not None:
            self.code = code

    def __str__(self) -> str:
        return f"{self.code}: {self.message}"


class InvalidArgument(ServiceError):
    """The request was malformed (bad observation, unknown goal, ...)."""

    code = "invalid_argument"


class Unauthenticated(ServiceError):
    """A bearer token is required and was missing or wrong."""

    code = "unauthenticated"


class PermissionDenied(ServiceError):
    """The caller may not do this."""

    code = "permission_denied"


class NotFound(ServiceError):
    """No such model or session (an expired session is not found too)."""

    code = "not_found"


class FailedPrecondition(ServiceError):
    """The request is well-formed but the server is not in a state to run it."""

    code = "failed_precondition"


class AlreadyExists(ServiceError):
    """A session id the client chose is taken by a session created with other parameters."""

    code = "already_exists"


class Aborted(ServiceError):
    """Another replica changed the session between this request's read and its write; nothing was applied and
    retrying is safe (the clients do, a few times)."""

    code = "aborted"


class ResourceExhausted(ServiceError):
    """Too many live sessions, or a message over the size limit."""

    code = "resource_exhausted"


class PayloadTooLarge(ResourceExhausted):
    """The request was larger than the server accepts (gRPC reports it as resource_exhausted)."""

    code = "payload_too_large"


class Unavailable(ServiceError):
    """The server answered that it cannot serve now (no model loaded, shutting down, store down)."""

    code = "unavailable"


class ConnectionFailed(Unavailable):
    """The server could not be reached at all, after the configured retries."""


class DeadlineExceeded(ServiceError):
    """The call did not complete within its timeout."""

    code = "deadline_exceeded"


class Internal(ServiceError):
    """The server failed unexpectedly."""

    code = "internal"


class ProtocolError(ServiceError):
    """The server's answer could not be understood (wrong shape, not JSON, ...)."""

    code = "protocol_error"


_BY_CODE: dict[str, type[ServiceError]] = {
    c.code: c
    for c in (
        InvalidArgument,
        Unauthenticated,
        PermissionDenied,
        NotFound,
        FailedPrecondition,
        AlreadyExists,
        Aborted,
        ResourceExhausted,
        PayloadTooLarge,
        Unavailable,
        DeadlineExceeded,
        Internal,
    )
}
_BY_HTTP_STATUS: dict[int, type[ServiceError]] = {
    400: InvalidArgument,
    401: Unauthenticated,
    403: PermissionDenied,
    404: NotFound,
    409: FailedPrecondition,
    413: PayloadTooLarge,
    422: InvalidArgument,
    429: ResourceExhausted,
    502: Unavailable,  # a proxy that lost its upstream
    503: Unavailable,
    504: DeadlineExceeded,
}


def error_for(code: str, message: str, status: int | str | None = None) -> ServiceError:
    """The `ServiceError` subclass for a server error code (a generic ServiceError for an unknown code)."""
    cls = _BY_CODE.get(code.lower())
    if cls is None and isinstance(status, int):
        cls = _BY_HTTP_STATUS.get(status, Internal if status >= 500 else None)
    return (cls or ServiceError)(message, code=code.lower(), status=status)
