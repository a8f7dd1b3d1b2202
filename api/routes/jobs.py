"""/v1/jobs: create (queued at once), list, get, cancel, and a job's event timeline; each key sees only its own."""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, Depends, Header, HTTPException, Query, Request, Response, status
from fastapi.responses import StreamingResponse
from sqlalchemy import func, select

from api.auth import mark_replayed, replayed_answer
from api.deps import CurrentKey, IdempotencyKey, QueueDep, RootPath, SessionDep, SettingsDep
from api.events import SSE_MEDIA_TYPE
from api.http_semantics import KEYS_OWN, StrictRoute, as_sent, combined, only_line
from api.paging import PageQuery, page_query
from api.schemas import (
    JobCreate, JobEventOut, JobOut, JobReconstruction, JobState, Models, Page, WebhookDeliveryOut,
)
from api.services import jobs
from voxe_core.presets import reconstruction_params
from voxe_service.models import EVALUATE, R_SUCCEEDED, RUNNING, SUCCEEDED, Job, JobEvent, utcnow
from voxe_service.progress import NO_FIT, fit_work, overall, stage_costs, stage_fraction
from voxe_service.settings import fid_model_label, model_label
from voxe_service.texts import listed

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=StrictRoute)

_ERRORS = {404: {"description": "no such job (or another key's)"}}


def job_out(job: Job, root: str = "") -> JobOut:
    """The job resource, its links under ``root``: the prefix a proxy serves the service under (api.deps.RootPath)."""
    rec = job.reconstruction
    now = utcnow()
    elapsed = ((job.finished_at or now) - job.started_at).total_seconds() if job.started_at else None
    base = f"{root}/v1/jobs/{job.id}"
    return JobOut(
        id=job.id, scene_id=job.scene_id, prompt=job.prompt, mode=job.mode, edit_words=job.edit_words,
        params=job.params,
        models=_models(job),
        device=job.device, state=job.state, stage=job.stage, iteration=job.iteration, total=job.total,
        progress=_stage_progress(job),
        completed_stages=job.completed_stages or [], elapsed_seconds=elapsed,
        eta_seconds=job.eta_seconds if job.state == RUNNING else None, losses=job.losses or {},
        **dict(zip(("overall_progress", "overall_eta_seconds"), _overall(job))),
        message=job.message, error=job.error, cancel_requested=job.cancel_requested,
        reconstruction=JobReconstruction(
            id=rec.id if rec else None, state=rec.state if rec else None, error=rec.error if rec else None,
            run_count=rec.run_count if rec else None, reused=job.reconstruction_reused,
        ),
        preview_url=f"{base}/artifacts/{job.preview_artifact}" if job.preview_artifact else None,
        artifacts_url=f"{base}/artifacts", events_url=f"{base}/events", worker_hostname=job.worker_hostname,
        source_job_ids=job.source_job_ids, result=job.result, batch_id=job.batch_id,
        webhook_url=job.webhook_url, webhook_events=job.webhook_events, webhooks_url=f"{base}/webhooks",
        created_at=job.created_at, started_at=job.started_at, stage_started_at=job.stage_started_at,
        finished_at=job.finished_at, updated_at=job.updated_at,
    )


def _stage_progress(job: Job) -> float:
    """The current stage's fraction done, within [0, 1] as the overall one (``stage_fraction``) reads it: the row's
    iteration and total are written by separate writers (a stage's reports, a resumed checkpoint's iteration, a
    waited-for fit's count), and one past its total had said more than all of the stage."""
    if not job.total:
        return 1.0 if job.state == SUCCEEDED else 0.0
    return min(1.0, max(0.0, job.iteration / job.total))


def _overall(job: Job) -> tuple[float, float | None]:
    """(overall progress, seconds left for the job): voxe_service.progress over the job's stage costs."""
    rec, result = job.reconstruction, job.result or {}
    reused = rec is not None and rec.state == R_SUCCEEDED and rec.owner_job_id != job.id and not _waited_for(job, rec)
    if reused or job.mode == EVALUATE or _reused_a_finished_fit(job):
        fit = NO_FIT  # a finished fit reused: nothing to fit or wait for (an evaluation fits nothing)
    else:
        steps = (rec.total if rec is not None else 0) or (job.total if job.stage == "reconstruct" else 0) or None
        fit = fit_work(rec.params if rec is not None else reconstruction_params(job.params), result.get("fit"), steps)
    edit_iterations = (result.get("edit_schedule") or {}).get("iterations")
    costs = stage_costs(mode=job.mode, params=job.params, fit=fit, device=job.device, edit_iterations=edit_iterations)
    fraction = stage_fraction(stage=job.stage, params=job.params, device=job.device, iteration=job.iteration,
                              total=job.total)
    running = job.state == RUNNING
    # The stage's share counts in any state (a failed, canceled or re-queued job keeps the fraction it reached);
    # only a running one has a time left.
    return overall(costs=costs, completed=job.completed_stages or [], stage=job.stage,
                   stage_fraction=fraction, stage_eta_s=job.eta_seconds if running else None,
                   finished=job.state == SUCCEEDED)


def _reused_a_finished_fit(job: Job) -> bool:
    """Whether the job, past its reconstruct stage, took a fit finished before it started: it neither ran the fit
    (``reconstruction_reused``) nor waited for it (the worker records ``result.fit`` as a job starts waiting). Read off
    the job: its reconstruction, fitted again since by another job (its grid deleted from the storage), was pending,
    then finished after the job began, and the job's progress had jumped by the whole fit's share."""
    return ("reconstruct" in (job.completed_stages or []) and bool(job.reconstruction_reused)
            and not (job.result or {}).get("fit"))


def _waited_for(job: Job, rec) -> bool:
    """Whether the job started before another job's fit of its reconstruction finished: it spent that fit's time
    waiting, so the fit keeps its weight in the job's progress (which then never drops when the fit ends)."""
    return job.started_at is not None and rec.finished_at is not None and rec.finished_at > job.started_at


def _models(job: Job) -> Models:
    if job.mode == EVALUATE:  # an evaluation's models live in its params, fixed when it was created
        return Models(sds=None, attention=None, clip=model_label(job.params.get("clip_model", "")),
                      fid=fid_model_label(job.params.get("fid_model", "")))
    return Models(sds=model_label(job.sds_model),
                  attention=model_label(job.attention_model) if job.mode == "local" else None)


@router.post("", status_code=status.HTTP_201_CREATED, response_model=JobOut,
             responses={200: replayed_answer(JobOut, "job"),
                        204: {"description": "with check=true: the body and its webhook_url are a job's this endpoint "
                                             "takes on some scene; nothing is made"},
                        401: {"description": "missing or invalid API key"},
                        404: {"description": "no such scene (or another key's)"},
                        409: {"description": "the scene failed processing (the reason is named), every worker "
                                             "reporting lacks a model the job loads (named, with how to provide it), "
                                             "a retry whose Idempotency-Key created a job that has since been "
                                             "deleted, or one sent while that first request has not answered yet "
                                             "(Retry-After); or the job was canceled and deleted with its scene "
                                             "before its creation answered"},
                        422: {"description": "invalid job (the field is named), an Idempotency-Key reused "
                                             "with a different body, or a webhook_url the service will not call "
                                             "(the rule is named)"},
                        429: {"description": "the key's quota of queued + running jobs is used up (Retry-After)"},
                        503: {"description": "the job could not be queued (broker unreachable), or its webhook_url "
                                             "host could not be looked up yet: every name lookup is stuck on a "
                                             "resolver (Retry-After)"}},
             summary="Create an edit job (queued at once; optionally with an Idempotency-Key header)")
def create_job(body: JobCreate, response: Response, session: SessionDep, settings: SettingsDep, queue: QueueDep,
               key: CurrentKey, idempotency_key: IdempotencyKey, root: RootPath,
               check: Annotated[bool, Query(description="only check the body and its webhook_url (204, or the 422 "
                                                        "its creation would answer), its scene_id not looked up: "
                                                        "what voxe submit --upload asks before it uploads")] = False,
               ) -> JobOut | Response:
    """201 with the queued job (on a scene still processing, it starts once the scene is ready); 200 with the
    original one for a retry carrying the same Idempotency-Key; with ``check``, 204 where what does not depend on the
    scene is one it takes (the body was read by the time it gets here)."""
    if check:
        jobs.check_webhook(settings=settings, body=body)
        return Response(status_code=status.HTTP_204_NO_CONTENT)
    job, replayed = jobs.create_job(session=session, settings=settings, queue=queue, key=key, body=body,
                                    idempotency_key=idempotency_key)
    if replayed:
        mark_replayed(response)
    return job_out(job, root)


@router.get("", response_model=Page[JobOut], summary="List jobs, newest first",
            responses={422: {"description": "a limit or offset out of range, an empty scene_id, or a cursor that is "
                                              "not this listing's or is sent with offset (named)"}})
def list_jobs(
    session: SessionDep,
    key: CurrentKey,
    root: RootPath,
    page: Annotated[PageQuery, Depends(page_query("/v1/jobs"))],
    state: JobState | None = Query(None),
    # (the pattern documents the NUL refusal of http_semantics; an empty one had listed no job: a 422)
    scene_id: str | None = Query(None, min_length=1, pattern=r"^[^\x00]*$"),
) -> Page[JobOut]:
    found = jobs.list_jobs(session=session, key=key, state=state, scene_id=scene_id, page=page)
    return Page[JobOut](items=[job_out(j, root) for j in found.rows], total=found.total, limit=page.limit,
                        offset=found.offset, next_cursor=found.next_cursor)


@router.get("/{job_id}", response_model=JobOut, responses=_ERRORS)
def get_job(job_id: str, session: SessionDep, key: CurrentKey, root: RootPath) -> JobOut:
    return job_out(jobs.get_job(session=session, key=key, job_id=job_id), root)


@router.get(
    "/{job_id}/events", response_model=list[JobEventOut],
    responses={**_ERRORS,
               200: {"description": "the timeline as JSON; with `Accept: text/event-stream` (its q at least "
                                    "application/json's), a live stream of Server-Sent Events (api/events.py) ending "
                                    "when the job ends",
                     "headers": {"Vary": {"description": "Accept: the answer depends on it",
                                          "schema": {"type": "string"}}},
                     "content": {SSE_MEDIA_TYPE: {"schema": {"type": "string"}}}},
               422: {"description": "Last-Event-ID is not an event id, is past the job's newest event, or is sent on "
                                    "several lines"}},
    summary="The job's timeline (stages, checkpoints, artifacts, its end), or a live stream of it",
)
def list_events(job_id: str, request: Request, response: Response, session: SessionDep, key: CurrentKey, root: RootPath,
                # (documents the header; every line of it is read from request.headers)
                last_event_id: Annotated[str | None, Header(description="stream: resume after this event id")] = None,
                ) -> list[JobEventOut] | StreamingResponse:
    jobs.get_job(session=session, key=key, job_id=job_id)
    # Either answer depends on Accept: said, so a cache never serves the timeline for the stream or the other way.
    negotiated = {"Vary": "Accept"}
    if wants_stream(request.headers.getlist("accept")):
        after = _event_id(only_line("Last-Event-ID", request.headers.getlist("last-event-id")))
        _check_sent(session, job_id, after)
        session.close()  # the stream reads through the hub's short sessions: hold no connection meanwhile
        return StreamingResponse(request.app.state.event_hub.stream(job_id, key.id, after, root),
                                 media_type=SSE_MEDIA_TYPE, headers={"Cache-Control": KEYS_OWN, "X-Accel-Buffering": "no", **negotiated})
    response.headers.update(negotiated)
    rows = session.scalars(select(JobEvent).where(JobEvent.job_id == job_id).order_by(JobEvent.id))
    return [JobEventOut.model_validate(e, from_attributes=True) for e in rows]


def wants_stream(accept: list[str]) -> bool:
    """Whether an Accept (all its lines) weights text/event-stream, in any case (RFC 9110 §8.3.1), above 0 and at
    least as high as application/json (named, or through application/* or */*).

    It had been found as a substring: ``text/event-stream;q=0`` (anything but a stream) got a stream open until the
    job ends, and ``Text/Event-Stream`` the JSON timeline; then any q above 0 streamed, also where JSON was preferred
    (``application/json, text/event-stream;q=0.1``).
    """
    weights: dict[str, float] = {}
    for media_range in combined(accept).split(","):
        media_type, *params = (part.strip().lower() for part in media_range.split(";"))
        q = [value.strip() for name, _, value in (p.partition("=") for p in params) if name.strip() == "q"]
        weights.setdefault(media_type, _qvalue(q[0]) if q else 1.0)
    stream = weights.get(SSE_MEDIA_TYPE, 0.0)
    as_json = next((weights[t] for t in ("application/json", "application/*", "*/*") if t in weights), 0.0)
    return stream > 0 and stream >= as_json


def _qvalue(text: str) -> float:
    """A media range's weight: RFC 9110 §12.4.2's (0 to 1, three decimals), or read leniently as a number within [0, 1]
    where a client writes it otherwise (``.5``, ``0.0001``: such a q had counted as 1, so a stream ranked below JSON
    was opened); one that is no number counts as absent (1)."""
    try:
        weight = float(text)
    except ValueError:
        return 1.0
    return min(max(weight, 0.0), 1.0) if math.isfinite(weight) else 1.0


def _event_id(value: str | None) -> int:
    text = (value or "").strip()
    if not text:
        return 0
    # Bounded before int(): a larger id would make the event hub's one query for every open stream fail in the
    # database (SQLite's integers are 64-bit), and thousands of digits make int() itself raise.
    digits = text.lstrip("0") or "0"
    if not (text.isascii() and text.isdigit()) or len(digits) > 19 or int(digits) > MAX_EVENT_ID:  # "²".isdigit()
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"Last-Event-ID must be the id of an event (an integer from 0 to {MAX_EVENT_ID}), "
                            f"not {listed([as_sent(value)])}")
    return int(digits)


MAX_EVENT_ID = 2**63 - 1


def _check_sent(session, job_id: str, after: int) -> None:
    """A 422 where ``after`` is past the job's newest event: no stream of the job sent that id (it is another job's,
    or a database's since restored), and a stream resumed after it had sent none of the job's events, its end
    included (ids are the whole table's: they would not reach it for as long as the job runs)."""
    if not after:
        return
    newest = session.scalar(select(func.max(JobEvent.id)).where(JobEvent.job_id == job_id)) or 0
    if after > newest:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"Last-Event-ID {after} is past job {job_id}'s newest event "
                            f"({newest if newest else 'it has none yet'}): no stream of it sent that id; resume after "
                            "an id its stream sent, or leave Last-Event-ID out for the whole timeline")


def progress_view(job: Job) -> dict:
    """What an event stream's ``progress`` event carries: the job resource's progress fields."""
    return job_out(job).model_dump(mode="json", include=PROGRESS_FIELDS)


PROGRESS_FIELDS = {"id", "state", "stage", "iteration", "total", "progress", "overall_progress", "completed_stages",
                   "eta_seconds", "overall_eta_seconds", "losses", "message", "error", "preview_url",
                   "cancel_requested"}


@router.get("/{job_id}/webhooks", response_model=list[WebhookDeliveryOut], responses=_ERRORS,
            summary="The job's webhook deliveries: one per event sent, with its attempts and last answer")
def list_webhooks(job_id: str, session: SessionDep, key: CurrentKey) -> list[WebhookDeliveryOut]:
    rows = jobs.list_webhooks(session=session, key=key, job_id=job_id)
    return [WebhookDeliveryOut.model_validate(d, from_attributes=True) for d in rows]


@router.post("/{job_id}/cancel", response_model=JobOut,
             responses={**_ERRORS, 409: {"description": "the job already succeeded or failed"}},
             summary="Cancel a job (a queued job at once; a running one stops within a few iterations)")
def cancel_job(job_id: str, session: SessionDep, key: CurrentKey, root: RootPath) -> JobOut:
    return job_out(jobs.cancel_job(session=session, key=key, job_id=job_id), root)
