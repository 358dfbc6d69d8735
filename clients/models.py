"""`gmt models list|load|promote|drain|unload`: manage the model versions a server serves, over its REST API.

Base install only (httpx and typer; no torch). The token is the server's `--admin-token`, else its `--auth-token`
(`--token`, or GMT_ADMIN_TOKEN / GMT_TOKEN); a server with no token at all takes management calls only from its
own machine (docs/models.md).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from urllib.parse import quote

import httpx
import typer

from gmt.client.errors import ServiceError
from gmt.client.rest import rest_base_url

DEFAULT_SERVER = "http://localhost:8000"
_VERSION = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")  # as the server checks it (gmt.model.checkpoint)


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

    def listing(self) -> dict:
        """`GET /models`: every model with its versions, and where the server keeps its defaults."""
        return self._call("GET", "/models")

    def models(self) -> list[dict]:
        """`GET /models`: every model with its versions."""
        return self.listing()["models"]

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


KEPT = {
    "file": "defaults and canaries are kept across restarts (in a file beside the server's checkpoint roots)",
    "redis": "defaults and canaries are kept across restarts (in the shared Redis store)",
    "off": "defaults and canaries are NOT kept across restarts (the server's checkpoint roots hold no folder of "
    "checkpoints to keep them in)",
}


def _target(server: str) -> None:
    """Say which server a command acts on (stderr: the tables on stdout stay parseable)."""
    typer.echo(f"server {rest_base_url(server)} (--server or GMT_SERVER)", err=True)


def _versions(server: str, token: str | None, name: str) -> dict:
    """Model `name`'s entry of `GET /models` ({} when the server does not serve it, or when it cannot be read: with
    an admin token that is not the auth token, `GET /models` refuses it, and the management call goes on)."""
    try:
        with AdminClient(server, token) as c:
            models = c.models()
    except ServiceError as e:
        typer.echo(f"(cannot list the server's versions first: {e})", err=True)
        return {}
    return next((m for m in models if m["name"] == name), {})


def _sessions(model: dict, version: str) -> str:
    n = next((v["sessions"] for v in model.get("versions", []) if v["version"] == version), None)
    return "sessions unknown" if n is None else f"{n} session(s)"


def _show(server: str, token: str | None, done: str = "") -> None:
    """Print the version table; after a management call (`done` says what it did), a table that cannot be read
    (an admin token that is not the auth token) is noted, not an error."""
    if done:
        try:
            with AdminClient(server, token) as c:
                body = c.listing()
        except ServiceError as e:
            typer.echo(f"{done}; cannot list the versions with this token: {e}", err=True)
            return
    else:
        body = _run(server, token, lambda c: c.listing())
    typer.echo(version_table(body["models"]))
    if body.get("model_state") in KEPT:
        typer.echo(KEPT[body["model_state"]])


@app.command("list")
def list_command(server: str = SERVER, token: str = TOKEN) -> None:
    """Every model's versions: state, sessions on this server, default and canary."""
    _target(server)
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
    _target(server)
    before = {v["version"] for v in _versions(server, token, name).get("versions", [])}
    v = _run(server, token, lambda c: c.load(name, path, fingerprint))
    if v["version"] in before:
        typer.echo(
            f"{name} {v['version']} was already loaded (the same checkpoint: fingerprint {v['fingerprint']}); "
            "nothing changed. A new version needs other weights or another `version` in its gmt.json "
            "(gmt models copy)"
        )
    else:
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
    _target(server)
    was = _versions(server, token, name).get("default_version") or "unknown"
    role = "the default" if share >= 1 else f"a canary with share {share:g}"
    typer.echo(
        f"promoting {name} {version} to {role} on {rest_base_url(server)} (default was {was})", err=True
    )
    _run(server, token, lambda c: c.promote(name, version, share))
    _show(server, token, done=f"{name} {version} promoted")


@app.command("drain")
def drain_command(
    name: str = typer.Argument(..., help="Model name."),
    version: str = typer.Argument(..., help="A loaded version other than the default."),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Give a version no new sessions; the server unloads it when its last session ends or expires."""
    _target(server)
    n = _sessions(_versions(server, token, name), version)
    typer.echo(f"draining {name} {version} ({n}) on {rest_base_url(server)}", err=True)
    _run(server, token, lambda c: c.drain(name, version))
    _show(server, token, done=f"{name} {version} draining")


@app.command("unload")
def unload_command(
    name: str = typer.Argument(..., help="Model name."),
    version: str = typer.Argument(..., help="A loaded version."),
    force: bool = typer.Option(False, help="Unload even while sessions use it (their next calls fail)."),
    server: str = SERVER,
    token: str = TOKEN,
) -> None:
    """Unload a version now (refused while sessions use it, unless --force)."""
    _target(server)
    n = _sessions(_versions(server, token, name), version)
    how = ", forced: their next calls fail" if force else ""
    typer.echo(f"unloading {name} {version} ({n}{how}) on {rest_base_url(server)}", err=True)
    _run(server, token, lambda c: c.unload(name, version, force))
    _show(server, token, done=f"{name} {version} unloaded")


@app.command("copy")
def copy_command(
    source: Path = typer.Argument(..., help="A checkpoint directory (with gmt.json and model.safetensors)."),
    dest: Path = typer.Argument(
        ..., help="The new checkpoint directory (under the server's checkpoint roots)."
    ),
    version: str = typer.Option(..., help="The copy's version (1 to 64 letters, digits, '.', '_' or '-')."),
) -> None:
    """Copy a checkpoint under a new version name: the same weights as another version of its model, to rehearse
    a rollout (`gmt train --init-from` makes a version with new weights). Works on files only: no server."""
    meta_path = source / "gmt.json"
    if not meta_path.is_file() or not (source / "model.safetensors").is_file():
        typer.echo(
            f"error: {source} is not a checkpoint directory (no gmt.json or model.safetensors)", err=True
        )
        raise typer.Exit(1)
    if not _VERSION.fullmatch(version):
        typer.echo(f"error: version {version!r} must be 1 to 64 letters, digits, '.', '_' or '-'", err=True)
        raise typer.Exit(1)
    if dest.exists():
        typer.echo(f"error: {dest} exists; name a new directory", err=True)
        raise typer.Exit(1)
    meta = json.loads(meta_path.read_text())
    dest.mkdir(parents=True)
    shutil.copyfile(source / "model.safetensors", dest / "model.safetensors")
    (dest / "gmt.json").write_text(json.dumps({**meta, "version": version}, indent=2) + "\n")
    typer.echo(f"wrote {dest} (version {version}, the weights of {source})")
