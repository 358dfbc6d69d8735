"""Who may change the served models (load, promote, drain and unload versions): the one rule, for both transports.

- With `--admin-token`: a management call must carry `Authorization: Bearer <admin token>` (the `--auth-token`
  does not do; the admin token is not needed for any other call).
- Else with `--auth-token`: the bearer auth token, as every other call.
- With no token at all: only a client on the server's own machine (a loopback peer) that did not come through a
  proxy (no `Forwarded`, `X-Forwarded-For` or `X-Real-IP` header, which nginx adds): a server without tokens
  answers anyone who reaches its ports, and a model swap must not be one of the things anyone can do. Everything
  else answers `permission_denied` naming the flags to set. Over REST such a call must also name a loopback host
  in its `Host` header (`localhost`, `127.0.0.1`, `[::1]`, with any port) and carry no `Origin` or `Referer` of
  another origin: a web page opened on the server's machine could otherwise reach the server under its own
  domain (DNS rebinding, whose requests carry the attacker's `Host`) or post to it across origins. gRPC needs
  no such check: a browser cannot speak gRPC (cleartext HTTP/2 with trailers), so no web page reaches it.

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


def authorize(
    settings: Settings,
    authorization: str | None,
    peer: str | None,
    proxied: bool,
    web: dict[str, str] | None = None,
) -> None:
    """Allow a management call, or raise why not.

    Args:
        authorization: The call's `Authorization` header / metadata (None: absent).
        peer: The client's IP address.
        proxied: The call carries a proxy's forwarding header.
        web: A REST call's headers (lower-case names), whose `Host`, `Origin` and `Referer` are checked when the
            server has no token; None for gRPC, which no browser speaks.

    Raises:
        Unauthenticated: a token is configured and the call's is missing or wrong.
        PermissionDenied: no token is configured and the call is not from this machine directly.
    """
    token = settings.management_token
    if token is None:
        if is_loopback(peer) and not proxied:
            if web is not None:
                _same_machine_page(web)
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


_NO_TOKEN = "model management without a token answers only clients on the server's machine"
_TOKEN_HINT = "; start the server with --admin-token (or --auth-token) to manage it with a token"


def _same_machine_page(headers: dict[str, str]) -> None:
    """Refuse a tokenless management call that a web page may have sent: a `Host` that is not a loopback name
    (DNS rebinding), or an `Origin` / `Referer` of another origin than the `Host` (a cross-origin request)."""
    host = headers.get("host")
    if host is None or not is_loopback_name(host):
        shown = "no Host header" if host is None else f"Host {host[:100]!r}"
        raise PermissionDenied(
            f"{_NO_TOKEN}, named by a loopback Host (localhost, 127.0.0.1 or [::1]); this call has {shown}, "
            "as a web page reaching the server under another name by DNS rebinding would" + _TOKEN_HINT
        )
    for name in ("origin", "referer"):
        value = headers.get(name)
        if value is not None and _netloc(value) != host.lower():
            raise PermissionDenied(
                f"{_NO_TOKEN}, not requests sent by a web page of another origin: {name.capitalize()} "
                f"{value[:100]!r} is not this server's origin ({host[:100]!r})" + _TOKEN_HINT
            )


def is_loopback_name(host: str) -> bool:
    """Whether a `Host` header value (`name[:port]`, `[v6][:port]`) names this machine: `localhost`, a name under
    `.localhost` (RFC 6761) or a loopback address."""
    try:
        parts = urllib.parse.urlsplit(f"//{host}")  # ValueError on a broken IPv6 literal
        name, _ = parts.hostname, parts.port  # ... and on a bad port
    except ValueError:
        return False
    if not name:
        return False
    return name == "localhost" or name.endswith(".localhost") or is_loopback(name)


def _netloc(url: str) -> str | None:
    """The `host[:port]` of an `Origin` / `Referer` URL, lower-case (None for `null` or a URL without one)."""
    try:
        return urllib.parse.urlsplit(url.strip()).netloc.lower() or None
    except ValueError:
        return None


def grpc_peer_host(peer: str) -> str | None:
    """The IP address of a gRPC peer string (`ipv4:127.0.0.1:5000`, `ipv6:[::1]:5000`); None for others."""
    kind, _, rest = urllib.parse.unquote(peer).partition(":")
    if kind == "ipv4":
        return rest.rpartition(":")[0]
    if kind == "ipv6":
        return rest.rpartition(":")[0].strip("[]")
    return None
