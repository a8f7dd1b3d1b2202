"""``Client``: one httpx connection pool to the service, one method per call, errors as ``ServiceError``."""

from __future__ import annotations

import email.utils
import errno
import fcntl
import hashlib
import itertools
import json
import math
import os
import re
import reprlib
import time
import uuid
import warnings
import zlib
from collections.abc import Callable, Iterator
from contextlib import ExitStack, closing, contextmanager, suppress
from datetime import datetime, timezone
from pathlib import Path, PureWindowsPath
from typing import Any, BinaryIO
from urllib.parse import quote

import httpx

from voxe_core.constants import TEXTURE_SUFFIXES
from voxe_core.files import NAME_MAX, flush_to_disk, head_that_fits, take_the_mode_of
from voxe_core.ply_header import read_ply_header

DEFAULT_URL = "http://127.0.0.1:8000"
DEFAULT_TIMEOUT_S = 60.0
DEFAULT_RETRIES = 3
MAX_RETRY_WAIT_S = 30.0
RECONNECT_FOR_S = 300.0
"""How long an event stream keeps reconnecting to a service that stopped answering (an API restarted during a long
job; it had given up after about 15 s) before :meth:`Client.events` gives up."""
MAX_RECONNECT_PAUSE_S = 5.0
STREAM_SILENCE_S = 60.0
"""How long an open event stream may deliver nothing before it counts as lost and is resumed: the service sends a
keepalive comment every 15 s, so a connection silent this long is dead (a NAT's or a Wi-Fi's drop sends no reset; with
no read timeout, :meth:`Client.wait` had waited on it for good)."""
LOOK_AT_JOB_S = 5.0
"""How long the one look at a job that :meth:`Client.wait` takes once its timeout ran out may last (at most the
client's timeout): under the client's own, against a hung service, ``wait(timeout=1)`` had taken 61 s."""
PROXY_UNAVAILABLE = (502, 503, 504)
"""What a proxy in front of the API answers while the API restarts: a lost stream, not the service's refusal."""
IDEMPOTENCY_HEADER = "Idempotency-Key"
LOST_ANSWERS = (httpx.NetworkError, httpx.ConnectTimeout, httpx.PoolTimeout, httpx.RemoteProtocolError)
"""A request never sent, or whose answer the connection lost (refused, reset, dropped: an API restarting): a
submission goes again with its Idempotency-Key."""
DROPPED_CONNECTIONS = (httpx.ReadError, httpx.WriteError, httpx.RemoteProtocolError)
"""A connection reset or closed before its answer came (a kept-alive connection the service or a proxy had closed, an
API restarting): a read goes again. Not a connection refused: a wrong URL is said at once."""
SAFE_METHODS = ("GET", "HEAD")
"""Reads: the service changes nothing for them, so they are sent again at no risk."""
UNANSWERED_IN_TIME = (httpx.ReadTimeout, httpx.WriteTimeout)
"""A request the service may still be working on (its answer slower than the timeout: a large upload's staging): a
submission is not sent again, which would have the service do it a second time."""
BROKEN_DOWNLOADS = (*LOST_ANSWERS, httpx.ReadTimeout)
"""A download the connection broke off or stalled: it goes on from the bytes it has (a GET, sent again at no risk)."""
TERMINAL_STATES = ("succeeded", "failed", "canceled")
MAX_ANSWER_BYTES = 8 * 2**20
"""The most bytes of an answer's body the client reads into memory (:func:`_read_capped`): a JSON answer or an error
page, each a few KiB from the service (an artifact and an event stream are read as they come). A hostile or broken
server's endless one had been buffered whole, gigabytes. Counted decoded (:func:`_decoded`): a gzip bomb, small on the
wire, had been inflated whole past it."""
MAX_EVENT_BYTES = 2**20
"""The most bytes one Server-Sent Event (its lines from the last empty one, each end counted one byte, a comment's
too) may run to (:func:`_event_stream_lines`): the service's are a few KiB; a server's endless line, never ended by a
newline, had been held whole."""
ACCEPTED_ENCODINGS = ("gzip", "deflate")
"""The Content-Encodings the client reads (its ``Accept-Encoding``; x-gzip is read as gzip, RFC 9110 8.4.1.3), but
for an artifact, asked unencoded (:meth:`Client._fill_part`)."""
UNENCODED = {"accept-encoding": "identity"}
"""The ``Accept-Encoding`` of an artifact's GET: a Range counts the bytes of the body as sent, and of an encoded one
they are no offset into the file; the client refuses an encoded answer (a gzip bomb of GiB, inflated a chunk at a
time into the part file, had been written past its listed size before the check)."""
DECODED_PIECE_BYTES = 2**16
"""The most bytes :func:`_decoded` inflates at a time."""


def _masked(url: str) -> str:
    """``url`` as a refusal quotes it: what comes before an ``@`` in its authority (a user name and password) as
    ``***``, where ``//`` leads it or where the scheme, or the ``//``, was left out (``--api admin:s3cret@host:8000``,
    ``http:/admin:s3cret@host``: refused as no http(s) URL, the password quoted).

    Examples:
        >>> _masked("http://user:secret@host:8000"), _masked("admin:s3cret@host:8000"), _masked("http://host/a@b")
        ('http://***@host:8000', 'admin:***@host:8000', 'http://host/a@b')
    """
    return re.sub(r"^((?:[^:/?#@]*:)?/*)[^/?#]*@", r"\1***@", url, count=1)


def _segment(value: str) -> str:
    """``value`` as one path segment: an id holding "/", "?" or "#" had addressed another resource (the status of
    job "../scenes" printed the scene listing). "." and ".." name no resource (a URL drops them as dot segments), nor
    does "" (``voxe status ""`` had asked for /v1/jobs/ and said the service's redirect was not the API's JSON)."""
    if value in ("", ".", ".."):
        raise ServiceError(f"{value!r} is not an id")
    return quote(value, safe="")


class ServiceError(Exception):
    """The service answered with an error status (its detail is the message), or could not be reached.

    ``status`` is the HTTP status (None when the service was not reached) and ``detail`` its ``detail`` field.
    """

    def __init__(self, message: str, status: int | None = None, detail: Any = None):
        super().__init__(message)
        self.status = status
        self.detail = detail

    @property
    def service_failed(self) -> bool:
        """Whether the service failed (an error status of 500 or more) or was not reached, rather than refused the
        request (4xx) or answered what the client refuses: a caller may try the one again later, not the other."""
        return isinstance(self, ServiceUnreachable) or (self.status or 0) >= 500


class _ArtifactReplaced(ServiceError):
    """A download answered with another version of the artifact than the one listed with SHA-256 ``listed`` (its
    ETag): replaced since the listing was read."""

    def __init__(self, message: str, status: int, listed: str):
        super().__init__(message, status)
        self.listed = listed


REPLACED_TRIES = 3
"""The listings a download reads, each followed by a download of the version it names, before an artifact replaced
each time as it downloaded (a preview republished faster than it downloads) is the error."""


class NotAServiceURL(ValueError):
    """A base URL the client refuses (no http(s) scheme or host, a password, a query, a bad port): ``voxe`` names its
    --api option with it."""


class ServiceUnreachable(ServiceError):
    """The service could not be reached, or stopped answering: no answer to go by."""


class EventStreamLost(ServiceUnreachable):
    """A job's event stream lost for longer than :meth:`Client.events` reconnects: the service stopped answering (the
    job itself goes on there)."""


class UndecodableAnswer(ServiceError):
    """An answer whose Content-Encoding this client cannot undo: one it does not read, or one broken or cut short."""


class EncodedAnswerCutShort(UndecodableAnswer, ServiceUnreachable):
    """An encoded answer whose body ended before its encoding's stream did where its body ends at its connection's
    close (:func:`_ends_at_close`): a dropped connection, sent again or resumed as one, and the service failing
    (``service_failed``) once it is not, as a drop is (it had read as a refusal: ``voxe`` exit 2, a sweep's wait given
    up). A body its Content-Length or chunks say came whole is broken by its sender, an UndecodableAnswer: sent
    again, it would come as broken."""


class _StreamCutShort(zlib.error):
    """:func:`_inflated`'s pieces ending before their stream did."""


def snapshot_number(value: Any, most: float = math.inf) -> float | None:
    """A number of a job's progress snapshot (``overall_progress``, ``overall_eta_seconds``) from 0 to ``most``, as a
    float; None for anything else a service sent: a str ("50%"), a bool, NaN, one over ``most`` (a progress of 1e9 had
    drawn a bar of 30 billion #'s), an infinity (a time left of "~inf s"), an integer too large for a float (its
    ``float()`` had been an OverflowError, a traceback ending ``voxe wait``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) and 0 <= number <= most else None


class JobWaitTimeout(TimeoutError):
    """A job not ended within the ``timeout`` its :meth:`Client.wait` (or :meth:`Client.events`) was given: it goes on
    in the service. ``job_id``, ``state`` and ``progress`` (the last progress snapshot heard, None before any) say
    where it stood."""

    def __init__(self, job_id: str, timeout: float, progress: dict | None):
        self.job_id, self.timeout, self.progress = job_id, timeout, progress
        self.state = None if progress is None else progress.get("state")
        if progress is None:
            stood = "no progress heard from its event stream"
        else:
            stood = f"last heard {self.state}"
            if progress.get("stage"):
                stood += f", stage {progress['stage']}"
            if (done := snapshot_number(progress.get("overall_progress"), 1.0)) is not None:
                stood += f", {done:.0%} done"  # (a snapshot's "50%" had been a ValueError in place of this timeout)
        super().__init__(f"job {job_id} did not end within {timeout:g} s ({stood}); it goes on in the service")


class Client:
    """The job service at ``base_url``; ``api_key`` goes as ``Authorization: Bearer`` (none on a loopback service).

    Use it as a context manager (or call :meth:`close`) to release its connections. ``transport`` replaces httpx's
    network transport (tests pass ``httpx.MockTransport``). A read (GET, HEAD) answered 503 or 429 with ``Retry-After``
    (the service's database or broker briefly unavailable, a rate or quota limit) is sent again after that wait (seconds
    or an HTTP-date; one asking more than :data:`MAX_RETRY_WAIT_S` is the error at once, naming it), at most ``retries``
    times, and so is one whose connection dropped before its answer (:data:`DROPPED_CONNECTIONS`), after a doubling
    pause. A submission (an upload, a job, an evaluation, a sweep) goes with an ``Idempotency-Key``, one per call, so it too is sent
    again, with the same key, when its answer is lost (a connection refused or dropped, a 502 / 503 / 504), the service
    is still answering its first sending (409 with ``Retry-After``) or asks it to wait (429 with ``Retry-After``, over a
    quota that waiting clears, where it asks no more than :data:`MAX_RETRY_WAIT_S`: the job quota's is the service's
    ``VOXE_QUOTA_RETRY_AFTER_S``, 60 s by default, so there it is the error at once, naming the wait; the upload-bytes
    quota, which only deleting scenes clears, has none): the service answers a retry with what the first sending
    created, never a second one. A submission not answered within ``timeout`` is not (the service may still be working
    on it): the error names its key, to send it again with once it is done. Other writes (a cancel, a deletion) are
    not.

    Examples:
        >>> def answer(request):
        ...     return httpx.Response(404, json={"detail": "scene 'nope' not found"})
        >>> with Client(transport=httpx.MockTransport(answer)) as client:
        ...     try:
        ...         client.get_sweep("nope")
        ...     except ServiceError as error:
        ...         print(error.status, error)
        404 GET /v1/sweeps/nope: HTTP 404: scene 'nope' not found
    """

    def __init__(self, base_url: str = DEFAULT_URL, api_key: str | None = None, timeout: float = DEFAULT_TIMEOUT_S,
                 transport: httpx.BaseTransport | None = None, retries: int = DEFAULT_RETRIES):
        self.base_url = base_url.rstrip("/")
        if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:  # (no sending is ever the last:
            raise ValueError(f"retries must be a whole number, 0 or more, got {retries!r}")  # -1 or 2.5 had sent on)
        self.retries = retries
        timeout = _checked_timeout(timeout)
        headers = {"accept": "application/json", "accept-encoding": ", ".join(ACCEPTED_ENCODINGS)}
        if api_key:  # (one with a line break, as a key file's CRLF leaves, had failed each call as "cannot reach the
            if HEADER_BREAKS.search(api_key):  # service: Illegal header value b'Bearer <the key>'", exit 3)
                raise ValueError("the API key cannot be sent: it holds a line break, NUL or other whitespace than "
                                 "spaces and tabs (the end of a line of the file it was read from?)")
            headers["authorization"] = f"Bearer {api_key}".encode()  # UTF-8, as _header_bytes (not ASCII only)
        shown = _masked(base_url)  # its password never quoted
        host = re.sub(r"^[^:/?#]*://|[/?#].*$", "", self.base_url, flags=re.S).rpartition("@")[2]
        if host.startswith("[") and "]" not in host:  # httpx had said "Invalid port: ':1'" of http://[::1
            raise NotAServiceURL(f"{shown!r} is not a service URL: its IPv6 address's '[' has no closing ']', as "
                                 "http://[::1]:8000")
        if host.startswith("[") and (after := host.partition("]")[2]) and not after.startswith(":"):  # (http://[::1]x:
            raise NotAServiceURL(f"{shown!r} is not a service URL: its IPv6 address's ']' is followed by {after!r}, "
                                 "where only a :port may be, as http://[::1]:8000")  # "Invalid port: 'x'")
        if host.count(":") > 1 and not host.startswith("["):  # (http://::1: "Invalid port: ':1'" too)
            raise NotAServiceURL(f"{shown!r} is not a service URL: an IPv6 address is written in [ ], as "
                                 "http://[::1]:8000")
        try:
            url = httpx.URL(self.base_url)
        except httpx.InvalidURL as exc:  # (httpx's own type: a traceback in the CLI, which reports ValueErrors)
            raise NotAServiceURL(f"{shown!r} is not a service URL: {exc}") from None
        if url.userinfo:  # httpx had sent it as Basic auth in place of the key's header (a 401), and each error quoted
            # the URL, its password with it; this one does not
            raise NotAServiceURL(f"{shown!r} is not a service URL: it has a user name or password, which the service "
                                 "takes none of (its API key goes as --api-key or VOXE_API_KEY; the client's api_key)")
        if url.scheme not in ("http", "https") or not url.host:  # (each call had failed as a service not reached)
            raise NotAServiceURL(f"{shown!r} is not a service URL: it takes http:// or https:// and a host, as "
                                 f"{DEFAULT_URL}")
        if url.port is not None and not 0 < url.port <= 65535:  # httpx takes any number, and the socket then
            # connects to it modulo 65536: --api http://host:80000 had sent every call, and its key, to port 14464
            raise NotAServiceURL(f"{shown!r} is not a service URL: its port {url.port} is none of 1 to 65535")
        if (tail := re.search(r"[?#].*", self.base_url, re.S)) is not None:  # httpx appends each call's path to
            # the query: --api "http://host:8000/?x=1" had sent every call to /?x=1/v1/... (a fragment: a page's place)
            part = "query" if tail[0][0] == "?" else "fragment"
            raise NotAServiceURL(f"{shown!r} is not a service URL: it has a {part}, {tail[0]!r}, which a base "
                                 f"URL takes none of (as {DEFAULT_URL} or https://host/prefix)")
        self._http = httpx.Client(base_url=url, headers=headers, timeout=timeout, transport=transport)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def request(self, method: str, path: str, body: dict | None = None, idempotency_key: str | None = None,
                **kwargs) -> Any:
        """The decoded JSON answer of ``method path`` (``body`` sent as JSON, ``kwargs`` to httpx), None for a 204
        No Content (``DELETE /v1/scenes/{id}``'s: it had been refused as not the API's JSON, the scene deleted);
        ServiceError for an error status. With ``idempotency_key`` (its ``Idempotency-Key`` header) the request is
        sent again when its answer is lost (see the class)."""
        if idempotency_key is not None:
            kwargs["headers"] = {**kwargs.get("headers", {}), IDEMPOTENCY_HEADER: _header_bytes(idempotency_key)}
        try:
            response = self._send(method, path, json=body, resendable=idempotency_key is not None, **kwargs)
        except (httpx.TransportError, httpx.InvalidURL) as exc:
            if idempotency_key is not None and isinstance(exc, UNANSWERED_IN_TIME):
                raise ServiceUnreachable(
                    f"{method} {path}: {self.base_url} did not answer in time ({type(exc).__name__}: {exc}); the "
                    "service may have taken the request and still be working on it, so it was not sent again (it "
                    f"would be done twice): send it again later with {IDEMPOTENCY_HEADER} '{idempotency_key}' (voxe: "
                    "--idempotency-key) for what it made") from None
            raise ServiceUnreachable(f"cannot reach the service at {self.base_url}: {exc}") from None
        _raise_for_error(response, method, path, keyed=idempotency_key is not None)
        if response.status_code == httpx.codes.NO_CONTENT:
            return None
        if response.is_redirect:
            raise _redirected(response, method, path, self.base_url)
        try:
            return response.json()
        except ValueError:  # (a proxy's HTML): it had surfaced as "Expecting value"
            raise ServiceError(f"{method} {path}: {self.base_url} answered {response.status_code} with "
                               f"{response.headers.get('content-type') or 'no content type'}, not the API's JSON "
                               "(is it the Vox-E service?)") from None

    def _send(self, method: str, path: str, stream: bool = False, resendable: bool = False,
              resend_dropped: bool = True, deadline: float | None = None, **kwargs) -> httpx.Response:
        """The answer to ``method path`` (``kwargs`` to httpx's request), sent again at most ``retries`` times: a read
        or a ``resendable`` one (it carries an Idempotency-Key) after the wait its answer asks (:func:`_resend_wait`),
        a read whose connection dropped before its answer (unless not ``resend_dropped``: a caller that goes on from
        where it stopped), a ``resendable`` one whose answer was lost; with ``stream`` its body is left unread (close
        it), else read (:func:`_read_capped`: at most :data:`MAX_ANSWER_BYTES`). No wait goes past ``deadline`` (a
        ``time.monotonic()``; a caller's timeout: three Retry-After waits had held a ``wait(timeout=5)`` for 90 s): one
        that would is cut there (:func:`_ends_before`), and the answer or loss at hand stands, not sent again at it.

        Each sending builds the request anew, which reads an upload's files again from their start (httpx rewinds
        them): a retried upload sends the same bytes, which the service's Idempotency-Key check compares."""
        read = method in SAFE_METHODS
        dropped = LOST_ANSWERS if resendable else DROPPED_CONNECTIONS if read and resend_dropped else None
        lost = () if dropped is None else (*dropped, EncodedAnswerCutShort)  # (a body its close cut: a drop too)
        for attempt in itertools.count():
            try:
                response = self._http.send(self._http.build_request(method, path, **kwargs), stream=True)
                if not stream:
                    response = _read_capped(response, method, path)
            except lost:
                wait = _backoff(attempt)
                if attempt == self.retries or not _ends_before(wait, deadline):
                    raise
            else:
                wait = _resend_wait(response, attempt, resendable) if read or resendable else None
                if wait is None or attempt == self.retries or not _ends_before(wait, deadline):
                    return response
                response.close()
            time.sleep(wait)

    # ------------------------------------------------------------------ scenes and jobs
    def upload_scene(self, path: str | os.PathLike, name: str | None = None,
                     texture: str | os.PathLike | None = None, idempotency_key: str | None = None,
                     mesh_shading: str | None = None, mesh_up_axis: str | None = None) -> dict:
        """``POST /v1/scenes``: a dataset zip, or one mesh file (.obj / .ply), sent under its own file name (the
        service reads a mesh's kind from it), with ``name`` the scene's display name (by default the service names it
        by the zip's or the mesh's file name without its suffix); the scene, ``processing``.

        A mesh goes with the files that colour it: an OBJ's .mtl and the texture that names
        (:func:`obj_upload_files`), a PLY's texture its header names (:func:`ply_upload_files`); or ``texture``, an
        image that colours it at its UVs instead (as ``voxe mesh-to-grid --texture``). ``mesh_shading`` (auto, baked,
        none) and ``mesh_up_axis`` (x, y, z: z for CAD and most scanners) are the upload's form fields of those
        names (the service's defaults where None: auto, y), as ``voxe mesh-to-grid --shading / --up``.

        ``idempotency_key`` (as :meth:`create_job`'s) makes a repeated call answer with the scene the first made."""
        path = Path(path)
        paths = scene_upload_files(path, texture)
        field = "archive" if path.suffix.lower() == ".zip" else "files"
        form = {"name": name} if name else {}
        form.update((field_name, value) for field_name, value in (("mesh_shading", mesh_shading),
                                                                  ("mesh_up_axis", mesh_up_axis)) if value is not None)
        with ExitStack() as stack:
            opened = [(each, stack.enter_context(open(each, "rb"))) for each in paths]
            sizes = [os.fstat(file.fileno()).st_size for _, file in opened]
            try:
                return self._record("scene", "POST", "/v1/scenes", files=[(field, (each.name, file))
                                                                          for each, file in opened],
                                    data=form or None,
                                    idempotency_key=_submission_key(idempotency_key))
            except ServiceError:
                raise
            except Exception:  # (h11's "Too little data for declared Content-Length" had been a traceback)
                if changed := [f"{each} ({size} bytes when the upload opened it, {now} bytes now)"
                               for (each, file), size in zip(opened, sizes)
                               if (now := os.fstat(file.fileno()).st_size) != size]:
                    raise ValueError(f"{', '.join(changed)} changed as it was uploaded (still being written?): "
                                     "upload it once it is whole") from None
                raise

    def delete_scene(self, scene_id: str) -> None:
        """``DELETE /v1/scenes/{id}``: the scene with its finished jobs and their results (409 while one runs)."""
        self.request("DELETE", f"/v1/scenes/{_segment(scene_id)}")

    def get_scene(self, scene_id: str) -> dict:
        """``GET /v1/scenes/{id}``: the scene, its ``state`` processing, ready, or failed (its ``error`` says why)."""
        return self._record("scene", "GET", f"/v1/scenes/{_segment(scene_id)}")

    def list_scenes(self, limit: int | None = None, offset: int | None = None, cursor: str | None = None) -> dict:
        """``GET /v1/scenes``: a page of this key's scenes, newest first, ``{items, total, limit, offset,
        next_cursor}``; the page after it is ``cursor=page["next_cursor"]`` (None on the last page)."""
        return self._page("/v1/scenes", limit=limit, offset=offset, cursor=cursor)

    def scene_reconstructions(self, scene_id: str) -> list[dict]:
        """``GET /v1/scenes/{id}/reconstructions``: the scene's cached reconstructions that its jobs use, each with its
        ``state``, ``params`` and how often it was fitted (``run_count``)."""
        return self._listed("reconstructions", f"/v1/scenes/{_segment(scene_id)}/reconstructions")

    def create_job(self, scene_id: str, prompt: str, idempotency_key: str | None = None, **fields) -> dict:
        """``POST /v1/jobs``: ``fields`` are the body's other members (mode, edit_words, params, webhook_url, ...).

        Sent with ``idempotency_key`` (a new one when None): a caller that gives its own makes a repeated call, in
        another run say, answer with the job the first call made rather than make another (the same key with another
        request is a 422)."""
        return self._record("job", "POST", "/v1/jobs", {"scene_id": scene_id, "prompt": prompt, **fields},
                            idempotency_key=_submission_key(idempotency_key))

    def check_job(self, prompt: str, **fields) -> None:
        """``POST /v1/jobs?check=true``: ServiceError (the 422 naming the field, as :meth:`create_job` would get) for
        a job the service refuses on any scene, ``fields`` as :meth:`create_job`'s; nothing is made. Only that
        refusal is raised: another answer (an older service that does not check, one failing) leaves the job to be
        said by its creation."""
        try:
            self.request("POST", "/v1/jobs", {"scene_id": "-", "prompt": prompt, **fields}, params={"check": "true"})
        except ServiceError as exc:
            if exc.status == 422 and "unknown query parameter(s) 'check'" not in str(exc):
                raise

    def get_job(self, job_id: str) -> dict:
        return self._record("job", "GET", f"/v1/jobs/{_segment(job_id)}")

    def cancel_job(self, job_id: str) -> dict:
        return self._record("job", "POST", f"/v1/jobs/{_segment(job_id)}/cancel")

    def list_jobs(self, state: str | None = None, scene_id: str | None = None, limit: int | None = None,
                  offset: int | None = None, cursor: str | None = None) -> dict:
        """``GET /v1/jobs``: a page of this key's jobs, newest first, those in ``state`` or of ``scene_id`` where
        given (as :meth:`list_scenes`' page)."""
        return self._page("/v1/jobs", state=state, scene_id=scene_id, limit=limit, offset=offset, cursor=cursor)

    def job_timeline(self, job_id: str) -> list[dict]:
        """``GET /v1/jobs/{id}/events`` as JSON: the job's timeline so far, each event ``{id, kind, stage, detail,
        ...}`` (:meth:`events` follows it live)."""
        return self._listed("events", f"/v1/jobs/{_segment(job_id)}/events")

    def job_webhooks(self, job_id: str) -> list[dict]:
        """``GET /v1/jobs/{id}/webhooks``: the job's webhook deliveries, each with its ``state`` (pending, delivered,
        failed), attempts and the receiver's last status and error."""
        return self._listed("webhook deliveries", f"/v1/jobs/{_segment(job_id)}/webhooks")

    def _record(self, kind: str, method: str, path: str, body: dict | None = None, **kwargs) -> dict:
        """The record of a ``kind`` (job, scene, sweep) that ``method path`` answers (``body`` and ``kwargs`` to
        :meth:`request`); an answer that is no object with a string ``id`` and ``state``, as each of them has (a
        proxy's JSON, a 201 ``{"detail": "moved"}``, a broken service's), is a ServiceError quoting it: :meth:`wait`
        had returned it as the job, ``voxe wait`` ending in a KeyError or TypeError reading its state, and ``voxe
        submit`` in a KeyError 'id'."""
        record = self.request(method, path, body, **kwargs)
        if not isinstance(record, dict) or not all(isinstance(record.get(name), str) for name in ("id", "state")):
            raise ServiceError(f"{method} {path}: {self.base_url} answered {reprlib.repr(record)}, not a {kind} with "
                               "an id and a state")
        return record

    def _page(self, path: str, **query) -> dict:
        """The page of the listing at ``path`` that ``query`` asks for (its members that are None left out: the
        service's defaults); an answer that is no page, an object with a list of ``items``, is a ServiceError quoting
        it."""
        page = self.request("GET", path, params={name: value for name, value in query.items() if value is not None})
        if not isinstance(page, dict) or not isinstance(page.get("items"), list):
            raise ServiceError(f"GET {path}: {self.base_url} answered {reprlib.repr(page)}, not a page of a listing "
                               "(an object with its items)")
        return page

    def _listed(self, what: str, path: str) -> list[dict]:
        """The list of ``what`` (objects) that ``GET path`` answers; another answer is a ServiceError quoting it."""
        listed = self.request("GET", path)
        if not isinstance(listed, list) or not all(isinstance(each, dict) for each in listed):
            raise ServiceError(f"GET {path}: {self.base_url} answered {reprlib.repr(listed)}, not a list of {what}")
        return listed

    def events(self, job_id: str, last_event_id: int | None = None, reconnect_for: float | None = None,
               on_reconnect: Callable[[str], None] | None = None, timeout: float | None = None) -> Iterator[dict]:
        """The job's live events (``{"event", "id", "data"}``) until it ends, over Server-Sent Events.

        A dropped connection, one silent for :data:`STREAM_SILENCE_S` (no keepalive either: dead without a reset), a
        stream the server ended before the job's end (it was stopping) or cut short inside its gzip or deflate encoding
        (:class:`EncodedAnswerCutShort`), or a proxy's 502 / 503 / 504 while the API restarts is resumed with
        ``Last-Event-ID``, so no timeline event is missed or repeated, for up to ``reconnect_for`` seconds (default
        :data:`RECONNECT_FOR_S`) from the first loss since the stream last brought news or a keepalive
        (:func:`_is_news`): a reconnect bringing only the snapshot already heard does not restart it (a stream
        dropped after it each time is given up then), so its error's "N attempts over M s" may span several
        reconnects; ``progress`` snapshots carry no id.
        ``on_reconnect`` hears a line when the stream is lost and one when it is back, after how long that loss lasted
        (the events had stopped with nothing said). A stream never opened is an error at once: a wrong URL is not
        waited for, nor an answer that is no event stream (a proxy's page); once one opened, such an answer is a loss,
        and a 404 an error saying the job was deleted while it was followed (it had read as a wrong id).

        With ``timeout`` (seconds), a job not ended by then is a :class:`JobWaitTimeout` naming it and the state it
        was last heard in. It is checked at each line the stream brings (the service's keepalive comes every 15 s)
        and at each reconnect, and a stream opens with a read timeout no longer than the time left (one gone silent
        is not waited on :data:`STREAM_SILENCE_S` past it), and a ``Retry-After`` waited while opening one is cut at
        it: it may run over by about a keepalive's interval.
        """
        reconnect_for = RECONNECT_FOR_S if reconnect_for is None else reconnect_for
        for limit, seconds in (("timeout", timeout), ("reconnect_for", reconnect_for)):
            if seconds is not None and not seconds >= 0:  # (NaN had never run out: a lost stream asked again for good)
                raise ValueError(f"{limit} must be 0 or more seconds, got {seconds!r}")
        deadline = None if timeout is None else time.monotonic() + timeout
        opened, lost_since, attempts, reconnecting, progress = False, None, 0, False, None
        down_since = None  # this outage's start, for "back after": lost_since, the window's, may be an earlier one's

        def left() -> float:
            """Seconds until ``timeout`` runs out (infinite without one); a JobWaitTimeout once it has."""
            if deadline is None:
                return math.inf
            if (remaining := deadline - time.monotonic()) <= 0:
                raise JobWaitTimeout(job_id, timeout, progress)
            return remaining

        def restart_window() -> None:
            """A sign of life: a later loss is counted, and paused after, from its own start."""
            nonlocal lost_since, attempts
            lost_since, attempts = None, 0

        def alive(lines: Iterator[str]) -> Iterator[str]:
            """The stream's lines, each a check of ``timeout``; a keepalive is a sign of life, as news is
            (:func:`_is_news`: reset on events only, a quiet stream's drop had given up at once, its quiet time counted
            as the outage); not the ``retry:`` every stream opens with, or a server opening and dropping streams is
            waited on for good."""
            for line in lines:
                left()
                if line.startswith(":"):
                    restart_window()
                yield line

        while True:
            headers = {"accept": "text/event-stream"}
            if last_event_id is not None:
                headers["last-event-id"] = str(last_event_id)
            path = f"/v1/jobs/{_segment(job_id)}/events"
            limit = left()
            silence = min(STREAM_SILENCE_S, limit)
            try:
                with closing(self._send("GET", path, stream=True, headers=headers, resend_dropped=False,
                                        deadline=deadline,
                                        timeout=httpx.Timeout(min(30.0, limit), read=silence))) as response:
                    if response.is_error:
                        if _resend_wait(response, attempts, False) is not None:
                            left()  # a wait for it cut at the deadline: the timeout, not the answer it stood on
                        if not opened or response.status_code not in PROXY_UNAVAILABLE:
                            try:
                                _raise_for_error(_read_capped(response, "GET", path), "GET", path)
                            except ServiceError as exc:
                                if not opened or exc.status != 404:  # (one opened: the job was there then)
                                    raise
                                raise ServiceError(f"event stream of job {job_id} ended: the job is gone, deleted "
                                                   f"while it was followed ({exc})", exc.status, exc.detail) from None
                        lost = f"HTTP {response.status_code} {response.reason_phrase}"
                    elif not _is_event_stream(response):  # (its lines had restarted the reconnect window, for good)
                        lost = (f"{self.base_url} answered {response.status_code} with "
                                f"{response.headers.get('content-type') or 'no content type'}, not an event stream")
                        if not opened:
                            if response.is_redirect:
                                raise _redirected(response, "GET", path, self.base_url)
                            raise ServiceError(f"GET {path}: {lost} (is it the Vox-E service?)")
                    else:
                        if reconnecting and on_reconnect is not None:
                            on_reconnect(f"event stream of job {job_id} back after "
                                         f"{time.monotonic() - down_since:.0f} s")
                        opened, ended, reconnecting = True, False, False
                        lost = "the server ended the stream before the job ended"
                        lines = _event_stream_lines(_decoded(response, "GET", path))
                        try:
                            for event in _job_events(parse_sse(alive(lines)), job_id):
                                if _is_news(event, last_event_id, progress):
                                    restart_window()
                                if event["id"] is not None:
                                    last_event_id = int(event["id"])
                                if event["event"] == "progress":
                                    progress = event["data"]
                                ended = ended or _ends_job(event)
                                yield event
                        except EncodedAnswerCutShort as exc:  # (a dropped connection: it had been the error)
                            lost = str(exc)
                        except UndecodableAnswer:
                            if not ended:  # (the job's end heard: a tail cut short or broken loses nothing)
                                raise
                        if ended:
                            return
            except httpx.TransportError as exc:
                left()
                if not opened:
                    raise ServiceUnreachable(f"cannot reach the service at {self.base_url}: {exc}") from None
                lost = f"nothing received for {silence:g} s" if isinstance(exc, httpx.ReadTimeout) else str(exc)
            remaining = left()
            now = time.monotonic()
            lost_since = now if lost_since is None else lost_since
            down_since = down_since if reconnecting else now
            attempts += 1
            if not reconnecting and now - lost_since < reconnect_for and on_reconnect is not None:
                on_reconnect(f"event stream of job {job_id} lost ({lost}); reconnecting for up to "
                             f"{reconnect_for - (now - lost_since):.0f} s (the job goes on in the service)")
            reconnecting = True
            if now - lost_since >= reconnect_for:
                raise EventStreamLost(f"event stream of job {job_id} at {self.base_url} lost: {lost} ({attempts} "
                                      f"attempt{'s' if attempts > 1 else ''} over {now - lost_since:.0f} s, "
                                      f"reconnecting for up to {reconnect_for:g} s); the job goes on in the service")
            time.sleep(min(_backoff(attempts - 1), reconnect_for - (now - lost_since), remaining))

    def wait(self, job_id: str, on_progress: Callable[[dict], None] | None = None,
             reconnect_for: float | None = None, on_reconnect: Callable[[str], None] | None = None,
             on_warning: Callable[[dict], None] | None = None, timeout: float | None = None) -> dict:
        """Follow the job's events until it ends (``reconnect_for``, ``on_reconnect``: see :meth:`events`), calling
        ``on_progress(snapshot)`` on each progress event and ``on_warning(event)`` on each warning (a stage's result
        to look at, or its start over: the job's message says it only until the next report); the finished job.

        ``timeout`` (seconds; none by default) bounds the whole wait, reconnects and ``Retry-After`` waits included:
        past it, a :class:`JobWaitTimeout` names the job and the state it was last heard in (it had waited for good on
        a job stuck queued or running). One that ran out before the stream said where the job stood (``timeout=0``)
        looks at the job once first, for at most :data:`LOOK_AT_JOB_S` more: one ended is returned (it had been a
        JobWaitTimeout, nothing asked). A stream the service ended with an ``error`` (the job deleted, the key
        revoked meanwhile) is a ServiceError saying so, with the status the job's record is then answered with (it
        had been that answer's own, ``HTTP 404: job 'j1' not found``, as if the job had never been). A job the stream
        said ended, then deleted before it is read (404), is returned as the stream last gave it: its last snapshot,
        with the terminal state heard (it had been that 404, the job's end unsaid)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        path = f"/v1/jobs/{_segment(job_id)}"
        ended_by = snapshot = ended_as = None
        try:
            for event in self.events(job_id, reconnect_for=reconnect_for, on_reconnect=on_reconnect, timeout=timeout):
                if event["event"] == "progress":
                    snapshot = event["data"]
                    if snapshot.get("state") in TERMINAL_STATES:
                        ended_as = {"id": job_id, **snapshot}
                elif event["event"] in TERMINAL_STATES:  # (its snapshot comes after it, unless the job is gone)
                    ended_as = {"id": job_id, **(snapshot or {}), "state": event["event"]}
                if event["event"] == "progress" and on_progress is not None:
                    on_progress(event["data"])
                elif event["event"] == "warning" and on_warning is not None:
                    on_warning(event["data"])
                elif event["event"] == "error":
                    detail = event["data"].get("detail") if isinstance(event["data"], dict) else None
                    ended_by = detail if isinstance(detail, str) else reprlib.repr(event["data"])
        except JobWaitTimeout as timed_out:
            if timed_out.progress is not None:  # the stream said where it stood, and that it had not ended
                raise
            try:
                job = self._record("job", "GET", path, deadline=deadline, timeout=httpx.Timeout(**{
                    part: LOOK_AT_JOB_S if limit is None else min(LOOK_AT_JOB_S, limit)
                    for part, limit in self._http.timeout.as_dict().items()}))
            except ServiceError:  # (the service gone: the timeout says where the job stood)
                raise timed_out from None
            if job["state"] not in TERMINAL_STATES:
                raise
            return job
        try:
            return self._record("job", "GET", path, deadline=deadline)
        except ServiceError as exc:
            if ended_as is not None and exc.status == 404:  # deleted once ended (its owner, a retention sweep)
                return ended_as
            if ended_by is None:
                raise
            raise ServiceError(f"event stream of job {job_id} ended: {ended_by}", exc.status, exc.detail) from None

    def artifacts(self, job_id: str) -> list[dict]:
        """``GET /v1/jobs/{id}/artifacts``: the job's artifacts, each ``{name, size, sha256, ...}``; an answer that is
        no list of named ones (a proxy's JSON, a broken service's) is a ServiceError quoting it (it had been a
        TypeError or KeyError from the code reading it)."""
        path = f"/v1/jobs/{_segment(job_id)}/artifacts"
        listed = self.request("GET", path)
        if not isinstance(listed, list) or not all(isinstance(each, dict) and isinstance(each.get("name"), str)
                                                   for each in listed):
            raise ServiceError(f"GET {path}: {self.base_url} answered {reprlib.repr(listed)}, not a list of artifacts "
                               "each with a name")
        return listed

    def download(self, job_id: str, name: str, dest: str | os.PathLike, listed: dict | None = None) -> Path:
        """Stream the artifact to ``dest`` and check its size and SHA-256 against the job's listing: ``listed``, its
        entry in :meth:`artifacts` where the caller has read it (``voxe download`` of N artifacts had read the listing
        N + 1 times), else read here.

        A connection broken off or stalled mid-way (:data:`BROKEN_DOWNLOADS`; a body its close ends, short of the size:
        :func:`_ends_at_close`) is resumed where it stopped, with ``Range`` and ``If-Range`` (the listed SHA-256, the
        service's ETag: an artifact replaced since comes whole, as does a 206 from byte 0; one from another byte than
        asked is the error), up to ``retries`` times in a row without a byte more; it had failed the download, its bytes
        thrown away, however large. The bytes go to a ``.part`` file beside ``dest`` named by that ETag
        (:func:`_part_file`), kept when the download fails or is interrupted, so the next call for it goes on from them
        (a run stopped by Ctrl-C or an outage had thrown them away), and locked while one call writes it
        (:func:`_locked_part`); those of its other versions are deleted but one another download holds
        (:func:`_drop_other_parts`). The part file's own bytes are checked, and land under ``dest`` only then: a whole
        one kept (a run stopped before its rename) without a request, one whose check fails having gone on from an
        earlier call's bytes (not a head of the artifact) fetched whole once more, and a 416 to their Range (no head of
        it either) fetched whole, once (a 416 to bytes this call fetched is the error). A mismatch then is a
        ServiceError and deletes them. A KeyboardInterrupt (Ctrl-C) mid-way comes back saying the bytes kept, and
        where. An answer whose ETag names another version than the listed one (the artifact
        replaced since the listing was read: a running job's preview.png republished) has the listing read again and
        that version downloaded, up to :data:`REPLACED_TRIES` listings (it had been checked against the old listing
        and failed, said as bytes corrupted or running past the listed size).
        """
        if name in ("", ".", "..") or any(c in name for c in "/\\\0"):  # it names a file inside dest's folder only
            raise ServiceError(f"artifact name {name!r} of job {job_id} is not a plain file name; nothing written")
        if len(os.fsencode(Path(dest).name)) > NAME_MAX:  # (Python 3.14's is_dir says False for it, raising nothing:
            # the whole artifact had been fetched into a part file cut to fit, then its rename refused, run after run)
            raise OSError(errno.ENAMETOOLONG, f"cannot download {name} of job {job_id} to {dest}: its name is "
                                              f"{len(os.fsencode(Path(dest).name))} bytes, more than the {NAME_MAX} "
                                              "of a file name; nothing downloaded")
        if Path(dest).is_dir():  # (the whole artifact had been fetched, then its rename failed naming the part file)
            raise IsADirectoryError(f"cannot download {name} of job {job_id} to {dest}: it is a folder; nothing "
                                    "downloaded")
        if listed is not None and listed.get("name") != name:
            raise ValueError(f"download of {name!r}: listed is the entry of {listed.get('name')!r}")
        unmatched = None
        for listing in range(1, REPLACED_TRIES + 1):
            try:
                return self._download_listed(job_id, name, Path(dest), unmatched, listed)
            except _ArtifactReplaced as replaced:
                if listing == REPLACED_TRIES:
                    raise
                unmatched, listed = replaced.listed, None  # (the listing is read again)

    def _download_listed(self, job_id: str, name: str, dest: Path, unmatched: str | None = None,
                         expected: dict | None = None) -> Path:
        """:meth:`download` of the version of the artifact ``expected`` (its listing entry) or, without it, the job's
        listing names now; _ArtifactReplaced when the service answers with another's ETag. Not when the listing still
        names ``unmatched``, the SHA-256 an ETag did not match before: the listing unchanged, a proxy's ETag (one
        rewriting them) says no version; the bytes' check does."""
        if expected is None:
            listed = {a["name"]: a for a in self.artifacts(job_id)}
            if name not in listed:
                raise ServiceError(f"job {job_id} has no artifact {name!r}; it has "
                                   f"{', '.join(sorted(listed)) or 'none'}", 404)
            expected = listed[name]
        if not SHA256_HEX.fullmatch(str(expected.get("sha256"))):  # (it names the part file)
            raise ServiceError(f"artifact {name!r} of job {job_id} is listed with sha256 {expected.get('sha256')!r}, "
                               "not a SHA-256; nothing written")
        size = expected.get("size")
        if isinstance(size, bool) or not isinstance(size, int) or size < 0:  # (one missing had been a KeyError)
            raise ServiceError(f"artifact {name!r} of job {job_id} is listed with size {size!r}, not a number of "
                               "bytes; nothing written")
        dest.parent.mkdir(parents=True, exist_ok=True)
        target = Path(os.path.realpath(dest))  # a symlink's target, as voxe_core.files.replacing writes one
        partial = _part_file(target, expected["sha256"])
        _drop_other_parts(target, partial)
        path = f"/v1/jobs/{_segment(job_id)}/artifacts/{_segment(name)}"
        what = f"{name} of job {job_id}"
        replaced = False
        with _locked_part(partial, what) as out:
            try:
                earlier = out.seek(0, os.SEEK_END)  # bytes an earlier call kept
                while True:
                    if not self._fill_part(out, path, expected, what, partial, expected["sha256"] != unmatched):
                        earlier = 0  # started over: none of them is checked now
                    size, sha256 = _size_and_sha256(out)
                    if (size, sha256) == (expected["size"], expected["sha256"]):
                        break
                    if not earlier:
                        partial.unlink()
                        raise ServiceError(f"{what}: downloaded {size} bytes with sha256 {sha256}, the service lists "
                                           f"{expected['size']} bytes with sha256 {expected['sha256']}")
                    out.truncate(0)  # the earlier call's bytes were no head of it (a crash's zeroed tail): once, whole
                    earlier = 0
                flush_to_disk(partial)  # (a power loss after the rename had been able to leave the target empty)
                take_the_mode_of(target, partial)
                os.replace(partial, target)
                replaced = True  # a part file there now is another download's (a zero-byte artifact's had deleted it)
            except OSError as exc:
                if exc.filename is not None:  # (it names its file)
                    raise
                held = os.fstat(out.fileno()).st_size  # writing the part failed: a full disk, a file size limit
                raise OSError(exc.errno, f"cannot download {what} to {dest} ({held} of {expected['size']} bytes "
                                         f"here{_kept_in(partial, held)}): {exc.strerror or exc}") from None
            except KeyboardInterrupt:  # (Ctrl-C: the bytes kept had gone unsaid, as a failure's error says them)
                held = os.fstat(out.fileno()).st_size
                raise KeyboardInterrupt(f"interrupted downloading {what} ({held} of {expected['size']} bytes "
                                        f"here{_kept_in(partial, held)})") from None
            finally:
                if not replaced and not out.seek(0, os.SEEK_END):  # nothing to go on from
                    partial.unlink(missing_ok=True)
        return dest

    def _fill_part(self, out: BinaryIO, path: str, expected: dict, what: str, partial: Path,
                   by_etag: bool = True) -> bool:
        """Append to ``out`` (the part file, open to append) the artifact at ``path`` from the bytes it holds (none
        or a head of it, the listing ``expected`` says its size), going on where a broken connection stopped (see
        :meth:`download`); whether the bytes it held at the start are kept (not started over: the service sent the
        whole, or a 416 to their Range said they are no head of it: once, for bytes an earlier call kept; one to
        bytes this call fetched is the error, or a whole fetch broken off mid-way every time had been asked again for
        good). An error names the bytes kept, and where. ``by_etag``: a whole answer (a 206 is the If-Range's, the
        listed version) whose ETag names another version is _ArtifactReplaced, its bytes unread."""
        size, kept, failures = out.seek(0, os.SEEK_END), True, 0
        earlier = size  # bytes an earlier call kept
        try:
            while size < expected["size"]:
                had = size
                resume = {"range": f"bytes={size}-", "if-range": f'"{expected["sha256"]}"'} if size else {}
                try:
                    with closing(self._send("GET", path, stream=True, headers={**resume, **UNENCODED},
                                            resend_dropped=False)) as response:
                        if response.status_code == httpx.codes.REQUESTED_RANGE_NOT_SATISFIABLE and kept and \
                                0 < size == earlier:
                            out.truncate(0)  # (kept, every later call had asked the same range again)
                            size, kept = 0, False
                            continue
                        if response.is_error:
                            _raise_for_error(_read_capped(response, "GET", path), "GET", path)
                        if codings := _content_codings(response):
                            raise ServiceError(f"GET {path}: answered {response.status_code} encoded as "
                                               f"{', '.join(codings)}, not the artifact's own bytes this client asks "
                                               "for (Accept-Encoding: identity)", response.status_code)
                        served = response.headers.get("etag")
                        if by_etag and served is not None and response.status_code != httpx.codes.PARTIAL_CONTENT \
                                and served.strip().removeprefix("W/") != f'"{expected["sha256"]}"':
                            out.truncate(0)  # (bytes of a version no longer served)
                            size = 0
                            raise _ArtifactReplaced(f"GET {path}: answered {response.status_code} with ETag "
                                                    f"{served}, not the listed sha256 {expected['sha256']}: the "
                                                    f"artifact was replaced {REPLACED_TRIES} times as it downloaded; "
                                                    "nothing kept", response.status_code, listed=expected["sha256"])
                        start = _range_start(response, size)
                        if start == 0:  # the whole file, from its start
                            out.truncate(0)
                            size, kept = 0, False
                        elif start != size:  # (appended, they had failed the check, the bytes held thrown away)
                            raise ServiceError(f"GET {path}: asked for its bytes from {size} on, answered "
                                               f"{response.status_code} with Content-Range "
                                               f"{response.headers.get('content-range')!r}")
                        announced = response.headers.get("content-length", "")
                        if announced.isdigit() and size + int(announced) > expected["size"]:
                            size = 0
                            raise _past_listing(out, path, response, expected["size"],
                                                f"its Content-Length, {announced} bytes from byte {start}, runs")
                        for chunk in response.iter_bytes():  # as received: a break loses none held back
                            # past the listing, not written (an endless body had filled the disk; then one chunk
                            # had gone past the size before the check)
                            if len(chunk) > expected["size"] - size:
                                size = 0
                                raise _past_listing(out, path, response, expected["size"], "its body runs")
                            out.write(chunk)
                            size += len(chunk)
                        if size < expected["size"] and _ends_at_close(response):  # (failed, its bytes thrown away)
                            raise httpx.RemoteProtocolError(f"the connection closed at byte {size} of the "
                                                            f"{expected['size']} listed")
                    return kept
                except BROKEN_DOWNLOADS:
                    failures = 0 if size > had else failures + 1
                    if failures > self.retries:
                        raise
                    if size < expected["size"]:  # (every byte listed here: the check says the rest)
                        time.sleep(_backoff(failures))
        except (httpx.TransportError, httpx.InvalidURL) as exc:
            raise ServiceUnreachable(f"cannot download {what} ({size} of {expected['size']} bytes here"
                                     f"{_kept_in(partial, size)}): {exc}") from None
        except ServiceError as exc:
            if not size:
                raise
            raise ServiceError(f"{exc} ({size} of {expected['size']} bytes here{_kept_in(partial, size)})",
                               exc.status, exc.detail) from None
        return kept

    # ------------------------------------------------------------------ evaluations and sweeps (SPEC §4)
    def create_evaluation(self, job_ids: list[str], object_name: str, params: dict | None = None,
                          idempotency_key: str | None = None) -> dict:
        """``POST /v1/evaluations``: a job (mode ``evaluate``) scoring succeeded edit jobs of one scene, ``object_name``
        what the object is called (the body's ``object``: the source text is "a render of a <object>"), ``params``
        its views, elevation, size, fid_input, save_renders; its result and ``evaluation.json`` / ``.md`` artifacts
        hold the metrics. ``idempotency_key`` as :meth:`create_job`'s."""
        body: dict = {"job_ids": job_ids, "object": object_name}
        if params is not None:
            body["params"] = params
        return self._record("evaluation", "POST", "/v1/evaluations", body,
                            idempotency_key=_submission_key(idempotency_key))

    def create_sweep(self, scenes: list[dict], params: dict | None = None, evaluation: dict | None = None,
                     idempotency_key: str | None = None) -> dict:
        """``POST /v1/sweeps``: every scene ({scene_id, object}) × the paper's six prompts, each edit then evaluated;
        ``idempotency_key`` as :meth:`create_job`'s."""
        body: dict = {"scenes": scenes}
        if params is not None:
            body["params"] = params
        if evaluation is not None:
            body["evaluation"] = evaluation
        return self._sweep("POST", "/v1/sweeps", body, idempotency_key=_submission_key(idempotency_key))

    def get_sweep(self, sweep_id: str) -> dict:
        """``GET /v1/sweeps/{id}``: the jobs' states and the summary table."""
        return self._sweep("GET", f"/v1/sweeps/{_segment(sweep_id)}")

    def cancel_sweep(self, sweep_id: str) -> dict:
        """``POST /v1/sweeps/{id}/cancel``: every unfinished job of the sweep canceled (finished ones and their results
        stay); the sweep, as :meth:`get_sweep` answers it."""
        return self._sweep("POST", f"/v1/sweeps/{_segment(sweep_id)}/cancel")

    def _sweep(self, method: str, path: str, body: dict | None = None, **kwargs) -> dict:
        """The sweep that ``method path`` answers (as :meth:`_record`); one with no list of ``entries``, object of
        ``counts`` or string ``table`` (a proxy's partial JSON) is a ServiceError quoting it: ``voxe sweep`` had ended
        in a KeyError traceback reading them."""
        sweep = self._record("sweep", method, path, body, **kwargs)
        if not (isinstance(sweep.get("entries"), list) and isinstance(sweep.get("counts"), dict)
                and isinstance(sweep.get("table"), str)):
            raise ServiceError(f"{method} {path}: {self.base_url} answered {reprlib.repr(sweep)}, not a sweep with its "
                               "entries, counts and table")
        return sweep

    # ------------------------------------------------------------------ webhooks
    def webhook_secret(self) -> str:
        """``GET /v1/webhooks/secret``: this key's webhook signing secret (``whsec_…``, made on first use), which
        verifies its jobs' deliveries' ``webhook-signature`` (Standard Webhooks)."""
        return self._secret("GET", "/v1/webhooks/secret")

    def rotate_webhook_secret(self) -> str:
        """``POST /v1/webhooks/secret/rotate``: a new signing secret for this key (the old one leaked), which signs
        every delivery attempt from now on, a retry of an earlier one included. Not sent again: a rotation whose
        answer is lost may have replaced the secret (:meth:`webhook_secret` reads the one in force)."""
        return self._secret("POST", "/v1/webhooks/secret/rotate")

    def _secret(self, method: str, path: str) -> str:
        """The ``secret`` that ``method path`` answers; an answer with none (a proxy's JSON) is a ServiceError
        quoting it, as :meth:`_record`'s."""
        answer = self.request(method, path)
        if not isinstance(answer, dict) or not isinstance(answer.get("secret"), str):
            raise ServiceError(f"{method} {path}: {self.base_url} answered {reprlib.repr(answer)}, not a webhook "
                               "secret")
        return answer["secret"]


class MissingCompanionWarning(UserWarning):
    """A file a mesh names (an OBJ's .mtl, a texture) that is not beside it: the upload goes without it."""


def _given_texture(mesh: Path, texture: str | os.PathLike) -> list[Path]:
    """The mesh and the ``texture`` given for it; a kind of image the service does not read is a ValueError (it
    would keep it as no texture)."""
    if Path(texture).suffix.lower() not in TEXTURE_SUFFIXES:
        raise ValueError(f"texture {Path(texture).name}: send it as one of {', '.join(TEXTURE_SUFFIXES)}")
    return [mesh, Path(texture)]


def scene_upload_files(path: Path, texture: str | os.PathLike | None = None) -> list[Path]:
    """The files :meth:`Client.upload_scene` sends for ``path`` (a zip; a mesh with what colours it), refused with a
    ValueError naming the problem before anything is sent: ``voxe submit --upload`` asks it before it asks the
    service anything."""
    kind = path.suffix.lower()
    if path.is_dir():  # (open() had said only "[Errno 21] Is a directory")
        raise ValueError(f"{path} is a folder: upload a dataset as a .zip of it, or one mesh file (.obj, .ply)")
    if texture is not None and kind not in MESH_UPLOADS:
        raise ValueError(f"a texture goes with a mesh upload (.obj or .ply); {path.name} is neither")
    paths = MESH_UPLOADS[kind](path, texture) if kind in MESH_UPLOADS else [path]
    for each in paths:  # (the multipart encoder had failed: "'utf-8' codec can't encode character '\udcff' ...")
        try:
            each.name.encode()
        except UnicodeEncodeError:
            shown = os.fsencode(each).decode(errors="backslashreplace")  # (no lone surrogate in the message)
            raise ValueError(f"cannot upload {shown}: its name is not UTF-8, which the upload sends names as: "
                             "rename it") from None
    return paths


def ply_upload_files(ply: Path, texture: str | os.PathLike | None = None) -> list[Path]:
    """The files a PLY upload sends: the PLY, then ``texture``, or else the image its header's ``comment
    TextureFile`` names (read as trimesh reads it: the rest of the line), looked up as an OBJ's are, where the
    header declares texture coordinates to map it with (the service refuses an image beside a PLY without them:
    one coloured by its vertices goes alone). One not found, or one the PLY cannot map, is a
    :class:`MissingCompanionWarning` and the PLY goes without it; one of a kind the service does not read, a
    ValueError."""
    if texture is not None:
        return _given_texture(ply, texture)
    header = read_ply_header(ply)
    name = header.texture_file if header.complete else None  # (an unread header: the service names it)
    if not name:
        return [ply]
    if not header.declares_texture_coordinates:
        warnings.warn(f"{ply.name} names the texture {name!r} (comment TextureFile) but declares no texture "
                      "coordinates to map it with: the PLY goes without it (its vertex or face colours)",
                      MissingCompanionWarning, stacklevel=3)
        return [ply]
    image = _beside(ply.parent, name)
    if image is None:
        warnings.warn(f"{ply.name} names the texture {name!r} (comment TextureFile), not found in {ply.parent}: the "
                      "PLY goes without it (put it beside the PLY)", MissingCompanionWarning, stacklevel=3)
        return [ply]
    return _given_texture(ply, image)


def obj_upload_files(obj: Path, texture: str | os.PathLike | None = None) -> list[Path]:
    """The files an OBJ upload sends: the OBJ, then ``texture``, or else the material library its first ``mtllib``
    line names and the texture image that library's ``map_Kd`` lines name (its Kd colours alone when none).

    Names are read as trimesh (the service's reader) reads them, the rest of the line, and looked up as it does,
    in the OBJ's folder as written (a name leading out of it by its base name only: :func:`_beside`), else by their
    base name; each is sent under its base name, where the service looks. A library not found, or textures none of
    which is found, are a :class:`MissingCompanionWarning` naming them, and the OBJ goes without them (as it went
    before they were looked for: uncoloured, or coloured by the library's Kd alone); some textures found and others
    not, a FileNotFoundError (the one found would colour every part); more textures than the one the service takes,
    or a ``texture`` it does not read, a ValueError."""
    if texture is not None:
        return _given_texture(obj, texture)
    library_name = next(_keyed_values(obj, "mtllib"), None)
    if library_name is None:
        return [obj]
    library = _beside(obj.parent, library_name)
    if library is None:
        warnings.warn(f"{obj.name} names the material library {library_name!r} (mtllib), not found in {obj.parent}: "
                      "the OBJ goes without it, uncoloured (put it beside the OBJ)", MissingCompanionWarning,
                      stacklevel=3)
        return [obj]
    named = list(dict.fromkeys(_keyed_values(library, "map_kd")))
    images = {name: _beside(obj.parent, name) for name in named}
    missing = [name for name, found in images.items() if found is None]
    if missing:
        options = "; map_Kd options such as -s are not read: write the file name alone" if any(
            name.startswith("-") for name in missing) else ""
        where = f"{library.name} names textures not found in {obj.parent} (map_Kd): {', '.join(map(repr, missing))}"
        if len(missing) < len(images):
            raise FileNotFoundError(f"{where}; sent without them, the texture found would colour every part (put "
                                    f"them beside the OBJ{options})")
        warnings.warn(f"{where}; the OBJ goes without, coloured by the library's Kd alone (put them beside the "
                      f"OBJ{options})", MissingCompanionWarning, stacklevel=3)
        return [obj, library]
    textures = sorted(set(images.values()))
    if len(textures) > 1:
        raise ValueError(f"{library.name} names {len(textures)} textures ({', '.join(map(repr, images))}); the "
                         "service takes one texture per OBJ: bake them into one image")
    return [obj, library, *textures]


MESH_UPLOADS = {".obj": obj_upload_files, ".ply": ply_upload_files}
"""The files a mesh upload sends, by the mesh's suffix."""


def _beside(folder: Path, name: str) -> Path | None:
    """The file ``name`` (as an OBJ or .mtl writes it) in ``folder``, as written or by its base name; None if
    neither is a file. A name leading out of ``folder`` (absolute, or up through ``..``) is looked for by its base
    name alone: a mesh from elsewhere naming ``mtllib /home/me/.aws/credentials`` or ``map_Kd ../../photo.jpg`` had
    had that file of the user's sent to the service with it."""
    written = os.path.normpath(name)
    inside = not (os.path.isabs(written) or written == os.pardir or written.startswith(os.pardir + os.sep))
    for candidate in ((folder / name,) if inside else ()) + (folder / PureWindowsPath(name).name,):  # (a Windows
        if candidate.is_file():  # path's base name too)
            return candidate
    return None


def _keyed_values(path: Path, key: str) -> Iterator[str]:
    """The values of the lines of ``path`` (an OBJ or .mtl) keyed ``key`` (any case), each the rest of its line,
    read lazily: an OBJ may be large, and only its first ``mtllib`` counts."""
    with open(path, "rb") as handle:
        for line in handle:
            words = line.decode("utf-8", errors="replace").split(maxsplit=1)
            if len(words) == 2 and words[0].lower() == key:
                yield words[1].strip()


SHA256_HEX = re.compile(r"[0-9a-f]{64}")


PART_SUFFIX = ".0123456789abcdef.part"
"""What a part file's name (:func:`_part_file`) adds to its stem (:func:`_part_stem`): the ETag's head."""


def _part_stem(dest: Path) -> str:
    """The start of the names of the part files of a download to ``dest``: "." and its name; where that and
    :data:`PART_SUFFIX` would pass the 255 bytes of a file name (an artifact name of 240 characters had failed "File
    name too long"), the head of it that fits with "~" and a digest of the whole name, so two long names alike at
    their start keep parts of their own (``voxe_core.files.head_that_fits``, as the library's partial files)."""
    return head_that_fits(f".{dest.name}", PART_SUFFIX, dest.name)


def _part_file(dest: Path, sha256: str) -> Path:
    """Where a download to ``dest`` of the artifact whose SHA-256 (its ETag) is ``sha256`` keeps its bytes until they
    are checked: hidden beside it, named by the ETag's head, so a later call goes on from bytes of that version only."""
    return dest.with_name(f"{_part_stem(dest)}.{sha256[:16]}.part")


LOCKS_REFUSED = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS, errno.EINVAL}
"""What ``flock`` fails with in a folder whose file system takes no locks (NFSv3 without lockd, some SMB or FUSE
mounts; EINVAL where it refuses the valid operation asked): a download there goes on unlocked, the part file's own
size and SHA-256 check its backstop. Any other failure (EIO) is the file's error."""


def _lock_alone(file: BinaryIO, path: Path) -> bool:
    """Whether ``file``, open at ``path``, is now locked (``flock``, not waiting) for this call alone, ``path`` still
    naming it: not where another download holds it, or renamed or deleted it as it was opened. Where the file system
    takes no locks (:data:`LOCKS_REFUSED`) it is not locked; another failure is an OSError naming ``path`` (a bare
    "[Errno 5] Input/output error" had said no file)."""
    try:
        fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError as exc:
        if exc.errno not in LOCKS_REFUSED:
            raise OSError(exc.errno, f"cannot lock the download's part file ({exc.strerror})", str(path)) from None
    try:
        return os.path.samestat(os.fstat(file.fileno()), os.stat(path))
    except FileNotFoundError:
        return False


@contextmanager
def _locked_part(partial: Path, what: str) -> Iterator[BinaryIO]:
    """``partial`` open to append and read, locked (:func:`_lock_alone`) for this download alone: two at once (two
    ``voxe download`` runs into one folder) had interleaved their bytes in it, the first to end renaming that mix over
    the target. Another is an OSError naming it, its part left alone, as is a part another download renamed as this
    one opened it. Where the file system takes no locks (:data:`LOCKS_REFUSED`) it is not locked (the download had
    failed there, leaving an empty part). A part that another call deletes as this one opens it (an earlier version's,
    dropped by :func:`_drop_other_parts`, locked only as long as that takes) is opened again, a few times, before
    the download is refused; one this call made and could not lock (an I/O error) is not left behind, empty."""
    for attempt in range(PART_LOCK_TRIES):
        made = not partial.exists()
        with open(partial, "a+b") as out:
            try:
                locked = _lock_alone(out, partial)
            except OSError:
                if made and os.fstat(out.fileno()).st_size == 0:
                    partial.unlink(missing_ok=True)
                raise
            if locked:
                yield out
                return
        time.sleep(PART_LOCK_PAUSE)
    raise OSError(f"another download of {what} to {partial.parent} is running (its part file {partial} is "
                  "locked): let it end, then download again if it failed")


PART_LOCK_TRIES = 3
PART_LOCK_PAUSE = 0.05
"""How often, and how many seconds apart, a download tries to lock its part file before it is refused as held by
another (:func:`_locked_part`): long enough for a drop of an old version's part, short beside any download."""


def _ends_at_close(response: httpx.Response) -> bool:
    """Whether ``response``'s body ends where its connection closes (no Content-Length, not chunked: HTTP/1.0, some
    proxies), so that one cut short by a dropped connection ends as a whole one does, httpx saying nothing."""
    return "content-length" not in response.headers and \
        "chunked" not in response.headers.get("transfer-encoding", "").lower()


CONTENT_RANGE = re.compile(r"bytes\s+(\d+)\s*-\s*\d+\s*/\s*(?:\d+|\*)", re.IGNORECASE)
"""A 206's Content-Range: its unit read case-blind (RFC 9110 14.1: a proxy writing ``Bytes`` is within it)."""


def _range_start(response: httpx.Response, asked: int) -> int | None:
    """The byte of the artifact a download's ``response`` starts at: 0 for the whole (not a 206), a 206's
    ``Content-Range`` start (``asked``, the Range's, without one); None for one unreadable."""
    if response.status_code != httpx.codes.PARTIAL_CONTENT:
        return 0
    if (content_range := response.headers.get("content-range")) is None:
        return asked
    match = CONTENT_RANGE.fullmatch(content_range.strip())
    return None if match is None else int(match.group(1))


def _past_listing(part: BinaryIO, path: str, response: httpx.Response, listed: int, runs: str) -> ServiceError:
    """The error of a download whose ``response`` ``runs`` past the ``listed`` size (a broken proxy's or a hostile
    service's body: not the listed artifact), its ``part`` file emptied (so the download deletes it): no byte past the
    listing is written, nor kept."""
    part.truncate(0)
    return ServiceError(f"GET {path}: answered {response.status_code}: {runs} past the {listed} bytes the artifact "
                        "is listed with; nothing kept", response.status_code)


def _size_and_sha256(part: BinaryIO) -> tuple[int, str]:
    """The size and SHA-256 of the bytes in the file ``part`` itself, as they will land (the bytes received had been
    checked, not the file)."""
    part.flush()
    part.seek(0)
    return os.fstat(part.fileno()).st_size, hashlib.file_digest(part, "sha256").hexdigest()


def _kept_in(partial: Path, size: int) -> str:
    """What an error says of a download's ``size`` bytes kept in its part file ``partial``."""
    return f", kept in {partial} for the next download of it to go on from" if size else ""


def _drop_other_parts(dest: Path, kept: Path) -> None:
    """Delete the part files (:func:`_part_file`) beside ``dest`` but ``kept``: bytes of the artifact's earlier
    versions (a preview republished since the download was interrupted), which no call completes now. Not one that
    another download holds locked (:func:`_lock_alone`: a download of another version, in another run, had lost its
    part mid-way), nor one gone or that cannot be locked (an I/O error): left for a later call."""
    others = re.compile(re.escape(f"{_part_stem(dest)}.") + r"[0-9a-f]{16}\.part")
    for part in dest.parent.iterdir():
        if part != kept and others.fullmatch(part.name):
            with suppress(OSError), open(part, "r+b") as other:  # writable: NFS locks only those
                if _lock_alone(other, part):
                    part.unlink()  # locked as it goes: a download opening it meanwhile opens it again


MAX_TIMEOUT_S = 1e6
"""The longest a :class:`Client`'s ``timeout`` (each of its parts) may be, about 11 days: a socket's timeout past
about 9.2e9 s (2**63 ns) fails, so ``Client(timeout=1e10)`` had been taken and each request then an OverflowError
("timestamp out of range for platform time_t"); None is no timeout."""


def _checked_timeout(timeout) -> httpx.Timeout:
    """A :class:`Client`'s ``timeout`` (seconds, an ``httpx.Timeout``, or None: none) as httpx takes it; a ValueError
    for a part that is no number of seconds above 0 and at most :data:`MAX_TIMEOUT_S`: NaN or a negative one had been
    taken, each request then failing at once as the service not reached, or never timing out."""
    try:
        parts = httpx.Timeout(timeout)
    except (TypeError, ValueError):  # (a tuple of the wrong length, a str)
        raise ValueError(f"timeout must be seconds above 0, an httpx.Timeout or None, got {timeout!r}") from None
    for part, seconds in parts.as_dict().items():
        if seconds is not None and (isinstance(seconds, bool) or not isinstance(seconds, (int, float))
                                    or not 0 < seconds <= MAX_TIMEOUT_S):
            parted = f" ({part} {seconds!r})" if isinstance(timeout, httpx.Timeout) else ""
            raise ValueError(f"timeout must be seconds above 0 and at most {MAX_TIMEOUT_S:.0f} (or None: none), got "
                             f"{timeout!r}{parted}")
    return parts


def _submission_key(given: str | None) -> str:
    """The Idempotency-Key of one submission, sent with each of its sendings: the caller's, else a fresh one."""
    return str(uuid.uuid4()) if given is None else given


HEADER_BREAKS = re.compile(r"[\x00\r\n\v\f]")
"""What no HTTP header value carries (httpx's h11 refuses NUL and any whitespace but spaces and tabs)."""


def _header_bytes(key: str) -> bytes:
    """An Idempotency-Key as its header's bytes: UTF-8, as the service reads it (httpx's default ASCII had refused a
    key the service takes, "clé", with "'ascii' codec can't encode"); a ValueError naming a key no header carries
    (one with a line break had been said as "cannot reach the service", exit 3)."""
    if HEADER_BREAKS.search(key):
        raise ValueError(f"Idempotency-Key {key!r} cannot be sent: a header carries no line break, NUL or other "
                         "whitespace than spaces and tabs")
    return key.encode()


DELAY_SECONDS = re.compile(r"[0-9]+(\.[0-9]+)?")
"""A ``Retry-After`` in seconds: RFC 9110's digits, a fraction taken too (Python's float() had also read "1_0", "1e1"
and "+5", which none sends as seconds, as a wait)."""


def retry_after_s(response: httpx.Response) -> float | None:
    """The seconds its ``Retry-After`` asks to wait before sending the request again (uncapped: one asking more
    than :data:`MAX_RETRY_WAIT_S` is refused, not cut short): a number of seconds, or an HTTP-date (RFC 9110
    §10.2.3; it had been ignored, the request not sent again) counted from the answer's ``Date`` (the server's clock:
    a client's skewed one had stretched or cut the wait), else from now, a date past being no wait; None without one
    or with one unreadable (an infinite one too)."""
    value = response.headers.get("retry-after")
    if value is None:
        return None
    if DELAY_SECONDS.fullmatch(value.strip()):
        seconds = float(value)
    else:
        when = _http_date(value)
        if when is None:
            return None
        seconds = max(0.0, (when - (_http_date(response.headers.get("date", "")) or datetime.now(timezone.utc)))
                      .total_seconds())
    return seconds if 0 <= seconds < math.inf else None


def _http_date(value: str) -> datetime | None:
    """``value`` as an HTTP-date (``Wed, 21 Oct 2015 07:28:00 GMT``), an aware datetime; None when it is not one."""
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError, OverflowError):
        return None
    return when if when.tzinfo is not None else when.replace(tzinfo=timezone.utc)  # ("-0000": UTC, said naively)


def _backoff(attempt: int) -> float:
    """Seconds to wait before sending again a request whose ``attempt``-th sending (from 0) was lost, where the
    service said nothing of when: doubling from 0.5 s, at most ``MAX_RECONNECT_PAUSE_S``, as the event stream's."""
    return min(MAX_RECONNECT_PAUSE_S, 0.5 * 2.0 ** min(attempt, 10))  # (2 ** 1024 overflows a float)


def _ends_before(wait: float, deadline: float | None) -> bool:
    """Whether a ``wait`` of seconds before sending a request again ends before ``deadline`` (a ``time.monotonic()``;
    None: none), with time left to send it; if not, the wait is slept up to the deadline only, where the caller's
    time is up: the request is not sent again there (it had been, sooner than its ``Retry-After`` asked, and a
    ``wait(timeout=5)`` had said the service's 503 to that early retry rather than its timeout)."""
    left = math.inf if deadline is None else deadline - time.monotonic()
    if wait < left:
        return True
    time.sleep(max(0.0, left))
    return False


def _resend_wait(response: httpx.Response, attempt: int, keyed: bool) -> float | None:
    """Seconds to wait before sending again a read, or a request carrying an Idempotency-Key (``keyed``), answered
    ``response``; None for an answer that stands. A 503 or 429 with ``Retry-After`` (busy, over a rate or quota: it
    had failed a waiting caller at once) after that wait. A keyed one also after a proxy's 502 / 503 / 504 (the
    answer lost, or the submission withdrawn: a retry with the key submits it anew), after its ``Retry-After``, else
    :func:`_backoff`, and after a 409 with ``Retry-After`` (the first sending not answered yet). One asking longer
    than :data:`MAX_RETRY_WAIT_S` stands (it had been sent again sooner than asked, in vain; its error names the
    wait)."""
    asked = retry_after_s(response)
    if asked is not None and asked > MAX_RETRY_WAIT_S:
        return None
    if response.status_code in (httpx.codes.SERVICE_UNAVAILABLE, httpx.codes.TOO_MANY_REQUESTS) and asked is not None:
        return asked
    if not keyed:
        return None
    if response.status_code in PROXY_UNAVAILABLE:
        return _backoff(attempt) if asked is None else asked
    return asked if response.status_code == httpx.codes.CONFLICT else None


def _read_capped(response: httpx.Response, method: str, path: str) -> httpx.Response:
    """``response`` (to ``method path``, streamed) read whole and closed, its body decoded as it comes
    (:func:`_decoded`), up to :data:`MAX_ANSWER_BYTES` decoded: a ServiceError naming that limit past it, the rest not
    read; but an error page past it reads as empty, as one none can decode, so its status still says what to do (a
    503's retry: the limit's error had replaced it)."""
    body = bytearray()
    with closing(response):
        try:
            for piece in _decoded(response, method, path):
                body += piece
                if len(body) > MAX_ANSWER_BYTES:
                    if response.is_error:
                        body.clear()
                        break
                    raise ServiceError(f"{method} {path}: HTTP {response.status_code}: its answer runs over "
                                       f"{MAX_ANSWER_BYTES // 2**20} MiB, the most this client reads of one (is it "
                                       "the Vox-E service?)", response.status_code)
        except UndecodableAnswer:
            if not response.is_error:
                raise
            body.clear()  # an error page none can read: its status still says what to do (a 503's retry)
    headers = [(name, value) for name, value in response.headers.multi_items() if name != "content-encoding"]
    return httpx.Response(response.status_code, headers=headers, content=bytes(body), request=response.request,
                          extensions=response.extensions)  # (decoded already: not again)


def _content_codings(response: httpx.Response) -> list[str]:
    """The codings ``response``'s Content-Encoding names, in the order they were applied, lower-cased, x-gzip as gzip
    (RFC 9110 8.4.1.3); identity and empty ones (``gzip,``, an empty header) left out, as httpx did."""
    named = (coding.strip().lower() for coding in response.headers.get_list("content-encoding", split_commas=True))
    return ["gzip" if coding == "x-gzip" else coding for coding in named if coding not in ("", "identity")]


def _decoded(response: httpx.Response, method: str, path: str) -> Iterator[bytes]:
    """The body of ``response`` (to ``method path``, streamed) as it is read, its Content-Encoding undone
    (:data:`ACCEPTED_ENCODINGS`, several in turn) in pieces of at most :data:`DECODED_PIECE_BYTES`, so that a cap on
    what a reader holds holds on the bytes decoded: httpx's decoder inflates each chunk read whole, a gzip bomb's 64
    KiB, the most one read takes, 64 MiB at once. Another encoding, or one broken or cut short, is an
    UndecodableAnswer naming it."""
    said = f"{method} {path}: HTTP {response.status_code}"
    if response.is_stream_consumed:  # an answer made in memory (httpx.MockTransport's), decoded already
        yield response.content
        return
    pieces, codings = response.iter_raw(), _content_codings(response)
    for coding in reversed(codings):
        if coding not in ACCEPTED_ENCODINGS:
            raise UndecodableAnswer(f"{said}: its answer is encoded as {coding!r}, which this client does not read "
                                    f"(it asks for {', '.join(ACCEPTED_ENCODINGS)})", response.status_code)
        pieces = _inflated(pieces, coding)
    try:
        yield from pieces
    except zlib.error as exc:  # cut short where a dropped connection ends the body as a whole one (else it came whole)
        cut = isinstance(exc, _StreamCutShort) and _ends_at_close(response)
        undecodable = EncodedAnswerCutShort if cut else UndecodableAnswer
        raise undecodable(f"{said}: its answer's {' then '.join(reversed(codings))} encoding is broken ({exc})",
                          response.status_code) from None


def _inflated(pieces: Iterator[bytes], coding: str) -> Iterator[bytes]:
    """``pieces`` inflated from ``coding`` (gzip or deflate) in pieces of at most :data:`DECODED_PIECE_BYTES`: the
    rest of a piece waits in the inflater until the one before is taken. A zlib.error where they end before their
    stream does (cut short: its checksum, at the end, had never been checked); an empty body is no stream."""
    pieces, head = iter(pieces), b""
    while len(head) < 2 and (piece := next(pieces, None)) is not None:  # what a deflate body is wrapped in
        head += piece
    if not head:
        return
    inflater = zlib.decompressobj(zlib.MAX_WBITS | 16 if coding == "gzip" else _deflate_wbits(head))
    for piece in itertools.chain([head], pieces):
        while True:
            out = inflater.decompress(piece, DECODED_PIECE_BYTES)
            if out:
                yield out
            piece = inflater.unconsumed_tail
            if not piece and len(out) < DECODED_PIECE_BYTES:  # all of it taken in and given out
                break
    if not inflater.eof:
        raise _StreamCutShort("cut short: the body ended before its stream did")


def _deflate_wbits(head: bytes) -> int:
    """zlib's ``wbits`` for a deflate body starting with ``head``: the zlib container (RFC 9110's deflate) where its
    first two bytes are that container's header, else raw deflate, which some servers and proxies send (httpx reads
    both; only the zlib one had been read)."""
    zlib_header = len(head) >= 2 and head[0] & 0x0F == 8 and head[0] >> 4 <= 7 and (head[0] << 8 | head[1]) % 31 == 0
    return zlib.MAX_WBITS if zlib_header else -zlib.MAX_WBITS


LINE_END = re.compile(rb"\r\n|\r|\n")


def _event_stream_lines(pieces: Iterator[bytes]) -> Iterator[str]:
    """The text lines (ended by CRLF, LF or CR, UTF-8) of an event stream whose decoded body comes in ``pieces``; a
    ValueError once an event, its lines since the last empty one, runs over :data:`MAX_EVENT_BYTES`: httpx's
    ``iter_lines`` had held a line never ended whole, for good."""
    def bounded(event_bytes: int) -> int:
        if event_bytes > MAX_EVENT_BYTES:
            raise ValueError(f"an event runs over {MAX_EVENT_BYTES // 2**20} MiB, the most this client reads of one")
        return event_bytes

    line, in_event, after_cr = bytearray(), 0, False
    for piece in pieces:
        if not piece:
            continue
        if after_cr and piece.startswith(b"\n"):  # the LF of a CRLF split between pieces
            piece = piece[1:]
        after_cr = piece.endswith(b"\r")
        *ended, rest = LINE_END.split(piece)
        for part in ended:
            line += part
            in_event = bounded(in_event + len(line) + 1) if line else 0  # (its end counted one byte, a CRLF too)
            yield line.decode("utf-8", "replace")
            line = bytearray()
        line += rest
        bounded(in_event + len(line))
    if line:
        yield line.decode("utf-8", "replace")


def _raise_for_error(response: httpx.Response, method: str, path: str, keyed: bool = False) -> None:
    """A ServiceError for an error ``response`` to ``method path``: its detail, and for a read or a request carrying
    an Idempotency-Key (``keyed``; the requests sent again) the ``Retry-After`` longer than this client waits."""
    if response.is_error:
        try:
            detail = response.json().get("detail")
        except (ValueError, AttributeError):
            detail = None
        if detail is None:  # not the API's error (a proxy's HTML, or JSON of its own): it had read "HTTP 502: None"
            detail = response.reason_phrase
        asked = retry_after_s(response) if method in SAFE_METHODS or keyed else None
        later = (f" (the service asks to send it again in {math.ceil(asked)} s, longer than this client waits: "
                 f"{MAX_RETRY_WAIT_S:g} s)" if asked is not None and asked > MAX_RETRY_WAIT_S else "")
        raise ServiceError(f"{method} {path}: HTTP {response.status_code}: {_readable(detail)}{later}",
                           response.status_code, detail)


def _redirected(response: httpx.Response, method: str, path: str, base_url: str) -> ServiceError:
    """The error of a redirect answered where the API's JSON or event stream was asked for: where it points, which this
    client does not follow. An http:// service URL that a proxy redirects to https:// had been "answered 301 with no
    content type, not the API's JSON (is it the Vox-E service?)", the redirect's target unsaid."""
    return ServiceError(f"{method} {path}: {base_url} answered {response.status_code}, a redirect to "
                        f"{response.headers['location']!r}, which this client does not follow: give it the URL the "
                        "service answers at (voxe: --api)")


def _readable(detail) -> str:
    """An error's ``detail`` as a person reads it: a validation error's list as ``field: message`` per entry (it
    had been printed as a Python list of dicts), anything else as it is.

    Examples:
        >>> _readable([{"loc": ["body", "params", "iterations"], "msg": "Input should be a valid integer"}])
        'body.params.iterations: Input should be a valid integer'
        >>> _readable("job 'x' not found")
        "job 'x' not found"
    """
    if isinstance(detail, list) and all(isinstance(error, dict) and "msg" in error for error in detail):
        return "; ".join(f"{'.'.join(map(str, error.get('loc') or ()))}: {error['msg']}" for error in detail)
    return str(detail)


def _ends_job(event: dict) -> bool:
    """Whether the service ends a job's stream after ``event``: the job's terminal event or a snapshot of a finished
    job (a stream resumed after the terminal event), or the job's deletion (``error``)."""
    return (event["event"] in (*TERMINAL_STATES, "error")
            or event["event"] == "progress" and event["data"].get("state") in TERMINAL_STATES)


def _is_news(event: dict, last_event_id: int | None, progress: dict | None) -> bool:
    """Whether ``event`` is news of the job, a sign of life that restarts a stream's reconnect window: a timeline event
    after ``last_event_id``, or a progress snapshot other than ``progress``, the last one heard. Not the snapshot every
    stream opens with, unchanged: a stream that brought it, then dropped, each time (a proxy cutting streams short) had
    restarted the window at each reconnect, asked again every 0.5 s for good."""
    if event["id"] is not None:
        return last_event_id is None or int(event["id"]) > last_event_id
    return event["event"] != "progress" or event["data"] != progress


def _is_event_stream(response: httpx.Response) -> bool:
    """Whether ``response`` is a stream of Server-Sent Events, not a page a proxy or a captive portal answered 200
    with, nor the job's timeline as JSON (what the events route answers a request not accepting a stream)."""
    return response.headers.get("content-type", "").partition(";")[0].strip().lower() == "text/event-stream"


def _job_events(events: Iterator[dict], job_id: str) -> Iterator[dict]:
    """``events`` (:func:`parse_sse`'s) of job ``job_id``'s stream, each as the client reads it, or a ServiceError
    quoting one that is not the service's (a broken proxy's, a hostile service's): data not JSON, an id not a number
    (``Last-Event-ID`` resumes from it), a progress snapshot not an object. They had been a JSONDecodeError, a
    ValueError or an AttributeError out of :meth:`Client.events`."""
    try:
        for event in events:
            if event["id"] is not None and not re.fullmatch(r"[0-9]+", event["id"]):
                raise ValueError(f"event id {event['id']!r} is not a number")
            if event["event"] == "progress" and not isinstance(event["data"], dict):
                raise ValueError(f"progress snapshot {reprlib.repr(event['data'])} is not an object")
            yield event
    except ValueError as exc:
        raise ServiceError(f"event stream of job {job_id}: {exc}: not the service's events") from None


def _json(fields: dict[str, str]) -> Any:
    """An event's ``data`` field decoded; a ValueError quoting it when it is not JSON (json's own said no event)."""
    try:
        return json.loads(fields["data"])
    except ValueError:
        raise ValueError(f"{fields.get('event', 'message')} event's data {reprlib.repr(fields['data'])} is not "
                         "JSON") from None


def parse_sse(lines) -> Iterator[dict]:
    """Server-Sent Events from text lines: ``{"event", "id", "data"}`` with ``data`` decoded as JSON.

    Examples:
        >>> list(parse_sse(["retry: 2000", "", "id: 7", "event: checkpoint", 'data: {"iteration": 4}', "",
        ...                 ": keepalive", "", "event: progress", 'data: {"state": "running"}', ""]))
        [{'event': 'checkpoint', 'id': '7', 'data': {'iteration': 4}}, {'event': 'progress', 'id': None, 'data': {'state': 'running'}}]
    """
    fields: dict[str, str] = {}
    data: list[str] = []  # an event's data lines, joined at its end (joined at each, an event of many had been slow)
    for line in lines:
        if line == "":
            if data:
                fields["data"] = "\n".join(data)
                yield {"event": fields.get("event", "message"), "id": fields.get("id"), "data": _json(fields)}
            fields, data = {}, []
        elif not line.startswith(":"):
            name, _, value = line.partition(":")
            value = value[1:] if value.startswith(" ") else value
            if name == "data":
                data.append(value)
            else:
                fields[name] = value

