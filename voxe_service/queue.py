"""The queue contract between the API and the workers: queues, task names and messages, the stage chain,
a Celery app factory and the sender.

Every task message carries one positional argument, an id (:class:`TaskSpec`); everything
else a task needs is in the database and the storage, so a message can be redelivered or
re-sent at any time. The API only *sends* by name (:class:`TaskQueue`); the worker builds
its own app with the same factory and registers the tasks (``worker/celery_app.py``).
Importing this module builds nothing: apps come from :func:`create_celery_app`.

Long GPU tasks: late acks, one prefetched message, a rejected (redelivered) message when
the worker process dies, and a broker visibility timeout above the hard time limit so
Redis never redelivers a task that is still running.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, TypedDict

from sqlalchemy import case, select, update
from sqlalchemy.orm import Session

from voxe_service.jobs import finish_jobs, record_event
from voxe_service.models import CANCELED, EVALUATE, FAILED, PROCESSING, QUEUED, RUNNING, Job, Scene, utcnow
from voxe_service.settings import Settings, get_settings

if TYPE_CHECKING:
    from datetime import datetime

    from celery import Celery
    from celery.canvas import Signature

log = logging.getLogger("voxe.queue")

GPU_QUEUE = "gpu"  # every voxe task: one per GPU worker at a time
DEFAULT_QUEUE = "celery"
STAGES = ("reconstruct", "edit", "refine", "export", "evaluate")


@dataclass(frozen=True)
class TaskSpec:
    """A task of the contract: its Celery name, its queue and the id its one positional argument is."""

    name: str
    argument: str
    queue: str = GPU_QUEUE


STAGE_TASKS = {stage: TaskSpec(f"voxe.{stage}", "job_id") for stage in STAGES}
INGEST_TASK = TaskSpec("voxe.ingest", "scene_id")  # decode (and for a mesh, render) an upload
TASK_NAMES = {stage: spec.name for stage, spec in STAGE_TASKS.items()}


class TaskResult(TypedDict, total=False):
    """What a task returns (logged by Celery; the service keeps no results: the database has the state)."""

    job_id: str
    scene_id: str
    stage: str
    state: str  # "done", "failed", "canceled", "ready"
    skipped: str  # why nothing ran (a redelivered or stale message)


QUEUE_UNAVAILABLE = "the job queue is unavailable"
"""What a user reads of a broker that refused a message: its own text (SQL of the embedded broker, a Redis address)
goes to the log only."""


class QueueUnavailable(RuntimeError):
    """The broker refused a message; the jobs (or the scene) it was for have been failed with the reason, unless
    the sender keeps them to send again (:func:`dispatch_job`'s ``fail_refused``)."""


def job_stages(mode: str) -> list[str]:
    if mode == EVALUATE:  # an evaluation job (SPEC §4) has one stage
        return ["evaluate"]
    return ["reconstruct", "edit"] + (["refine"] if mode == "local" else []) + ["export"]


def is_sql_broker(url: str) -> bool:
    return url.split("://", 1)[0].split("+", 1)[0] in ("sqla", "sqlalchemy")


def broker_transport_options(settings: Settings) -> dict:
    if is_sql_broker(settings.broker_url):
        return {"polling_interval": settings.broker_polling_interval}  # SQLite: WAL and timeouts in voxe_service.broker
    # Redis / SQS: a message not acked within this many seconds is redelivered.
    if settings.broker_visibility_timeout_s <= settings.task_time_limit_s:
        log.warning("VOXE_BROKER_VISIBILITY_TIMEOUT_S (%d s) is not above VOXE_TASK_TIME_LIMIT_S (%d s): the "
                    "broker sends a stage that runs longer to a second worker, which waits for the first run's next "
                    "renewal of its hold on the job, then drops it",
                    settings.broker_visibility_timeout_s, settings.task_time_limit_s)
    return {"visibility_timeout": settings.broker_visibility_timeout_s,
            "socket_timeout": settings.broker_socket_timeout_s,
            "socket_connect_timeout": settings.broker_socket_timeout_s}


def create_celery_app(settings: Settings | None = None, include: Sequence[str] = ()) -> Celery:
    """A Celery app on the settings' broker; ``include``: task modules a worker imports (none for a sender)."""
    from celery import Celery
    from kombu import Queue

    from voxe_service.broker import register as register_sql_transport
    from voxe_service.db import ensure_sqlite_dir

    settings = settings or get_settings()
    register_sql_transport()
    if is_sql_broker(settings.broker_url) and "+sqlite" in settings.broker_url:
        ensure_sqlite_dir(settings.broker_url.split("+", 1)[1])
    app = Celery("voxe", broker=settings.broker_url, include=list(include))
    app.conf.update(
        task_serializer="json",
        accept_content=["json"],
        result_backend=None,
        task_ignore_result=True,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        worker_max_tasks_per_child=settings.worker_max_tasks_per_child,
        task_soft_time_limit=settings.task_soft_time_limit_s,
        task_time_limit=settings.task_time_limit_s,
        broker_transport_options=broker_transport_options(settings),
        broker_connection_retry_on_startup=True,
        task_default_queue=DEFAULT_QUEUE,
        task_queues=(Queue(GPU_QUEUE), Queue(DEFAULT_QUEUE)),
        task_routes={"voxe.*": {"queue": GPU_QUEUE}},
        worker_send_task_events=False,
        task_track_started=False,
        worker_hijack_root_logger=False,
    )
    return app


class TaskQueue:
    """Sends the contract's messages by task name: the sender needs none of the task code."""

    def __init__(self, app: Celery):
        self.app = app

    def stage_chain(self, job_id: str, mode: str, done: Iterable[str] = (), then_evaluate: Iterable[str] = ()):
        """The Celery chain of a job's stages not in ``done``.

        ``then_evaluate``: evaluation jobs whose task follows the last stage (a sweep scores each
        edit once it is done; a failed or canceled edit still lets the evaluation record why).
        """
        from celery import chain

        done = set(done)
        stages = [s for s in job_stages(mode) if s not in done]
        return chain(*(self._message(STAGE_TASKS[s], job_id) for s in stages),
                     *(self._message(STAGE_TASKS["evaluate"], e) for e in then_evaluate))

    def send(self, signature) -> str | None:
        """Hand a signature or chain to the broker; its task id."""
        return getattr(signature.apply_async(), "id", None)

    def send_ingest(self, scene_id: str) -> str | None:
        return self.send(self._message(INGEST_TASK, scene_id))

    def _message(self, spec: TaskSpec, object_id: str) -> Signature:
        return self.app.signature(spec.name, args=(object_id,), immutable=True, queue=spec.queue)


@lru_cache
def get_queue() -> TaskQueue:
    """The process's sender, on the broker of the settings (``reset_queue`` forgets it)."""
    return TaskQueue(create_celery_app())


def reset_queue() -> None:
    get_queue.cache_clear()


# ------------------------------------------------------------------ dispatch
def evaluations_waiting_on(session: Session, job: Job) -> list[str]:
    """Queued evaluation jobs of ``job``'s sweep that score it (their task follows its chain)."""
    if job.batch_id is None or job.mode == EVALUATE:
        return []
    waiting = session.scalars(select(Job).where(Job.batch_id == job.batch_id, Job.mode == EVALUATE,
                                                Job.state == QUEUED))
    return [e.id for e in waiting if job.id in (e.source_job_ids or [])]


def dispatch_job(session: Session, queue: TaskQueue, job: Job, done: Iterable[str] = (),
                 message: str | None = None, fail_refused: bool = True, requeued: str | None = None) -> None:
    """Send the job's remaining stages (and the evaluations waiting on it), recording the task id on each, and
    ``message`` on the job; with ``requeued``, a ``requeued`` event of that detail on its timeline in the same
    commit, so that a send the broker refused is never on it (:func:`send_queued_again`), unless the job is no longer
    queued (canceled while the broker took it: its end stays its timeline's last event; or started by the message
    taken as lost: the new one is a copy its stages drop).

    When the broker refuses, :class:`QueueUnavailable` is raised, the jobs failed with the reason first unless
    ``fail_refused`` is off (a caller withdrawing a job it has just created: no failed event, no webhook; or
    one leaving an accepted job queued with no task id, for the reaper to send once the broker is back).
    """
    ids = [job.id, *evaluations_waiting_on(session, job)]
    try:
        task_id = queue.send(queue.stage_chain(job.id, job.mode, done, ids[1:]))
    except Exception:  # noqa: BLE001 - broker down: the jobs cannot run
        log.exception("could not queue job(s) %s", ids)  # the broker's own words: the log's, not the user's
        reason = f"could not queue the job: {QUEUE_UNAVAILABLE}"
        if fail_refused:
            finish_jobs(session, ids, FAILED, error=reason)
            session.commit()
        raise QueueUnavailable(reason) from None
    # One UPDATE per row: PostgreSQL re-checks the foreign keys of a row updated twice in one transaction. The
    # message changes: updated_at tells the event streams to read it (they had kept "waiting for the scene ...").
    # A job ended while the broker took it (canceled as it was created, a waiting evaluation failed with it) keeps
    # the message of its end: it had been overwritten.
    now = utcnow()
    state = session.execute(update(Job).where(Job.id == job.id).values(
        task_id=task_id, message=case((Job.state == job.state, message), else_=Job.message), updated_at=now)
        .returning(Job.state)).scalar_one_or_none()
    if ids[1:]:
        session.execute(update(Job).where(Job.id.in_(ids[1:])).values(
            task_id=task_id, message=case((Job.state == QUEUED, None), else_=Job.message), updated_at=now))
    if requeued is not None and state == QUEUED:  # (a canceled one's timeline had gone on past its end)
        record_event(session, job.id, "requeued", stage=job.stage, detail=requeued)
    session.commit()


def send_queued_again(session: Session, queue: TaskQueue, job_id: str, *, sent_as: str | None, reason: str,
                      message: str | None = None, where: Iterable = ()) -> bool:
    """Hand a queued job's remaining stages (and the evaluations waiting on it) to the broker again, once: claimed by
    a conditional update (its task id still ``sent_as``, that of a message taken as lost, or None for a job never
    sent; and ``where``, what the caller saw: several senders may run side by side), then sent with ``message``,
    ``requeued`` going on its timeline with ``reason`` as the broker takes it. Returns False, nothing done, when the
    row changed since it was read.

    A broker that refuses raises :class:`QueueUnavailable`, nothing on the timeline (a refused re-send counted as one
    had doubled the reaper's next wait: ``api.reaper``), the job given its task id ``sent_as`` and its time back
    (the reaper's next pass tries again) unless another sender changed it meanwhile: left as it was, for a later try (with no task id, a sweep's evaluation would be
    failed by the reaper as never sent with its edit). A sender that stops after the broker took the chain, before
    recording it, leaves the job with no task id, which the reaper sends again. A job canceled (or deleted) just
    after the claim is not sent: False."""
    claimed_at = utcnow()
    seen_at = session.scalar(select(Job.updated_at).where(Job.id == job_id))
    claimed = session.execute(update(Job).where(  # task_id NULL until the new chain is handed over
        Job.id == job_id, Job.state == QUEUED, Job.task_id.is_(None) if sent_as is None else Job.task_id == sent_as,
        Job.updated_at == seen_at, *where).values(task_id=None, updated_at=claimed_at))
    if claimed.rowcount != 1:
        return False
    session.commit()
    job = session.get(Job, job_id, populate_existing=True)
    if job is None or job.state != QUEUED:  # canceled or deleted since the claim: its ending stands, nothing sent
        return False
    try:
        dispatch_job(session, queue, job, done=job.completed_stages or [], message=message, fail_refused=False,
                     requeued=reason)
    except QueueUnavailable:  # as it was (its time too, so the next pass tries again, as a scene's ingest is)
        session.execute(update(Job).where(Job.id == job_id, Job.task_id.is_(None), Job.updated_at == claimed_at)
                        .values(task_id=sent_as, updated_at=seen_at))
        session.commit()
        raise
    return True


def send_ingest_again(session: Session, queue: TaskQueue, scene_id: str, seen_updated_at: datetime, *,
                      lost: bool = False) -> bool:
    """Hand the ingest of a processing scene to the broker again, once, recorded as waiting for a worker (no worker,
    no hold); ``lost``: its message taken as lost (the reaper's timeout, or a starting worker's SQL broker holding
    none), counted in ``Scene.lost_ingest_resends``, which doubles the reaper's wait before the next. Claimed first,
    by a conditional update of the row as it was read (``seen_updated_at``): of several senders reading it at once
    (API processes reaping, workers starting), each had sent a copy; now one does. Returns False, nothing sent, when
    the row changed since it was read (a worker took it, another sender claimed it); a worker taking it after the
    claim keeps it (the message finds it held or ready), nothing recorded. A sender stopping between claim and send
    leaves it as it was but for the time, for a later try; a broker that refuses raises :class:`QueueUnavailable`,
    the scene given back as read."""
    claimed_at = utcnow()
    claimed = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING,
                                                  Scene.updated_at == seen_updated_at).values(updated_at=claimed_at))
    session.commit()
    if claimed.rowcount != 1:
        return False
    try:
        task_id = queue.send_ingest(scene_id)
    except Exception:  # noqa: BLE001 - the broker refused: a later try sends it
        log.exception("could not send the ingest of scene %s again", scene_id)  # the broker's words: the log's
        session.execute(update(Scene).where(Scene.id == scene_id, Scene.updated_at == claimed_at)
                        .values(updated_at=seen_updated_at))
        session.commit()
        raise QueueUnavailable(f"could not send the ingest again: {QUEUE_UNAVAILABLE}") from None
    counted = {"lost_ingest_resends": Scene.lost_ingest_resends + 1} if lost else {}
    sent = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING,
                                               Scene.updated_at == claimed_at).values(
        task_id=task_id, worker_hostname=None, ingest_token=None, ingest_lease_until=None, updated_at=utcnow(),
        **counted))
    session.commit()
    return sent.rowcount == 1


def requeue_limit_error(requeues: int, settings: Settings, reason: str) -> str | None:
    """Why a job (or a scene's ingest) interrupted again (``reason``) fails, once it was sent again ``requeues`` times
    already, the ``job_max_requeues`` limit (what kills its workers must not loop); None below the limit."""
    if requeues < settings.job_max_requeues:
        return None
    return (f"{reason}; it was sent again {requeues} time(s) already, the limit "
            f"(VOXE_JOB_MAX_REQUEUES={settings.job_max_requeues})")


def storage_outage_limit_error(outages: int, settings: Settings, reason: str) -> str | None:
    """Why a job (or a scene's ingest) a storage outage stopped again (``reason``) fails, once outages had stopped it
    ``outages`` times already, the ``storage_outage_max_retries`` bound (a storage object that answers 5xx every time
    must not be retried for ever); None below the bound."""
    if outages < settings.storage_outage_max_retries:
        return None
    times = "once" if outages == 0 else f"{outages + 1} times"
    retries = {0: "no retry", 1: "1 retry"}.get(outages, f"{outages} retries")
    return (f"{reason}; storage outages stopped it {times} ({retries}, the limit: "
            f"VOXE_STORAGE_OUTAGE_MAX_RETRIES={settings.storage_outage_max_retries})")


def send_evaluations_alone(session: Session, queue: TaskQueue, job: Job, message: str | None) -> None:
    """Send the sweep's evaluations that rode in an ended job's chain alone (no stage of it is left), to record why;
    the job keeps ``message``. Raises :class:`QueueUnavailable`, the evaluations failed with the reason, when the
    broker refuses them (they have no chain left to wait in); the job's ending stands."""
    if evaluations_waiting_on(session, job):
        dispatch_job(session, queue, job, done=job_stages(job.mode), message=message)


def requeue_interrupted(session: Session, queue: TaskQueue, job: Job, settings: Settings, *, reason: str,
                        where: Iterable = ()) -> str | None:
    """Send a running job's remaining stages again after its worker stopped: the job is queued again, waiting
    for a worker like any sent job (the reaper leaves those alone until their message is taken as lost), the hold
    of an interrupted run is released, so the new message takes the job at once, and ``requeued`` goes on its
    timeline.

    A job whose stage was interrupted (a run held it) ``job_max_requeues`` times already fails instead: a job
    that kills its workers must not loop; the evaluations that ride in its chain are sent alone, to record why.
    A job between stages (its next message waited, or was lost with the worker) is sent without counting.
    A job its user asked to cancel ends canceled instead (it had been sent again, or failed at the limit).
    ``where``: what the caller saw of the row. Returns "requeued", "failed", "canceled", or None when the row
    changed since it was read (nothing done). A broker that refuses the job's chain raises :class:`QueueUnavailable`
    and leaves the job queued with no task id, which the reaper sends later, as it does a job the API recorded
    and never sent (a broker outage must not fail accepted jobs, nor lose their checkpoints); the evaluations
    sent alone after an ending fail with the reason (they have no chain to wait in), the ending standing.
    """
    def end(state: str, **fields) -> str | None:
        """End the job in ``state``; the evaluations riding in its chain are sent alone (no stage left), to record
        why (the job's message kept). Canceled, the outputs its interrupted stage published are withdrawn."""
        ended = finish_jobs(session, [job.id], state, where=[Job.state == RUNNING, *where], settings=settings,
                            **fields)
        session.commit()
        if ended:
            try:  # the message it ended with: finish_jobs' (which names a revoked key's), not the one asked for
                send_evaluations_alone(session, queue, job, session.scalar(select(Job.message)
                                                                           .where(Job.id == job.id)))
            except QueueUnavailable:  # they failed with the reason; the job's ending stands
                pass
        return state if ended else None

    if job.cancel_requested:
        return end(CANCELED, message=f"canceled: {reason}")
    interrupted = job.run_token is not None
    if interrupted and (error := requeue_limit_error(job.requeues, settings, reason)):
        return end(FAILED, error=error)
    # task_id NULL until the new chain is handed over: a sender that dies in between leaves a job the reaper sends
    released = session.execute(update(Job).where(Job.id == job.id, Job.state == RUNNING, *where).values(
        state=QUEUED, task_id=None, run_token=None, run_lease_until=None, message=f"re-queued: {reason}",
        requeues=Job.requeues + (1 if interrupted else 0), updated_at=utcnow()))
    if released.rowcount != 1:
        return None
    record_event(session, job.id, "requeued", stage=job.stage, worker=job.worker_hostname, detail=reason)
    session.commit()
    dispatch_job(session, queue, job, done=job.completed_stages or [], message=f"re-queued: {reason}",
                 fail_refused=False)
    return "requeued"
