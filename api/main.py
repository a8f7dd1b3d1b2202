"""The FastAPI application factory. ``uvicorn api.main:app`` (or ``--factory api.main:create_app``)."""

from __future__ import annotations

import asyncio
import logging
import math
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from typing import NamedTuple

from fastapi import FastAPI, HTTPException
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse
from starlette.requests import HTTPConnection

from api import http_semantics
from voxe_service.db import outage_line, run_migrations, sync_clock
from voxe_service.settings import Settings, SettingsError, get_settings, model_label, refuse_settings
from voxe_service.texts import shorter

log = logging.getLogger("voxe.api")


class UploadLimit:
    """Answer 413 to a request body above ``max_bytes`` (VOXE_MAX_UPLOAD_BYTES), or to one not sent as a
    multipart form above ``max_json_bytes`` (VOXE_MAX_JSON_BODY_BYTES), by Content-Length, or counted while
    streaming, for every method whose body means something (a DELETE's too: no route takes one, and a 64 MiB one
    had been read whole before its 415). Only an upload's form carries files; any other body is JSON or refused, and
    FastAPI holds it in memory whole before its 415 (whatever its media type) or its parse on the event loop: up to
    the upload limit (2 GiB), one had been the whole process's memory and seconds of every request's time."""

    def __init__(self, app, max_bytes: int, max_json_bytes: int):
        self.app, self.max_bytes, self.max_json_bytes = app, max_bytes, max_json_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] not in http_semantics.TAKE_CONTENT:
            return await self.app(scope, receive, send)
        limit = _Limit(self.max_bytes, "VOXE_MAX_UPLOAD_BYTES", "request body")
        if http_semantics.media_type(HTTPConnection(scope)) != http_semantics.FORM_MEDIA_TYPE:
            limit = min(limit, _Limit(self.max_json_bytes, "VOXE_MAX_JSON_BODY_BYTES",
                                      "JSON body (any body but an upload's multipart form)"))
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and length.isdigit() and int(length) > limit.max_bytes:
            return await self._reject(send, limit)
        received = 0
        started = False

        async def counting_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit.max_bytes:
                    raise _TooLarge(limit)
            return message

        async def tracking_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, tracking_send)
        except _TooLarge:
            if not started:
                await self._reject(send, limit)

    @staticmethod
    async def _reject(send, limit: _Limit):
        """The 413, rendered as every other answer is (JSONResponse's compact JSON)."""
        response = JSONResponse({"detail": _TooLarge(limit).detail}, status_code=413)
        await send({"type": "http.response.start", "status": 413, "headers": response.raw_headers})
        await send({"type": "http.response.body", "body": response.body})


class SecurityHeaders:
    """No answer is sniffed as another type than it declares, nor framed by another site (ASGI middleware; the
    500 of an unhandled error, answered outside every middleware, by :func:`internal_error`). The UI's pages add
    their Content-Security-Policy themselves (api/ui.py)."""

    HEADERS = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY")]

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", []), *self.HEADERS]}
            await send(message)

        await self.app(scope, receive, send_with_headers)


@contextmanager
def on_exit_signal(callback: Callable[[], None]) -> Iterator[None]:
    """Run ``callback`` in the event loop as soon as SIGINT or SIGTERM asks the server to stop, then the server's
    own handler of it; the server's handlers again on leaving.

    uvicorn waits for every open response to end before the lifespan's shutdown, and an event stream ends only
    with its job: one open stream had kept a stopped API (its webhook sender and reaper too) running for good.
    Only where the server handles signals in this, the main, thread (not a TestClient's app, nor a server's in
    another thread).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    loop = asyncio.get_running_loop()
    handlers = {sig: handler for sig in (signal.SIGINT, signal.SIGTERM) if callable(handler := signal.getsignal(sig))}

    def chained(sig: int, frame) -> None:
        loop.call_soon_threadsafe(callback)
        handlers[sig](sig, frame)

    for sig in handlers:
        signal.signal(sig, chained)
    try:
        yield
    finally:
        for sig, handler in handlers.items():
            if signal.getsignal(sig) is chained:
                signal.signal(sig, handler)


class _Limit(NamedTuple):
    """A body size limit: its bytes, its setting, and what it limits."""

    max_bytes: int
    setting: str
    body: str


class _TooLarge(HTTPException):
    """A body found too large while streaming. An HTTPException, so that FastAPI, reading the body for a route,
    answers it as the 413 it is (any other exception there becomes its 400 "error parsing the body")."""

    def __init__(self, limit: _Limit):
        super().__init__(413, f"{limit.body} over the limit of {limit.max_bytes} bytes ({limit.setting})")


def log_as_uvicorn() -> None:
    """The API's own lines (``voxe.*``) to uvicorn's handler at its ``--log-level``: uvicorn configures only its own
    loggers, so those below WARNING (authentication ON, ready, each webhook attempt) had gone nowhere, and the
    warnings out bare. Nothing changes where logging is configured otherwise (a root handler, ``--log-config``)."""
    voxe, served_by = logging.getLogger("voxe"), logging.getLogger("uvicorn")
    if logging.getLogger().handlers or voxe.handlers or not served_by.handlers:
        return
    for handler in served_by.handlers:
        voxe.addHandler(handler)
    voxe.setLevel(logging.getLogger("uvicorn.error").getEffectiveLevel())


def create_app(settings: Settings | None = None, migrate: bool = True) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(_app: FastAPI):
        from api.auth import check_startup

        log_as_uvicorn()
        auth_line = check_startup(settings)  # refuses auth off on a reachable address before anything else
        (log.info if settings.auth_enabled else log.warning)("Vox-E API: %s", auth_line)
        if migrate:
            run_migrations(settings.database_url)
        sync_clock()  # times this process writes read on the database's clock (again at each reaper pass)
        from voxe_service.storage import get_storage

        get_storage(settings)  # fail at startup, not on the first request, when storage is misconfigured
        from api.uploads import sweep_staging

        if swept := sweep_staging(settings.work_dir):
            log.info("removed %d upload staging folder(s) that stopped API processes left in %s", swept,
                     settings.work_dir)
        log.info("Vox-E API ready: SDS model %s, attention model %s", model_label(settings.sds_model),
                 model_label(settings.attention_model))
        from api.reaper import Reaper

        from api.webhooks import WebhookSender

        reaper = Reaper(settings).start()  # fails orphaned jobs (a dead worker, never queued)
        sender = WebhookSender(settings).start()  # POSTs job events to their webhooks, off the request path
        try:
            with on_exit_signal(app.state.event_hub.end_streams):
                yield
        finally:
            sender.stop()
            reaper.stop()
            await app.state.event_hub.close()

    app = FastAPI(
        title="Vox-E",
        version="1.0.0",
        summary="Text-guided editing of 3D objects (Vox-E, ICCV 2023) as a job service",
        description=(
            "Upload a posed image set (`POST /v1/scenes`), create an edit job (`POST /v1/jobs`), poll it "
            "(`GET /v1/jobs/{id}`) and download its artifacts: voxel grids, edit mask, renders, turntable "
            "video and a mesh. A scene is reconstructed once per reconstruction-parameter set and reused by "
            "every later job on it."
        ),
        lifespan=lifespan,
        docs_url=None,  # served by api.ui from the vendored Swagger UI (FastAPI's default loads it from a CDN)
        redoc_url=None,
    )
    from api.events import EventHub
    from api.routes import artifacts, evaluations, health, jobs, scenes, webhooks

    app.state.event_hub = EventHub(settings.progress_interval_s, jobs.progress_view)

    app.include_router(health.router)
    app.include_router(scenes.router)
    app.include_router(jobs.router)
    app.include_router(artifacts.router)
    app.include_router(evaluations.router)
    app.include_router(webhooks.router)
    from api import ui

    ui.mount(app)
    from api.auth import RequireKey

    app.add_middleware(RequireKey)  # inside UploadLimit: an over-size body is 413 first, then a missing key 401
    app.add_middleware(UploadLimit, max_bytes=settings.max_upload_bytes,
                       max_json_bytes=settings.max_json_body_bytes)
    app.add_exception_handler(RequestValidationError, validation_error)
    http_semantics.install(app)
    app.add_middleware(SecurityHeaders)  # outermost: the 401, 404 and 413 of the middleware above get them too
    app.add_exception_handler(Exception, internal_error)
    return app


def internal_error(request, _exc) -> PlainTextResponse:
    """Starlette's plain 500 for an unhandled error (still logged by the server), with the security headers and, on
    /v1, the Cache-Control every /v1 answer has: it is answered outside every middleware."""
    headers = {name.decode(): value.decode() for name, value in SecurityHeaders.HEADERS}
    if http_semantics.keys_own(request.scope):
        headers["Cache-Control"] = http_semantics.KEYS_OWN
    return PlainTextResponse("Internal Server Error", 500, headers=headers)


def _json_safe(value, most: int | None = None):
    """JSON-encodable errors: non-finite floats (a body may send NaN or Infinity) become their names, and strings
    holding lone surrogates (JSON may escape "\\ud800"; UTF-8 cannot encode it) their backslash escapes. ``most``:
    strings (an object's names too) cut to that many characters (``shorter``)."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, str):
        value = value if most is None else shorter(value, most)
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, dict):
        return {(k if most is None else shorter(k, most)): _json_safe(v, most) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v, most) for v in value]
    return value


async def validation_error(request, exc: RequestValidationError) -> JSONResponse:
    """FastAPI's 422 (400 for a body that is not JSON, 415 for one not sent as JSON), but never a 500 for the
    offending input it echoes."""
    if (malformed := http_semantics.malformed_body(request, exc)) is not None:
        return malformed
    # The input and its place as the client sent them, cut: a query value of any length had been echoed whole
    errors = [{**error, **{key: _json_safe(error[key], http_semantics.ID_SHOWN) for key in ("loc", "input")
                           if key in error}} for error in jsonable_encoder(exc.errors())]
    return JSONResponse(status_code=422, content={"detail": _json_safe(errors)})


class RefuseAtStartup:
    """The app as uvicorn serves it: a :class:`SettingsError` its lifespan's startup raises (a VOXE_WORK_DIR that is
    a file), or a database it cannot reach (``outage_line``), is said in one line (:func:`refuse_settings`) before
    uvicorn's "Application startup failed. Exiting." (its exit status 3), not in the traceback of some thirty lines
    uvicorn had printed, the variable on its last.
    Starlette sends that traceback as the startup failure's message, then raises: the message is held until then."""

    def __init__(self, app: FastAPI):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "lifespan":
            return await self.app(scope, receive, send)
        failed = None

        async def holding_send(message):
            nonlocal failed
            if message["type"] != "lifespan.startup.failed":
                return await send(message)
            failed = message

        try:
            await self.app(scope, receive, holding_send)
        except BaseException as exc:
            if failed is not None:
                line = exc if isinstance(exc, SettingsError) else outage_line(exc)
                if line is not None:
                    refuse_settings("Vox-E API", line)
                await send(failed if line is None else {**failed, "message": ""})
            raise


def __getattr__(name: str):  # ``uvicorn api.main:app`` builds the app on first access
    if name == "app":
        try:
            globals()["app"] = RefuseAtStartup(create_app())
        except SettingsError as exc:  # one line naming the setting, as uvicorn's traceback had ended with
            sys.exit(refuse_settings("Vox-E API", exc))
        return globals()["app"]
    raise AttributeError(name)
