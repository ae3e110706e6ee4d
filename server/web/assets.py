"""Static files of the operator page: our own (server/web/static) and the npm packages' builds.

The front-end libraries come from their npm registry packages, pinned by package-lock.json and
installed with ``npm ci`` into server/web/node_modules (the Makefile's venv step, the
Dockerfile's node stage); only the files listed in :data:`VENDOR` are served, and nothing is
fetched from a CDN at run time. ``/docs`` is Swagger UI from the ``swagger-ui-dist`` package.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

from server.errors import NotFoundError

HERE = Path(__file__).resolve().parent
STATIC = HERE / "static"
NODE_MODULES = HERE / "node_modules"

#: URL name under /static/vendor/ -> file in node_modules (package/dist file)
VENDOR: dict[str, str] = {
    "htmx.min.js": "htmx.org/dist/htmx.min.js",
    "uPlot.iife.min.js": "uplot/dist/uPlot.iife.min.js",
    "uPlot.min.css": "uplot/dist/uPlot.min.css",
    "swagger-ui-bundle.js": "swagger-ui-dist/swagger-ui-bundle.js",
    "swagger-ui.css": "swagger-ui-dist/swagger-ui.css",
    "favicon-32x32.png": "swagger-ui-dist/favicon-32x32.png",
}
OWN = {"app.js", "app.css", "session.js"}
_MEDIA = {".js": "text/javascript", ".css": "text/css", ".png": "image/png"}
# Our files change with the code: a short cache. Vendor files are pinned by the lock file.
_OWN_CACHE = "no-cache"
_VENDOR_CACHE = "public, max-age=86400"

router = APIRouter(include_in_schema=False)


def vendor_path(name: str) -> Path:
    """The installed file behind /static/vendor/<name>, or NotFoundError saying how to get it."""
    rel = VENDOR.get(name)
    if rel is None:
        raise NotFoundError(f"/static/vendor/{name} is not one of {sorted(VENDOR)}")
    path = NODE_MODULES / rel
    if not path.is_file():
        raise NotFoundError(
            f"{path} is missing: install the page's libraries with "
            f"`npm ci --ignore-scripts --prefix {HERE}` (make venv does it)"
        )
    return path


@router.get("/static/vendor/{name}")
def vendor_file(name: str) -> FileResponse:
    path = vendor_path(name)
    return FileResponse(path, media_type=_MEDIA.get(path.suffix),
                        headers={"Cache-Control": _VENDOR_CACHE})


@router.get("/static/{name}")
def own_file(name: str) -> FileResponse:
    if name not in OWN:
        raise NotFoundError(f"/static/{name} is not one of {sorted(OWN)}")
    path = STATIC / name
    return FileResponse(path, media_type=_MEDIA.get(path.suffix),
                        headers={"Cache-Control": _OWN_CACHE})


@router.get("/favicon.ico")
def favicon() -> FileResponse:
    return vendor_file("favicon-32x32.png")


@router.get("/docs")
def swagger_ui(request: Request) -> HTMLResponse:
    """Swagger UI over this app's OpenAPI, every asset served by this app (works offline)."""
    return get_swagger_ui_html(
        openapi_url=request.app.openapi_url or "/openapi.json",
        title=f"{request.app.title} — API",
        swagger_js_url="/static/vendor/swagger-ui-bundle.js",
        swagger_css_url="/static/vendor/swagger-ui.css",
        swagger_favicon_url="/static/vendor/favicon-32x32.png",
    )
