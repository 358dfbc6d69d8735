"""Methods no route answers (TRACE, CONNECT, PATCH, ...) get 405 before anything else looks at the request.

Authentication comes after: a method the server never answers is the same answer for everyone, so a client
without a token learns only what `Allow` says, and a fuzzer sees 405 (not 401) for what the API cannot do.
"""

from __future__ import annotations

from collections.abc import Iterator

from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Receive, Scope, Send

from gmt.service.rest.answers import error_response


class KnownMethods:
    """Answers 405 `method_not_allowed` (with the path's methods in `Allow`) to a method no route has.

    Args:
        app: The application (its authentication included) that gets every other request.
        routes: The application's routes, read at each refusal (routes added later count).
    """

    def __init__(self, app: ASGIApp, routes: list[BaseRoute]) -> None:
        self.app = app
        self.routes = routes
        self._known: frozenset[str] | None = None

    def known(self) -> frozenset[str]:
        """Every method some route answers."""
        if self._known is None:
            self._known = frozenset(m for r in _flat(self.routes) for m in getattr(r, "methods", None) or ())
        return self._known

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in self.known():
            return await self.app(scope, receive, send)
        path = scope.get("path", "")
        allow = sorted(
            {
                m
                for r in _flat(self.routes)
                if getattr(r, "methods", None) and getattr(r, "path_regex", None) and r.path_regex.match(path)
                for m in r.methods
            }
        )
        message = (
            f"{scope['method'][:16]} is not a method this server answers (here: {', '.join(allow) or 'none'})"
        )
        response = error_response(405, "method_not_allowed", message, {"Allow": ", ".join(allow)})
        await response(scope, receive, send)


def _flat(routes: list[BaseRoute]) -> Iterator[BaseRoute]:
    """The routes with each included router's own (FastAPI keeps an `include_router`'s routes in its router; the
    routers here have no prefix)."""
    for r in routes:
        inner = getattr(r, "original_router", None)
        if inner is not None:
            yield from _flat(inner.routes)
        else:
            yield r
