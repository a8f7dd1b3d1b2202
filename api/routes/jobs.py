"""/v1/jobs: create (queues the stage chain), list, get, cancel; each key sees only its own."""

from __future__ import annotations

import logging

from celery import Celery
import hashlib

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.auth import Idempotency, check_active_jobs, current_key, idempotency_key, lock_key
from api.db import get_sessionmaker
from api.deps import celery_dep, get_session, settings_dep
from api.models import (
    CANCELED, EVALUATE, FAILED, QUEUED, RUNNING, TERMINAL_STATES, ApiKey, Job, Reconstruction, Scene, new_id, utcnow,
)
from api.routes.scenes import MAX_OFFSET, get_scene_or_404
from api.schemas import JobCreate, JobOut, JobReconstruction, JobState, Models, Page
from api.settings import Settings, model_label
from api.uploads import MESH_FORMAT
from worker.celery_app import stage_chain
from voxe_core.presets import reconstruction_key, reconstruction_params

log = logging.getLogger("voxe.api")
router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

_ERRORS = {404: {"description": "no such job (or another key's)"}}


def job_out(job: Job, request: Request | None = None) -> JobOut:
    rec = job.reconstruction
    now = utcnow()
    elapsed = ((job.finished_at or now) - job.started_at).total_seconds() if job.started_at else None
    base = f"/v1/jobs/{job.id}"
    return JobOut(
        id=job.id, scene_id=job.scene_id, prompt=job.prompt, mode=job.mode, edit_words=job.edit_words,
        params=job.params,
        models=_models(job),
        device=job.device, state=job.state, stage=job.stage, iteration=job.iteration, total=job.total,
        progress=(job.iteration / job.total) if job.total else (1.0 if job.state == "succeeded" else 0.0),
        completed_stages=job.completed_stages or [], elapsed_seconds=elapsed,
        eta_seconds=job.eta_seconds if job.state == RUNNING else None, losses=job.losses or {},
        message=job.message, error=job.error, cancel_requested=job.cancel_requested,
        reconstruction=JobReconstruction(
            id=rec.id if rec else None, state=rec.state if rec else None,
            run_count=rec.run_count if rec else None, reused=job.reconstruction_reused,
        ),
        preview_url=f"{base}/artifacts/{job.preview_artifact}" if job.preview_artifact else None,
        artifacts_url=f"{base}/artifacts", worker_hostname=job.worker_hostname,
        source_job_ids=job.source_job_ids, result=job.result, batch_id=job.batch_id,
        created_at=job.created_at, started_at=job.started_at, finished_at=job.finished_at, updated_at=job.updated_at,
    )


def _models(job: Job) -> Models:
    if job.mode == EVALUATE:  # an evaluation's models live in its params, fixed when it was created
        return Models(sds=None, attention=None, clip=model_label(job.params.get("clip_model", "")),
                      fid=model_label(job.params.get("fid_model") or "inception-2015-12-05.pt in VOXE_MODEL_DIR"))
    return Models(sds=model_label(job.sds_model),
                  attention=model_label(job.attention_model) if job.mode == "local" else None)


def new_edit_job(body: JobCreate, key: ApiKey, settings: Settings, rec: Reconstruction, batch_id: str | None = None) -> Job:
    """The queued record of an edit job (not yet added to a session)."""
    return Job(
        id=new_id(), scene_id=body.scene_id, owner_key_id=key.id, reconstruction_id=rec.id, prompt=body.prompt,
        mode=body.mode, edit_words=body.edit_words, params=body.params.model_dump(mode="json"),
        sds_model=settings.sds_model, attention_model=settings.attention_model, device=settings.device, state=QUEUED,
        batch_id=batch_id,
    )


def queue_chain(session: Session, chain, jobs: list[Job]) -> None:
    """Hand ``chain`` to the broker and record its id on ``jobs``; when the broker is down, fail them and 503."""
    try:
        result = chain.apply_async()
    except Exception as exc:  # noqa: BLE001 - broker down: the jobs cannot run
        log.exception("could not queue job(s) %s", [j.id for j in jobs])
        session.execute(update(Job).where(Job.id.in_([j.id for j in jobs])).values(
            state=FAILED, error=f"could not queue the job: {type(exc).__name__}: {exc}", finished_at=utcnow()))
        session.commit()
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"could not queue the job: {exc}") from None
    for job in jobs:
        job.task_id = getattr(result, "id", None)
    session.commit()


def get_job_or_404(session: Session, job_id: str, key: ApiKey) -> Job:
    """The key's job; another key's job is as absent as a missing one."""
    job = session.get(Job, job_id)
    if job is None or job.owner_key_id != key.id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id!r} not found")
    return job


def check_route(scene: Scene, params: dict) -> None:
    """422 for ``reconstruction.route`` "voxelize" on a scene that has no mesh to voxelize."""
    route = (params.get("reconstruction") or {}).get("route", "auto")
    if route == "voxelize" and scene.format != MESH_FORMAT:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"reconstruction.route 'voxelize' needs a scene uploaded as a mesh; scene {scene.id!r} "
                            f"is {scene.format!r} images: use route 'fit' or 'auto'")


def _reconstruction_for(session: Session, scene_id: str, params: dict) -> Reconstruction:
    """The scene's reconstruction for these parameters, created if new.

    Race-free through the unique (scene_id, params_key) constraint: the row is inserted in
    its own short transaction, and a request that loses the race reads the winner's row.
    """
    scene = session.get(Scene, scene_id)  # already loaded by the caller's 404 check
    check_route(scene, params)
    rec_params = reconstruction_params(params, mesh_scene=scene.format == MESH_FORMAT)
    try:
        key = reconstruction_key(rec_params)
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"params.reconstruction: {exc}") from exc
    query = select(Reconstruction).where(Reconstruction.scene_id == scene_id, Reconstruction.params_key == key)
    rec = session.scalars(query).first()
    if rec is not None:
        return rec
    with get_sessionmaker()() as insert:
        try:
            insert.add(Reconstruction(id=new_id(), scene_id=scene_id, params_key=key, params=rec_params))
            insert.commit()
        except IntegrityError:  # another request created it first
            insert.rollback()
    return session.scalars(query).one()


@router.post("", status_code=status.HTTP_201_CREATED, response_model=JobOut,
             responses={200: {"description": "a retry with the same Idempotency-Key: the job it created"},
                        401: {"description": "missing or invalid API key"},
                        404: {"description": "no such scene (or another key's)"},
                        422: {"description": "invalid job (the field is named), or an Idempotency-Key reused "
                                             "with a different body"},
                        429: {"description": "the key's quota of queued + running jobs is used up (Retry-After)"},
                        503: {"description": "the job could not be queued (broker unreachable)"}},
             summary="Create an edit job (queued at once; optionally with an Idempotency-Key header)")
def create_job(
    body: JobCreate,
    request: Request,
    response: Response,
    session: Session = Depends(get_session),
    settings: Settings = Depends(settings_dep),
    celery: Celery = Depends(celery_dep),
    key: ApiKey = Depends(current_key),
) -> JobOut:
    """201 with the queued job; 200 with the original one for a retry carrying the same Idempotency-Key."""
    idem_key = idempotency_key(request)
    idem = None
    if idem_key:
        idem = Idempotency(idem_key, hashlib.sha256(body.model_dump_json().encode()).hexdigest(), "jobs")
        if (replayed := idem.replayed(session, key, response, Job)) is not None:
            return job_out(replayed)
    get_scene_or_404(session, body.scene_id, key)
    rec = _reconstruction_for(session, body.scene_id, body.params.model_dump(mode="json"))
    job = new_edit_job(body, key, settings, rec)
    try:
        lock_key(session, key)
        session.add(job)
        if idem is not None:
            idem.record(session, key, job.id)
        session.flush()
        check_active_jobs(session, key, settings)
        session.commit()
    except BaseException as exc:
        session.rollback()
        if idem is not None and isinstance(exc, IntegrityError):  # a concurrent retry created it first
            if (replayed := idem.replayed(session, key, response, Job)) is not None:
                return job_out(replayed)
        raise
    queue_chain(session, stage_chain(celery, job.id, body.mode), [job])
    session.refresh(job)
    return job_out(job)


@router.get("", response_model=Page[JobOut], summary="List jobs, newest first")
def list_jobs(
    state: JobState | None = Query(None),
    scene_id: str | None = Query(None),
    limit: int = Query(20, ge=1, le=200),
    offset: int = Query(0, ge=0, le=MAX_OFFSET),
    session: Session = Depends(get_session),
    key: ApiKey = Depends(current_key),
) -> Page[JobOut]:
    filters = [Job.owner_key_id == key.id]
    if state is not None:
        filters.append(Job.state == state)
    if scene_id is not None:
        filters.append(Job.scene_id == scene_id)
    total = session.scalar(select(func.count()).select_from(Job).where(*filters)) or 0
    rows = session.scalars(select(Job).where(*filters).order_by(Job.created_at.desc(), Job.id)
                           .limit(limit).offset(offset))
    return Page[JobOut](items=[job_out(j) for j in rows], total=total, limit=limit, offset=offset)


@router.get("/{job_id}", response_model=JobOut, responses=_ERRORS)
def get_job(job_id: str, session: Session = Depends(get_session), key: ApiKey = Depends(current_key)) -> JobOut:
    return job_out(get_job_or_404(session, job_id, key))


@router.post("/{job_id}/cancel", response_model=JobOut,
             responses={**_ERRORS, 409: {"description": "the job already succeeded or failed"}},
             summary="Cancel a job (a queued job at once; a running one stops within a few iterations)")
def cancel_job(job_id: str, session: Session = Depends(get_session), key: ApiKey = Depends(current_key)) -> JobOut:
    job = get_job_or_404(session, job_id, key)
    if job.state in TERMINAL_STATES and job.state != CANCELED:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id!r} already {job.state}")
    request_cancel(session, [job_id])
    session.refresh(job)
    return job_out(job)


def request_cancel(session: Session, job_ids: list[str]) -> None:
    """Flag the unfinished ``job_ids`` canceled: queued ones at once, running ones when their task next checks."""
    now = utcnow()
    session.execute(update(Job).where(Job.id.in_(job_ids), Job.state.not_in(TERMINAL_STATES))
                    .values(cancel_requested=True, updated_at=now))
    session.execute(update(Job).where(Job.id.in_(job_ids), Job.state == QUEUED)
                    .values(state=CANCELED, finished_at=now, message="canceled before it started"))
    session.commit()
