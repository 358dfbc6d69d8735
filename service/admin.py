"""Who may change the served models (load, promote, drain and unload versions): the one rule, for both transports.

- With `--admin-token`: a management call must carry `Authorization: Bearer <admin token>` (the `--auth-token`
  does not do; the admin token is not needed for any other call).
- Else with `--auth-token`: the bearer auth token, as every other call.
- With no token at all: only a client on the server's own machine (a loopback peer) that did not come through a
  proxy (no `Forwarded`, `X-Forwarded-For` or `X-Real-IP` header, which nginx adds): a server without tokens
  answers anyone who reaches its ports, and a model swap must not be one of the things anyone can do. Everything
  else answers `permission_denied` naming the flags to set.

Whatever the caller, a checkpoint is loaded only from under the configured checkpoint roots (`Core.checkpoint_path`).
"""

from __future__ import annotations

import ipaddress
import re
import secrets
import urllib.parse

from gmt.service.errors import PermissionDenied, Unauthenticated
from gmt.service.settings import Settings

PROXY_HEADERS = ("forwarded", "x-forwarded-for", "x-real-ip")
GRPC_SERVICE = "/gmt.v1.ModelAdmin/"
# REST: /models/{name}/versions, /models/{name}/versions/{v}, /models/{name}/versions/{v}/drain, /models/{name}/default
_REST_PATH = re.compile(r"^/models/[^/]+/(?:versions(?:/[^/]+(?:/drain)?)?|default)/?$")


def is_management_path(path: str) -> bool:
    """Whether a REST path is a management call's."""
    return bool(_REST_PATH.match(path))


def is_loopback(host: str | None) -> bool:
    """Whether `host` (an IP address, as a peer is reported) is a loopback address."""
    if not host:
        return False
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def authorize(settings: Settings, authorization: str | None, peer: str | None, proxied: bool) -> None:
    """Allow a management call, or raise why not.

    Args:
        authorization: The call's `Authorization` header / metadata (None: absent).
        peer: The client's IP address.
        proxied: The call carries a proxy's forwarding header.

    Raises:
        Unauthenticated: a token is configured and the call's is missing or wrong.
        PermissionDenied: no token is configured and the call is not from this machine directly.
    """
    token = settings.management_token
    if token is None:
        if is_loopback(peer) and not proxied:
            return
        raise PermissionDenied(
            "model management is open only to clients on the server's machine when the server has no token "
            "(and never through a proxy); start it with --admin-token (or --auth-token) to manage it remotely"
        )
    which = "admin token" if settings.admin_token else "bearer token"
    if authorization is None or authorization[:7].lower() != "bearer ":
        raise Unauthenticated(f"model management needs the {which}: send 'Authorization: Bearer <token>'")
    if not secrets.compare_digest(authorization[7:].strip().encode(), token.encode()):
        raise Unauthenticated(f"invalid {which} for model management")


def grpc_peer_host(peer: str) -> str | None:
    """The IP address of a gRPC peer string (`ipv4:127.0.0.1:5000`, `ipv6:[::1]:5000`); None for others."""
    kind, _, rest = urllib.parse.unquote(peer).partition(":")
    if kind == "ipv4":
        return rest.rpartition(":")[0]
    if kind == "ipv6":
        return rest.rpartition(":")[0].strip("[]")
    return None
