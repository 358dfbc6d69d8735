"""`/docs` (Swagger UI) and `/redoc` (ReDoc) served with their scripts and styles from this server, never a CDN.

FastAPI's own pages load Swagger UI and ReDoc from cdn.jsdelivr.net, and are blank without internet access. The
assets here come from the `fastapi-offline` distribution (MIT; its `static/` folder holds the `swagger-ui-dist`
bundle, Apache-2.0, and ReDoc's standalone bundle, MIT, as published on npm), installed with the `serve` extra.
Nothing makes the browser reach another host: Swagger UI's validator badge (validator.swagger.io) is off, ReDoc
gets no Google Fonts, and ReDoc's "API docs by Redocly" logo, an image on cdn.redoc.ly, is served as `data:,`
(which fails to decode, and ReDoc hides a logo that fails).
"""

from __future__ import annotations

import functools
from pathlib import Path

import fastapi_offline
from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse, Response

STATIC = Path(fastapi_offline.__file__).parent / "static"
ASSETS = "/docs/assets"
FILES = {  # name -> media type
    "swagger-ui-bundle.js": "text/javascript",
    "swagger-ui.css": "text/css",
    "redoc.standalone.js": "text/javascript",
    "favicon.png": "image/png",
}
REDOCLY_LOGO = b"https://cdn.redoc.ly/redoc/logo-mini.svg"
CACHE = {"Cache-Control": "public, max-age=86400"}
SWAGGER, OAUTH2_REDIRECT, REDOC = "/docs", "/docs/oauth2-redirect", "/redoc"
PATHS = frozenset({SWAGGER, OAUTH2_REDIRECT, REDOC, *(f"{ASSETS}/{name}" for name in FILES)})
"""Every path this module answers (open without a token: see `app.AuthFirst`)."""


def add_docs(app: FastAPI) -> None:
    """Add the documentation pages and their assets to `app` (created with `docs_url=None, redoc_url=None`)."""
    router = APIRouter(include_in_schema=False)

    def url(request: Request, path: str) -> str:
        return f"{request.scope.get('root_path', '')}{path}"

    @router.get(SWAGGER)
    async def swagger_ui(request: Request) -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=url(request, app.openapi_url),
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=url(request, OAUTH2_REDIRECT),
            swagger_js_url=url(request, f"{ASSETS}/swagger-ui-bundle.js"),
            swagger_css_url=url(request, f"{ASSETS}/swagger-ui.css"),
            swagger_favicon_url=url(request, f"{ASSETS}/favicon.png"),
            swagger_ui_parameters={"validatorUrl": None},
        )

    @router.get(OAUTH2_REDIRECT)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @router.get(REDOC)
    async def redoc(request: Request) -> HTMLResponse:
        return get_redoc_html(
            openapi_url=url(request, app.openapi_url),
            title=f"{app.title} - ReDoc",
            redoc_js_url=url(request, f"{ASSETS}/redoc.standalone.js"),
            redoc_favicon_url=url(request, f"{ASSETS}/favicon.png"),
            with_google_fonts=False,
        )

    for name, media_type in FILES.items():
        router.add_api_route(f"{ASSETS}/{name}", _asset(STATIC / name, media_type), methods=["GET"])
    app.include_router(router)


@functools.cache
def redoc_bundle() -> bytes:
    """ReDoc's bundle with its one image from another host (the Redocly logo) replaced by `data:,`."""
    return (STATIC / "redoc.standalone.js").read_bytes().replace(REDOCLY_LOGO, b"data:,")


def _asset(path: Path, media_type: str):
    if path.name == "redoc.standalone.js":

        async def asset() -> Response:
            return Response(redoc_bundle(), media_type=media_type, headers=CACHE)

    else:

        async def asset() -> FileResponse:
            return FileResponse(path, media_type=media_type, headers=CACHE)

    asset.__name__ = f"docs_asset_{path.stem.replace('-', '_').replace('.', '_')}"
    return asset
