"""/v1/evaluations and /v1/sweeps: the paper's evaluation (SPEC §4) as jobs.

An evaluation is a job of mode ``evaluate`` over finished edit jobs of one scene; its
result (the metrics, a Markdown table) is the job's ``result`` and its ``evaluation.json``
/ ``evaluation.md`` artifacts. A sweep submits the paper's protocol as one batch: every
scene × the six prompts of SPEC §4 (local ones refined), each edit followed by its own
evaluation in the same Celery chain, so the batch spreads over every listening worker;
``GET /v1/sweeps/{id}`` gathers the evaluations into one summary table.
"""

from __future__ import annotations

from collections import Counter

from celery import Celery
from fastapi import APIRouter, Depends, HTTPException, status
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from api.auth import check_active_jobs, current_key, lock_key
from api.deps import celery_dep, get_session, settings_dep
from api.models import (
    CANCELED, EVALUATE, FAILED, QUEUED, RUNNING, SUCCEEDED, TERMINAL_STATES, ApiKey, Job, new_id, utcnow,
)
from api.routes.jobs import (
    _reconstruction_for, check_route, get_job_or_404, job_out, new_edit_job, queue_chain, request_cancel,
)
from api.routes.scenes import get_scene_or_404
from api.schemas import (
    EvaluationCreate, EvaluationParams, JobCreate, JobOut, SweepCreate, SweepEntry, SweepOut,
)
from api.settings import Settings
from voxe_core.evaluate import format_table, mean_by_mode, paper_protocol
from worker.celery_app import stage_chain

router = APIRouter(tags=["evaluation"])

_QUOTA = {429: {"description": "the key's quota of queued + running jobs is used up (Retry-After)"},
          503: {"description": "the jobs could not be queued (broker unreachable)"}}


def new_evaluation_job(key: ApiKey, settings: Settings, sources: list[Job], object_name: str,
                       params: EvaluationParams, batch_id: str | None = None, index: int = 0) -> Job:
    """The queued record of an evaluation of ``sources`` (edit jobs of one scene and reconstruction)."""
    first = sources[0]
    return Job(
        id=new_id(), scene_id=first.scene_id, owner_key_id=key.id, reconstruction_id=first.reconstruction_id,
        prompt=f"evaluate {len(sources)} edit(s) of a {object_name}", mode=EVALUATE, edit_words=[],
        params={**params.model_dump(mode="json"), "object": object_name, "clip_model": settings.clip_model,
                "fid_model": settings.fid_model, "sweep_index": index},
        sds_model="", attention_model="", device=settings.device, state=QUEUED,
        source_job_ids=[s.id for s in sources], batch_id=batch_id,
    )


def _add_within_quota(session: Session, key: ApiKey, settings: Settings, jobs: list[Job]) -> None:
    try:
        lock_key(session, key)
        session.add_all(jobs)
        session.flush()
        check_active_jobs(session, key, settings)
        session.commit()
    except BaseException:
        session.rollback()
        raise


@router.post("/v1/evaluations", status_code=status.HTTP_201_CREATED, response_model=JobOut,
             responses={404: {"description": "a listed job does not exist (or is another key's)"},
                        409: {"description": "a listed job has not succeeded"},
                        422: {"description": "invalid request, an evaluation listed, or jobs of different scenes"},
                        **_QUOTA},
             summary="Evaluate finished edit jobs of one scene (CLIP_sim, CLIP_dir, FID, PSNR/SSIM outside the mask)")
def create_evaluation(
    body: EvaluationCreate,
    session: Session = Depends(get_session),
    settings: Settings = Depends(settings_dep),
    celery: Celery = Depends(celery_dep),
    key: ApiKey = Depends(current_key),
) -> JobOut:
    sources = [get_job_or_404(session, job_id, key) for job_id in body.job_ids]
    for source in sources:
        if source.mode == EVALUATE:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, f"job {source.id!r} is an evaluation, not an edit")
        if source.state != SUCCEEDED:
            raise HTTPException(status.HTTP_409_CONFLICT, f"job {source.id!r} is {source.state}: only succeeded "
                                                          "edit jobs can be evaluated")
    if len({s.scene_id for s in sources}) > 1:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, "the jobs belong to different scenes: an "
                                                                  "evaluation scores edits of one object")
    if len({s.reconstruction_id for s in sources}) > 1:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_ENTITY, "the jobs edit different reconstructions of the "
                                                                  "scene (reconstruction parameters differ)")
    job = new_evaluation_job(key, settings, sources, body.object, body.params)
    _add_within_quota(session, key, settings, [job])
    queue_chain(session, stage_chain(celery, job.id, EVALUATE), [job])
    session.refresh(job)
    return job_out(job)


@router.post("/v1/sweeps", status_code=status.HTTP_201_CREATED, response_model=SweepOut,
             responses={404: {"description": "no such scene (or another key's)"},
                        422: {"description": "invalid request (the field is named)"}, **_QUOTA},
             summary="Submit the paper's protocol: scenes × the six prompts of SPEC §4, each edit then evaluated")
def create_sweep(
    body: SweepCreate,
    session: Session = Depends(get_session),
    settings: Settings = Depends(settings_dep),
    celery: Celery = Depends(celery_dep),
    key: ApiKey = Depends(current_key),
) -> SweepOut:
    for scene in body.scenes:  # every scene checked before any reconstruction row is made
        check_route(get_scene_or_404(session, scene.scene_id, key), body.params.model_dump(mode="json"))
    batch_id = new_id()
    pairs: list[tuple[Job, Job]] = []
    for scene in body.scenes:
        rec = _reconstruction_for(session, scene.scene_id, body.params.model_dump(mode="json"))
        for edit in paper_protocol(scene.object):
            # Through JobCreate, so each edit is exactly what POST /v1/jobs would accept (a valid object
            # name always gives valid protocol prompts: short, and "wearing" / "a" besides the edit words).
            request = JobCreate(scene_id=scene.scene_id, prompt=edit.prompt, mode=edit.mode,
                                edit_words=list(edit.edit_words), params=body.params)
            job = new_edit_job(request, key, settings, rec, batch_id)
            pairs.append((job, new_evaluation_job(key, settings, [job], scene.object, body.evaluation, batch_id,
                                                  index=len(pairs))))
    _add_within_quota(session, key, settings, [j for pair in pairs for j in pair])
    for k, (job, evaluation) in enumerate(pairs):
        try:
            queue_chain(session, stage_chain(celery, job.id, job.mode, then_evaluate=[evaluation.id]), [job, evaluation])
        except HTTPException:  # the broker went away mid-batch: nothing after this pair can run either
            later = [j.id for pair in pairs[k + 1:] for j in pair]
            if later:
                session.execute(update(Job).where(Job.id.in_(later)).values(
                    state=FAILED, error="could not queue the sweep: the broker became unreachable", finished_at=utcnow()))
                session.commit()
            raise
    return sweep_out(session, batch_id, key)


@router.get("/v1/sweeps/{sweep_id}", response_model=SweepOut,
            responses={404: {"description": "no such sweep (or another key's)"}},
            summary="A sweep's jobs and, for the evaluations done so far, one summary table")
def get_sweep(sweep_id: str, session: Session = Depends(get_session), key: ApiKey = Depends(current_key)) -> SweepOut:
    return sweep_out(session, sweep_id, key)


@router.post("/v1/sweeps/{sweep_id}/cancel", response_model=SweepOut,
             responses={404: {"description": "no such sweep (or another key's)"}},
             summary="Cancel every unfinished job of a sweep (finished ones and their results stay)")
def cancel_sweep(sweep_id: str, session: Session = Depends(get_session),
                 key: ApiKey = Depends(current_key)) -> SweepOut:
    jobs = _sweep_jobs(session, sweep_id, key)
    request_cancel(session, [j.id for j in jobs])
    session.expire_all()
    return sweep_out(session, sweep_id, key)


def sweep_state(states: list[str]) -> str:
    """Queued until a job starts, running until all are finished; then failed / canceled if any was, else succeeded."""
    if all(s == QUEUED for s in states):
        return QUEUED
    if any(s not in TERMINAL_STATES for s in states):
        return RUNNING
    for state in (FAILED, CANCELED):
        if state in states:
            return state
    return SUCCEEDED


def _sweep_jobs(session: Session, sweep_id: str, key: ApiKey) -> list[Job]:
    jobs = list(session.scalars(select(Job).where(Job.batch_id == sweep_id, Job.owner_key_id == key.id)))
    if not jobs:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"sweep {sweep_id!r} not found")
    return jobs


def sweep_out(session: Session, sweep_id: str, key: ApiKey) -> SweepOut:
    jobs = _sweep_jobs(session, sweep_id, key)
    edits = {j.id: j for j in jobs if j.mode != EVALUATE}
    evaluations = sorted((j for j in jobs if j.mode == EVALUATE), key=lambda j: j.params.get("sweep_index", 0))
    entries, rows = [], []
    for evaluation in evaluations:
        edit = edits[evaluation.source_job_ids[0]]
        entries.append(SweepEntry(
            scene_id=edit.scene_id, object=evaluation.params["object"], prompt=edit.prompt, mode=edit.mode,
            edit_job_id=edit.id, edit_state=edit.state, evaluation_job_id=evaluation.id,
            evaluation_state=evaluation.state,
        ))
        if evaluation.result:
            rows.extend(evaluation.result["rows"])
    return SweepOut(
        id=sweep_id, state=sweep_state([j.state for j in jobs]), counts=dict(Counter(j.state for j in jobs)),
        entries=entries, rows=rows, means=mean_by_mode(rows), table=format_table(rows, extra_columns=("object",)),
    )
