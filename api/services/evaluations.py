"""Evaluations (SPEC §4) as jobs, and sweeps: the paper's protocol submitted as one batch.

An evaluation is a job of mode ``evaluate`` over finished edit jobs of one scene. A sweep
is every scene × the six prompts of SPEC §4 (local ones refined), each edit followed by its
own evaluation in the same Celery chain, so the batch spreads over every listening worker.
"""

from __future__ import annotations

from fastapi import HTTPException, status
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api.schemas import EvaluationCreate, EvaluationParams, JobCreate, SweepCreate
from api.auth import Idempotency, sha256_hex
from api.http_semantics import ID_SHOWN
from api.services.jobs import (
    get_job, new_edit_job, reconstruction_for, record_and_send, request_cancel, scene_deleted, submit, usable_scene,
)
from voxe_core.evaluate import check_source_text_length, paper_protocol
from voxe_core.guidance.prompts import check_prompt_length
from voxe_service.models import (
    CANCELED, EVALUATE, FAILED, QUEUED, RUNNING, SUCCEEDED, TERMINAL_STATES, ApiKey, Job, Reconstruction, Scene, new_id,
)
from voxe_service.queue import QueueUnavailable, TaskQueue
from voxe_service.settings import Settings
from voxe_service.texts import listed


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


def refuse_fid_input_of_one_image(params: EvaluationParams, scene: Scene, max_images: int | None,
                                  field: str, edit_job_id: str | None = None) -> None:
    """422 naming ``field`` (the request's fid_input) for FID_input against fewer than 2 input images (the edits'
    fit's: the scene's training images, the first ``max_images``): FID compares two sets' statistics, and the
    evaluation had been accepted and failed in the worker, a sweep's after each edit it follows had run.
    ``edit_job_id``: the edit job whose params set ``max_images`` (an evaluation's; a sweep's are its own)."""
    kept = scene.image_count if max_images is None else min(max_images, scene.image_count)
    if params.fid_input and kept < 2:
        if max_images is not None and max_images < 2:
            why = (f"params.max_images {max_images}" if edit_job_id is None
                   else f"the edits' params.max_images {max_images} (job {edit_job_id!r})") + f" keeps {kept}"
        else:
            why = f"scene {scene.id!r} has {kept}"
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"{field} needs at least 2 input images to compare the ring with (FID), but {why}: set "
                            f"{field} false, or fit from more images")


def create_evaluation(*, session: Session, settings: Settings, queue: TaskQueue, key: ApiKey,
                      body: EvaluationCreate, idempotency_key: str | None) -> tuple[Job, bool]:
    """Record and queue an evaluation of succeeded edit jobs of one scene and reconstruction; (the job, whether this
    was a replay of an earlier request with the same Idempotency-Key)."""
    idem = None
    if idempotency_key:
        idem = Idempotency(idempotency_key, sha256_hex(body.model_dump_json(exclude_unset=True)), "evaluations")
        if (replayed := idem.replayed(session, key, Job)) is not None:
            return replayed, True
    try:
        check_source_text_length(body.object)
    except ValueError as exc:  # CLIP would refuse it in the worker, the evaluation accepted and its models loaded
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"object: {exc}") from None
    sources = [get_job(session=session, key=key, job_id=job_id) for job_id in body.job_ids]
    for source in sources:
        if source.mode == EVALUATE:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"job {source.id!r} is an evaluation, not an edit")
        if source.state != SUCCEEDED:
            raise HTTPException(status.HTTP_409_CONFLICT, f"job {source.id!r} is {source.state}: only succeeded "
                                                          "edit jobs can be evaluated")
    first = sources[0]
    if other := next((s for s in sources if s.scene_id != first.scene_id), None):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"the jobs belong to different scenes: job {other.id!r} edits scene {other.scene_id!r}, "
                            f"job {first.id!r} scene {first.scene_id!r}; an evaluation scores edits of one object")
    if other := next((s for s in sources if s.reconstruction_id != first.reconstruction_id), None):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            "the jobs edit different reconstructions of the scene (reconstruction parameters "
                            f"differ): job {other.id!r} edits reconstruction {other.reconstruction_id!r}, job "
                            f"{first.id!r} {first.reconstruction_id!r}")
    scene = session.get(Scene, first.scene_id)
    rec = None if first.reconstruction_id is None else session.get(Reconstruction, first.reconstruction_id)
    if scene is None or rec is None:  # deleted since the jobs were read (a reconstruction goes only with its scene)
        raise scene_deleted(sources)
    refuse_fid_input_of_one_image(body.params, scene, rec.params.get("max_images"), "params.fid_input", first.id)
    job = new_evaluation_job(key, settings, sources, body.object, body.params)
    return submit(session=session, settings=settings, queue=queue, key=key, job=job, idem=idem)


def create_sweep(*, session: Session, settings: Settings, queue: TaskQueue, key: ApiKey, body: SweepCreate,
                 idempotency_key: str | None) -> tuple[str, bool]:
    """Record every scene × protocol prompt edit with its evaluation, all or none, and send them; (the sweep's id,
    whether this was a replay of an earlier request with the same Idempotency-Key).

    A broker refusing part of it (503) withdraws the whole sweep: what was sent is canceled with the rest (a worker
    skips a canceled job, and one it already started stops at its next cancel check), so a retry, which the
    Idempotency-Key lets run anew, repeats none of it.
    """
    idem = None
    if idempotency_key:  # the record names the last job this request sends (add_jobs), whose batch_id is the sweep's
        idem = Idempotency(idempotency_key, sha256_hex(body.model_dump_json(exclude_unset=True)), "sweeps",
                           noun="sweep holding job")
        if (replayed := idem.replayed(session, key, Job)) is not None:
            return replayed.batch_id, True
    params = body.params.model_dump(mode="json")
    scenes = [usable_scene(session=session, key=key, scene_id=s.scene_id, params=params) for s in body.scenes]
    for scene in scenes:
        refuse_fid_input_of_one_image(body.evaluation, scene, body.params.max_images, "evaluation.fid_input")
    for index, entry in enumerate(body.scenes):  # as JobCreate will check each edit, before any row is made
        for edit in paper_protocol(entry.object):
            try:
                check_prompt_length(edit.prompt, body.params.view_words)
            except ValueError as exc:  # a long object name (it had been a 500 from JobCreate below)
                raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"scenes[{index}].object: {exc}") from None
    batch_id = new_id()  # every scene checked above, before any reconstruction row is made
    jobs: list[Job] = []
    for scene, entry in zip(scenes, body.scenes):
        rec = reconstruction_for(session=session, scene=scene, params=params)
        for edit in paper_protocol(entry.object):
            # Through JobCreate, so each edit is exactly what POST /v1/jobs would accept (a valid object
            # name whose prompts fit, checked above, gives valid ones: "wearing" / "a" besides the edit words).
            request = JobCreate(scene_id=scene.id, prompt=edit.prompt, mode=edit.mode,
                                edit_words=list(edit.edit_words), params=body.params)
            job = new_edit_job(request, key, settings, rec, batch_id)
            jobs += [job, new_evaluation_job(key, settings, [job], entry.object, body.evaluation, batch_id,
                                             index=len(jobs) // 2)]

    def withdraw(exc: QueueUnavailable) -> str:  # the sweep whole: what was sent canceled with the rest
        # Read, not counted from what this request sent: a scene still processing when the sweep was recorded has its
        # jobs sent by its ingest, which may have sent them meanwhile.
        sent = session.scalar(select(func.count()).select_from(Job)
                              .where(Job.batch_id == batch_id, Job.task_id.is_not(None)))
        request_cancel(session=session, job_ids=[j.id for j in jobs],
                       message="the sweep was withdrawn: the broker refused part of it")
        return (f"{exc}; the sweep is withdrawn: its {len(jobs)} jobs are canceled (the {sent} already sent too: any "
                f"a worker already started stops at its next cancel check; sweep {batch_id!r} lists them), so a retry "
                "repeats none of them")

    replayed = record_and_send(session=session, settings=settings, queue=queue, key=key, jobs=jobs, idem=idem,
                               withdraw=withdraw)
    if replayed is not None:
        return replayed.batch_id, True
    return batch_id, False


def sweep_jobs(*, session: Session, key: ApiKey, sweep_id: str) -> list[Job]:
    jobs = list(session.scalars(select(Job).where(Job.batch_id == sweep_id, Job.owner_key_id == key.id)))
    if not jobs:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"sweep {listed([sweep_id], width=ID_SHOWN)} not found")
    return jobs


def cancel_sweep(*, session: Session, key: ApiKey, sweep_id: str) -> None:
    """Cancel every unfinished job of the sweep (finished ones and their results stay)."""
    request_cancel(session=session, job_ids=[j.id for j in sweep_jobs(session=session, key=key, sweep_id=sweep_id)])
    session.expire_all()


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
