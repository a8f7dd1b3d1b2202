"""/v1/jobs/{id}/artifacts: list a job's files and download them (HTTP Range, If-Range, If-Match and If-None-Match)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Annotated

from fastapi import APIRouter, Header, HTTPException, Request, Response, status
from fastapi.responses import StreamingResponse
from sqlalchemy import select

from api.deps import CurrentKey, RootPath, SessionDep, StorageDep
from api.http_semantics import ID_SHOWN, StrictRoute, as_sent, combined, only_line
from api.schemas import ArtifactOut
from api.services.jobs import get_job
from voxe_service.models import Artifact
from voxe_service.storage import ObjectNotFound, Storage
from voxe_service.texts import listed

router = APIRouter(prefix="/v1/jobs/{job_id}/artifacts", tags=["artifacts"], route_class=StrictRoute)

_RANGE = re.compile(r"^\s*(\d*)\s*-\s*(\d*)\s*$")
_ENTITY_TAG = re.compile(r'(?:W/)?"[\x21\x23-\x7e\x80-\xff]*"')  # RFC 9110 §8.8.3 (a header's text is Latin-1)
_MONTH = "(?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec)"
_CLOCK = r"\d{2}:\d{2}:\d{2}"
_HTTP_DATE = re.compile(  # RFC 9110 §5.6.7, the whole value: parsedate_tz had read a date at the start of any text
    rf"(?:Mon|Tue|Wed|Thu|Fri|Sat|Sun), \d{{2}} {_MONTH} \d{{4}} {_CLOCK} GMT"  # IMF-fixdate
    rf"|(?:Mon|Tues|Wednes|Thurs|Fri|Satur|Sun)day, \d{{2}}-{_MONTH}-\d{{2}} {_CLOCK} GMT"  # obsolete RFC 850
    rf"|(?:Mon|Tue|Wed|Thu|Fri|Sat|Sun) {_MONTH} [ \d]\d {_CLOCK} \d{{4}}")  # obsolete asctime
_LIST_ELEMENT = re.compile(r'(?:W/)?"[^"]*"|[^,]+')  # a quoted tag may hold a comma
# How to send an ETag in each header: W/ only where a weak tag can match (If-Match and If-Range compare strongly, RFC
# 9110 §13.1.1, §13.1.5).
_SEND_ETAG = {
    "If-None-Match": 'send ETags quoted, as the ETag header gives them ("<sha256>" or W/"<sha256>"), or *',
    "If-Match": 'send ETags quoted, as the ETag header gives them ("<sha256>"), or *',
    "If-Range": 'send the ETag quoted, as the ETag header gives it ("<sha256>")',
}


class ClosingStreamingResponse(StreamingResponse):
    """A streamed answer that closes its chunks (``Storage.open_range``'s) when it ends, also when its client leaves
    mid-stream: Starlette drops the iterator unclosed, and its file (or S3 connection) stayed open until a garbage
    collection found it."""

    def __init__(self, chunks: Iterator[bytes], **kwargs):
        super().__init__(chunks, **kwargs)
        self.chunks = chunks

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            getattr(self.chunks, "close", lambda: None)()


def artifact_out(job_id: str, artifact: Artifact, root: str) -> ArtifactOut:
    return ArtifactOut(
        name=artifact.name, kind=artifact.kind, size=artifact.size, content_type=artifact.content_type,
        sha256=artifact.sha256, url=f"{root}/v1/jobs/{job_id}/artifacts/{artifact.name}",
        created_at=artifact.created_at,
    )


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """(first, last) inclusive for a single ``bytes=`` range; None to send the whole file (an empty file's suffix
    range too); 416 when unsatisfiable or invalid, saying which,
    naming the range cut short (a header of thousands of digits had come back whole in the message)."""
    if not header:
        return None
    sent = listed([as_sent(header)], width=60)
    unit, _, spec = header.partition("=")
    if unit.strip().lower() != "bytes":
        return None  # unknown unit: ignore the header (RFC 9110 §14.2)
    if "," in spec:
        return None  # several ranges: answer with the whole file (allowed by RFC 9110)
    match = _RANGE.match(spec)
    if not match or (not match.group(1) and not match.group(2)):
        raise _unsatisfiable(size, f"malformed range {sent}")
    first, last = match.group(1), match.group(2)
    if not first:  # suffix: the last N bytes
        n = _position(last)
        if n == 0:
            raise _unsatisfiable(size, f"range {sent} is a suffix of 0 bytes: it selects none")
        if size == 0:  # (RFC 9110 §14.1.1: satisfiable, by the empty file; no Content-Range can say 0 bytes)
            return None
        return max(0, size - n), size - 1
    start = _position(first)
    end = _position(last) if last else size - 1
    if last and end < start:  # (an invalid range, RFC 9110 §14.1.1; it had been said to be outside the file)
        raise _unsatisfiable(size, f"range {sent} ends before it starts: send bytes=first-last with last >= first")
    if start >= size:
        raise _unsatisfiable(size, f"range {sent} is outside the {size}-byte file")
    return start, min(end, size - 1)


def _position(digits: str) -> int:
    """A byte position; past 18 significant digits, one beyond any file (``int`` refuses over 4,300 digits)."""
    digits = digits.lstrip("0") or "0"
    return int(digits) if len(digits) <= 18 else 10**18


def entity_tags(header: str, lines: list[str] | None) -> set[str] | None:
    """The entity tags, or {"*"}, that an If-Match or If-None-Match lists over all its field lines (RFC 9110 §5.3: a
    list may be sent as several lines; only the first had been read); None when it is not sent.

    422 naming the header for an element that is not an entity tag: a bare tag (the listing's sha256, unquoted) had
    never matched, so an If-Match was a 412 saying the artifact "was replaced" and an If-None-Match a whole download.
    So is an If-Match listing nothing, which no artifact matches (it too had been told "it was replaced").
    """
    if lines is None:
        return None
    elements = [element.strip() for element in _LIST_ELEMENT.findall(combined(lines)) if element.strip()]
    if bad := [element for element in elements if element != "*" and not _ENTITY_TAG.fullmatch(element)]:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{header} {listed([as_sent(tag) for tag in bad], width=70)} is not an entity tag: {_SEND_ETAG[header]}")
    if "*" in elements and set(elements) != {"*"}:  # (* on two lines, one list, had been told so too)
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{header} lists * with entity tags: * (any version) stands alone")
    if not elements and header == "If-Match":  # (an empty If-None-Match is simply true: the file)
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"If-Match is empty: {_SEND_ETAG[header]}")
    return set(elements)


def range_validator(if_range_lines: list[str], range_: str | None) -> str | None:
    """If-Range's entity tag or date when a Range is sent; None without one (RFC 9110 §13.1.5: it is then ignored,
    on several lines too).

    422 naming the header for anything else: a bare tag (the listing's sha256, unquoted) had never matched, so a
    resumed download silently got the whole file again (If-Match and If-None-Match refuse it so).
    """
    if not if_range_lines or not range_:
        return None
    if_range = only_line("If-Range", if_range_lines)
    validator = if_range.strip()
    if not _ENTITY_TAG.fullmatch(validator) and not _HTTP_DATE.fullmatch(validator):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"If-Range {listed([as_sent(if_range)], width=70)} is neither an entity tag nor a date: "
                            f"{_SEND_ETAG['If-Range']}")
    return validator


def _unsatisfiable(size: int, detail: str) -> HTTPException:
    return HTTPException(status.HTTP_416_RANGE_NOT_SATISFIABLE, detail,
                         headers={"Content-Range": f"bytes */{size}", "Accept-Ranges": "bytes"})


@router.get("", response_model=list[ArtifactOut], responses={404: {"description": "no such job (or another key's)"}})
def list_artifacts(job_id: str, session: SessionDep, key: CurrentKey, root: RootPath) -> list[ArtifactOut]:
    get_job(session=session, key=key, job_id=job_id)
    rows = session.scalars(select(Artifact).where(Artifact.job_id == job_id).order_by(Artifact.id))
    return [artifact_out(job_id, a, root) for a in rows]


_HEAD = {
    200: {"description": "the whole file: without Range, or with an If-Range that is not the current ETag (a "
                         "resumed download of a replaced artifact starts over; RFC 9110 §13.1.5)"},
    206: {"description": "the requested byte range (Range: bytes=..., If-Range, when sent, the current ETag)"},
    304: {"description": "not modified: If-None-Match names the current ETag (or is *); no body"},
    404: {"description": "no such job or artifact"},
    412: {"description": "If-Match names none of the current ETag (or *): the artifact was replaced; or it names it "
                         "only as a weak (W/) tag, or lists only those, which never match (If-Match compares "
                         "strongly)"},
    416: {"description": "range not satisfiable"},
    500: {"description": "the artifact's stored object is not the size it is listed with: damaged (both sizes named)"},
    422: {"description": "If-Match or If-None-Match is not * or a list of quoted entity tags, If-Match is empty, or "
                         "If-Range (with a Range) is neither an entity tag nor a date, or is sent on several lines (the "
                         "header named)"},
}
# A GET's 200 and 206 carry the artifact's bytes, as its listed content_type (image/png, video/mp4, ...): documented
# as FastAPI documents a streamed answer, with no body, a client generated from the document read a download as empty.
# A HEAD's carry none (they had been documented as JSON).
_BYTES = {"*/*": {"schema": {"type": "string", "format": "binary"}}}
_DOWNLOAD = {**_HEAD, **{code: {**_HEAD[code], "content": _BYTES} for code in (200, 206)}}


@router.head("/{name}", response_class=Response, responses=_HEAD,
             summary="An artifact's headers (size, checksum) without its bytes")
@router.get("/{name}", response_class=StreamingResponse, responses=_DOWNLOAD,
            summary="Download an artifact (supports Range: bytes=..., If-Range, If-Match and If-None-Match)")
def get_artifact(
    job_id: str, name: str, request: Request, session: SessionDep, storage: StorageDep, key: CurrentKey,
    # Range and If-Range are read from every line below (request.headers); these parameters document them.
    range_: Annotated[str | None, Header(alias="Range", description="bytes=first-last, first- or -suffix")] = None,
    if_range: Annotated[str | None, Header(description="the ETag the Range's earlier bytes came from: another "
                                                       "(or a date) gets the whole file; a bare sha256, 422")] = None,
    if_none_match: Annotated[list[str] | None, Header(description="ETags held (or *): the current one gets 304")
                             ] = None,
    if_match: Annotated[list[str] | None, Header(description="ETags any of which the artifact must still have (or "
                                                             "*): else 412")] = None,
) -> Response:
    # The session is closed before the body streams: a download had held its pooled connection (on PostgreSQL, a
    # transaction open) until its client read the last byte, and two slow ones made every other request wait.
    try:
        held, required = entity_tags("If-None-Match", if_none_match), entity_tags("If-Match", if_match)
        range_ = combined(request.headers.getlist("range") or None)
        if_range = range_validator(request.headers.getlist("if-range"), range_)
        get_job(session=session, key=key, job_id=job_id)
        for attempt in range(2):
            # Only names recorded for this job are served: no path is ever built from the request.
            artifact = session.scalars(select(Artifact).where(Artifact.job_id == job_id, Artifact.name == name)).first()
            if artifact is None:
                raise HTTPException(status.HTTP_404_NOT_FOUND,
                                    f"job {job_id!r} has no artifact {listed([name], width=ID_SHOWN)}")
            try:
                return _answer(request.method, storage, artifact, range_, if_range, held, required)
            except ObjectNotFound:
                if attempt:
                    raise HTTPException(status.HTTP_404_NOT_FOUND,
                                        f"artifact {name!r} is missing from storage") from None
                session.rollback()  # read the row anew: a replaced artifact (a republished preview) has a new key
    finally:
        session.close()


def _answer(method: str, storage: Storage, artifact: Artifact, range_: str | None, if_range: str | None,
            if_none_match: set[str] | None, if_match: set[str] | None) -> Response:
    """The artifact's answer to a GET or HEAD with these headers; ObjectNotFound when its object is not stored."""
    etag = f'"{artifact.sha256}"'
    # Strong comparison, before If-None-Match (RFC 9110 §13.1.1, §13.2.2): a download fetched in parts, each asking
    # If-Match, had been given the replaced artifact's bytes for the later parts (a spliced file) where a 412 says so.
    # The 412 names why no tag matched: "it was replaced" only where a strong tag names another version and no W/
    # one the current (it had been said of W/ tags too, the current ETag's among them).
    if if_match is not None and not {"*", etag} & if_match:
        sent, weak = listed(sorted(if_match), width=70), {tag for tag in if_match if tag.startswith("W/")}
        if f"W/{etag}" in weak or weak == if_match:
            held = ("lists no other" if weak == if_match
                    else f"names artifact {artifact.name!r}'s current ETag {etag} only with W/")
            raise HTTPException(status.HTTP_412_PRECONDITION_FAILED,
                                f"If-Match compares strongly: a W/ tag never matches, and If-Match {sent} {held} "
                                "(send the ETag as the ETag header gives it, without W/)")
        raise HTTPException(status.HTTP_412_PRECONDITION_FAILED,
                            f"If-Match {sent} does not name artifact {artifact.name!r}'s current ETag {etag}: it was "
                            "replaced (download it again from the start)"
                            + ("; its W/ tags never match (If-Match compares strongly)" if weak else ""))
    if if_none_match is not None and {"*", etag} & {tag.removeprefix("W/") for tag in if_none_match}:
        return Response(status_code=status.HTTP_304_NOT_MODIFIED, headers={"ETag": etag})  # (weak comparison)
    if if_range is not None and if_range != etag:  # strong comparison; a date never matches (no Last-Modified)
        range_ = None
    size = artifact.size
    # The object's own size, before any byte is sent: one shorter than listed (cut short in the storage) had been
    # streamed with the listed Content-Length, its connection dropped at its end, and resumed by a client again and
    # again from there until its error read as an outage. Its absence, ObjectNotFound (an empty artifact's too).
    if (stored := storage.size(artifact.key)) != size:
        raise HTTPException(status.HTTP_500_INTERNAL_SERVER_ERROR,
                            f"artifact {artifact.name!r} is stored with {stored} bytes, not the {size} it is listed "
                            "with: its stored object is damaged")
    headers = {
        "Accept-Ranges": "bytes",
        "ETag": etag,
        "Content-Disposition": f'inline; filename="{artifact.name}"',
        "X-Checksum-SHA256": artifact.sha256,
    }
    byte_range = parse_range(range_, size)
    if byte_range is None:
        start, end, code = 0, size - 1, status.HTTP_200_OK
    else:
        start, end = byte_range
        code = status.HTTP_206_PARTIAL_CONTENT
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    headers["Content-Length"] = str(max(0, end - start + 1))
    if method == "HEAD":  # answers as the GET would (it had said 200 for a file the GET could not serve)
        return Response(status_code=code, headers=headers, media_type=artifact.content_type)
    body = storage.open_range(artifact.key, start, end)
    return ClosingStreamingResponse(body, status_code=code, headers=headers, media_type=artifact.content_type)
