"""One error hierarchy for the service, mapped once to HTTP status codes and gRPC status codes.

The core raises these; the REST adapter answers `{"error": {"code", "message"}}` with `http_status`, the gRPC
adapter aborts with `grpc_code` (the name of a `grpc.StatusCode`, so this module needs no gRPC import).
"""

from __future__ import annotations

MAX_MESSAGE = 1024  # longest error message answered (well inside gRPC's 8 KiB metadata budget for a status)


class ServiceError(Exception):
    """Base class: an error a client can see.

    Attributes:
        code: Stable snake_case code used in REST bodies and gRPC in-band errors.
        http_status: HTTP status code of the REST answer.
        grpc_code: Name of the `grpc.StatusCode` of the gRPC answer.
        message: Human-readable explanation.
    """

    code = "internal"
    http_status = 500
    grpc_code = "INTERNAL"

    def __init__(self, message: str) -> None:
        if len(message) > MAX_MESSAGE:  # a message may quote the request: never echo a hostile amount of it
            message = f"{message[: MAX_MESSAGE - 40]}... ({len(message) - MAX_MESSAGE + 40} characters cut)"
        super().__init__(message)
        self.message = message


class InvalidArgument(ServiceError):
    """The request is malformed: bad observation, unknown goal, bad blend_steps, ..."""

    code, http_status, grpc_code = "invalid_argument", 400, "INVALID_ARGUMENT"


class Unauthenticated(ServiceError):
    """A bearer token is required and was missing or wrong."""

    code, http_status, grpc_code = "unauthenticated", 401, "UNAUTHENTICATED"


class PermissionDenied(ServiceError):
    """The caller is known (or needs no token) but may not do this: a management call from where it is not
    allowed, a checkpoint path outside the checkpoint roots."""

    code, http_status, grpc_code = "permission_denied", 403, "PERMISSION_DENIED"


class NotFound(ServiceError):
    """No such model or session."""

    code, http_status, grpc_code = "not_found", 404, "NOT_FOUND"


class SessionExpired(NotFound):
    """The session existed but was idle for longer than the idle timeout."""


class FailedPrecondition(ServiceError):
    """The request is well-formed but the system is not in a state to run it."""

    code, http_status, grpc_code = "failed_precondition", 409, "FAILED_PRECONDITION"


class AlreadyExists(ServiceError):
    """A client-chosen session id is taken by a session created with other parameters."""

    code, http_status, grpc_code = "already_exists", 409, "ALREADY_EXISTS"


class Aborted(ServiceError):
    """Another replica changed the session between this request's read and its write; retrying is safe."""

    code, http_status, grpc_code = "aborted", 409, "ABORTED"


class PayloadTooLarge(ServiceError):
    """The request body or message is larger than the configured limit."""

    code, http_status, grpc_code = "payload_too_large", 413, "RESOURCE_EXHAUSTED"


class UnsupportedMediaType(ServiceError):
    """A REST request body that is not declared JSON (see `gmt.service.rest.media`); gRPC has no such case."""

    code, http_status, grpc_code = "unsupported_media_type", 415, "INVALID_ARGUMENT"


class ResourceExhausted(ServiceError):
    """The server holds its maximum number of live sessions, or a session's goal changed too often at one step."""

    code, http_status, grpc_code = "resource_exhausted", 429, "RESOURCE_EXHAUSTED"


class Unavailable(ServiceError):
    """No model is loaded, the server is shutting down, or the session store is unreachable."""

    code, http_status, grpc_code = "unavailable", 503, "UNAVAILABLE"


class DeadlineExceeded(ServiceError):
    """The caller's deadline passed before the answer was ready."""

    code, http_status, grpc_code = "deadline_exceeded", 504, "DEADLINE_EXCEEDED"


class Internal(ServiceError):
    """A bug: anything unexpected."""
