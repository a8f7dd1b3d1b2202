"""Jobs: creation (the shared reconstruction, the key's quota, idempotency, the scene's state, the webhook
target), listing, cancel, webhook deliveries.

A job is recorded ``queued``; its stage chain goes to the broker at once when its scene is
ready, or later, from the scene's ingest, when the scene is still processing (it waits without
holding a worker). A failed scene refuses new jobs with a 409 naming its reason.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from fastapi import HTTPException, status
from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.auth import Idempotency, check_active_jobs, lock_live_key, sha256_hex
from api.http_semantics import ID_SHOWN, try_again_soon
from api.paging import PageQuery, PageRows, read_page
from api.schemas import JobCreate
from api.services.scenes import get_scene, refuse_unless_usable
from voxe_core.presets import check_fit, reconstruction_key, reconstruction_params
from voxe_service.datasets import MESH_FORMAT
from voxe_service import webhooks
from voxe_service.db import get_sessionmaker
from voxe_service.jobs import finish_jobs, record_event
from voxe_service.model_inventory import job_models, live_worker_models, unavailable_models
from voxe_service.models import (
    CANCELED, EVALUATE, FAILED, PROCESSING, QUEUED, READY, TERMINAL_STATES, ApiKey, Job, Reconstruction, Scene,
    WebhookDelivery, new_id, utcnow,
)
from voxe_service.queue import QueueUnavailable, TaskQueue, dispatch_job, evaluations_waiting_on
from voxe_service.scenes import lock_scene
from voxe_service.settings import Settings
from voxe_service.texts import listed

log = logging.getLogger("voxe.api")


def get_job(*, session: Session, key: ApiKey, job_id: str) -> Job:
    """The key's job, read anew (its row as it is now: a deleted one is gone); another key's job is as absent as a
    missing one."""
    job = session.get(Job, job_id, populate_existing=True)
    if job is None or job.owner_key_id != key.id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {listed([job_id], width=ID_SHOWN)} not found")
    return job


def check_route(scene: Scene, params: dict) -> None:
    """422 for ``reconstruction.route`` "voxelize" on a scene that has no mesh to voxelize."""
    route = (params.get("reconstruction") or {}).get("route", "auto")
    if route == "voxelize" and scene.format != MESH_FORMAT:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"reconstruction.route 'voxelize' needs a scene uploaded as a mesh; scene {scene.id!r} "
                            f"is {scene.format!r} images: use route 'fit' or 'auto'")


def usable_scene(*, session: Session, key: ApiKey, scene_id: str, params: dict) -> Scene:
    """The key's scene, if jobs with these parameters can run on it (404, 409 for a failed scene, 422)."""
    scene = get_scene(session=session, key=key, scene_id=scene_id)
    refuse_unless_usable(scene)
    check_route(scene, params)
    rec_params = reconstruction_params(params, mesh_scene=scene.format == MESH_FORMAT)
    refuse_unfit(scene, rec_params)
    refuse_downsample_past_images(scene, rec_params["downsample"])
    return scene


def refuse_downsample_past_images(scene: Scene, downsample: int) -> None:
    """422 for a ``downsample`` larger than the scene's images (known from its upload's checks, even while it is
    processing): the fit would fail in the worker, after the job was accepted."""
    if downsample > min(scene.width, scene.height):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"params.downsample {downsample} is larger than scene {scene.id!r}'s images "
                            f"({scene.width}x{scene.height}): at most {min(scene.width, scene.height)}")


def refuse_unfit(scene: Scene, rec_params: dict) -> None:
    """422 when the backbone the scene's ingest chose cannot take these reconstruction parameters, naming what
    ``auto`` became and why (a processing scene's jobs are checked once its ingest decides)."""
    try:
        check_fit(rec_params, scene.backbone, scene.image_count)
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"params.reconstruction: {exc}") from exc


def reconstruction_for(*, session: Session, scene: Scene, params: dict) -> Reconstruction:
    """The scene's reconstruction for these parameters, created if new.

    Race-free through the unique (scene_id, params_key) constraint: the row is inserted in
    its own short transaction, and a request that loses the race reads the winner's row.
    """
    rec_params = reconstruction_params(params, mesh_scene=scene.format == MESH_FORMAT)
    try:
        params_key = reconstruction_key(rec_params)
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"params.reconstruction: {exc}") from exc
    query = select(Reconstruction).where(Reconstruction.scene_id == scene.id, Reconstruction.params_key == params_key)
    rec = session.scalars(query).first()
    if rec is not None:
        return rec
    with get_sessionmaker()() as insert:
        try:
            insert.add(Reconstruction(id=new_id(), scene_id=scene.id, params_key=params_key, params=rec_params))
            insert.commit()
        except IntegrityError:  # another request created it first, or the scene was deleted meanwhile
            insert.rollback()
    if (rec := session.scalars(query).first()) is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene.id!r} was deleted while the job was created")
    return rec


def new_edit_job(body: JobCreate, key: ApiKey, settings: Settings, rec: Reconstruction,
                 batch_id: str | None = None) -> Job:
    """The queued record of an edit job (not yet added to a session)."""
    return Job(
        id=new_id(), scene_id=body.scene_id, owner_key_id=key.id, reconstruction_id=rec.id, prompt=body.prompt,
        mode=body.mode, edit_words=body.edit_words, params=body.params.model_dump(mode="json"),
        sds_model=settings.sds_model, attention_model=settings.attention_model, device=settings.device, state=QUEUED,
        batch_id=batch_id, webhook_url=body.webhook_url, webhook_events=body.webhook_events,
    )


def check_webhook(*, settings: Settings, body: JobCreate) -> None:
    """422 naming the rule for a webhook target the service will not call."""
    if body.webhook_url is None:
        return
    try:
        webhooks.check_target(body.webhook_url, settings.webhook_networks, settings.webhook_timeout_s)
    except webhooks.TargetRefused as exc:
        if exc.logged != str(exc):  # what the answer keeps from its key holder, the address refused: the operator's
            log.info("a job's webhook refused: %s", exc.logged)
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)) from None
    except webhooks.LookupSlotsBusy:  # other hosts' lookups stuck on their resolvers: had been a 422 "did not resolve"
        raise try_again_soon(
            f"the webhook_url host could not be looked up within {settings.webhook_timeout_s:g} s: every name lookup "
            f"({webhooks.LOOKUP_THREADS}) waits on a resolver that has not answered") from None


def refuse_without_models(*, session: Session, settings: Settings, jobs: list[Job]) -> None:
    """409 naming each model some job loads that every worker reporting on it lacks, and how to provide it."""
    inventories = live_worker_models(session, settings)
    messages = sorted({message for job in jobs for message in unavailable_models(
        job_models(job.mode, job.sds_model, job.attention_model, job.params or {}), inventories)})
    if messages:
        raise HTTPException(status.HTTP_409_CONFLICT, "; ".join(messages))


def add_jobs(*, session: Session, key: ApiKey, settings: Settings, jobs: list[Job],
             idempotency: Idempotency | None = None) -> list[Job]:
    """Record ``jobs`` within the key's quota of active jobs, all or none; the ones to send now.

    Jobs whose model no worker has are refused first (``refuse_without_models``). An ``idempotency`` record names
    the last job this request sends (``last_sent``), so a retry replays the batch only once all of that is with the
    broker.

    The scenes' states are read after the jobs' rows are written, under a lock on each scene's
    row, so an ingest finishing meanwhile either sees these jobs or is seen as done: jobs on a
    ready scene are returned to be sent (422 for one its backbone cannot take: its ingest may have
    decided since the submission looked), each edit told the scene's ``warnings`` (``told_warnings``; as its ingest told
    the jobs waiting for it), jobs on a processing one are left for its ingest, and a
    scene that failed meanwhile refuses them all (409).
    """
    refuse_without_models(session=session, settings=settings, jobs=jobs)
    try:
        lock_live_key(session, key)
        session.add_all(jobs)
        # Recorded before the quota is counted: a racing twin waits on the key's lock, then fails here and replays.
        record = idempotency.record(session, key, jobs[-1].id) if idempotency is not None else None
        try:
            session.flush()
        except IntegrityError:  # a racing Idempotency-Key twin (the caller replays it), or a scene deleted meanwhile
            session.rollback()
            scene_ids = {j.scene_id for j in jobs}
            if session.scalar(select(func.count()).select_from(Scene).where(Scene.id.in_(scene_ids))) < len(scene_ids):
                raise scene_deleted(jobs) from None
            raise
        check_active_jobs(session, key, settings, adding=len(jobs))
        states, warnings = {}, {}
        for scene_id in sorted({j.scene_id for j in jobs}):
            if (scene := lock_scene(session, scene_id)) is None:
                raise scene_deleted(jobs)
            refuse_unless_usable(scene)
            states[scene_id], warnings[scene_id] = scene.state, told_warnings(scene)
            for job in jobs:  # (its ingest may have decided since usable_scene read it processing)
                if job.scene_id == scene_id and job.mode != EVALUATE:
                    refuse_unfit(scene, job.reconstruction.params)
        for job in jobs:
            if states[job.scene_id] == PROCESSING:
                job.message = f"waiting for the scene {job.scene_id} to be processed (its upload is being decoded)"
            elif job.mode != EVALUATE:  # told what its ingest told the jobs waiting for it (worker.ingest._ready)
                for text in warnings[job.scene_id]:
                    record_event(session, job.id, "warning", stage="ingest", detail=text)
        # A sweep's evaluation is not sent on its own: its task follows its edit's chain.
        to_send = [j for j in jobs if states[j.scene_id] == READY and not (j.mode == EVALUATE and j.batch_id)]
        if record is not None:
            record.resource_id = last_sent(jobs, to_send).id
        session.commit()
    except BaseException:
        session.rollback()
        raise
    return to_send


def told_warnings(scene: Scene) -> list[str]:
    """What a job created on the ready ``scene`` is told of its ingest: its ``warnings``; for a mesh scene processed
    before they were kept (migration 0022: NULL), that they are not known. Its jobs had been told nothing, which reads
    as none, and one reusing a fit never reloads the mesh to say them."""
    if scene.warnings is None and scene.format == MESH_FORMAT:
        return [f"scene {scene.id} was processed before its warnings were kept: whether its mesh loads without "
                "something its files name (an OBJ's .mtl not sent, a PLY's TextureFile unread: the mesh loads grey) "
                "is not known; a fit by the voxelize route says it as it loads the mesh, a fit reused says nothing "
                "(upload the mesh again to be told)"]
    return scene.warnings or []


def last_sent(jobs: list[Job], to_send: list[Job]) -> Job:
    """The job an Idempotency record names: the last one this request sends (the evaluation riding in the last
    edit's chain), so a retry replays only once the broker has taken all it sends; the last job when it sends none.

    ``jobs[-1]`` had been named always: when its scene was still processing, that scene's ingest could send it while
    this request was still sending the others, and a retry replayed a sweep that a broker refusing one of them then
    withdrew.
    """
    if not to_send:
        return jobs[-1]
    last = to_send[-1]
    return [j for j in jobs if j is last or j.source_job_ids == [last.id]][-1]


def scene_deleted(jobs: list[Job]) -> HTTPException:
    """404 for ``jobs`` whose scene was deleted while they were being created."""
    scenes = ", ".join(repr(s) for s in sorted({j.scene_id for j in jobs}))
    return HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scenes} was deleted while the job was created")


def create_job(*, session: Session, settings: Settings, queue: TaskQueue, key: ApiKey, body: JobCreate,
               idempotency_key: str | None) -> tuple[Job, bool]:
    """Record and queue an edit job; (the job, whether this was a replay of an earlier request)."""
    idem = None
    if idempotency_key:
        # What the client sent, not the defaults filled in: a release adding a field or changing a default must
        # not turn a retry into "another request" (the whole body's digest, recorded before, still matches).
        idem = Idempotency(idempotency_key, sha256_hex(body.model_dump_json(exclude_unset=True)), "jobs",
                           earlier_sha256=sha256_hex(body.model_dump_json()))
        if (replayed := idem.replayed(session, key, Job)) is not None:
            return replayed, True
    params = body.params.model_dump(mode="json")
    scene = usable_scene(session=session, key=key, scene_id=body.scene_id, params=params)
    check_webhook(settings=settings, body=body)
    job = new_edit_job(body, key, settings, reconstruction_for(session=session, scene=scene, params=params))
    if job.webhook_url:  # after reconstruction_for: its own transaction must not wait on this one's write
        webhooks.key_secret(session, key)  # committed with the job
    return submit(session=session, settings=settings, queue=queue, key=key, job=job, idem=idem)


def submit(*, session: Session, settings: Settings, queue: TaskQueue, key: ApiKey, job: Job,
           idem: Idempotency | None) -> tuple[Job, bool]:
    """Record ``job`` and hand it to the broker; (the job, whether a concurrent retry with the same Idempotency-Key
    created it first). A broker refusing it (503) withdraws it: nothing is listed, and a retry with the key runs
    anew."""
    job_id = job.id

    def withdraw(exc: QueueUnavailable) -> str:  # the job was never accepted (no failed event): nothing listed
        session.execute(delete(Job).where(Job.id == job_id))
        return str(exc)

    replayed = record_and_send(session=session, settings=settings, queue=queue, key=key, jobs=[job], idem=idem,
                               withdraw=withdraw)
    if replayed is not None:
        return replayed, True
    return created_job(session, job_id), False


def record_and_send(*, session: Session, settings: Settings, queue: TaskQueue, key: ApiKey, jobs: list[Job],
                    idem: Idempotency | None, withdraw: Callable[[QueueUnavailable], str]) -> Job | None:
    """Record ``jobs`` (:func:`add_jobs`) and hand the ones it sends now to the broker, each chain with the
    evaluations following it; the job an earlier request with the same Idempotency-Key recorded when a concurrent
    retry created them first (nothing recorded here), else None.

    A broker refusing a send is a 503 saying what ``withdraw(exc)`` did to take the jobs back (in the transaction
    that forgets the Idempotency record, so a retry with the key runs anew); only once every send is taken may a
    retry replay the request (:meth:`Idempotency.answered`).
    """
    try:
        to_send = add_jobs(session=session, key=key, settings=settings, jobs=jobs, idempotency=idem)
    except IntegrityError:
        if idem is not None and (replayed := idem.replayed(session, key, Job)) is not None:
            return replayed  # a concurrent retry created them first
        raise
    try:
        for queued in to_send:
            dispatch_job(session, queue, queued, fail_refused=False)
    except QueueUnavailable as exc:
        if idem is not None:
            idem.forget(session, key)
        said = withdraw(exc)
        session.commit()
        raise try_again_soon(said) from None
    if idem is not None:
        idem.answered(session, key)
        session.commit()
    return None


def created_job(session: Session, job_id: str) -> Job:
    """The job a request created, read anew once sent; 409 when it is gone: listed as soon as it is recorded, it can
    be canceled and its scene deleted while the broker takes it (reading it again had raised, a 500)."""
    if (job := session.get(Job, job_id, populate_existing=True)) is None:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id!r} was canceled and deleted with its scene "
                                                      "before its creation answered")
    return job


def list_jobs(*, session: Session, key: ApiKey, state: str | None, scene_id: str | None,
              page: PageQuery) -> PageRows:
    """A page of the key's jobs, newest first, and how many match."""
    filters = [Job.owner_key_id == key.id]
    if state is not None:
        filters.append(Job.state == state)
    if scene_id is not None:
        filters.append(Job.scene_id == scene_id)
    return read_page(session, "/v1/jobs", Job, filters, page)


def cancel_job(*, session: Session, key: ApiKey, job_id: str) -> Job:
    """Cancel the key's job (409 once it succeeded or failed); canceling a canceled job changes nothing."""
    get_job(session=session, key=key, job_id=job_id)
    request_cancel(session=session, job_ids=[job_id])  # flags only an unfinished job
    job = get_job(session=session, key=key, job_id=job_id)  # (a 404 if deleted with its scene meanwhile)
    if job.state in TERMINAL_STATES and job.state != CANCELED:  # (also one that ended as the request came)
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id!r} already {job.state}")
    return job


def request_cancel(*, session: Session, job_ids: list[str], message: str = "canceled while queued") -> None:
    """Flag the unfinished ``job_ids`` canceled: queued ones at once (with ``message``), running ones when their task
    next checks.

    A sweep's evaluations waiting on an edit canceled while queued fail with it, as its chain's evaluate stage would
    fail them: one whose edit waited for its scene's ingest had stayed queued, never sent, holding a quota slot and
    its scene, until the reaper failed it as never handed to the broker.
    """
    session.execute(update(Job).where(Job.id.in_(job_ids), Job.state.not_in(TERMINAL_STATES))
                    .values(cancel_requested=True, updated_at=utcnow()))
    # (a job the reaper re-queued from a stage its dead worker had begun: that stage's outputs are withdrawn)
    canceled = finish_jobs(session, job_ids, CANCELED, message=message, where=[Job.state == QUEUED])
    for job in session.scalars(select(Job).where(Job.id.in_(canceled))).all():
        finish_jobs(session, evaluations_waiting_on(session, job), FAILED,  # (its message names a revoke)
                    error=f"evaluate: source job {job.id} {CANCELED}: {job.message}")
    session.commit()


def list_webhooks(*, session: Session, key: ApiKey, job_id: str) -> list[WebhookDelivery]:
    """The job's webhook deliveries in the order of their events."""
    get_job(session=session, key=key, job_id=job_id)
    return list(session.scalars(select(WebhookDelivery).where(WebhookDelivery.job_id == job_id)
                                .order_by(WebhookDelivery.event_id)))


def webhook_secret(*, session: Session, key: ApiKey) -> str:
    """The key's webhook signing secret (made on first request)."""
    secret = webhooks.key_secret(session, key)
    session.commit()
    return secret


def rotate_webhook_secret(*, session: Session, key: ApiKey) -> str:
    """A new webhook signing secret for the key, the old one signing nothing from now on."""
    secret = webhooks.rotate_secret(session, key)
    session.commit()
    return secret
