"""REST routes of model management: load a version, promote it (or run a canary), drain it, unload it.

Who may call them is decided before the body is read (`app.AuthFirst`, by `gmt.service.admin`'s rule).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query

from gmt.service.rest import schemas as S
from gmt.service.rest.media import require_json
from gmt.service.rest.routes import CoreDep, errors

admin_api = APIRouter(tags=["model management"], dependencies=[Depends(require_json)])
_ADMIN_ERRORS = {
    403: {
        "model": S.ErrorOut,
        "description": "Permission denied: a management call without a token from another machine, through a "
        "proxy, or with a Host that is not a loopback name or an Origin / Referer of another origin (no "
        "--admin-token / --auth-token), or a path outside the checkpoint roots",
    }
}


@admin_api.post(
    "/models/{name}/versions",
    response_model=S.LoadVersionOut,
    status_code=201,
    responses={**errors(400, 409, 413, 503), **_ADMIN_ERRORS},
)
async def load_version(name: str, body: S.LoadVersion, core: CoreDep) -> S.LoadVersionOut:
    """Load a checkpoint as a version of the model (a new name starts a new model); the load runs in a thread, so
    acts are answered meanwhile. A checkpoint that cannot be served is refused (400, naming the problem) and
    every served version is left as it was."""
    v = await core.load_version(name, body.path, body.fingerprint)
    return S.LoadVersionOut(
        name=name, version=v.version, sessions=v.sessions, state=v.state, fingerprint=v.fingerprint
    )


@admin_api.put(
    "/models/{name}/default",
    response_model=S.ModelVersionsOut,
    responses={**errors(400, 404, 413, 503), **_ADMIN_ERRORS},
)
async def promote(name: str, body: S.Promote, core: CoreDep) -> S.ModelVersionsOut:
    """Make a loaded version the default of new sessions (`share` 1), or a canary with `share` of them."""
    return S.ModelVersionsOut.of(await core.promote(name, body.version, body.share))


@admin_api.post(
    "/models/{name}/versions/{version}/drain",
    response_model=S.ModelVersionsOut,
    responses={**errors(400, 404, 409, 503), **_ADMIN_ERRORS},
)
async def drain(name: str, version: str, core: CoreDep) -> S.ModelVersionsOut:
    """Give the version no new sessions; it is unloaded once this server holds none of its sessions."""
    return S.ModelVersionsOut.of(await core.drain(name, version))


@admin_api.delete(
    "/models/{name}/versions/{version}",
    response_model=S.ModelVersionsOut,
    responses={**errors(400, 404, 409, 503), **_ADMIN_ERRORS},
)
async def unload(
    name: str,
    version: str,
    core: CoreDep,
    force: bool = Query(False, description="Unload even while sessions use it (their next calls fail)."),
) -> S.ModelVersionsOut:
    """Unload the version now; refused (409) while sessions use it unless `force=true`."""
    return S.ModelVersionsOut.of(await core.unload(name, version, force))
