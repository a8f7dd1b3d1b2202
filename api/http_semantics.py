"""HTTP answers the routes themselves never give, made true to the OpenAPI document.

* A body that is not JSON at all is a 400 ``malformed JSON body`` (FastAPI would say 422, the status
  the document keeps for bodies that parse but break the schema), and one sent as another media type than
  JSON a 415 naming it (FastAPI reads it as a string and said 422 "Input should be a valid dictionary"). JSON that
  ``json.loads`` refuses otherwise than as a syntax error (a number past Python's int-string conversion limit, bytes
  not UTF-8, nesting past the recursion limit) is that 400 too, naming why, not FastAPI's bare "There was an error
  parsing the body".
* A JSON body whose object names a member twice is that 400 too, naming it (:class:`StrictRoute`): ``json.loads``
  keeps the last one silently, where another reader of the same body (a proxy, the client's own checks) may take
  the first.
* On /v1, a query parameter an operation does not take, or a one-valued one sent twice, is a 422 naming them
  (:class:`StrictRoute`), rather than ignored or read as its last value.
* A body sent to a POST or DELETE that takes none (a cancel, a deletion) is a 415 naming the operation
  (:class:`StrictRoute`): it had been ignored, the caller left believing it was read.
* A body sent with a Content-Encoding other than identity (gzip) is a 415 naming it, with ``Accept-Encoding:
  identity`` (:func:`refuse_encoded`): none is decoded, and it had been read as the bytes of an unencoded one.
* A form route's body (an upload) sent as another media type than multipart/form-data (a urlencoded form cannot
  carry a file), or with none, is a 415 naming it (:class:`api.routes.scenes.UploadFilesRoute`); Starlette's 400
  for a multipart body it cannot parse is documented.
* A path holding a NUL character is a 404 (no resource is named so) and such a query string a 422: neither
  reaches the database, whose PostgreSQL text cannot hold one.
* ``HEAD`` is served wherever ``GET`` is (:class:`HeadAsGet`).
* Every /v1 answer is ``Cache-Control: private`` (:class:`PrivateAnswers`): it is one key's.
* A method a path does not serve is a 405 whose ``Allow`` lists every method of every route on that
  path (Starlette names only the first route it tried), and ``OPTIONS`` on any path answers 204
  with the same ``Allow``. Without a key too: it says nothing ``/openapi.json`` does not.
* A database this process cannot use now (every pooled connection busy past ``VOXE_DATABASE_POOL_TIMEOUT_S``, the
  server unreachable, SQLite locked), or a storage (``voxe_service.storage.StorageUnavailable``: S3 unreachable, timed
  out, throttled), is a 503 with ``Retry-After``, not a bare 500: the request may be sent again.

Examples:
    >>> from api.main import create_app
    >>> allowed_methods(create_app(), "/v1/jobs")
    ['GET', 'HEAD', 'OPTIONS', 'POST']
"""

from __future__ import annotations

import json
import logging
import sys
from functools import cached_property
from typing import get_args, get_origin

from fastapi import FastAPI, HTTPException, Request, params
from fastapi.dependencies.utils import get_flat_params
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi.routing import APIRoute
from starlette.datastructures import URL
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import HTTPConnection
from starlette.routing import Match, Mount

from voxe_service.db import DATABASE_UNAVAILABLE, database_outage
from voxe_service.storage import StorageError, StorageUnavailable
from voxe_service.texts import listed, shorter

log = logging.getLogger("voxe.api")
_PROBLEM = {"application/json": {"schema": {"$ref": "#/components/schemas/Problem"}}}
_ALLOW = {"Allow": {"description": "the methods this path serves", "schema": {"type": "string"}}}
SECURITY_SCHEMES = {
    "bearer": {"type": "http", "scheme": "bearer", "description": "Authorization: Bearer voxe_<id>_<secret>"},
    "apiKey": {"type": "apiKey", "in": "header", "name": "X-API-Key", "description": "the same token"},
}


_METHODS = ("DELETE", "GET", "HEAD", "PATCH", "POST", "PUT")
TAKE_CONTENT = ("DELETE", "PATCH", "POST", "PUT")  # methods whose content means something (RFC 9110 §9.3)
FORM_MEDIA_TYPE = "multipart/form-data"
UNAVAILABLE = (*DATABASE_UNAVAILABLE, StorageError)
RETRY_AFTER_S = 5
_UNAVAILABLE_503 = "the database or the storage is busy or unreachable (Retry-After says when to try again)"
_ODD_QUERY_422 = "a query parameter the operation does not take, or a one-valued one sent twice (named)"


_MOUNTED_METHODS = ("GET", "HEAD")  # what a mount serves: the only one is the UI's static files (api/ui.py)


def routed(app: FastAPI, path: str, method: str) -> bool:
    """Whether some route fully matches ``method`` on ``path``.

    Asked of each top-level route, so routes inside included routers count too. A mount matches any method: it
    counts for those it serves.
    """
    scope = {"type": "http", "path": path, "method": method, "root_path": ""}
    return any(route.matches(scope)[0] == Match.FULL
               and (not isinstance(route, Mount) or method in _MOUNTED_METHODS) for route in app.router.routes)


def allowed_methods(app: FastAPI, path: str) -> list[str]:
    """Sorted methods served on ``path``: those some route matches, HEAD wherever GET is (:class:`HeadAsGet`), and
    OPTIONS always."""
    methods = {method for method in _METHODS if routed(app, path, method)}
    return sorted({"OPTIONS", *methods, *(("HEAD",) if "GET" in methods else ())})


def route_path(scope) -> str:
    """The path the app's routes match: ``scope["path"]`` without the ``root_path`` a proxy mounts the service
    under (``uvicorn --root-path /api``: "/api/v1/jobs" is routed as "/v1/jobs"). Inside a mount (``/static``), whose
    scope's ``root_path`` takes in the mount's own prefix, the app's (``app_root_path``): the 405 of a static file
    had named the methods of its path under the mount ("/app.js": none but OPTIONS).

    Examples:
        >>> route_path({"path": "/api/v1/jobs", "root_path": "/api"}), route_path({"path": "/v1/jobs"})
        ('/v1/jobs', '/v1/jobs')
        >>> route_path({"path": "/static/app.js", "root_path": "/static", "app_root_path": ""})
        '/static/app.js'
    """
    path, root = scope["path"], scope.get("app_root_path", scope.get("root_path", ""))
    return path[len(root):] if root and path.startswith(root + "/") else path


def root_of(scope) -> str:
    """The prefix a proxy serves the service under (``uvicorn --root-path /api``: "/api"; "" at the top), which the
    links the service gives (its page's, an artifact's URL) start with.

    Examples:
        >>> root_of({"root_path": "/api/"}), root_of({"root_path": "/static", "app_root_path": ""})
        ('/api', '')
    """
    return scope.get("app_root_path", scope.get("root_path", "")).rstrip("/")


async def method_not_allowed(request: Request, exc: StarletteHTTPException) -> Response:
    """405 with the path's whole ``Allow``; OPTIONS answered 204 with it."""
    allow = ", ".join(allowed_methods(request.app, route_path(request.scope)))
    if request.method == "OPTIONS":
        return Response(status_code=204, headers={"Allow": allow})
    # The path as the client sent it, under the proxy's prefix: a server that leaves the prefix out of the path
    # (Starlette's TestClient, ASGI servers before the spec said otherwise) had it named without ("/v1/jobs").
    sent = URL(scope={**request.scope, "path": root_of(request.scope) + route_path(request.scope)})  # (its %3F kept)
    path = shorter(sent.path, ID_SHOWN)  # (the client's, of any length)
    return JSONResponse({"detail": f"method {request.method} is not allowed on {path}; allowed: {allow}"},
                        status_code=405, headers={"Allow": allow})


def media_type(request: HTTPConnection) -> str:
    """The request's Content-Type without its parameters, lower-case, as written (:func:`as_sent`); "" when none is
    sent."""
    return as_sent(request.headers.get("content-type", "")).split(";")[0].strip().lower()


def media_type_shown(request: HTTPConnection) -> str:
    """The request's media type for a 415's message, cut to :data:`ID_SHOWN` characters: the whole Content-Type had
    been quoted (5,000 characters of it sent, 5,000 back)."""
    return shorter(media_type(request), ID_SHOWN) or "no media type"


def sends_body(request: Request) -> bool:
    """Whether the request frames a body (RFC 9112 section 6.1): a Content-Length other than 0, or a
    Transfer-Encoding."""
    length = request.headers.get("content-length", "0").strip()
    return "transfer-encoding" in request.headers or not (length.isdigit() and int(length) == 0)


def refuse_encoded(request: Request) -> None:
    """415 with ``Accept-Encoding: identity`` (RFC 9110 §15.5.16) for a body sent with a Content-Encoding other than
    identity, before any of it is read: none is decoded, and a gzipped JSON body had been a 400 "malformed JSON
    body: it is not UTF-8" (an upload's, "Invalid multipart data."), a plain one labelled gzip read as unencoded."""
    sent = ", ".join(request.headers.getlist("content-encoding"))
    if sends_body(request) and any(coding.strip().lower() not in ("", "identity") for coding in sent.split(",")):
        raise HTTPException(415, f"the body was sent with Content-Encoding {listed([as_sent(sent)], width=ID_SHOWN)}: send it "
                                 "unencoded (only identity is read)", headers={"Accept-Encoding": "identity"})


ID_SHOWN = 100  # characters of an id, name or path from a request a 404 or 405 shows (ids are 32; artifact names fewer)


def json_sent(sent_as: str) -> bool:
    """Whether FastAPI reads a body sent as the media type ``sent_as`` as JSON: application/json or another ``+json``
    type."""
    return sent_as == "application/json" or sent_as.endswith("+json")


def malformed_body(request: Request, exc: RequestValidationError) -> JSONResponse | None:
    """The 400 for a body that did not parse as JSON, the 415 for one not sent as JSON, else None (a schema
    error: the 422 stays)."""
    sent_as = media_type(request)
    as_json = json_sent(sent_as)
    for error in exc.errors():
        if not as_json and error.get("loc") == ("body",) and error.get("type") == "model_attributes_type":
            return JSONResponse({"detail": f"the body must be sent as JSON (Content-Type: application/json), not as "
                                           f"{media_type_shown(request)}"}, status_code=415)
        if error.get("type") == "json_invalid":
            reason = (error.get("ctx") or {}).get("error", "JSON decode error")
            position = error.get("loc", [None, None])[-1]
            return JSONResponse({"detail": f"malformed JSON body: {reason} (at character {position})"},
                                status_code=400)
    return None


async def unreadable_body(request: Request, exc: StarletteHTTPException) -> Response:
    """The 400 ``malformed JSON body`` naming why ``json.loads`` refused the body with an error other than
    ``JSONDecodeError`` (FastAPI answers those with a bare "There was an error parsing the body"); any other 400
    unchanged."""
    cause = exc.__cause__ if json_sent(media_type(request)) else None  # a form's parse error is no JSON's
    if isinstance(cause, UnicodeDecodeError):
        reason = f"it is not UTF-8 ({cause.reason} at byte {cause.start})"
    elif isinstance(cause, RecursionError):
        reason = "its arrays or objects nest too deeply"
    elif isinstance(cause, ValueError):  # json.loads' only other ValueError: int() past the int-string limit
        reason = f"a number has more than {sys.get_int_max_str_digits()} digits"
    else:
        return await http_exception_handler(request, exc)
    return JSONResponse({"detail": f"malformed JSON body: {reason}"}, status_code=400)


class _NamedTwice(ValueError):
    """A JSON object naming the member ``args[0]`` twice."""


def _unique_members(pairs: list[tuple[str, object]]) -> dict:
    """``json.loads``' ``object_pairs_hook``: the object, or _NamedTwice for a name it holds twice."""
    members = {}
    for name, value in pairs:
        if name in members:
            raise _NamedTwice(name)
        members[name] = value
    return members


def combined(lines: list[str] | None) -> str | None:
    """A list header's field lines as one value, joined by commas as RFC 9110 §5.3 combines them (None: not sent).

    FastAPI reads a ``str`` header's first line only, where a proxy may read the last: the bytes of one range had
    been served as those of the other. Combined, two ranges are several (the whole file)."""
    return None if lines is None else ", ".join(lines)


def as_sent(value: str) -> str:
    """A header's value as the client wrote it, for quoting in a message: the server reads a header's bytes as
    Latin-1, one character a byte, so UTF-8 text was quoted garbled (a full-width "３" as 'ï¼\\x93'); bytes that are
    not UTF-8 are quoted as read."""
    try:
        return value.encode("latin-1").decode("utf-8")
    except UnicodeError:
        return value


def only_line(header: str, lines: list[str]) -> str | None:
    """A one-valued header's value (If-Range, Last-Event-ID; None: not sent); 422 naming it when sent on several lines.

    Such a header is no list, so its lines cannot be combined: an HTTP-date holds a comma, and a date joined with
    anything had been read as that date alone. Its first line had been read where a proxy may read the last (a
    download resumed on the first line's ETag, a stream after the first line's event)."""
    if len(lines) > 1:
        raise HTTPException(422, f"{header} was sent on {len(lines)} lines: it holds one value, send it once")
    return lines[0] if lines else None


def takes_several(annotation) -> bool:
    """Whether a parameter or form field of this annotation takes several values (``list[UploadFile] | None``)."""
    return get_origin(annotation) is list or any(get_origin(arg) is list for arg in get_args(annotation))


class UniqueMembersRequest(Request):
    """A request whose JSON body is parsed refusing an object naming a member twice (400, naming it), in FastAPI's
    own single parse: FastAPI reads the body (a client gone mid-body is its 400) and parses it with
    :meth:`json`."""

    async def json(self):
        if not hasattr(self, "_json"):
            try:
                self._json = json.loads(await self.body(), object_pairs_hook=_unique_members)
            except _NamedTwice as named:
                raise HTTPException(400, f"malformed JSON body: an object names the member {named.args[0]!r} "
                                         "twice (which one counts is undefined: send it once)") from None
        return self._json


async def _any_content(request: Request) -> bool:
    """Whether the request's body holds a byte, read up to its first non-empty chunk only."""
    async for chunk in request.stream():
        if chunk:
            return True
    return False


class StrictRoute(APIRoute):
    """A route refusing what FastAPI would read one way silently: a query parameter it does not take or a
    one-valued one sent twice (422, naming them: ``GET /v1/jobs?stat=running`` had listed every job, and
    ``?limit=1&limit=500`` took the last), and a JSON body one of whose objects names a member twice (400, naming
    it: ``{"prompt": "a", "prompt": "b"}`` had made a job of "b"; :class:`UniqueMembersRequest`), and a body sent to
    a POST or DELETE taking none (415, :meth:`refuse_body`), or one sent encoded (415, :func:`refuse_encoded`). A
    body that does not parse is FastAPI's error as before (:func:`malformed_body`, :func:`unreadable_body`)."""

    @cached_property
    def query_fields(self) -> dict:
        """The query parameters the route takes, by name."""
        return {f.alias: f for f in get_flat_params(self.dependant) if isinstance(f.field_info, params.Query)}

    def refuse_odd_query(self, request: Request) -> None:
        """422 for a query parameter the route does not take, or a one-valued one sent more than once."""
        sent, takes = request.query_params, self.query_fields
        if unknown := sorted(set(sent) - set(takes)):
            raise HTTPException(422, f"unknown query parameter(s) {listed(unknown)}: "
                                     f"{request.method} {self.path} takes {', '.join(map(repr, takes)) or 'none'}")
        if twice := sorted(name for name in set(sent) if len(sent.getlist(name)) > 1
                           and not takes_several(takes[name].field_info.annotation)):
            raise HTTPException(422, f"query parameter(s) {listed(twice)} sent more than once: send each once")

    async def refuse_body(self, request: Request) -> None:
        """415 for a body sent to a POST or DELETE that takes none (a cancel's ``{"reason": ...}`` had been ignored
        silently); an empty one is none. A GET's is left alone: RFC 9110 gives it no meaning.

        The body is not read to be refused (a 64 MiB DELETE had been held whole in memory before its 415): its
        Content-Length says it is there, and one sent in chunks is read only to its first non-empty chunk."""
        if request.method not in TAKE_CONTENT or not sends_body(request):
            return
        length = request.headers.get("content-length", "").strip()
        if "transfer-encoding" not in request.headers and length.isdigit():
            sent = f"{int(length)} bytes"
        elif await _any_content(request):
            sent = "a chunked body"
        else:
            return
        sent_as = f" of {media_type_shown(request)}" if media_type(request) else ""
        raise HTTPException(415, f"{request.method} {self.path} takes no body: send none (got {sent}{sent_as})")

    def get_route_handler(self):
        handler = super().get_route_handler()

        async def check_then_handle(request: Request) -> Response:
            self.refuse_odd_query(request)
            if self.body_field is None:
                await self.refuse_body(request)
            else:
                refuse_encoded(request)
                if json_sent(media_type(request)):
                    request = UniqueMembersRequest(request.scope, request.receive)  # nothing read yet
            return await handler(request)

        return check_then_handle


def unavailability(exc: Exception) -> str | None:
    """Why an ``UNAVAILABLE`` error means the database or the storage cannot serve now, or None when it does not: a
    fault of the service or its settings (``voxe_service.db.database_outage``; a missing bucket, access denied, a bad
    key, a missing object: a retry would meet them again), which stays a 500."""
    if isinstance(exc, StorageError):
        return "the storage cannot be reached or is busy" if isinstance(exc, StorageUnavailable) else None
    return database_outage(exc)


def unavailable(_request: Request | None, exc: Exception) -> JSONResponse:
    """The 503 for a database or storage that cannot serve now (:func:`unavailability`); its text (host names, SQL,
    buckets) stays in the log. Any other such error is raised again, for the 500 and its traceback."""
    reason = unavailability(exc)
    if reason is None:
        raise exc
    log.warning("answered 503: %s", exc, exc_info=exc)
    return JSONResponse({"detail": f"{reason}; try again in {RETRY_AFTER_S} s"}, status_code=503,
                        headers={"Retry-After": str(RETRY_AFTER_S)})


def try_again_soon(detail: str) -> HTTPException:
    """A 503 saying ``detail`` and when to send the request again (``Retry-After``): what a dependency's outage
    refused (nothing of the request kept) may succeed then."""
    return HTTPException(503, f"{detail}; try again in {RETRY_AFTER_S} s", headers={"Retry-After": str(RETRY_AFTER_S)})


class _HeadersSent(Exception):
    """Raised into a streamed answer to a HEAD once its headers are out: its body would be dropped anyway, and an
    event stream's runs until its job ends."""


class HeadAsGet:
    """HEAD wherever GET is served (RFC 9110 §9.3.2), answered as that GET with its status and headers (a
    Content-Length too), without the body (ASGI middleware). FastAPI's GET routes answered it 405: ``curl -I`` on
    a job's URL. A route serving HEAD itself (an artifact's download, which reads no bytes for it) answers it."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] != "HEAD":
            return await self.app(scope, receive, send)
        path = route_path(scope)
        if routed(scope["app"], path, "HEAD") or not routed(scope["app"], path, "GET"):
            return await self.app(scope, receive, send)
        body_sent = False

        async def headers_only(message):
            nonlocal body_sent
            if message["type"] != "http.response.body":
                return await send(message)
            if not body_sent:
                body_sent = True
                await send({"type": "http.response.body", "body": b"", "more_body": False})
            if message.get("more_body"):
                raise _HeadersSent

        try:
            await self.app({**scope, "method": "GET"}, receive, headers_only)
        except _HeadersSent:
            pass


KEYS_OWN = "private, no-cache"
"""The Cache-Control of a /v1 answer whose route says none: a browser may keep it, revalidating it (an artifact's
ETag) before each use; a shared cache keeps none."""


def keys_own(scope) -> bool:
    """Whether a request's answer is one key's: any under /v1."""
    return (route_path(scope) + "/").startswith("/v1/")


class PrivateAnswers:
    """``Cache-Control: private, no-cache`` on every /v1 answer whose route sets no Cache-Control (ASGI middleware).

    Each is the key's own (its jobs, scenes, artifacts, webhook secret), but its key may come in ``X-API-Key``, a
    header shared caches know nothing of (RFC 9111 §3.5 keeps only answers to ``Authorization`` out of them) and no
    answer varied on: a proxy caching by URL (Varnish's default: 120 s for a 200 with no Cache-Control) had answered
    one key's ``GET /v1/jobs``, or its webhook secret, to the next key asking."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or not keys_own(scope):
            return await self.app(scope, receive, send)

        async def send_private(message):
            if message["type"] == "http.response.start" and not any(
                    name.lower() == b"cache-control" for name, _ in message.get("headers", [])):
                message = {**message, "headers": [*message.get("headers", []),
                                                  (b"cache-control", KEYS_OWN.encode())]}
            await send(message)

        await self.app(scope, receive, send_private)


class RefuseNul:
    """The NUL answers above, before any route (ASGI middleware)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] == "http":
            query = scope.get("query_string", b"")
            if "\x00" in scope["path"]:
                return await JSONResponse({"detail": "not found: the path holds a NUL character"}, 404)(
                    scope, receive, send)
            if b"%00" in query or b"\x00" in query:
                return await JSONResponse({"detail": "the query string holds a NUL character"}, 422)(
                    scope, receive, send)
        return await self.app(scope, receive, send)


def install(app: FastAPI) -> None:
    """Answer NUL paths, unreadable JSON, HEAD, 405 and OPTIONS as above, keep /v1 answers out of shared caches, and
    document them with the statuses no route declares itself."""
    app.add_middleware(RefuseNul)
    app.add_middleware(HeadAsGet)
    app.add_middleware(PrivateAnswers)
    app.add_exception_handler(405, method_not_allowed)
    app.add_exception_handler(400, unreadable_body)
    for error in UNAVAILABLE:
        app.add_exception_handler(error, unavailable)
    generate = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = document(generate())
        return app.openapi_schema

    app.openapi = openapi


def _or_problem(content: dict | None) -> dict:
    """A response's ``content`` whose JSON schema admits a Problem too: the answer merged into a response the route
    documents (FastAPI's 422, HTTPValidationError, whose detail is an array) sends its detail as a string."""
    schema = (content or {}).get("application/json", {}).get("schema")
    problem = _PROBLEM["application/json"]["schema"]
    if schema is None or schema == problem:
        return _PROBLEM
    return {**content, "application/json": {**content["application/json"], "schema": {"anyOf": [schema, problem]}}}


def document(schema: dict) -> dict:
    """Add to each operation what middleware and handlers answer: 400 and 415 (a JSON or multipart body; 415 for any
    body sent to a POST or DELETE taking none), 413 (any body), 401, 422 (:class:`StrictRoute`'s query checks), 503
    and the key schemes (/v1), and an OPTIONS operation per path (204 + Allow; other methods 405 + Allow); and the
    Problem body of each error a /v1 route documents with none (a 404, 409, 412, 416, 429: documented as no body, a
    client generated from the document could not read why it was refused)."""
    components = schema.setdefault("components", {})
    components.setdefault("securitySchemes", {}).update(SECURITY_SCHEMES)
    components.setdefault("schemas", {})["Problem"] = {
        "type": "object", "required": ["detail"], "title": "Problem",
        "properties": {"detail": {"description": "what was wrong, naming the field, file or rule"}}}
    for path, item in schema["paths"].items():
        for method, operation in item.items():
            responses = operation["responses"]
            if "application/json" in operation.get("requestBody", {}).get("content", {}):
                responses.setdefault("400", {"description": "malformed JSON body (it does not parse as JSON, or an "
                                                            "object names a member twice)",
                                             "content": _PROBLEM})
                responses.setdefault("415", {"description": "the body was not sent as JSON (Content-Type), or was "
                                                            "sent encoded (a Content-Encoding other than identity)",
                                             "content": _PROBLEM})
            if FORM_MEDIA_TYPE in operation.get("requestBody", {}).get("content", {}):
                responses.setdefault("400", {"description": "malformed multipart body (Starlette's parser names "
                                                            "the fault: a missing boundary, a bad part header)",
                                             "content": _PROBLEM})
                responses.setdefault("415", {"description": f"the body was not sent as a form ({FORM_MEDIA_TYPE}), or "
                                                            "was sent encoded (a Content-Encoding other than identity)",
                                             "content": _PROBLEM})
            if method.upper() in TAKE_CONTENT and "requestBody" not in operation:
                responses.setdefault("415", {"description": "a body was sent: the operation takes none",
                                             "content": _PROBLEM})
            if method.upper() in TAKE_CONTENT:
                responses.setdefault("413", {"description": "request body over the upload limit "
                                                            "(VOXE_MAX_UPLOAD_BYTES; a JSON body over "
                                                            "VOXE_MAX_JSON_BODY_BYTES)", "content": _PROBLEM})
            if path.startswith("/v1"):
                body = {} if method == "head" else {"content": _PROBLEM}  # a HEAD's answers carry none
                responses.setdefault("401", {"description": "authentication on (VOXE_AUTH) and no live API key "
                                                            "sent", **body})
                operation["security"] = [{"bearer": []}, {"apiKey": []}, {}]
                for code, answer in (("503", _UNAVAILABLE_503), ("422", _ODD_QUERY_422)):
                    documented = responses.setdefault(code, {"description": answer, **body})
                    if documented["description"] != answer:
                        documented["description"] += f"; or {answer}"
                        if body:
                            documented["content"] = _or_problem(documented.get("content"))
                if method != "head":  # the errors a route documents itself answer a Problem too (a HEAD's no body)
                    for code, documented in responses.items():
                        if code[0] in "45":
                            documented.setdefault("content", _PROBLEM)
        methods = ", ".join(m.upper() for m in sorted({*item, "options", *(("head",) if "get" in item else ())}))
        item["options"] = {
            "summary": "The methods this path serves", "operationId": "options" + path.replace("/", "_").replace(
                "{", "").replace("}", ""),
            "description": f"204 with `Allow: {methods}` (no key needed). Any other method answers 405 with the same "
                           "`Allow` header.",
            "responses": {"204": {"description": "the Allow header lists the path's methods", "headers": _ALLOW},
                          "405": {"description": "(other methods) not served here; Allow lists those that are",
                                  "headers": _ALLOW, "content": _PROBLEM}},
            "security": [{}],
        }
    return schema
