"""`gmt models list|load|promote|drain|unload`: manage the model versions a server serves, over its REST API.

Base install only (httpx and typer; no torch). The token is the server's `--admin-token`, else its `--auth-token`
(`--token`, or GMT_ADMIN_TOKEN / GMT_TOKEN); a server with no token at all takes management calls only from its
own machine (docs/models.md).
"""

from __future__ import annotations

from urllib.parse import quote

import httpx
import typer

from gmt.client.errors import ServiceError
from gmt.client.rest import rest_base_url

DEFAULT_SERVER = "http://localhost:8000"


class AdminClient:
    """The management calls of one server's REST API.

    Args:
        server: REST base URL, e.g. http://127.0.0.1:8000.
        token: Bearer token (the admin token, else the auth token), or None.
        timeout_s: Per-call timeout (a load reads and hashes the checkpoint).
    """

    def __init__(self, server: str, token: str | None = None, timeout_s: float = 120.0) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=rest_base_url(server), headers=headers, timeout=timeout_s)

    def __enter__(self) -> AdminClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.close()

    def _call(self, method: str, path: str, **kw) -> dict:
        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as e:
            raise ServiceError(f"cannot reach {self.http.base_url}: {e}", "unavailable") from None
        try:
            body = r.json()
        except ValueError:
            body = {}
        if r.status_code >= 400:
            err = body.get("error", {}) if isinstance(body, dict) else {}
            raise ServiceError(err.get("message", r.text[:200]), err.get("code", "unknown"), r.status_code)
        return body

    def models(self) -> list[dict]:
        """`GET /models`: every model with its versions."""
        return self._call("GET", "/models")["models"]

    def model(self, name: str) -> dict:
        """`GET /models/{name}`."""
        return self._call("GET", f"/models/{quote(name, safe='')}")

    def load(self, name: str, path: str, fingerprint: str | None = None) -> dict:
        """Load the checkpoint at `path` (under the server's checkpoint roots) as a version of `name`."""
        body = {"path": path, **({"fingerprint": fingerprint} if fingerprint else {})}
        return self._call("POST", f"/models/{quote(name, safe='')}/versions", json=body)

    def promote(self, name: str, version: str, share: float = 1.0) -> dict:
        """Make `version` the default (share 1) or a canary with `share` of new sessions."""
        return self._call(
            "PUT", f"/models/{quote(name, safe='')}/default", json={"version": version, "share": share}
        )

    def drain(self, name: str, version: str) -> dict:
        """Give `version` no new sessions; the server unloads it once its sessions end."""
        return self._call("POST", f"/models/{quote(name, safe='')}/versions/{quote(version, safe='')}/drain")

    def unload(self, name: str, version: str, force: bool = False) -> dict:
        """Unload `version` now (refused while sessions use it unless `force`)."""
        params = {"force": "true"} if force else {}
        return self._call(
            "DELETE", f"/models/{quote(name, safe='')}/versions/{quote(version, safe='')}", params=params
        )


def version_table(models: list[dict]) -> str:
    """`GET /models`' versions as aligned text: one line per version, the default and canary marked."""
    rows = [("MODEL", "VERSION", "STATE", "SESSIONS", "ROLE")]
    for m in models:
        canary = m.get("canary") or {}
        for v in m.get("versions", []):
            role = (
                "default"
                if v["version"] == m.get("default_version")
                else f"canary {canary['share']:g}"
                if v["version"] == canary.get("version")
                else ""
            )
            rows.append((m["name"], v["version"], v["state"], str(v["sessions"]), role))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows)


# ----- the command ---------------------------------------------------------------------------------------------
app = typer.Typer(
    help="Model versions of a running server: list, load, promote, drain, unload.", no_args_is_help=True
)
SERVER = typer.Option(
    DEFAULT_SERVER, "--server", "-s", envvar="GMT_SERVER", help="The server's REST base URL."
)
TOKEN = typer.Option(
    None,
    "--token",
    envvar=["GMT_ADMIN_TOKEN", "GMT_TOKEN"],
    help="The server's --admin-token, else its --auth-token (none: the server must be on this machine).",
)


def _run(server: str, token: str | None, call) -> dict | list:
    try:
        with AdminClient(server, token) as c:
            return call(c)
    except ServiceError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None


def _show(server: str, token: str | None) -> None:
    typer.echo(version_table(_run(server, token, lambda c: c.models())))


@app.command("list")
def list_command(server: str = SERVER, token: str = TOKEN) -> None:
    """Every model's versions: state, sessions on this server, default and canary."""
    _show(server, token)


@app.command("load")
def load_command(
    name: str = typer.Argument(..., help="Model name (a new name starts a new model)."),
    path: str = typer.Argument(..., help="Checkpoint directory under the server's checkpoint roots."),
    fingerprint: str = typer.Option(None, help="Refuse unless the fingerprint starts with these hex digits."),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Load a checkpoint as a new version of a model (it serves nobody until promoted or named)."""
    v = _run(server, token, lambda c: c.load(name, path, fingerprint))
    typer.echo(f"{name} {v['version']} loaded ({v['state']}, fingerprint {v['fingerprint']})")


@app.command("promote")
def promote_command(
    name: str = typer.Argument(..., help="Model name."),
    version: str = typer.Argument(..., help="A loaded version."),
    share: float = typer.Option(
        1.0, help="1: the default of new sessions; below 1: a canary with this share."
    ),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Make a version the default of new sessions, or a canary with --share of them."""
    _run(server, token, lambda c: c.promote(name, version, share))
    _show(server, token)


@app.command("drain")
def drain_command(
    name: str = typer.Argument(..., help="Model name."),
    version: str = typer.Argument(..., help="A loaded version other than the default."),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Give a version no new sessions; the server unloads it when its last session ends or expires."""
    _run(server, token, lambda c: c.drain(name, version))
    _show(server, token)


@app.command("unload")
def unload_command(
    name: str = typer.Argument(..., help="Model name."),
    version: str = typer.Argument(..., help="A loaded version."),
    force: bool = typer.Option(False, help="Unload even while sessions use it (their next calls fail)."),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Unload a version now (refused while sessions use it, unless --force)."""
    _run(server, token, lambda c: c.unload(name, version, force))
    _show(server, token)
