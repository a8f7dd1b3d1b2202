"""The browser UI at ``/`` and Swagger UI at ``/docs``, both from files in the repository.

Nothing is fetched from the internet at run time (an offline GPU cluster gets the same pages): the UI is
plain HTML + one JS module + CSS in ``api/static/``, and its third-party code is vendored there from pinned
npm packages with their licences (``api/static/vendor/<package>-<version>/``).

Both pages carry a Content-Security-Policy that allows their own origin only (and neither may be framed): the
UI has no inline script and shows its media from ``blob:`` URLs; the few inline elements the vendored code
needs, Swagger UI's start-up script and model-viewer's stylesheet, are allowed by their hashes.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import html
import re
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from starlette.responses import Response
from starlette.types import Scope

from api.http_semantics import root_of

STATIC_DIR = Path(__file__).resolve().parent / "static"
SWAGGER_UI = "/static/vendor/swagger-ui-dist-5.17.14"
MODEL_VIEWER = STATIC_DIR / "vendor/model-viewer-3.5.0/model-viewer.min.js"
# The app's own files revalidated on every load (an upgrade's app.js runs at once); the vendored ones sit in a
# folder named by their version, so a URL never changes its content.
REVALIDATE, IMMUTABLE = "no-cache", "public, max-age=31536000, immutable"

router = APIRouter(include_in_schema=False)


def inline_sources(text: str, tag: str) -> str:
    """CSP sources that allow exactly the inline ``<tag>`` elements (without attributes) in ``text``: their
    contents' sha256 hashes."""
    contents = re.findall(rf"<{tag}>(.*?)</{tag}>", text, flags=re.DOTALL)
    return " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(c.encode()).digest()).decode()}'" for c in contents)


# blob: for the media app.js fetches with the key (model-viewer fetches its GLB's URL too, and makes data: and
# blob: textures); the <style> element in model-viewer's shadow DOM template by its hash. form-action, which
# default-src does not cover: 'none', as app.js sends every form itself (a form injected into the page, or one of
# its own submitted before app.js ran, had been free to send its fields anywhere).
UI_POLICY = (f"default-src 'self'; style-src 'self' {inline_sources(MODEL_VIEWER.read_text(), 'style')}; "
             "img-src 'self' blob: data:; media-src 'self' blob:; connect-src 'self' blob:; object-src 'none'; "
             "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")


PAGE = (STATIC_DIR / "index.html").read_text()
_PAGE_LINK = re.compile(r'\b(href|src)="/(?!/)')  # the page's links to this service: "/static/app.js", "/docs"


def page(scope: Scope) -> Response:
    """The page; under a proxy's prefix with its links to ``/static`` and ``/docs`` under it too (they had pointed
    at the proxy's top, another site's pages or none)."""
    headers, root = {"Cache-Control": REVALIDATE, "Content-Security-Policy": UI_POLICY}, root_of(scope)
    if not root:
        return FileResponse(STATIC_DIR / "index.html", headers=headers)
    prefix = html.escape(root)
    return HTMLResponse(_PAGE_LINK.sub(lambda link: f'{link[1]}="{prefix}/', PAGE), headers=headers)


@router.api_route("/", methods=["GET", "HEAD"])
def index(request: Request) -> Response:
    return page(request.scope)


class UiStaticFiles(StaticFiles):
    """``/static`` with the Cache-Control above (a missing file raises its 404 in ``super()``), and the UI's policy
    on every file: the page is also ``/static/index.html``, which had been served with none, and under a proxy's
    prefix is the page ``/`` serves (the file's links, at the proxy's top, had left it bare)."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        if path == "index.html" and root_of(scope):
            return page(scope)
        response.headers["Cache-Control"] = IMMUTABLE if path.startswith("vendor/") else REVALIDATE
        response.headers["Content-Security-Policy"] = UI_POLICY
        return response


def mount(app: FastAPI) -> None:
    """Serve the UI, its static files and the vendored Swagger UI on ``app`` (built with ``docs_url=None``)."""
    app.include_router(router)
    app.mount("/static", UiStaticFiles(directory=STATIC_DIR), name="static")

    @functools.lru_cache(maxsize=8)
    def docs_page(root: str) -> tuple[bytes, str]:
        """/docs under the prefix ``root`` (its /openapi.json and assets under it too), and its policy: the inline
        start-up script names the document's URL, so its hash differs by prefix."""
        docs = get_swagger_ui_html(openapi_url=root + app.openapi_url, title=f"{app.title} API",
                                   swagger_js_url=f"{root}{SWAGGER_UI}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{root}{SWAGGER_UI}/swagger-ui.css",
                                   swagger_favicon_url=f"{root}{SWAGGER_UI}/favicon-32x32.png",
                                   swagger_ui_parameters={"validatorUrl": None})  # its badge: an image from swagger.io
        policy = (f"default-src 'self'; script-src 'self' {inline_sources(docs.body.decode(), 'script')}; "
                  # blob: the images "Try it out" shows (an artifact's PNG); form-action: a form sends to this origin
                  "img-src 'self' data: blob:; object-src 'none'; base-uri 'none'; form-action 'self'; "
                  "frame-ancestors 'none'")
        return docs.body, policy

    @app.api_route("/docs", methods=["GET", "HEAD"], include_in_schema=False)
    def swagger_ui(request: Request) -> HTMLResponse:
        body, policy = docs_page(root_of(request.scope))
        return HTMLResponse(body, headers={"Content-Security-Policy": policy})
