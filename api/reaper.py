"""The reaper: send again, or fail, jobs that nothing would ever finish, so no job stays "running" or "queued"
for ever and no accepted job is lost to a dead worker.

A job is orphaned when

* it is ``running``, its record has not changed for ``VOXE_JOB_STALE_TIMEOUT_S`` (a running
  stage writes progress twice a second), no run holds its lease (a live stage renews it), and
  either its worker has not written a heartbeat for as long (the worker is gone: killed, its
  machine lost), or the run holding it stopped renewing as long ago (it ended without recording
  how, e.g. the database was unreachable at that moment). Its remaining stages are sent again
  (``requeued`` on its timeline; they resume from their checkpoints); a job whose stage was
  interrupted (a run held it) ``VOXE_JOB_MAX_REQUEUES`` times fails with the reason instead, one
  between stages (its worker gone) is sent without counting. A job between stages on a live worker waits
  while its next message may be waiting its turn behind other jobs' (sending it again doubles its remaining
  stages): the worker whose broker refused that message says so at once (``worker.tasks``: the job is queued
  with no task id, below), and one whose next stage has not started for ``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S`` is
  sent again (a broker that lost what it had accepted; a copy that still comes is skipped or dropped). One
  whose user asked to cancel it ends canceled at once, between stages or once no run renews its hold (its worker
  died mid-stage, or the run stalled): no run would see the flag. A message the
  broker still delivers later (Redis redelivering hours later) finds the job done or ended
  (skipped), held by a live run (dropped), or waiting, and then runs it, the other copy being
  the one dropped (``worker.runtime.begin_stage``);
* or it is ``queued`` with no task id for as long on a scene that is not processing: the API (or the
  ingest that readied its scene) stopped between recording the job and handing its chain to the
  broker, so no message exists (a job on a processing scene waits for the scene's ingest to send
  it). Such a job is not failed but sent now (``requeued`` on its timeline): it was accepted, and
  nothing else will send it. A sweep's evaluation, which only its edit's chain sends, fails (unless that
  edit is itself still to be sent);
* or it is ``queued``, handed to the broker, and no stage has taken it for ``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S``:
  its message is taken as lost (a broker that lost what it had accepted, as between stages above) and its
  remaining stages are sent again (``requeued``); a copy that still comes is dropped or skipped. A sweep's
  evaluation waits while its edit's chain may still carry it: until its edit ended as long ago.

Each time a job's message was already taken as lost doubles the wait before it is again (from
``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S``): one waiting its turn behind a long backlog is sent again ever more rarely,
not each period. On the SQL broker, whose table lists the waiting messages, a job one of them carries is never
taken as lost, and none is while that table cannot be read (the rest of the pass goes on).

A broker that refuses a message fails nothing here: the job stays (or becomes) ``queued`` with no task
id (one whose message was taken as lost keeps its task id), its checkpoints kept, and a pass after the broker is
back sends it, as above.

A scene is orphaned when it is ``processing``, unchanged for as long, and no run holds its ingest (a live run
renews its lease), and either its ingest was never handed to the broker (it fails with the reason, the jobs waiting on
it with it), or the worker that took it has stopped heartbeating, or the run that took it stopped renewing as long
ago on a live worker: its ingest is sent again (a copy that still comes finds it held, and is dropped, or ready, and
is skipped: ``worker.ingest``), an accepted upload lost to no dead worker, unless the SQL broker's waiting messages
carry it (or cannot be read). A scene whose ingest was taken ``VOXE_JOB_MAX_REQUEUES`` + 1 times (each run that took it
was interrupted) fails instead, naming why, as a job does. A processing scene whose ingest waits in the broker for a
worker is not orphaned, as a queued job is not, until no worker took it for ``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S``: its
message is then taken as lost, as a job's is, and its ingest sent again (a copy that still comes finds the scene held,
or ready), the scene counting such re-sends, each doubling the wait before the next, as a job's do. Each re-send of
an ingest is claimed first (a conditional update of the row as read), so of several reapers reading it at once one
sends it.

Stored objects are orphaned when what lies under ``scenes/<id>/``, ``jobs/<id>/`` or ``reconstructions/<id>/`` (an
unfinished S3 multipart upload included) has no row and was last written ``VOXE_ORPHANED_UPLOAD_AGE_S`` ago: the API
process storing an upload was killed before it recorded the scene, or a delete's storage cleanup failed after its rows
went (:func:`reap_orphaned_uploads` deletes them), and so is a ``_probe/<uuid>`` object an older version's readiness
probe left (its delete failed) as old: only ``_probe/ready`` is written now. An unfinished write started as long ago
under a row that lives on, or in no ``<id>/`` folder, is abandoned (``Storage.discard_unfinished``).

An Idempotency-Key's record is deleted once ``VOXE_IDEMPOTENCY_RETENTION_S`` old (:func:`reap_idempotency_records`).

The API runs :func:`reap_orphaned_jobs` at startup and then every ``VOXE_REAPER_INTERVAL_S`` in a
background thread (:class:`Reaper`). Every update is conditional on the row still being what the
reaper saw, so several API processes may reap side by side and a worker that reports in at the
last moment wins.
"""

from __future__ import annotations

import logging
import threading
import time
from datetime import datetime, timedelta

from sqlalchemy import and_, delete, func, or_, select

from voxe_service.broker import waiting_tasks
from voxe_service.db import session_scope, sync_clock
from voxe_service.failing import FailingStreak
from voxe_service.jobs import finish_jobs
from voxe_service.models import (CANCELED, EVALUATE, FAILED, PROCESSING, QUEUED, RUNNING, IdempotencyRecord, Job,
                                 JobEvent, Reconstruction, Scene, WorkerHeartbeat, system_now, utcnow)
from voxe_service.queue import (QueueUnavailable, get_queue, is_sql_broker, requeue_interrupted, requeue_limit_error,
                                 send_ingest_again, send_queued_again)
from voxe_service.scenes import fail_scene
from voxe_service.settings import Settings
from voxe_service.storage import (JOBS_PREFIX, PROBE_KEY, PROBES_PREFIX, RECONSTRUCTIONS_PREFIX, SCENES_PREFIX,
                                  get_storage, job_key, scene_key)

log = logging.getLogger("voxe.reaper")

UPLOAD_SWEEP_INTERVAL_S = 3600.0
"""How often a reaper runs :func:`reap_orphaned_uploads` (it lists every stored object, too much for each pass) and
:func:`reap_idempotency_records` (a day's retention needs no finer grain than this)."""

LOST_MESSAGE_SETTING = "VOXE_JOB_LOST_MESSAGE_TIMEOUT_S"
"""Named in the reason of each re-send of a job whose message was taken as lost: what counts them."""


def _fail(session, job_id: str, seen_updated_at: datetime, seen_state: str, error: str, *where) -> bool:
    return bool(finish_jobs(session, [job_id], FAILED, error=error,
                            where=[Job.state == seen_state, Job.updated_at == seen_updated_at, *where]))


def _stale_window(settings: Settings, now: datetime | None):
    """(timeout, cutoff, the hostnames of workers heard from since the cutoff) for one pass."""
    timeout = settings.job_stale_timeout_s
    cutoff = (now or utcnow()) - timedelta(seconds=timeout)
    return timeout, cutoff, select(WorkerHeartbeat.hostname).where(WorkerHeartbeat.last_seen >= cutoff)


def reap_orphaned_jobs(settings: Settings, now: datetime | None = None) -> list[str]:
    """Send orphaned jobs again, or fail them with the reason (cancel those their users asked to cancel); returns
    the ids of those ended."""
    now = now or utcnow()
    timeout, cutoff, alive = _stale_window(settings, now)
    lost_cutoff = now - timedelta(seconds=settings.job_lost_message_timeout_s)
    reaped = []
    with session_scope() as session:
        lapsed = or_(Job.run_lease_until.is_(None), Job.run_lease_until < now)  # no live run renews a hold
        between_stages = Job.run_token.is_(None)  # no run holds it: its next message waits
        running = session.scalars(
            select(Job).where(
                Job.state == RUNNING, lapsed,
                or_(and_(Job.updated_at < cutoff,
                         or_(Job.worker_hostname.is_(None), Job.worker_hostname.not_in(alive),
                             Job.run_lease_until < cutoff)),  # (a run that ended without a word on a live worker)
                    and_(between_stages, Job.updated_at < lost_cutoff),  # its next message lost unseen
                    Job.cancel_requested),  # no run will see the cancel (none renews a hold): ended now
            )
        ).all()
        alive_now = set(session.scalars(alive)) if running else set()
        unstarted = _messages_taken_as_lost(session, settings, now, [  # (between stages on a live worker)
            job for job in running if job.run_token is None and not job.cancel_requested
            and job.worker_hostname in alive_now])
        for job in running:
            if job.run_token is None and job.cancel_requested:  # (a stage not done: its run gave the job back)
                done = job.stage in (job.completed_stages or [])
                reason = f"asked between stages, after {job.stage}" if done else f"asked during {job.stage}"
            elif job.cancel_requested and job.updated_at >= cutoff:  # its run died or stalled, lately
                reason = f"asked during {job.stage}"
            elif job.worker_hostname not in alive_now:
                reason = (f"worker {job.worker_hostname or '(unknown)'} stopped while the job was in {job.stage}: "
                          f"no heartbeat and no progress for {timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S)")
            elif job.run_token is None:
                if job.id not in unstarted:  # its next message waits its turn (or not as long as a lost one)
                    continue
                reason = (f"no stage started for {unstarted[job.id]:.0f} s after {job.stage} ({LOST_MESSAGE_SETTING}, "
                          "doubled for each earlier such re-send): sent again, its next message taken as lost")
            else:
                reason = (f"the run of {job.stage} on worker {job.worker_hostname} stopped renewing its hold "
                          f"{timeout:.0f} s ago and made no progress (VOXE_JOB_STALE_TIMEOUT_S)")
            try:
                outcome = requeue_interrupted(session, get_queue(), job, settings, reason=reason,
                                              where=[Job.updated_at == job.updated_at, lapsed])
            except QueueUnavailable:  # the broker refused: queued with no task id, a later pass sends it
                outcome = None  # (and its checkpoints are kept)
            if outcome in (FAILED, CANCELED):
                reaped.append(job.id)
        waiting_for_ingest = select(Scene.id).where(Scene.state == PROCESSING)
        never_sent = session.execute(
            select(Job.id, Job.mode, Job.batch_id, Job.source_job_ids, Job.updated_at).where(
                Job.state == QUEUED, Job.task_id.is_(None), Job.updated_at < cutoff,
                Job.scene_id.not_in(waiting_for_ingest))
        ).all()
        evaluations = [job for job in never_sent if job.mode == EVALUATE and job.batch_id is not None]
        never_sent_detail = (f"sent by the reaper: recorded but not handed to the broker for {timeout:.0f} s (the API "
                             "or the scene's ingest stopped in between, or the broker refused it)")
        for job in never_sent:
            if job not in evaluations:  # (an edit sent now takes its sweep's evaluations along)
                _send_now(session, job.id, job.updated_at, never_sent_detail)
        sent_long_ago = session.execute(select(Job.id, Job.mode, Job.source_job_ids, Job.task_id, Job.updated_at)
                                        .where(Job.state == QUEUED, Job.task_id.is_not(None),
                                               Job.updated_at < lost_cutoff)).all()
        lost = _messages_taken_as_lost(session, settings, now, sent_long_ago)
        for job in sent_long_ago:
            if job.id not in lost or job.mode == EVALUATE and session.scalar(select(Job.id).where(  # it rides in
                    Job.id.in_(job.source_job_ids or []),  # its edit's chain, sent on when the edit ended: lately,
                    or_(Job.finished_at.is_(None), Job.finished_at >= lost_cutoff)).limit(1)):  # or not yet
                continue
            lost_reason = (f"no stage started for {lost[job.id]:.0f} s after the job was sent ({LOST_MESSAGE_SETTING}, "
                           "doubled for each earlier such re-send): sent again, its message taken as lost")
            _send_now(session, job.id, job.updated_at, lost_reason, sent_as=job.task_id,
                      message=f"re-queued: {lost_reason}")
        unsent = set(session.scalars(select(Job.id).where(Job.state == QUEUED, Job.task_id.is_(None),
                                                          Job.mode != EVALUATE))) if evaluations else set()
        for job in evaluations:  # those still unsent: their edit's chain will never carry them ...
            if unsent & set(job.source_job_ids or []):
                continue  # ... unless an edit they score is still to be sent (the broker refused it)
            error = (f"the sweep's evaluation was never handed to the broker with its edit; failed after "
                     f"{timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S): create it again")
            if _fail(session, job.id, job.updated_at, QUEUED, error, Job.task_id.is_(None)):
                reaped.append(job.id)
    for job_id in reaped:
        log.warning("reaper: job %s ended as orphaned (failed, or canceled as asked)", job_id)
    return reaped


def _messages_taken_as_lost(session, settings: Settings, now: datetime, jobs) -> dict[str, float]:
    """Of ``jobs`` (rows with ``id`` and ``updated_at``: sent, no stage started since), those whose message is taken
    as lost, each with the wait that decided it: ``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S``, doubled for each time the job
    was already sent again so. A job waiting its turn behind a long backlog had been sent again each period, without
    end (a ``requeued`` event and a copy of its message each time); now ever more rarely. On the SQL broker, whose
    table lists the waiting messages, a job one of them carries is not lost at all; while that table cannot be read,
    none is (the rest of the pass goes on: :func:`_sql_broker_waiting`)."""
    if not jobs:
        return {}
    resent = dict(session.execute(select(JobEvent.job_id, func.count()).where(
        JobEvent.job_id.in_([job.id for job in jobs]), JobEvent.kind == "requeued",
        JobEvent.detail.contains(LOST_MESSAGE_SETTING)).group_by(JobEvent.job_id)).all())
    waiting = _sql_broker_waiting(settings.broker_url) if is_sql_broker(settings.broker_url) else set()
    if waiting is None:
        return {}
    lost = {}
    for job in jobs:
        wait = _lost_message_wait(settings, resent.get(job.id, 0))
        if job.id not in waiting and job.updated_at < now - timedelta(seconds=wait):
            lost[job.id] = wait
    return lost


def _lost_message_wait(settings: Settings, resends: int) -> float:
    """How long a message no worker took waits before it is taken as lost, once the job (or scene) was already sent
    again so ``resends`` times: ``VOXE_JOB_LOST_MESSAGE_TIMEOUT_S``, doubled for each."""
    return settings.job_lost_message_timeout_s * 2 ** min(resends, 20)


_broker_unreadable: set[str] = set()
"""The SQL brokers whose table of waiting messages the last try could not read (said once per outage)."""


def _sql_broker_waiting(broker_url: str) -> set[str] | None:
    """The ids of the jobs (and scenes) the SQL broker's waiting messages carry; None while its table cannot be read
    (its database unreachable, say), as a warning says once until it is read again: no message can be taken as lost
    then, and the reaper's other work (cancels, dead workers' jobs, jobs never sent) must not stop for it."""
    try:
        waiting = {job_id for _task, job_id in waiting_tasks(broker_url)}
    except Exception as exc:  # noqa: BLE001 - whatever the broker's database says, the pass goes on
        if broker_url not in _broker_unreadable:
            _broker_unreadable.add(broker_url)
            log.warning("reaper: the SQL broker's waiting messages cannot be read (%s: %s): no queued job's message "
                        "is taken as lost until they can", type(exc).__name__, exc)
        return None
    _broker_unreadable.discard(broker_url)
    return waiting


def _send_now(session, job_id: str, seen_updated_at: datetime, detail: str, sent_as: str | None = None,
              message: str | None = None) -> None:
    """Hand an accepted queued job's remaining stages to the broker, once (``send_queued_again``: several API
    processes may reap side by side); a broker that refuses leaves it as it was for a later pass. ``sent_as``: the
    task id of a message taken as lost (None: the job was never sent)."""
    try:
        sent = send_queued_again(session, get_queue(), job_id, sent_as=sent_as, reason=detail, message=message,
                                 where=[Job.updated_at == seen_updated_at])
    except QueueUnavailable:
        return
    if sent:
        log.warning("reaper: job %s %s", job_id, detail)


def reap_orphaned_scenes(settings: Settings, now: datetime | None = None) -> list[str]:
    """Send again the ingests of processing scenes whose worker died or whose message is taken as lost, or fail them
    (and those never sent) with the reason; returns the ids of those failed."""
    now = now or utcnow()
    timeout, cutoff, alive = _stale_window(settings, now)
    lost_cutoff = now - timedelta(seconds=settings.job_lost_message_timeout_s)
    reaped = []
    with session_scope() as session:
        stale = session.execute(select(
            Scene.id, Scene.task_id, Scene.worker_hostname, Scene.ingest_attempts, Scene.updated_at).where(
            Scene.state == PROCESSING, Scene.updated_at < cutoff,
            or_(Scene.ingest_lease_until.is_(None), Scene.ingest_lease_until < now),  # no live run renews a hold
            or_(Scene.task_id.is_(None),  # its worker gone (one no worker took waits, even while none is alive):
                and_(Scene.worker_hostname.is_not(None), Scene.worker_hostname.not_in(alive)),
                Scene.ingest_lease_until < cutoff))).all()  # (a run that ended without a word on a live worker)
        untaken = session.execute(select(  # its message taken as lost, as a job's (after its doubled wait, below)
            Scene.id, Scene.lost_ingest_resends, Scene.updated_at).where(
            Scene.state == PROCESSING, Scene.task_id.is_not(None), Scene.worker_hostname.is_(None),
            Scene.ingest_token.is_(None), Scene.updated_at < lost_cutoff)).all()
        alive_now = set(session.scalars(alive)) if stale else set()
        waiting = (_sql_broker_waiting(settings.broker_url) if (stale or untaken) and is_sql_broker(settings.broker_url)
                   else set())
        for scene in untaken:
            wait = _lost_message_wait(settings, scene.lost_ingest_resends)
            if scene.updated_at < now - timedelta(seconds=wait) and waiting is not None and scene.id not in waiting:
                _send_ingest_again(session, scene.id, scene.updated_at, f"no worker took its ingest for {wait:.0f} s "
                                   f"({LOST_MESSAGE_SETTING}, doubled for each earlier such re-send): its message "
                                   "taken as lost", lost=True)
        for scene in stale:
            if scene.task_id is None:
                reason = (f"the upload was never handed to a worker (the API stopped while storing it); failed after "
                          f"{timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S): upload it again")
            else:
                if scene.worker_hostname in alive_now:
                    why = (f"its run on worker {scene.worker_hostname} stopped renewing its hold {timeout:.0f} s ago "
                           "(VOXE_JOB_STALE_TIMEOUT_S)")
                else:
                    why = (f"worker {scene.worker_hostname} stopped while processing the upload: no heartbeat for "
                           f"{timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S)")
                # (each run that took it was interrupted: the runs, less the first, were re-sends)
                reason = requeue_limit_error(scene.ingest_attempts - 1, settings, f"ingest: interrupted "
                                             f"{scene.ingest_attempts} times, the last as {why}")
                if reason is None:
                    if waiting is not None and scene.id not in waiting:  # (its message waits: a worker takes it)
                        _send_ingest_again(session, scene.id, scene.updated_at, why)
                    continue
            if fail_scene(session, scene.id, reason, where=[Scene.updated_at == scene.updated_at]):
                reaped.append(scene.id)
    for scene_id in reaped:
        log.warning("reaper: scene %s failed as orphaned", scene_id)
    return reaped


def reap_idempotency_records(settings: Settings, now: datetime | None = None) -> int:
    """Delete the Idempotency-Key records created ``idempotency_retention_s`` ago; returns how many. A client sends a
    key with every upload, job, evaluation and sweep: kept for good, they had grown the table for good.

    A pending one goes too: a record is pending only while its request answers, so one pending that long is a dead
    request's (its job or scene the reaper has sent or failed since). One whose resource was deleted stays as long as
    the others: until then a retry is told that it was deleted ("use a new key"), not given a new one unasked."""
    cutoff = (now or utcnow()) - timedelta(seconds=settings.idempotency_retention_s)
    with session_scope() as session:
        deleted = session.execute(delete(IdempotencyRecord).where(IdempotencyRecord.created_at < cutoff)).rowcount
    if deleted:
        log.info("reaper: %d Idempotency-Key record(s) older than VOXE_IDEMPOTENCY_RETENTION_S deleted", deleted)
    return deleted


ORPHANS_SWEPT = ((SCENES_PREFIX, Scene, "scene"), (JOBS_PREFIX, Job, "job"),
                 (RECONSTRUCTIONS_PREFIX, Reconstruction, "reconstruction"))
"""The key layout's prefixes :func:`reap_orphaned_uploads` sweeps, each with the model whose row records an id."""


def reap_orphaned_uploads(settings: Settings, now: datetime | None = None) -> list[str]:
    """Delete what lies under a ``scenes/<id>/``, ``jobs/<id>/`` or ``reconstructions/<id>/`` prefix no row records,
    last written ``orphaned_upload_age_s`` ago (their unfinished S3 multipart uploads aborted: ``delete_prefix``);
    returns the prefixes deleted (one whose delete failed stays, logged, for the next sweep), then the keys of the
    older versions' readiness probe objects deleted as old (:func:`_reap_old_probes`). An unfinished write (an S3
    multipart upload, a local temporary file) started as long ago under a recorded row, or in no ``<id>/`` folder, is
    abandoned too (``discard_unfinished``), its key returned: a writer stopped mid-write under a job that lived on
    had left its parts, billed, until the job was deleted. An API process killed
    mid-store, or between storing and recording, or a delete whose storage cleanup failed after its rows went, had
    left them for good: every other cleanup starts from a row.

    An object lying directly under one of these folders (``jobs/notes.txt``, an S3 console's ``jobs/`` folder marker:
    in no ``<id>/`` folder, so not the service's) is left alone: it had been named an orphan, ``jobs/notes.txt/``,
    said deleted and kept, at every sweep."""
    storage = get_storage(settings)
    cutoff = (now or system_now()) - timedelta(seconds=settings.orphaned_upload_age_s)
    orphans = []
    for prefix, model, kind in ORPHANS_SWEPT:
        newest: dict[str, datetime] = {}
        for key, written in storage.written_at(prefix):  # (one time per row id kept, not the whole listing)
            row_id, in_a_folder, _name = key.removeprefix(prefix).partition("/")
            if not in_a_folder:
                continue
            newest[row_id] = max(written, newest.get(row_id, written))
        old = [row_id for row_id, written in newest.items() if written < cutoff]
        recorded = set()
        with session_scope() as session:
            for start in range(0, len(old), 500):
                recorded |= set(session.scalars(select(model.id).where(model.id.in_(old[start:start + 500]))))
        # (one whose delete failed is the cleanup's warning alone, and stays for the next sweep)
        deleted = storage.discard_prefixes(*[f"{prefix}{row_id}/" for row_id in old if row_id not in recorded])
        for orphan in deleted:
            log.warning("reaper: deleted the stored objects under %s, which no %s records (a process stopped between "
                        "storing and recording them, or their cleanup failed after a delete)", orphan, kind)
        orphans += deleted
        unfinished = storage.discard_unfinished(prefix, cutoff)  # (under a row that lives on, or in no <id>/ folder)
        if unfinished:
            log.warning("reaper: abandoned %d unfinished writes under %s started before %s (their writers were "
                        "stopped mid-write): %s", len(unfinished), prefix, f"{cutoff:%Y-%m-%d %H:%M:%S %Z}",
                        ", ".join(unfinished[:5]) + (", ..." if len(unfinished) > 5 else ""))
        orphans += unfinished
    return orphans + _reap_old_probes(storage, cutoff)


def _reap_old_probes(storage, cutoff: datetime) -> list[str]:
    """Delete the ``_probe/<uuid>`` objects of older versions' readiness probes (each probe wrote its own and deleted
    it; a failed delete left it for good) last written before ``cutoff``; the probe's own :data:`PROBE_KEY` stays.
    Returns those deleted; one whose delete failed is logged and stays for the next sweep."""
    deleted = []
    for key, written in storage.written_at(PROBES_PREFIX):
        if key == PROBE_KEY or written >= cutoff:  # (a young one: a probe of an older replica still running)
            continue
        try:
            storage.delete(key)
        except Exception:  # noqa: BLE001 - as discard_prefixes: the next sweep tries again
            log.warning("reaper: could not delete the old readiness probe's object %s", key, exc_info=True)
            continue
        deleted.append(key)
    if deleted:
        log.warning("reaper: deleted %d objects older versions' readiness probes left under %s", len(deleted),
                    PROBES_PREFIX)
    return deleted


def _send_ingest_again(session, scene_id: str, seen_updated_at: datetime, why: str, lost: bool = False) -> None:
    """``send_ingest_again`` (claimed: of several reapers reading the scene at once, one sends it), said in the log;
    a broker that refuses leaves the scene as it was read, for a later pass."""
    try:
        sent = send_ingest_again(session, get_queue(), scene_id, seen_updated_at, lost=lost)
    except QueueUnavailable:
        log.warning("reaper: scene %s: %s; the broker refused its ingest: a later pass sends it", scene_id, why)
        return
    if sent:
        log.warning("reaper: scene %s: %s; its ingest sent again", scene_id, why)


class Reaper:
    """Runs :func:`reap_orphaned_jobs` (and the other reaps) now and every ``reaper_interval_s`` until :meth:`stop`."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="voxe-reaper", daemon=True)
        self._uploads_swept_at: float | None = None  # (time.monotonic)

    def start(self) -> Reaper:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        """Pass after pass: the first of passes failing in a row (the database unreachable) logged with its
        traceback, the next ones a line each, and the recovery (a traceback every pass had filled the log while
        the database was down)."""
        streak = FailingStreak(log, "reaper", "pass", "passes")
        while not self._stop.is_set():
            sync_clock()  # the cut-offs below are read on the database's clock, as the workers write theirs
            try:
                scenes = reap_orphaned_scenes(self.settings)  # first: their waiting jobs fail with them
                prefixes = [scene_key(s) for s in scenes]
                prefixes += [job_key(j, "checkpoints/") for j in reap_orphaned_jobs(self.settings)]
                get_storage(self.settings).discard_prefixes(*prefixes)
                swept = self._uploads_swept_at
                if swept is None or time.monotonic() - swept >= UPLOAD_SWEEP_INTERVAL_S:
                    reap_idempotency_records(self.settings)
                    reap_orphaned_uploads(self.settings)  # last: a storage outage keeps the rest of the pass
                    self._uploads_swept_at = time.monotonic()
            except Exception as exc:  # noqa: BLE001 - a failed pass is retried on the next one
                interval = self.settings.reaper_interval_s  # (not backing off: a pass a minute is no flood)
                self._stop.wait(streak.failed_once_more(exc, interval, interval))
                continue
            streak.succeeded()
            self._stop.wait(self.settings.reaper_interval_s)
