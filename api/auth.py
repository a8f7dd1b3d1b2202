"""Access: API keys (hashed tokens), the current-key dependency, per-key quotas and Idempotency-Key replay.

Tokens read ``voxe_<key id>_<secret>`` (32 random bytes of secret). The database keeps only the
sha256 of the whole token; the id finds the row and the hashes are compared in constant time.
With authentication off (allowed on a loopback host only, see :func:`check_startup`) every
request acts as the built-in ``local`` key, so the same ownership rules hold either way. The
``CurrentKey`` dependency itself is in :mod:`api.deps`.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated
from urllib.parse import urlsplit

import anyio
from fastapi import Header, HTTPException, Request, Response, status
from fastapi.responses import JSONResponse
from sqlalchemy import and_, delete, func, select, update
from sqlalchemy.orm import Session
from starlette.datastructures import Headers

from api.http_semantics import DATABASE_UNAVAILABLE, as_sent, route_path, unavailable
from voxe_service.db import get_sessionmaker
from voxe_service.quotas import lock_key, stored_bytes, upload_limit
from voxe_service.models import LOCAL_KEY_ID, PROCESSING, QUEUED, RUNNING, ApiKey, IdempotencyRecord, Job, utcnow
from voxe_service.settings import Settings, SettingsError, get_settings, is_loopback
from voxe_service.texts import listed

TOKEN_PREFIX = "voxe_"
_TOKEN = re.compile(r"^voxe_([0-9a-f]{12})_[A-Za-z0-9_-]{20,}$")
IDEMPOTENCY_HEADER = "Idempotency-Key"
REPLAYED_HEADER = "Idempotent-Replayed"


def sha256_hex(text: str) -> str:
    """The hex sha256 of ``text``'s UTF-8: what is stored of a token, and a request's Idempotency-Key digest."""
    return hashlib.sha256(text.encode()).hexdigest()


def create_key(session: Session, name: str, max_active_jobs: int | None = None,
               max_upload_bytes: int | None = None, expires_at: datetime | None = None) -> tuple[ApiKey, str]:
    """A new key row and its token (the only time the token exists outside the client)."""
    key_id = secrets.token_hex(6)
    token = f"{TOKEN_PREFIX}{key_id}_{secrets.token_urlsafe(32)}"
    key = ApiKey(id=key_id, name=name, token_sha256=sha256_hex(token), max_active_jobs=max_active_jobs,
                 max_upload_bytes=max_upload_bytes, expires_at=expires_at)
    session.add(key)
    session.commit()
    return key, token


def token_key_id(token: str) -> str | None:
    """The key id a token names (``voxe_<key id>_<secret>``); None for text of any other form."""
    match = _TOKEN.fullmatch(token)  # (match: its "$" also matched before a final "\n", a token no key has)
    return match.group(1) if match else None


def key_of_token(session: Session, token: str) -> ApiKey | None:
    """The key a token belongs to, revoked or not, or None."""
    key = session.get(ApiKey, key_id) if (key_id := token_key_id(token)) is not None else None
    if key is None or key.token_sha256 is None:
        return None
    return key if hmac.compare_digest(key.token_sha256, sha256_hex(token)) else None


def has_expired(key: ApiKey) -> bool:
    """Whether the key is past its ``expires_at`` (a key without one never expires)."""
    return key.expires_at is not None and key.expires_at <= utcnow()


CHALLENGE = {"WWW-Authenticate": "Bearer"}


def presented_token(request: Request) -> str | None:
    """``Authorization: Bearer <token>``, else ``X-API-Key: <token>`` (the header for clients whose
    ``Authorization`` carries another scheme: a proxy's Basic credentials).

    401 when the request carries two different tokens (the headers repeated, or both forms): only the first line had
    counted, where a proxy or another server may read the last, so one request could be taken as two keys.
    """
    bearers = [value.strip() for scheme, _, value in (line.partition(" ") for line in request.headers.getlist(
        "authorization")) if scheme.lower() == "bearer"]
    keys = request.headers.getlist("x-api-key")
    tokens = [token for token in bearers + keys if token]
    if len(set(tokens)) > 1:
        # The lines that carried them: two Bearer lines had been told "Authorization: Bearer and X-API-Key lines".
        lines = " and ".join(f"{count} {name} line{'s' if count > 1 else ''}" for name, count in (
            ("Authorization: Bearer", sum(map(bool, bearers))), ("X-API-Key", sum(map(bool, keys)))) if count)
        raise HTTPException(status.HTTP_401_UNAUTHORIZED,
                            f"{len(set(tokens))} different API keys sent ({lines}): send one key", headers=CHALLENGE)
    return tokens[0] if tokens else None


def unauthorized(token: str | None, authorization: list[str] = ()) -> str:
    """The 401's detail for a request presenting ``token`` (None: none read from its ``authorization`` lines)."""
    problem = "invalid or revoked API key" + _schemed(token) if token else "missing API key" + _unread(authorization)
    return (f"{problem}: send 'Authorization: Bearer <key>' or 'X-API-Key: <key>' "
            "(keys come from 'python -m api.admin create-key')")


def _schemed(token: str) -> str:
    """Why a key is not read when ``Bearer `` is sent before it where the key goes alone (``X-API-Key: Bearer
    voxe_...``, as Authorization is written): it had been told "invalid or revoked", a live key's holder left to
    suspect the key. "" for any other text."""
    scheme, _, rest = token.partition(" ")
    if scheme.lower() == "bearer" and token_key_id(rest.strip()) is not None:
        return " ('Bearer ' sent before it: X-API-Key takes the key alone, 'Authorization: Bearer <key>' once)"
    return ""


def _unread(authorization: list[str]) -> str:
    """Why Authorization lines gave no key, said without quoting one: a key sent without "Bearer " before it (curl -H
    "Authorization: voxe_..."), or under another scheme (Token, Basic), had been told "missing API key", as though
    none was sent. "" for none sent, or only empty Bearer ones."""
    schemes = [line.strip().partition(" ")[0] for line in authorization if line.strip()]
    if any(scheme.startswith(TOKEN_PREFIX) for scheme in schemes):
        return " (Authorization holds a key without 'Bearer ' before it)"
    others = sorted({as_sent(scheme) for scheme in schemes if scheme.lower() != "bearer"})  # (quoted as written)
    return f" (Authorization's scheme {listed(others, width=20)} is not read: only Bearer is)" if others else ""


def refusal(key: ApiKey | None, token: str | None) -> str | None:
    """The 401's detail for a request presenting ``token`` (``key``: the key it belongs to, None for none); None
    when the key is live. An expired key is told so and since when: it had answered "invalid or revoked", leaving its
    holder to guess why a key that had worked stopped. Only the token's holder learns it (the hash matched)."""
    if key is None or key.revoked_at is not None:
        return unauthorized(token)
    if has_expired(key):
        return (f"API key {key.id} expired at {key.expires_at.isoformat(timespec='seconds')}: ask the service's admin "
                "for a later expiry ('python -m api.admin update-key --expires-in') or a new key")
    return None


def _live_key_id(token: str) -> tuple[str | None, str | None]:
    """(the id of the live key ``token`` belongs to, None), or (None, why it is refused)."""
    with get_sessionmaker()() as session:
        key = key_of_token(session, token)
        refused = refusal(key, token)
        return (None, refused) if refused is not None else (key.id, None)


def off_loopback_address(scope) -> str | None:
    """The local address a request came in on when it is an IP address but not a loopback one; None for a loopback
    address, a Unix socket or a test client's "testserver"."""
    host = (scope.get("server") or (None,))[0]
    try:
        address = str(ipaddress.ip_address(host))
    except (TypeError, ValueError):
        return None
    return None if is_loopback(address) else address


PROXY_HEADERS = ("Forwarded", "X-Forwarded-For", "X-Forwarded-Host", "X-Forwarded-Proto", "X-Real-IP")


def proxy_header(scope) -> str | None:
    """The first header by which a proxy says it relayed the request (RFC 7239's, or the de facto X-Forwarded-* and
    X-Real-IP); None when it has none."""
    sent = {name.decode("latin-1").lower() for name, _ in scope.get("headers", ())}
    return next((name for name in PROXY_HEADERS if name.lower() in sent), None)


def foreign_name(scope) -> str | None:
    """The Host or Origin header (as sent, cut short) naming a host other than a loopback one or the server's own
    name in the request's scope (uvicorn's is its loopback address; an in-process test client's "testserver");
    None when neither does. A browser sends them: a page of another site posting a form here
    (Origin), or one whose name its owner pointed at 127.0.0.1 reading and writing the API as its own (DNS
    rebinding: Host), had acted as the local key."""
    server = (scope.get("server") or (None,))[0]
    headers = Headers(scope=scope)
    for name in ("Host", "Origin"):
        if (value := headers.get(name)) is None:
            continue
        try:
            host = urlsplit(value if name == "Origin" else f"//{value}").hostname
        except ValueError:  # (an unclosed IPv6 bracket, a port that is no number)
            host = None
        if host is None or not (is_loopback(host) or host == server):
            return f"{name}: {value[:80]}"
    return None


def not_local(scope, settings: Settings) -> str | None:
    """With authentication off, why the request is not served as the local key (the clause of the 401's message that
    says it and what to do); None when it came in on loopback from this machine."""
    turn_on = "turn authentication on (VOXE_AUTH=on; keys from 'python -m api.admin create-key')"
    if (address := off_loopback_address(scope)) is not None:
        return (f"this one came in on {address}: have uvicorn listen on VOXE_HOST (--host {settings.host}, as bash "
                f".ci/serve does), or {turn_on}")
    if (relayed := proxy_header(scope)) is not None:
        return f"this one was relayed by a proxy (its {relayed} header), which serves whoever reaches it: {turn_on}"
    if (named := foreign_name(scope)) is not None:
        return (f"this one names another host ({named}): a page of another site, or of a name pointed at this "
                f"machine, may not act as the local key; open the API as 127.0.0.1 or localhost, or {turn_on}")
    return None


class RequireKey:
    """ASGI middleware: with authentication on, a /v1 request without a live key is answered 401 before its
    body is read, so an anonymous client cannot make the server receive and spool an upload.

    With authentication off, a /v1 request that came in on an address other than loopback is a 401 too: VOXE_HOST
    only tells the API where uvicorn listens, and uvicorn run with ``--host 0.0.0.0`` beside the default VOXE_HOST
    had served the network as the local key, with no key asked. So is one a proxy says it relayed (``proxy_header``):
    a proxy on the machine comes in on loopback, and had served whoever reached the proxy as the local key; and one a
    browser sent for a page of another site (``foreign_name``)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or not route_path(scope).startswith("/v1") or scope["method"] == "OPTIONS":
            return await self.app(scope, receive, send)  # OPTIONS: the Allow header only (api/http_semantics.py)
        settings = get_settings()
        if not settings.auth_enabled:
            if (why := not_local(scope, settings)) is None:
                return await self._unless_upload_refused(scope, receive, send, LOCAL_KEY_ID)
            detail = (f"authentication is off (VOXE_AUTH={settings.auth}, VOXE_HOST={settings.host}), so only "
                      f"loopback connections are served, and {why}")
            response = JSONResponse({"detail": detail}, status.HTTP_401_UNAUTHORIZED, headers=CHALLENGE)
            return await response(scope, receive, send)
        request = Request(scope)
        try:
            token = presented_token(request)
        except HTTPException as exc:
            response = JSONResponse({"detail": exc.detail}, exc.status_code, headers=exc.headers)
            return await response(scope, receive, send)
        try:
            key_id, refused = (await anyio.to_thread.run_sync(_live_key_id, token) if token
                               else (None, unauthorized(token, request.headers.getlist("authorization"))))
        except DATABASE_UNAVAILABLE as exc:  # outside the app's handlers: answered here, as a route's would be
            return await unavailable(None, exc)(scope, receive, send)
        if key_id is None:
            response = JSONResponse({"detail": refused}, status.HTTP_401_UNAUTHORIZED, headers=CHALLENGE)
            return await response(scope, receive, send)
        scope.setdefault("state", {})["api_key_id"] = key_id
        await self._unless_upload_refused(scope, receive, send, key_id)

    async def _unless_upload_refused(self, scope, receive, send, key_id: str):
        """The app, unless the request is an upload its key has no byte of quota left for: then that 429, before
        the body is read (FastAPI receives and spools an upload's form whole before its route runs, which had
        refused it so only once the GBs were in)."""
        if scope["method"] == "POST" and route_path(scope).rstrip("/") == "/v1/scenes":
            try:
                refused = await anyio.to_thread.run_sync(upload_refused_unread, key_id, Headers(scope=scope))
            except DATABASE_UNAVAILABLE as exc:
                return await unavailable(None, exc)(scope, receive, send)
            if refused is not None:
                response = JSONResponse({"detail": refused.detail}, refused.status_code, headers=refused.headers)
                return await response(scope, receive, send)
        await self.app(scope, receive, send)


def check_startup(settings: Settings) -> str:
    """The startup line about authentication; SettingsError when it would be off on a reachable address (said in
    one line as the API starts, where a RuntimeError had been uvicorn's traceback)."""
    if settings.auth_enabled:
        return f"authentication ON (VOXE_AUTH={settings.auth}, host {settings.host}): every request needs an API key"
    if not is_loopback(settings.host):
        raise SettingsError(f"refusing to start: VOXE_AUTH=off on the non-loopback host {settings.host!r}; "
                           "authentication may be off only on 127.0.0.1 / ::1 / localhost")
    return (f"authentication OFF (VOXE_AUTH={settings.auth}, loopback host {settings.host}): every request acts "
            "as the local key; set VOXE_AUTH=on to require API keys")


# ------------------------------------------------------------------ quotas
def lock_live_key(session: Session, key: ApiKey) -> None:
    """Lock the key for what this request records under it (:func:`voxe_service.quotas.lock_key`); 401 when it was
    revoked since the request was authenticated (an upload is unpacked for minutes in between): a job or scene
    recorded after ``revoke-key`` had canceled the key's jobs ran on, for a key nothing could read or cancel it with.
    ``revoke-key`` writes the key's row, so it waits for a request holding the lock, and then finds its jobs."""
    lock_key(session, key.id)
    if session.scalar(select(ApiKey.revoked_at).where(ApiKey.id == key.id)) is not None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, f"API key {key.id} was revoked while this request was "
                            "handled: nothing was recorded", headers=CHALLENGE)


class QuotaExceeded(HTTPException):
    """429 over a key's quota, with ``Retry-After`` only where waiting can clear it (``retry_after_s``): a job
    ending frees a place, but only deleting scenes frees upload bytes (a client waiting that out had sent the whole
    upload again and again, to the same 429)."""

    def __init__(self, message: str, retry_after_s: int | None):
        super().__init__(status.HTTP_429_TOO_MANY_REQUESTS, message,
                         headers=None if retry_after_s is None else {"Retry-After": str(retry_after_s)})


def check_active_jobs(session: Session, key: ApiKey, settings: Settings, adding: int = 1) -> None:
    """With the ``adding`` new jobs' rows flushed: 429 when the key now has more queued + running jobs than allowed,
    or 422 when ``adding`` alone is more (no retry could ever be accepted)."""
    limit = key.max_active_jobs or settings.max_active_jobs_per_key
    if adding > limit:
        # Raised on this key: "use a key created with a higher --max-active-jobs" had sent its holder to a new key,
        # which sees none of this one's scenes and jobs, where update-key raises this one's, token unchanged.
        raise_it = ("raise VOXE_MAX_ACTIVE_JOBS_PER_KEY" if key.id == LOCAL_KEY_ID else "have the service's admin "
                    f"raise the key's own ('python -m api.admin update-key {key.id} --max-active-jobs {adding}')")
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"this request creates {adding} jobs but key {key.name!r} may have at most {limit} queued "
                            "or running (VOXE_MAX_ACTIVE_JOBS_PER_KEY or the key's own), so it can never be accepted: "
                            f"ask for fewer (a sweep over fewer scenes), or {raise_it}")
    active = session.scalar(select(func.count()).select_from(Job)
                            .where(Job.owner_key_id == key.id, Job.state.in_((QUEUED, RUNNING)))) or 0
    if active > limit:
        raise QuotaExceeded(f"quota of concurrent jobs exceeded: key {key.name!r} already has {active - adding} "
                            f"queued or running job(s) and asked for {adding} more, the limit is {limit} "
                            "(VOXE_MAX_ACTIVE_JOBS_PER_KEY or the key's own); retry when one finishes, or cancel one",
                            settings.quota_retry_after_s)


def check_upload_bytes(session: Session, key: ApiKey, settings: Settings, adding: int,
                       including_new: bool = False) -> None:
    """429 when the key's stored scenes plus ``adding`` bytes exceed its upload quota; 413 when ``adding`` alone
    does (deleting scenes could never make room). ``adding`` 0: the check before an upload's size is known, which
    refuses a key whose quota is exactly used up (every upload stores at least a byte; it had been unpacked and
    checked first).

    ``including_new``: the new scene's row (of ``adding`` bytes) is already flushed into the sum.
    """
    limit = upload_limit(key, settings)
    total = stored_bytes(session, key.id)
    stored = total - adding if including_new else total
    if adding > limit:
        # As over the job quota: the advice names how to raise this key's own (it had named none), to a size that
        # fits this upload beside what the key stores.
        raise_it = ("raise VOXE_MAX_UPLOAD_BYTES_PER_KEY" if key.id == LOCAL_KEY_ID else "have the service's admin "
                    f"raise the key's own ('python -m api.admin update-key {key.id} --max-upload-bytes "
                    f"{stored + adding}')")
        raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE,
                            f"this upload stores {adding} bytes, more than the whole upload quota of key {key.name!r} "
                            f"({limit} bytes: VOXE_MAX_UPLOAD_BYTES_PER_KEY or the key's own), so it can never be "
                            f"accepted: {raise_it}")
    if stored + max(adding, 1) > limit:
        this = f"this upload adds {adding}" if adding else "before this upload is read"
        raise QuotaExceeded(f"quota of upload bytes exceeded: key {key.name!r} stores {stored} bytes of scenes, "
                            f"{this}, the limit is {limit} (VOXE_MAX_UPLOAD_BYTES_PER_KEY or the key's own); delete "
                            "scenes to free space", None)


def upload_refused_unread(key_id: str, headers: Headers) -> QuotaExceeded | None:
    """The 429 of an upload whose key's quota has no byte left (:func:`check_upload_bytes` adding nothing: every
    upload stores one), asked before its body is read; None where there is room, or where its Idempotency-Key has
    a record (a retry: the route replays what its first request created, whatever the quota)."""
    keys = headers.getlist(IDEMPOTENCY_HEADER)
    with get_sessionmaker()() as session:
        if (key := session.get(ApiKey, key_id)) is None:
            return None
        try:
            check_upload_bytes(session, key, get_settings(), 0)
            return None
        except QuotaExceeded as exc:
            refused = exc
        # (its records read only for a key with no room: an upload that fits asks the quota alone)
        if keys and session.scalar(select(IdempotencyRecord.id).where(
                IdempotencyRecord.owner_key_id == key_id, IdempotencyRecord.endpoint == "scenes",
                IdempotencyRecord.idempotency_key.in_([as_sent(k) for k in keys]))) is not None:
            return None
    return refused


# ------------------------------------------------------------------ Idempotency-Key
@dataclass
class Idempotency:
    """A request's Idempotency-Key and the digest of what it asks for."""

    key: str
    request_sha256: str
    endpoint: str
    earlier_sha256: str | None = None
    """The digest an earlier version recorded for the same request, still matched: a retry across an upgrade."""
    noun: str = ""
    """What messages call the recorded resource when it is not the endpoint's own (a sweep records one of its jobs)."""

    def record(self, session: Session, owner: ApiKey, resource_id: str) -> IdempotencyRecord:
        """Add the record, pending until :meth:`answered`, to the session that creates the resource (one
        transaction; a racing twin fails it); returned, so the caller can name another of its resources before it
        commits."""
        record = IdempotencyRecord(owner_key_id=owner.id, endpoint=self.endpoint, idempotency_key=self.key,
                                   request_sha256=self.request_sha256, resource_id=resource_id, pending=True,
                                   created_at=utcnow())
        session.add(record)
        return record

    def answered(self, session: Session, owner: ApiKey) -> None:
        """The request keeps what it created (the broker took it, or it waits for its scene): retries replay it."""
        session.execute(update(IdempotencyRecord).where(self._this_record(owner)).values(pending=False))

    def forget(self, session: Session, owner: ApiKey) -> None:
        """Delete the record (its request was withdrawn: a retry with this Idempotency-Key runs it anew)."""
        session.execute(delete(IdempotencyRecord).where(self._this_record(owner)))

    def replayed(self, session: Session, owner: ApiKey, model: type):
        """For a retry: the ``model`` row the first request created (409 if it has been deleted since); None
        when this Idempotency-Key is new.

        Also 409 while that request has not answered and its job or scene is not yet with the broker: a refusal
        would withdraw it (a replay had answered 200 with a job deleted a moment later). A request that died there
        leaves its record pending: its job is replayed once it is sent (by the reaper, or by its scene's ingest),
        its scene once failed.
        """
        found = self.original(session, owner, model)
        if found is None:
            return None
        row, resource = found
        created = self._created(row)
        if resource is None:
            raise HTTPException(status.HTTP_409_CONFLICT, f"the {created} that Idempotency-Key {self.key!r} created "
                                "has been deleted; use a new key")
        if row.pending and resource.task_id is None and resource.state in (QUEUED, PROCESSING):  # (job, scene)
            raise HTTPException(status.HTTP_409_CONFLICT,
                                f"the first request with Idempotency-Key {self.key!r} has not answered yet (the "
                                f"broker may still refuse its {created}); retry in a moment",
                                headers={"Retry-After": "1"})
        return resource

    def original(self, session: Session, owner: ApiKey, model: type) -> tuple[IdempotencyRecord, object] | None:
        """The record of the first request with this key and the ``model`` row it created (None once deleted), None
        if none; 422 if it asked for something else.

        One statement reads both: read apart, a withdrawal (the 503 deleting the row with this record) committed
        in between made a retry answer "has been deleted; use a new key" for a key free to run anew.
        """
        found = session.execute(select(IdempotencyRecord, model)
                                .outerjoin(model, model.id == IdempotencyRecord.resource_id)
                                .where(self._this_record(owner))).first()
        if found is None:
            return None
        row, resource = found
        if not any(hmac.compare_digest(row.request_sha256, digest)
                   for digest in (self.request_sha256, self.earlier_sha256) if digest is not None):
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                                f"Idempotency-Key {self.key!r} was already used with a different request body "
                                f"(it created {self._created(row)}); use a new key for a "
                                "new request")
        return row, resource

    def _created(self, row: IdempotencyRecord) -> str:
        """What the record's request created, as messages name it: "job 'ab12'" (the 422 for another body had said
        "it created jobs 'ab12'", the endpoint's plural)."""
        return f"{self.noun or self.endpoint[:-1]} {row.resource_id!r}"

    def _this_record(self, owner: ApiKey):
        """The condition selecting this Idempotency-Key's record."""
        return and_(IdempotencyRecord.owner_key_id == owner.id, IdempotencyRecord.endpoint == self.endpoint,
                    IdempotencyRecord.idempotency_key == self.key)


def replayed_answer(model: type, what: str) -> dict:
    """The document's 200 of a POST taking an Idempotency-Key: the body its 201 has (``model``, the resource the first
    request created) and the Idempotent-Replayed header. It had been documented with no body, so a client generated
    from the document read a retry's answer as empty."""
    return {"model": model, "description": f"a retry with the same Idempotency-Key: the {what} it created",
            "headers": {REPLAYED_HEADER: {"description": "true: the answer to a retry", "schema": {"type": "string"}}}}


def mark_replayed(response: Response) -> None:
    """A retry answers 200 with ``Idempotent-Replayed: true`` and the resource the first request created."""
    response.status_code = status.HTTP_200_OK
    response.headers[REPLAYED_HEADER] = "true"


def idempotency_key(value: Annotated[str | None, Header(
        alias=IDEMPOTENCY_HEADER, json_schema_extra={"minLength": 1, "maxLength": 255, "pattern": r"\S"},
        description="a retry with the same key and body answers 200 with what the first request created")] = None,
        lines: Annotated[list[str] | None, Header(alias=IDEMPOTENCY_HEADER, include_in_schema=False)] = None,
        ) -> str | None:
    """The request's Idempotency-Key header (422 when blank, longer than 255 characters, not UTF-8, or sent more
    than once: the first line had silently counted, where a proxy or the client's own retry logic may take the last).

    Counted in characters, as the README and the schema's ``maxLength`` say: the server reads a header's bytes as
    Latin-1, one character per byte, and had refused a key of 200 "é" as 400 characters long. ``lines``: every line
    of the header (``value`` documents it).
    """
    if value is None:
        return None
    if lines is not None and len(lines) > 1:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{IDEMPOTENCY_HEADER} header sent more than once: send one key")
    try:
        value = value.encode("latin-1").decode("utf-8").strip()
    except UnicodeDecodeError:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{IDEMPOTENCY_HEADER} header must be UTF-8 text") from None
    if not value:  # "got 0" had counted what was left once the spaces sent were stripped, not what was sent
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{IDEMPOTENCY_HEADER} header is blank (empty or only spaces): send a key of 1-255 "
                            "characters, or leave the header out")
    if len(value) > 255:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{IDEMPOTENCY_HEADER} header must be 1-255 characters, got {len(value)}")
    return value

