"""What the tasks share: job-record updates, throttled progress, cancellation, storage I/O, model cache.

Nothing here knows the method; it moves data between the database, the storage
and ``voxe_core`` calls, so the tasks in :mod:`worker.tasks` stay a few lines each.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import math
import os
import shutil
import tempfile
import threading
import time
import uuid
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

from sqlalchemy import Update, case, func, or_, select, update
from sqlalchemy.exc import SQLAlchemyError

from voxe_core.progress import Callbacks, Progress, StageCancelled
from voxe_service import datasets
from voxe_service.db import DATABASE_UNAVAILABLE, database_outage, locked, session_scope, sync_clock
from voxe_service.jobs import finish_jobs, record_event
from voxe_service.models import (
    CANCELED, EVALUATE, FAILED, PROCESSING, QUEUED, R_FAILED, R_PENDING, R_RUNNING, R_SUCCEEDED, READY, RUNNING,
    SUCCEEDED, TERMINAL_STATES, Artifact, Job, JobEvent, Reconstruction, Scene, utcnow,
)
from voxe_service.queue import requeue_limit_error, storage_outage_limit_error
from voxe_service.settings import TINY_MODEL, Settings
from voxe_service.storage import (ObjectNotFound, Storage, StorageError, StorageUnavailable, StoredObject, file_sha256,
                                  get_storage, job_key)

log = logging.getLogger("voxe.worker")

CONTENT_TYPES = {  # (no PLY type is registered: model/ply is the one model/obj's family and 3D viewers use)
    ".safetensors": "application/octet-stream",
    ".png": "image/png",
    ".mp4": "video/mp4",
    ".gif": "image/gif",
    ".ply": "model/ply",
    ".glb": "model/gltf-binary",
    ".obj": "model/obj",
    ".mtl": "model/mtl",
    ".json": "application/json",
    ".md": "text/markdown; charset=utf-8",
}


class JobSkipped(Exception):
    """The job is no longer runnable (canceled, failed, deleted): the task ends quietly."""


def content_type(name: str) -> str:
    return CONTENT_TYPES.get(Path(name).suffix.lower(), "application/octet-stream")


def failure_text(exc: BaseException, say_the_worker: bool = True) -> str:
    """``exc`` as a job's or a scene's failure says it: ``Type: words``, or the type alone when it has no words; a
    failed allocation as the worker out of memory, in the first line of its words (Python's MemoryError has none,
    and had read "MemoryError: "; CUDA's adds a paragraph of allocator advice). Said to the job's or scene's owner,
    it names nothing of the worker's (its log does): an OSError not the files on its disk it names, a database
    error only the first line of the driver's words (SQLAlchemy adds the statement and its parameters, PostgreSQL
    quotes the statement). Such an OSError, the worker's environment (its scratch), says the fault is the worker's
    (unless ``say_the_worker`` is False: its caller says so): its bare errno had read as the owner's doing."""
    from voxe_core.guidance.loading import is_out_of_memory

    words = str(exc)
    if isinstance(exc, OSError) and exc.strerror and (exc.filename is not None or exc.filename2 is not None):
        words = f"[Errno {exc.errno}] {exc.strerror}" if exc.errno is not None else exc.strerror
        if say_the_worker:
            words += " on the worker (see its log)"
    elif isinstance(exc, SQLAlchemyError) and getattr(exc, "orig", None) is not None:
        words = str(exc.orig).strip().partition("\n")[0]  # (PostgreSQL's next lines quote the statement)
    if is_out_of_memory(exc):  # (PyTorch's advice follows "... is free." on the same line)
        said = words.splitlines()[0].split(" If reserved but unallocated")[0] if words else type(exc).__name__
        return f"out of memory on the worker ({said})"
    return f"{type(exc).__name__}: {words}" if words else type(exc).__name__


# --------------------------------------------------------------------------- job records
def load_job(job_id: str) -> Job | None:
    with session_scope() as session:
        return session.get(Job, job_id)


def update_job(job_id: str, *, held_by: str | None = None, **values) -> None:
    """Write ``values`` on the job; with ``held_by`` (a run's token) only while that run still holds it: a stalled
    run's progress must not overwrite a job another run took over or an ending (its message, its iteration)."""
    held = () if held_by is None else (Job.run_token == held_by,)
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id, *held).values(updated_at=utcnow(), **values))


class RunSuperseded(JobSkipped):
    """This run stalled past its lease and another run took its job over, or the job ended (its hold went with the
    ending): the job's results are the other run's to write, or no run's, so this run's are refused."""


_HOLDING: ContextVar[tuple[str, str] | None] = ContextVar("voxe_holding", default=None)
"""(job id, run token) of the stage this thread runs (:func:`holding_job`)."""


@contextmanager
def holding_job(job_id: str, run_token: str, settings: Settings) -> Iterator[None]:
    """While a stage runs: its hold on the job renewed (:func:`stage_lease`), and the job's artifacts and results
    written only while the hold is still this run's (:class:`RunSuperseded` otherwise)."""
    mark = _HOLDING.set((job_id, run_token))
    try:
        with stage_lease(job_id, run_token, settings):
            yield
    finally:
        _HOLDING.reset(mark)


def _refuse_if_superseded(job_id: str, read_token) -> None:
    """Raise RunSuperseded when this thread runs a stage of ``job_id`` and ``read_token()``, the job's token now,
    is not its own; outside a stage of that job nothing is read."""
    held = _HOLDING.get()
    if held is not None and held[0] == job_id and read_token() != held[1]:
        raise RunSuperseded(f"job {job_id}: this run no longer holds it (another run took the job over, or the job "
                            "ended); this run's results are refused")


def _token_query(job_id: str):
    return select(Job.run_token).where(Job.id == job_id)


def _change_result(job_id: str, change) -> None:
    """``Job.result`` replaced by ``change(result)`` under the job's lock, so stages writing at once lose nothing."""
    with session_scope() as session:
        if (job := locked(session, Job, job_id)) is not None:
            _refuse_if_superseded(job_id, lambda: job.run_token)  # (read under the lock just taken)
            job.result = change(dict(job.result or {}))
            job.updated_at = utcnow()


def merge_job_result(job_id: str, values: dict) -> None:
    """``Job.result`` updated with ``values``, keeping what other stages put there (e.g. their peak memory)."""
    _change_result(job_id, lambda result: {**result, **values})


def record_peak_memory(job_id: str, stage: str, peak_gb: float, kind: str | None) -> None:
    """``Job.result["peak_memory_gb"][stage]`` (GiB) and ``["peak_memory_kind"]``, as a stage reported them."""
    _change_result(job_id, lambda result: {**result, "peak_memory_gb": {**result.get("peak_memory_gb", {}),
                                                                         stage: peak_gb},
                                            "peak_memory_kind": kind})


class StageHeld(JobSkipped):
    """Another run holds the job and renews its lease (this message is a duplicate): it is dropped, and its chain
    goes no further (the holder's own chain carries the job on)."""


class StageCarriedOn(JobSkipped):
    """The message's stage is done and a later stage has begun (a copy delivered again after its run carried the
    chain on): it is dropped at once, and its chain goes no further (a second chain had followed the first's)."""


def begin_stage(job_id: str, stage: str, hostname: str | None, device: str, settings: Settings,
                run_token: str | None = None) -> Job:
    """Take the job for one run of ``stage`` and mark it running; the returned job's ``run_token`` is the run's:
    ``run_token``, drawn by the caller once for all its tries (a fresh one when not given). A try whose UPDATE
    committed with its answer lost (a dropped connection) left the job held by that token: the next try finds it so
    and returns the job as this run's, where it had waited out its own lease and taken the job over from itself,
    counting a re-queue.

    The run holds the job under a lease (``run_lease_until``, renewed by :func:`stage_lease`) until the stage
    completes. Raises :class:`JobSkipped` when the job is terminal, canceled or has done ``stage`` already (a
    redelivered message: its chain goes on, as the worker that ran the stage may have died before sending the next
    stage's message), :class:`StageCarriedOn` when it has done ``stage`` and begun a later one (that message was
    sent), and :class:`StageHeld` when another run holds the job and renews its lease. A holder that stopped
    renewing (its process died) is taken over once its lease has run out, which counts in ``requeues`` as a
    re-queue does: a job whose stage was interrupted ``job_max_requeues`` times already fails instead
    (:class:`JobSkipped`), so a job that kills its workers (a redelivered message each time) cannot loop.

    The job is read, then taken by one UPDATE conditional on the row being as read (``updated_at``: a stage
    completing meanwhile changes it, and the read is retried). One statement, not a claim followed by an update:
    PostgreSQL re-checks the foreign keys of a row updated twice in one transaction, locking the API key's row,
    which job creation holds while it waits for this job's row (a deadlock). Leases are read and written on the
    database's clock (``sync_clock``), so machines whose clocks disagree agree on who holds the job.
    """
    run_token = run_token or uuid.uuid4().hex
    sync_clock()
    while True:
        job = load_job(job_id)
        if job is None or job.state in TERMINAL_STATES:
            raise JobSkipped(f"job {job_id} is {job.state if job else 'gone'}")
        if job.run_token == run_token:  # taken by an earlier try of this run, its answer lost
            return job
        if stage in (job.completed_stages or []) and job.stage not in (None, stage):  # (not waiting on its hold)
            raise StageCarriedOn(f"job {job_id}: {stage} already done and {job.stage} begun (a redelivered task)")
        now = utcnow()
        if job.run_token is not None and job.run_lease_until >= now:
            _wait_for_release(job_id, stage, (job.run_token, job.run_lease_until), settings)
            continue
        with session_scope() as session:
            if job.cancel_requested:  # "during": a run of the stage started, and left its end unrecorded (an outage)
                when = "during" if job.stage == stage and stage not in (job.completed_stages or []) else "before"
                finish_jobs(session, [job_id], CANCELED, message=f"canceled {when} {stage}",
                            settings=settings)  # (its outputs withdrawn)
                session.commit()  # before raising: session_scope rolls back on the way out of an exception
                raise JobSkipped(f"job {job_id} canceled")
            if stage in (job.completed_stages or []):
                raise JobSkipped(f"job {job_id}: {stage} already done (redelivered task)")
            as_read = [Job.updated_at == job.updated_at,  # and no hold renewed since (that changes only the lease)
                       or_(Job.run_token.is_(None), Job.run_lease_until < now)]
            interrupted = job.run_token is not None  # a lapsed hold: its run's process died, which counts
            reason = (f"the run of {job.stage} on worker {job.worker_hostname} stopped renewing its hold on the "
                      "job (its process died: killed, out of memory or crashed; or the database refused its give-back "
                      "in an outage)")
            if interrupted and (error := requeue_limit_error(job.requeues, settings, reason)):
                if not finish_jobs(session, [job_id], FAILED, error=error, where=as_read):
                    continue  # the row changed since it was read: read it again
                session.commit()
                log.error("job %s failed: %s", job_id, error)
                raise JobSkipped(f"job {job_id} failed: {error}")
            values = dict(state=RUNNING, stage=stage, eta_seconds=None, message=None, stage_started_at=now,
                          worker_hostname=hostname, device=device, updated_at=now, run_token=run_token,
                          run_lease_until=now + timedelta(seconds=settings.stage_lease_s))
            if job.stage != stage:  # a run taking over the same stage keeps where it got to until it reports
                values.update(iteration=0, total=0, losses={})  # (it resumes from a checkpoint, often near there)
            if job.started_at is None:
                values["started_at"] = now
            if interrupted:
                values["requeues"] = Job.requeues + 1
            taken = session.execute(update(Job).where(
                Job.id == job_id, Job.state.in_((QUEUED, RUNNING)), *as_read).values(**values)).rowcount == 1
            if taken:
                record_event(session, job_id, "stage_started", stage=stage, worker=hostname)
        if taken:
            return load_job(job_id)


def count_unstarted(job_id: str, stage: str, reason: str, settings: Settings) -> str | None:
    """Count a run of ``stage`` that could not start (``reason``: the database refused it again and again) as a
    re-queue, its message going back to the queue, with a ``requeued`` event; at ``job_max_requeues`` fail the job
    instead and return why: a job whose start fails each time (one of its rows, not the database) must not bounce
    between the broker and the workers for ever. A job that ended, or that a live run holds (the message is a
    duplicate), is left as it is. During an outage this write fails too, raising: nothing counts, and the message
    goes back, as an accepted job must not fail for an outage."""
    free = [Job.id == job_id, Job.state.in_((QUEUED, RUNNING)),
            or_(Job.run_token.is_(None), Job.run_lease_until < utcnow())]
    with session_scope() as session:
        return _count_requeue(session, job_id, stage, reason, settings, free)


def _count_requeue(session, job_id: str, stage: str, reason: str, settings: Settings, where: list,
                   counted: Callable[[], None] | None = None, storage_outage: bool = False,
                   **values) -> str | None:
    """One more re-queue of the job while it matches ``where`` (with ``values`` set, a ``requeued`` event naming
    ``reason``, and ``counted()`` called before the commit), or at ``job_max_requeues`` the job failed and why
    returned; nothing when it matches no more. ``storage_outage``: the same, but counted in ``Job.storage_outages``
    and failed at ``storage_outage_max_retries`` instead (an outage of a service the job shares, no fault of its
    own, yet one that answers every time must not re-run the stage for ever)."""
    counts = session.execute(select(Job.requeues, Job.storage_outages).where(*where)).first()
    if counts is None:
        return None
    as_read = [*where, Job.requeues == counts.requeues, Job.storage_outages == counts.storage_outages]
    if error := (storage_outage_limit_error(counts.storage_outages, settings, reason) if storage_outage
                 else requeue_limit_error(counts.requeues, settings, reason)):
        return error if finish_jobs(session, [job_id], FAILED, error=error, where=as_read) else None
    one_more = {"storage_outages": Job.storage_outages + 1} if storage_outage else {"requeues": Job.requeues + 1}
    if session.execute(update(Job).where(*as_read).values(**one_more, updated_at=utcnow(), **values)).rowcount == 1:
        record_event(session, job_id, "requeued", stage=stage, detail=reason)
        if counted is not None:
            counted()
    return None


def _wait_for_release(job_id: str, stage: str, held: tuple, settings: Settings) -> None:
    """Return once the hold seen (token, lease end) was released or ran out; raise StageHeld once it was renewed
    or passed to another run: a live run holds the job."""
    while True:
        time.sleep(settings.stage_lease_s / 8)
        with session_scope() as session:
            row = session.execute(select(Job.run_token, Job.run_lease_until, Job.state)
                                  .where(Job.id == job_id)).first()
        if row is None or row.state in TERMINAL_STATES or row.run_token is None or row.run_lease_until < utcnow():
            return
        if (row.run_token, row.run_lease_until) != held:
            raise StageHeld(f"job {job_id}: another run holds it (this {stage} message is a duplicate)")


def complete_stage(job_id: str, stage: str, run_token: str, final: bool = False, again: bool = False,
                   message: str | None = None) -> bool:
    """Record ``stage`` done and release the job (or end it, ``final``, with ``message``: None clears the stage's
    progress notes); False when the run no longer held it. A final stage whose job was asked to cancel after the
    stage's last check (during its last uploads) raises StageCancelled instead: the user who canceled sees it
    canceled, not succeeded (a cancel landing once it succeeded finds it so, as the API answers).
    ``again``: a try before raised, and may have committed with its answer lost (a dropped connection): the stage
    found recorded done and the job released (or succeeded) counts as this run's. (Another run completing the same
    stage would look the same, but none can have taken the job over within the retries' seconds: the hold was
    renewed until the stage's body ended, with most of its lease left.)"""
    with session_scope() as session:
        job = session.get(Job, job_id)
        if job is None:
            return False
        done = list(job.completed_stages or [])
        if stage not in done:
            done.append(stage)
        values = dict(completed_stages=done, eta_seconds=0.0, updated_at=utcnow(), run_token=None,
                      run_lease_until=None)
        held = [Job.id == job_id, Job.state == RUNNING, Job.run_token == run_token]
        if final:
            values.update(state=SUCCEEDED, finished_at=utcnow(), message=message)
        result = session.execute(update(Job).where(*held, *([Job.cancel_requested.is_(False)] if final else []))
                                 .values(**values))
        if result.rowcount == 1:
            record_event(session, job_id, "stage_completed", stage=stage, worker=job.worker_hostname)
            if final:
                record_event(session, job_id, SUCCEEDED, stage=stage)
            return True
        if final and session.scalar(select(Job.cancel_requested).where(*held)):
            raise StageCancelled(f"{stage} canceled before its end was recorded")
        return (again and stage in (job.completed_stages or []) and job.run_token is None
                and job.state == (SUCCEEDED if final else RUNNING))


def worker_in_cold_shutdown() -> bool:
    """Whether this worker is in a cold shutdown (SIGQUIT, or the image's remapped SIGTERM). Celery then cancels
    the running task; in the solo pool, whose tasks run in the worker's own thread, by raising in it
    (NotImplementedError: the pool cannot kill a job). That is no failure of the job or the upload: the task's
    message goes back to the queue."""
    from celery.worker import state

    return state.should_terminate is not None and state.should_terminate is not False  # (an exit code: 0 counts)


OUTAGE_PAUSE_S = 5.0
"""How long a stage that a storage outage or a full disk stopped, or an ingest any outage stopped, waits before its
message goes back to the queue, doubled for each run before it: a storage down for a while must not have the
workers take and drop the message in a tight loop, nor spend the job's or the scene's runs in seconds."""


def storage_or_disk_outage(exc: BaseException) -> str | None:
    """What ``exc`` says stopped a stage or an ingest, when it is the storage out of reach (``StorageUnavailable``:
    unreachable, throttled, a 5xx) or the worker's disk (or quota) full: the service's or the machine's state, which
    a later run, or another worker, may not meet; None for anything else (a ``StorageError`` that is no outage, a
    missing bucket or access denied, is a fault a retry meets again)."""
    if isinstance(exc, StorageUnavailable):
        return f"a storage outage ({exc})"
    if disk_full(exc):
        return f"the worker's disk full ({failure_text(exc, say_the_worker=False)})"
    return None


def disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is the worker's disk (or quota) full."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def pause_after_outage(runs_before: int) -> None:
    """Wait ``OUTAGE_PAUSE_S`` doubled ``runs_before`` times (5, 10, 20 s ..., at most 64 times) before an outage's
    message goes back to the queue. A cold shutdown raising in the task cuts it short, no more: raised through, the
    message had been acknowledged as failed."""
    try:
        time.sleep(OUTAGE_PAUSE_S * 2 ** min(runs_before, 6))
    except Exception:  # noqa: BLE001 - what a cold shutdown raises in a solo pool's task
        if not worker_in_cold_shutdown():
            raise


def give_back_stage(job_id: str, stage: str, run_token: str, reason: str, settings: Settings,
                    free_scratch: bool = False, storage_outage: bool = False) -> str | None:
    """Give the run's hold back after an outage (the database's, the storage's) or its worker's full disk stopped its
    stage (its redelivery resumes from the stored checkpoint), counted as a re-queue with a ``requeued`` event naming
    ``reason``, and ``reason`` the job's message until the redelivery starts (its last progress note had stayed,
    nothing saying why the job waited); at ``job_max_requeues`` fail the job instead and return why: what the database answers as an outage
    every time (a statement timeout, a full disk) must not re-run a stage for ever. ``storage_outage`` (throttling,
    a 5xx, the store unreachable, which every job meets alike) gives it back with its event and message, neither
    counted as a re-queue nor failed at its limit (a minute of throttling had failed the running jobs near it), but
    counted in ``Job.storage_outages``, failing at ``storage_outage_max_retries``: a permanent 5xx on one object had
    re-run the stage for ever.
    A job this run no longer holds, or that it ended (a commit whose answer was lost keeps the ended job's token),
    is left as it is.
    ``free_scratch``: the job's scratch folder is deleted once the give-back matched, before it commits (the row
    still this run's, locked by its update): never the scratch of a run that took the job over from this one, on
    this machine, and none can take it over while the folder goes."""
    counted = (lambda: cleanup_scratch(job_id, settings)) if free_scratch else None
    with session_scope() as session:
        return _count_requeue(session, job_id, stage, reason, settings,
                              [Job.id == job_id, Job.state == RUNNING, Job.run_token == run_token], counted=counted,
                              storage_outage=storage_outage, run_token=None, run_lease_until=None,
                              message=f"re-queued: {reason}")


def release_stage(job_id: str, run_token: str) -> None:
    """Give the hold back without finishing the stage (the worker is going down: its redelivery takes over)."""
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id, Job.run_token == run_token)
                        .values(run_token=None, run_lease_until=None))


def finish_job(job_id: str, state: str, message: str | None = None, error: str | None = None,
               run_token: str | None = None, settings: Settings | None = None) -> bool:
    """End the job in ``state``; with ``run_token``, only while that run holds it. Whether it ended now. Canceled,
    the artifacts its unfinished stage published are withdrawn (:func:`~voxe_service.jobs.finish_jobs`)."""
    with session_scope() as session:
        return bool(finish_jobs(session, [job_id], state, message=message, error=error, settings=settings,
                                where=[Job.run_token == run_token] if run_token else []))


def record_job_event(job_id: str, kind: str, **fields) -> None:
    """One event on the job's timeline, in its own transaction (checkpoints, resumes); refused
    (:class:`RunSuperseded`) to a stage's run that no longer holds the job: not after an ending or a take-over that
    came meanwhile (a checkpoint stored as the job ended had put its event after the ending)."""
    with session_scope() as session:
        if (job := locked(session, Job, job_id)) is None:
            return
        _refuse_if_superseded(job_id, lambda: job.run_token)  # (read under the lock just taken)
        record_event(session, job_id, kind, **fields)


def run_checkpoint_key(job: Job, stage: str, iteration: int) -> str:
    """Where this run of ``stage`` stores the job's checkpoint taken at ``iteration``: a key of that checkpoint's own
    (the run's token and the iteration), so that no upload, a stalled run's or one whose record failed, overwrites
    the recorded checkpoint's bytes, and one left unrecorded can always be deleted."""
    return job_key(job.id, f"checkpoints/{job.run_token}/{iteration}/{stage}.safetensors")


def _record_checkpoint(job_id: str, stage: str, iteration: int, key: str | None) -> str | None:
    """The ``checkpoint`` event at ``iteration`` and, given ``key``, that key recorded as the job's live checkpoint,
    in one transaction under the job's lock, refused (:class:`RunSuperseded`) to a run that no longer holds the job
    or whose job is gone (deleted: its storage cleanup may have run already); the key it replaced (None when none)."""
    with session_scope() as session:
        if (job := locked(session, Job, job_id)) is None:
            raise RunSuperseded(f"job {job_id}: deleted; this run's checkpoint is refused")
        _refuse_if_superseded(job_id, lambda: job.run_token)  # (read under the lock just taken)
        replaced = job.checkpoint_key
        if key is not None:
            job.checkpoint_key = key
        record_event(session, job_id, "checkpoint", stage=stage, iteration=iteration)
    return replaced if key is not None else None


def forget_checkpoint(job_id: str, key: str) -> None:
    """Clear the job's record of its live checkpoint ``key``, which a stage starting over is about to delete: a
    record naming a deleted object had a later run of the stage look for it. A record naming another key is left as
    it is; refused (:class:`RunSuperseded`) to a run that no longer holds the job: the checkpoint is not its own. A
    database blip skips it, as it does a progress write (the stage starting over goes on: raised, it had been a
    counted re-queue), and a later run finds the record's object gone and starts from the start."""
    with outage_skipped(f"job {job_id}: the record of its dropped checkpoint cleared"), session_scope() as session:
        if (job := locked(session, Job, job_id)) is None:
            raise RunSuperseded(f"job {job_id}: deleted; this run's start over is refused")
        _refuse_if_superseded(job_id, lambda: job.run_token)  # (read under the lock just taken)
        if job.checkpoint_key == key:
            job.checkpoint_key = None


def record_warning(job_id: str, stage: str, text: str) -> None:
    """Say ``text`` as the job's message and as a ``warning`` event on its timeline, in one transaction: a stage that
    completed with a result the user should look at, or started over from a checkpoint it could not go on from (the
    message is the next report's once that comes; the event stays). A warning the timeline holds for ``stage``
    already (an earlier run of it said it: a resume, a redelivery) is not recorded again, nor its webhook sent."""
    with session_scope() as session:
        if (job := locked(session, Job, job_id)) is None:
            return
        _refuse_if_superseded(job_id, lambda: job.run_token)  # (read under the lock just taken)
        job.message, job.updated_at = text, utcnow()
        said = select(JobEvent.id).where(JobEvent.job_id == job_id, JobEvent.kind == "warning",
                                         JobEvent.stage == stage, JobEvent.detail == text)
        if session.scalar(said.limit(1)) is None:
            record_event(session, job_id, "warning", stage=stage, detail=text)


# --------------------------------------------------------------------------- callbacks
@contextmanager
def outage_skipped(what: str) -> Iterator[None]:
    """``what`` the block does (a progress write, a lease renewal), skipped with a warning when the database cannot
    serve now (``database_outage``: down, locked), for the next one to try again: a blip in a long stage must not
    fail it. A fault that is no outage (SQLite's OperationalError for a missing column) raises."""
    try:
        yield
    except DATABASE_UNAVAILABLE as exc:
        if (why := database_outage(exc)) is None:
            raise
        log.warning("%s skipped: %s", what, why)


class StageCallbacks:
    """``voxe_core.progress.Callbacks`` for one stage of one job.

    Progress is written at most once per ``progress_interval_s`` (and always for
    the last iteration); the cancel flag is read at most once per
    ``cancel_check_interval_s``. ``extra_progress`` is called on every write
    (the reconstruction owner renews its lease there). ``on_checkpoint(path, iteration)`` stores
    a checkpoint taken at ``iteration`` (returning the ``StoredObject`` where it is the job's own, stored at
    :func:`run_checkpoint_key`); a ``checkpoint`` event at the iteration it was taken follows it.
    ``phase_seconds``: seconds per unit of each sub-step of a stage counted in phases
    (``voxe_core.progress.in_phases``; ``voxe_service.progress.refine_phase_seconds``), by which the
    time left weighs each sub-step's units left against the current one's, whose rate it measures.
    """

    def __init__(self, job: Job, stage: str, settings: Settings, extra_progress=None, on_checkpoint=None,
                 note: str | None = None, phase_seconds: dict[str, float] | None = None):
        self.job_id, self.stage, self.settings, self.note = job.id, stage, settings, note
        self.phase_seconds = phase_seconds or {}
        self.run_token = job.run_token  # the run holding the job: a run that lost it stops as if canceled
        self.extra_progress = extra_progress
        self._last_write = 0.0
        self._last_check = 0.0
        self._canceled = False
        self._rate_origin: tuple[float, int] | None = None
        self._last_report: Progress | None = None
        self._written: Progress | None = None
        self._store_checkpoint = on_checkpoint
        self.lost = False  # a checkpoint refused as the run lost its job or fit: it says no more warnings
        self.peak_memory_gb: float | None = None
        self._peak_written: float | None = None
        self.callbacks = Callbacks(on_progress=self.on_progress, should_cancel=self.should_cancel,
                                   on_checkpoint=self.on_checkpoint if on_checkpoint else None,
                                   on_warning=self.on_warning)

    def on_warning(self, stage: str, text: str) -> None:
        """Say what the stage warns of as a ``warning`` event (the timeline, its webhook, the CLI's line) and keep it
        in the message its progress reports carry, which had replaced it at the next write. In a database outage the
        event is skipped, as a progress write is (it had stopped the stage: a counted re-queue); the message stays
        for the next progress write to carry. A run that lost its job or its fit (a checkpoint refused it) says
        nothing: the checkpoint at a cancel refused so had said "the earlier checkpoint stands" on the job, where the
        new owner's does."""
        text = text if stage == self.stage else f"{stage}: {text}"
        if self.lost:
            log.info("job %s: %s: not said on the job, as the run lost it or its fit: %s", self.job_id, self.stage,
                     text)
            return
        log.warning("job %s: %s: %s", self.job_id, self.stage, text)
        self.note = text if self.note is None else f"{self.note}; {text}"
        with outage_skipped(f"job {self.job_id}: {self.stage}'s warning event"):
            record_warning(self.job_id, self.stage, text)

    def on_checkpoint(self, path: str) -> None:
        """Store the checkpoint, then record where it was taken (stages report progress just before). A run that
        lost its job stores nothing (:class:`RunSuperseded`): its older state would replace the new owner's. A job's
        own checkpoint (``on_checkpoint`` returns its ``StoredObject``, stored at :func:`run_checkpoint_key`) is
        recorded as the job's live one with its event, under the job's lock and only while this run holds it; the
        one it replaces goes. One whose record failed (refused: the job ended, was deleted or taken over meanwhile;
        or the database out of reach) is deleted: its key is its own, so it is never the recorded checkpoint, whose
        bytes it leaves as they were. A reconstruction's checkpoint is the fit's, recorded by the fit's owner
        (``worker.tasks``), which raises :class:`LeaseLost` once another owns it."""
        try:
            with session_scope() as session:
                _refuse_if_superseded(self.job_id, lambda: session.scalar(_token_query(self.job_id)))
            iteration = int(self._last_report.iteration if self._last_report is not None else 0)
            stored = self._store_checkpoint(path, iteration)
            own = stored.key if isinstance(stored, StoredObject) else None
            try:
                replaced = _record_checkpoint(self.job_id, self.stage, iteration, own)
            except Exception:
                if own is not None:
                    get_storage(self.settings).discard(own)
                raise
        except (RunSuperseded, LeaseLost):
            self.lost = True
            raise
        if replaced is not None and replaced != own:
            get_storage(self.settings).discard(replaced)

    def on_progress(self, report: Progress) -> None:
        now = time.monotonic()
        if self._rate_origin is None or report.stage != getattr(self, "_sub_stage", None):
            self._rate_origin, self._sub_stage = (now, report.iteration), report.stage
        self._last_report = report
        peak = report.info.get("peak_memory_gb")
        if peak is not None and (self.peak_memory_gb is None or peak > self.peak_memory_gb):
            self.peak_memory_gb = float(peak)
        final = report.iteration >= report.total
        if not final and now - self._last_write < self.settings.progress_interval_s:
            return
        self._last_write = now
        self._written = report
        t0, i0 = self._rate_origin
        eta = None
        if report.iteration > i0 and now > t0:
            eta = (now - t0) / (report.iteration - i0) * self._units_left(report)
        losses = {k: round(float(v), 6) for k, v in report.losses.items() if math.isfinite(float(v))}
        message = self.note if report.stage == self.stage else f"{self.stage}: {report.stage}"
        with outage_skipped(f"job {self.job_id}: {self.stage}'s progress write"):
            update_job(self.job_id, held_by=self.run_token, iteration=int(report.iteration), total=int(report.total),
                       eta_seconds=eta, losses=losses, message=message)
            if self.peak_memory_gb is not None and self.peak_memory_gb != self._peak_written:
                record_peak_memory(self.job_id, self.stage, self.peak_memory_gb, report.info.get("peak_memory_kind"))
                self._peak_written = self.peak_memory_gb
        if self.extra_progress is not None:
            self.extra_progress(report)

    def _units_left(self, report: Progress) -> float:
        """The units left, in the current sub-step's units: a later sub-step's each weigh its cost per unit over
        the current one's (the paper's refinement: an attention pass costs 50 of its fitting steps on a CPU, and
        counting the steps at the passes' rate had put the time left some 30x too high)."""
        left = report.info.get("phase_units_left")
        current = self.phase_seconds.get(report.stage)
        if not left or not current:
            return max(0, report.total - report.iteration)
        return sum(units * self.phase_seconds.get(phase, current) / current for phase, units in left.items())

    def should_cancel(self) -> bool:
        if self._canceled:
            return True
        now = time.monotonic()
        if now - self._last_check < self.settings.cancel_check_interval_s:
            return False
        self._last_check = now
        row = unread = object()
        with outage_skipped(f"job {self.job_id}: {self.stage}'s cancel check"):
            with session_scope() as session:
                row = session.execute(select(Job.cancel_requested, Job.state, Job.run_token)
                                      .where(Job.id == self.job_id)).first()
        if row is unread:  # the database out of reach: the stage goes on, and asks again at the next check
            return False
        self._canceled = (row is None or bool(row.cancel_requested) or row.state in TERMINAL_STATES
                          or (self.run_token is not None and row.run_token != self.run_token))
        if self._canceled and self._last_report is not None and self._last_report is not self._written:
            # Record where the stage stopped (the throttle may have held the last report back).
            report = self._last_report
            update_job(self.job_id, held_by=self.run_token, iteration=int(report.iteration), total=int(report.total))
        return self._canceled


# --------------------------------------------------------------------------- storage
def scratch_dir(job_id: str, settings: Settings) -> Path:
    path = Path(settings.work_dir) / "jobs" / job_id
    path.mkdir(parents=True, exist_ok=True)
    return path


def cleanup_scratch(job_id: str, settings: Settings) -> None:
    shutil.rmtree(Path(settings.work_dir) / "jobs" / job_id, ignore_errors=True)


def _leading_id(name: str) -> str:
    """The id a scratch folder's name starts with (``<id>-<suffix>``; ``.<id>-...`` keeps its dot)."""
    return name.partition("-")[0]


def _sweep(root: Path, owner, kept) -> list[str]:
    """Delete the folders under ``root`` whose owner (``owner(name)``) is not among ``kept(owners)``; the names swept.
    The folders are listed before ``kept`` reads the database, so each is judged by a state its maker had written
    before making it (a job running, a scene processing), or by a later one."""
    names = [p.name for p in root.iterdir() if p.is_dir()] if root.is_dir() else []
    if not names:
        return []
    owner_of = {name: owner(name) for name in names}
    keep = kept(set(owner_of.values()))
    swept = [name for name in names if owner_of[name] not in keep]
    for name in swept:
        shutil.rmtree(root / name, ignore_errors=True)
    return swept


def sweep_scratch(settings: Settings) -> list[str]:
    """Delete the scratch folders of jobs that have ended or are gone; the ids swept.

    The worker that runs a job's last stage cleans its scratch; in a scale-out the workers that ran
    its earlier stages would otherwise keep their copies of its grids and checkpoints for ever.
    """
    def live(ids: set[str]) -> set[str]:
        with session_scope() as session:
            return set(session.scalars(select(Job.id).where(Job.id.in_(ids), Job.state.not_in(TERMINAL_STATES))))

    return _sweep(Path(settings.work_dir) / "jobs", lambda name: name, live)


def sweep_scene_datasets(settings: Settings) -> list[str]:
    """Delete this machine's unpacked datasets (``<scene id>-<sha>``) of scenes that are gone or not ready, and the
    half-unpacked debris (``.<scene id>-*``) of unpacks no running job of a ready scene may be making (a job's
    run killed mid-unpack left it), then evict datasets over ``VOXE_SCENE_CACHE_MAX_BYTES`` (a limit lowered since
    they were unpacked: :func:`evict_scene_datasets`); the folder names swept. A job unpacks its scene while it runs,
    and a ready scene cannot be deleted while it does."""
    def kept(owners: set[str]) -> set[str]:
        with session_scope() as session:
            ready = set(session.scalars(select(Scene.id).where(Scene.id.in_({o.lstrip(".") for o in owners}),
                                                               Scene.state == READY)))
            unpacking = set(session.scalars(select(Job.scene_id).where(Job.scene_id.in_(ready), Job.state == RUNNING)))
        return ready | {f".{scene_id}" for scene_id in unpacking}

    return _sweep(Path(settings.work_dir) / "scenes", _leading_id, kept) + evict_scene_datasets(settings)


def sweep_ingest_scratch(settings: Settings) -> list[str]:
    """Delete this machine's unpacked uploads (``ingest/<scene id>-*``) of scenes no longer processing; the folder
    names swept. An ingest removes its own as it ends; one whose process was killed left it (up to
    ``VOXE_MAX_EXTRACTED_BYTES``), which the scene's next run on this machine removes as it starts
    (``worker.ingest``), and this sweep once the scene is ready, failed (an ingest interrupted too often fails it)
    or deleted."""
    def processing(ids: set[str]) -> set[str]:
        with session_scope() as session:
            return set(session.scalars(select(Scene.id).where(Scene.id.in_(ids), Scene.state == PROCESSING)))

    return _sweep(Path(settings.work_dir) / "ingest", _leading_id, processing)


def publish_artifact(job_id: str, name: str, path: str | os.PathLike, kind: str, storage: Storage | None = None,
                     key: str | None = None) -> Artifact:
    """Upload ``path`` as the job's artifact ``name``, then record it with the stored bytes' size and SHA-256
    (:func:`publish_artifacts`). Given ``key``, the bytes are already stored there (e.g. the shared reconstruction's
    grid) and are only recorded."""
    return _publish(job_id, [(name, path, kind, key)], storage)[0]


def publish_artifacts(job_id: str, files: list[tuple[str, str | os.PathLike, str]],
                      storage: Storage | None = None) -> list[Artifact]:
    """Publish ``files`` ((name, path, kind) each) as one set: every one is uploaded before any is recorded, and all
    are recorded in one transaction, so a failure part way (the storage refusing the third of a mesh's formats) lists
    none of them rather than some (mesh.obj without its mesh.mtl)."""
    return _publish(job_id, [(name, path, kind, None) for name, path, kind in files], storage)


def _publish(job_id: str, files: list[tuple[str, str | os.PathLike, str, str | None]],
             storage: Storage | None) -> list[Artifact]:
    """Upload (where no key is given) and record (name, path, kind, key) each.

    A row is written only once the bytes are final, so a failed or killed upload is never listed.
    A replaced artifact goes to a fresh key and the row switches to it in one update (the old
    object is deleted after): the listed size and checksum always describe the bytes of its key.
    """
    storage = storage or get_storage()
    with session_scope() as session:  # a run that lost its job uploads nothing ...
        _refuse_if_superseded(job_id, lambda: session.scalar(_token_query(job_id)))
    # uploaded: name -> key, taken as its upload starts (one that failed, its answer lost, may have stored the bytes)
    previous, stored, uploaded = {}, {}, {}
    try:
        for name, path, _kind, key in files:
            previous[name] = recorded_key(job_id, name)
            if key is None:
                fixed = job_key(job_id, name)
                key = fixed if previous[name] != fixed else job_key(job_id, f"v-{uuid.uuid4().hex[:12]}/{name}")
                uploaded[name] = key
                stored[name] = storage.put_file(key, path, content_type(name))
            else:  # already in storage under another key (e.g. the shared reconstruction)
                size, sha = file_sha256(path)
                stored[name] = StoredObject(key, size, sha)
        with session_scope() as session:
            job = locked(session, Job, job_id)
            # ... and records nothing (checked again under the job's lock)
            _refuse_if_superseded(job_id, lambda: job.run_token if job is not None else None)
            artifacts = [_record_artifact(session, job_id, name, kind, stored[name]) for name, _, kind, _ in files]
    except RunSuperseded:
        ended = bool(uploaded) and has_ended(job_id)
        # the fixed key may be the new owner's; an ended job has none (unless a row lists it)
        for name, key in uploaded.items():
            if key != job_key(job_id, name) or (ended and not _may_be_recorded(job_id, name, key)):
                storage.discard(key)
        raise
    except BaseException:  # the records were not written: neither are the bytes kept, unless a row does record them
        for name, key in uploaded.items():  # (a commit may fail on its way back)
            if not _may_be_recorded(job_id, name, key):
                storage.discard(key)  # (a storage failing now must not hide the error that stopped us)
        raise
    for name, old in previous.items():
        if old and old != stored[name].key and old.startswith(job_key(job_id, "")):
            storage.discard(old)  # never the shared reconstruction's grid: that lives outside jobs/<id>/
    return artifacts


def _record_artifact(session, job_id: str, name: str, kind: str, stored: StoredObject) -> Artifact:
    """The job's artifact row ``name`` (made when missing) pointing at ``stored``, and its event on the timeline."""
    artifact = session.execute(
        select(Artifact).where(Artifact.job_id == job_id, Artifact.name == name)
    ).scalar_one_or_none()
    if artifact is None:
        artifact = Artifact(job_id=job_id, name=name)
        session.add(artifact)
    artifact.key, artifact.size, artifact.sha256 = stored.key, stored.size, stored.sha256
    artifact.content_type, artifact.kind, artifact.created_at = content_type(name), kind, utcnow()
    # On the timeline in the same transaction: an event stream announces each artifact once it can be read.
    record_event(session, job_id, "preview" if kind == "preview" else "artifact", detail=name)
    return artifact


def has_ended(job_id: str) -> bool:
    """Whether the job is finished or deleted: no run holds it, nor will (a skipped message that found it so may
    clean up after it; one for a stage already done, redelivered, may not)."""
    with session_scope() as session:
        state = session.scalar(select(Job.state).where(Job.id == job_id))
    return state is None or state in TERMINAL_STATES


def _may_be_recorded(job_id: str, name: str, key: str) -> bool:
    """Whether an artifact row of the job may point at ``key``: it does, or the database cannot say (then the
    bytes are kept: a listed artifact whose file is gone would be worse than an unlisted file)."""
    try:
        return recorded_key(job_id, name) == key
    except Exception:  # noqa: BLE001 - the database failing is why this is asked
        return True


def recorded_key(job_id: str, name: str) -> str | None:
    """The storage key the job's artifact ``name`` is recorded under (it moves when the artifact is replaced)."""
    with session_scope() as session:
        return session.scalar(select(Artifact.key).where(Artifact.job_id == job_id, Artifact.name == name))


def recorded_artifact(job_id: str, name: str) -> StoredObject:
    """The job's artifact ``name`` as recorded: its key, size and SHA-256 (what a :func:`fetch` of it must get)."""
    with session_scope() as session:
        row = session.execute(select(Artifact.key, Artifact.size, Artifact.sha256)
                              .where(Artifact.job_id == job_id, Artifact.name == name)).first()
    if row is None:
        raise RuntimeError(f"job {job_id} has no artifact {name!r}")
    return StoredObject(row.key, row.size, row.sha256)


def reconstruction_grid(rec: Reconstruction) -> StoredObject:
    """The grid G_i a succeeded reconstruction recorded."""
    return StoredObject(rec.grid_key, rec.grid_size, rec.grid_sha256)


def scene_archive(scene: Scene) -> StoredObject:
    """The scene's archive as recorded when it was stored: its upload, or a mesh scene's rendered dataset."""
    return StoredObject(scene.storage_key, scene.size_bytes, scene.sha256)


def fetch(storage: Storage, stored: StoredObject, dest: Path, what: str | None = None) -> Path:
    """``stored`` at ``dest``. A file already there is reused only when it holds the recorded bytes: a run that
    lost its job or the fit leaves its own, unpublished, grid in the job's scratch. A download that does not match
    the record (the object truncated or corrupted in the storage) is an error naming ``what`` (default: the key)
    and both sizes and checksums; one the storage no longer holds (deleted there), an error naming ``what`` too
    (the storage's had said only ``ObjectNotFound: '<key>'``)."""
    if dest.is_file() and _holds(dest, stored):
        return dest
    try:
        storage.get_file(stored.key, dest)
    except ObjectNotFound as exc:
        raise StorageError(f"{what or stored.key}: not in the storage, deleted there since it was recorded") from exc
    size, sha256 = file_sha256(dest)
    if (size, sha256) != (stored.size, stored.sha256):
        dest.unlink(missing_ok=True)
        raise StorageError(f"{what or stored.key}: the stored bytes are not the ones recorded ({stored.size} bytes, "
                           f"SHA-256 {stored.sha256}; the storage holds {size} bytes, SHA-256 {sha256}): truncated "
                           "or corrupted in the storage")
    return dest


def _holds(path: Path, stored: StoredObject) -> bool:
    return path.stat().st_size == stored.size and file_sha256(path) == (stored.size, stored.sha256)


@contextmanager
def scene_dataset(scene: Scene, settings: Settings, storage: Storage) -> Iterator[Path]:
    """The scene's dataset folder on this machine, for the block to read: downloaded (checked against its recorded
    size and SHA-256) and unpacked once, then reused, while the datasets fit in ``VOXE_SCENE_CACHE_MAX_BYTES``. The
    block holds the dataset's ``.complete`` locked shared, so no eviction (:func:`evict_scene_datasets`, which a new
    unpack runs before and after) takes it meanwhile; a dataset evicted is unpacked again when next asked for."""
    root = Path(settings.work_dir) / "scenes" / f"{scene.id}-{scene.sha256[:12]}"
    with _held_here(root):
        lock = _read_lock(root)
        while lock is None:  # not unpacked on this machine, or evicted before its lock was taken
            lock = _unpack(scene, root, settings, storage)
        with lock:
            yield root


def _make_room(settings: Settings, room: int) -> None:
    """Evict unpacked datasets so that they and ``room`` bytes about to be written fit in
    ``VOXE_SCENE_CACHE_MAX_BYTES``: run before an unpack writes (evicted only after it, a full cache had needed the
    space the eviction frees before it could unpack), and after (:func:`_unpack`). The cache's upkeep never fails
    the stage that reads it."""
    try:
        if evicted := evict_scene_datasets(settings, room):
            log.info("evicted the unpacked dataset(s) %s (VOXE_SCENE_CACHE_MAX_BYTES)", ", ".join(evicted))
    except OSError:
        log.warning("could not evict unpacked datasets", exc_info=True)


_held_datasets: Counter[Path] = Counter()
_held_datasets_lock = threading.Lock()


@contextmanager
def _held_here(root: Path) -> Iterator[None]:
    """``root`` recorded as read by a stage of this process, from before its lock is taken until after it is
    released, so that no eviction in this process takes it (:func:`_evict`). Its lock cannot keep those off where
    ``flock`` is emulated by POSIX locks (NFS): those belong to the process, so its own eviction's exclusive lock is
    granted, and closing that eviction's descriptor releases the stage's."""
    with _held_datasets_lock:
        _held_datasets[root] += 1
    try:
        yield
    finally:
        with _held_datasets_lock:
            _held_datasets[root] -= 1
            if not _held_datasets[root]:
                del _held_datasets[root]


def _unpack(scene: Scene, root: Path, settings: Settings, storage: Storage):
    """Unpack the scene's archive aside and rename it into place as ``root``; its read lock (:func:`_read_lock`),
    taken before the folder shows, so no eviction takes it first; None when another process on this machine unpacked
    it first and it was evicted since. Room is made before the archive is fetched, before it is unpacked, and again
    once it is in place (its lock held, so it stays): an unpack in flight in another process (a folder still named
    ``.<scene id>-...``) is not counted, and two at once had left the cache over the limit until the next sweep."""
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=root.parent, prefix=f".{scene.id}-"))
    try:
        _make_room(settings, scene.size_bytes)
        archive = fetch(storage, scene_archive(scene), tmp / datasets.DATASET_ARCHIVE,
                        f"scene {scene.id}'s archive {scene.storage_key}")
        _make_room(settings, scene.size_bytes + datasets.unpacked_bytes(archive))  # (the archive goes once unpacked)
        datasets.unpack(archive, tmp / "data")
        archive.unlink()
        (tmp / "data" / datasets.UNPACKED_MARK).write_text("ok")
        lock = open(tmp / "data" / datasets.UNPACKED_MARK, "rb")
        _share(lock)
        try:
            os.rename(tmp / "data", root)
        except OSError:  # another process on this machine finished first
            lock.close()
            if not (root / datasets.UNPACKED_MARK).is_file():
                raise
            return _read_lock(root)
        _make_room(settings, 0)
        return lock
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _read_lock(root: Path):
    """``root/.complete`` open and locked shared, its time of use marked (the eviction's order); None when ``root``
    holds no dataset (never unpacked here, or evicted before the lock was taken)."""
    path = root / datasets.UNPACKED_MARK
    try:
        lock = open(path, "rb")
    except FileNotFoundError:
        return None
    _share(lock)
    with contextlib.suppress(FileNotFoundError):
        if os.path.samestat(os.fstat(lock.fileno()), os.stat(path)):  # (not evicted while the lock was awaited)
            os.utime(path)
            return lock
    lock.close()
    return None


def _share(lock) -> None:
    with contextlib.suppress(OSError):  # a filesystem without locks: no eviction can lock a dataset there either
        fcntl.flock(lock, fcntl.LOCK_SH)


EVICTION_LOCK = ".evict.lock"
_said_no_locks: set[Path] = set()


def evict_scene_datasets(settings: Settings, room: int = 0) -> list[str]:
    """Delete this machine's least recently used unpacked datasets that no stage is reading until the rest, and
    ``room`` bytes more, fit in ``VOXE_SCENE_CACHE_MAX_BYTES``; the folder names evicted. A dataset a stage reads
    stays (its lock is held: :func:`scene_dataset`), over the limit if need be. Evictions run one at a time on the
    machine (a lock on the file ``scenes/.evict.lock``), so two never both free the same excess.

    Each exclusive lock is taken on a file open for writing: NFS emulates ``flock`` with ``fcntl`` locks, which take
    an exclusive lock on nothing else (EBADF: on the folder, or on a ``.complete`` opened to read, it had evicted
    nothing, silently). Nothing is evicted on a filesystem without locks, as a warning says once."""
    root = Path(settings.work_dir) / "scenes"
    if not root.is_dir():
        return []
    folder_lock = os.open(root / EVICTION_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(folder_lock, fcntl.LOCK_EX)
        except OSError as exc:  # a filesystem without locks
            if root not in _said_no_locks:
                _said_no_locks.add(root)
                log.warning("%s takes no file locks (%s): its unpacked datasets are never evicted, whatever "
                            "VOXE_SCENE_CACHE_MAX_BYTES says", root, exc)
            return []
        unpacked = []
        for folder in root.iterdir():
            with contextlib.suppress(FileNotFoundError):  # (a sweep removed it meanwhile)
                if not folder.name.startswith(".") and (folder / datasets.UNPACKED_MARK).is_file():
                    unpacked.append(((folder / datasets.UNPACKED_MARK).stat().st_mtime, folder, _folder_bytes(folder)))
        total, evicted = sum(size for *_, size in unpacked), []
        for _used, folder, size in sorted(unpacked):  # least recently used first
            if total + room <= settings.scene_cache_max_bytes:
                break
            if _evict(folder):
                total -= size
                evicted.append(folder.name)
        return evicted
    finally:
        os.close(folder_lock)


def _folder_bytes(folder: Path) -> int:
    return sum(os.lstat(os.path.join(parent, name)).st_size for parent, _, names in os.walk(folder) for name in names)


def _evict(folder: Path) -> bool:
    """Delete the dataset ``folder`` unless a stage reads it (its ``.complete`` locked); whether it went. It is
    renamed to unpack debris (``.<scene id>-...``) first, so a reader never finds it half deleted, and a deletion cut
    short is swept as debris. One a stage of this process reads is not even opened (:func:`_held_here`); that check
    and the rename are one step for this process's stages, so none takes the folder's lock in between."""
    doomed = folder.with_name(f".{folder.name}-{uuid.uuid4().hex[:8]}")
    with _held_datasets_lock:
        if folder in _held_datasets:
            return False
        try:
            with open(folder / datasets.UNPACKED_MARK, "r+b") as lock:  # (for writing: see evict_scene_datasets)
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                os.rename(folder, doomed)
        except OSError:  # read by a stage, evicted or swept meanwhile, or a filesystem without locks
            return False
    shutil.rmtree(doomed, ignore_errors=True)
    return True


# --------------------------------------------------------------------------- reconstruction claim
@dataclass
class Claim:
    reconstruction: Reconstruction
    owner: bool  # this job runs the fit


def try_claim_reconstruction(rec_id: str, job_id: str, hostname: str | None, settings: Settings,
                             allow_failed: bool, run_token: str | None = None) -> bool:
    """Atomically take the fit: pending (or failed, or a lapsed lease, or our own job's) -> running, owned by the
    job's run ``run_token``, only while that run holds the job (a later run of the same job takes the fit from an
    earlier one that lost the job, never the other way round)."""
    now = utcnow()
    states = [R_PENDING] + (["failed"] if allow_failed else [])
    holds_job = [] if run_token is None else [select(Job.id).where(Job.id == job_id, Job.run_token == run_token)
                                              .exists()]
    with session_scope() as session:
        result = session.execute(
            update(Reconstruction)
            .where(
                Reconstruction.id == rec_id,
                (Reconstruction.state.in_(states))
                | ((Reconstruction.state == R_RUNNING)
                   & ((Reconstruction.lease_until < now) | (Reconstruction.owner_job_id == job_id))),
                *holds_job,
            )
            .values(
                state=R_RUNNING, owner_job_id=job_id, owner_run_token=run_token, worker_hostname=hostname,
                error=None, lease_until=now + timedelta(seconds=settings.reconstruction_lease_s),
                run_count=Reconstruction.run_count + 1,
                started_at=func.coalesce(Reconstruction.started_at, now),
            )
        )
        return result.rowcount == 1


def _owned(rec_id: str, job_id: str, run_token: str | None) -> list:
    """The conditions that ``job_id`` (its run ``run_token``, when given) owns the fit."""
    owner = [Reconstruction.id == rec_id, Reconstruction.owner_job_id == job_id]
    return owner + ([Reconstruction.owner_run_token == run_token] if run_token is not None else [])


def renew_lease(rec_id: str, job_id: str, settings: Settings, run_token: str | None = None, **values) -> bool:
    """Extend the job's running claim on the fit (recording ``values``); False when it no longer holds it."""
    with session_scope() as session:
        return session.execute(
            update(Reconstruction)
            .where(*_owned(rec_id, job_id, run_token), Reconstruction.state == R_RUNNING)
            .values(lease_until=utcnow() + timedelta(seconds=settings.reconstruction_lease_s), **values)
        ).rowcount == 1


def set_reconstruction(rec_id: str, job_id: str, run_token: str | None = None, *, running: bool = False,
                       **values) -> bool:
    """Change the reconstruction if ``job_id`` (its run ``run_token``, when given) owns it (and, with ``running``,
    the fit still runs: a record of its grid whose answer an outage lost may have made it succeeded); whether it
    did."""
    still = [Reconstruction.state == R_RUNNING] if running else []
    with session_scope() as session:
        return session.execute(update(Reconstruction).where(*_owned(rec_id, job_id, run_token), *still)
                               .values(**values)).rowcount == 1


def record_fit_checkpoint(rec_id: str, job_id: str, run_token: str | None, key: str) -> str | None:
    """Record ``key`` as the fit's checkpoint while ``job_id`` (its run ``run_token``) owns the running fit, under
    the reconstruction's lock; the key it replaced (None when none), for the caller to delete. :class:`LeaseLost`
    when the run does not own it (taken over, or the fit ended: no checkpoint is kept past its end)."""
    owned_and_running = (*_owned(rec_id, job_id, run_token), Reconstruction.state == R_RUNNING)
    with session_scope() as session:
        # A write first: it locks the row (PostgreSQL) or the database (SQLite) until the key is swapped.
        if session.execute(update(Reconstruction).where(*owned_and_running)
                           .values(owner_job_id=Reconstruction.owner_job_id)).rowcount != 1:
            raise LeaseLost(f"reconstruction {rec_id}: another job took the fit over (or it ended) before its "
                            "checkpoint was recorded")
        replaced = session.scalar(select(Reconstruction.checkpoint_key).where(Reconstruction.id == rec_id))
        session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(checkpoint_key=key))
    return replaced


def forget_fit_checkpoint(rec_id: str, job_id: str, run_token: str | None, key: str) -> None:
    """Clear the fit's record of its checkpoint ``key``, which the fit starting over is about to delete, while
    ``job_id`` (its run ``run_token``) owns the running fit, as :func:`forget_checkpoint` does a job's (a database
    blip skips it); :class:`LeaseLost` when the run does not own it: the checkpoint is the new owner's."""
    unless_another = case((Reconstruction.checkpoint_key == key, None), else_=Reconstruction.checkpoint_key)
    with outage_skipped(f"reconstruction {rec_id}: the record of its dropped checkpoint cleared"), \
            session_scope() as session:
        if session.execute(update(Reconstruction).where(*_owned(rec_id, job_id, run_token),
                                                        Reconstruction.state == R_RUNNING)
                           .values(checkpoint_key=unless_another)).rowcount != 1:
            raise LeaseLost(f"reconstruction {rec_id}: another job took the fit over (or it ended) before its "
                            "checkpoint was dropped")


def hand_back_fit(rec_id: str, job_id: str, run_token: str | None, error: str) -> str | None:
    """Give back the fit ``job_id`` owns, stopped by no fault of the scene's (its worker out of memory, its G_i made
    and not kept: the storage refusing it), its job failing, with ``error`` recorded: pending while another job of the
    reconstruction has neither ended nor done its reconstruct stage (it takes the fit over, maybe on a worker with more
    memory), failed when none is left to (a later job's first claim tries a failed fit again). A sweep's evaluation
    shares its edits' reconstruction but never fits: it takes nothing over (counted, the fit of a sweep had stayed
    pending for ever); nor does a job that went on with the grid a refit replaces (``refit_lost_grid``: counted, the
    refit had stayed pending with no job left to take it over). Handed back with no word, it had been listed pending
    with no error, as if a job were about to fit it, and each job that took it over failed without it saying why. The
    state it was handed back in; None when the job no longer owned the fit, running: one whose success this run
    recorded before an error (out of memory after the record's commit) had been handed back, fitted all over again."""
    with session_scope() as session:
        waiting = any("reconstruct" not in (done or []) for done in session.scalars(
            select(Job.completed_stages).where(Job.reconstruction_id == rec_id, Job.id != job_id, Job.mode != EVALUATE,
                                               Job.state.not_in(TERMINAL_STATES))))
        values = ({"state": R_PENDING, "owner_job_id": None, "owner_run_token": None} if waiting
                  else {"state": R_FAILED, "finished_at": utcnow()})
        handed = session.execute(update(Reconstruction).where(*_owned(rec_id, job_id, run_token),
                                                              Reconstruction.state == R_RUNNING)
                                 .values(lease_until=None, error=error, **values)).rowcount == 1
        return values["state"] if handed else None


def refit_lost_grid(rec_id: str, grid_key: str) -> bool:
    """Set the succeeded fit whose recorded grid ``grid_key`` the storage no longer holds back to pending, its grid
    forgotten and its progress back to none (kept, a refit that reports only at its end, a mesh's voxelizing, read as
    done to the jobs waiting on it), for the next claim to fit it again; whether it did (not when another job did so
    first, or the fit records another grid by now)."""
    with session_scope() as session:
        return session.execute(
            update(Reconstruction).where(Reconstruction.id == rec_id, Reconstruction.state == R_SUCCEEDED,
                                         Reconstruction.grid_key == grid_key)
            .values(state=R_PENDING, grid_key=None, grid_size=None, grid_sha256=None, iteration=0, total=0,
                    owner_job_id=None, owner_run_token=None, lease_until=None, finished_at=None)).rowcount == 1


class LeaseLost(RuntimeError):
    """A lease lapsed and another took it over, or may have (a fit: this job stops and waits for the job now fitting
    it, or takes the fit it handed back again)."""


class LeaseKeeper:
    """Holds a lease while a block runs: a thread calls ``renew()`` every quarter lease (loading images,
    voxelizing or storing a checkpoint report no progress), and :meth:`check` raises :class:`LeaseLost` once a
    renewal found the lease taken by another, or the lease last renewed ran out (the database out of reach
    meanwhile: another may have taken it), so two runs never both write one result.

    ``renew(**values) -> bool`` extends the lease (recording ``values``) and says whether it was still held.
    Use as ``with fit_lease(rec_id, job_id, settings, taken_at=...) as lease: ...`` (or :func:`stage_lease`);
    ``taken_at``: the ``time.monotonic()`` read before the claim that took the lease (default: now), from which it
    runs out at the latest. ``subject`` and ``taken_over`` name the holder and what a loss means in LeaseLost's
    message.
    """

    def __init__(self, renew, lease_s: float, subject: str, taken_over: str, name: str, taken_at: float | None = None):
        self._renew, self.lease_s, self.subject, self.taken_over = renew, lease_s, subject, taken_over
        self.lost = False
        self._runs_until = (time.monotonic() if taken_at is None else taken_at) + lease_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def __enter__(self) -> LeaseKeeper:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def renew(self, **values) -> bool:
        """Renew now (recording ``values``, e.g. the fit's iteration); whether the lease is still held (not known
        lost). A database outage (locked, a dropped connection) skips the renewal: the next one tries again."""
        asked = time.monotonic()
        held = None
        with outage_skipped(f"{self._thread.name}: a renewal ({self._runs_until - asked:.0f} s of the lease left)"):
            held = self._renew(**values)
        if held is None:  # skipped
            return not self.lost
        if held:
            self._runs_until = asked + self.lease_s  # (the database counts from its own moment, after this one)
        self.lost = self.lost or not held
        return held

    def check(self) -> None:
        if self.lost:
            raise LeaseLost(f"{self.subject}: its lease lapsed and {self.taken_over}")
        if time.monotonic() >= self._runs_until:
            raise LeaseLost(f"{self.subject}: its lease ran out unrenewed (the database out of reach), and "
                            "another may have taken it over")

    def _run(self) -> None:
        while not self._stop.wait(self.lease_s / 4):
            try:
                if not self.renew():
                    return
            except Exception:  # noqa: BLE001 - a database error other than an outage: the next renewal tries again
                log.warning("%s: could not renew the lease", self._thread.name, exc_info=True)


def fit_lease(rec_id: str, job_id: str, settings: Settings, run_token: str | None = None,
              taken_at: float | None = None) -> LeaseKeeper:
    """The lease of a fit the job's run claimed (:func:`try_claim_reconstruction`, ``time.monotonic()`` read
    before it as ``taken_at``)."""
    return LeaseKeeper(lambda **values: renew_lease(rec_id, job_id, settings, run_token, **values),
                       settings.reconstruction_lease_s, f"reconstruction {rec_id}", "another job took the fit over",
                       f"voxe-lease-{rec_id}", taken_at)


def _held_row_renewal(held_row: Callable[[], Update], lease_s: float, lease_column: str) -> Callable[[], bool]:
    """A :class:`LeaseKeeper`'s renewal: ``lease_column`` of the row ``held_row`` selects moved ``lease_s`` on from
    now; whether the row is still held (one updated)."""
    def renew() -> bool:
        with session_scope() as session:
            return session.execute(
                held_row().values({lease_column: utcnow() + timedelta(seconds=lease_s)})).rowcount == 1
    return renew


def stage_lease(job_id: str, run_token: str, settings: Settings) -> LeaseKeeper:
    """The lease of the run that holds the job (:func:`begin_stage`), kept while its stage runs."""
    renew = _held_row_renewal(lambda: update(Job).where(Job.id == job_id, Job.run_token == run_token),
                              settings.stage_lease_s, "run_lease_until")
    return LeaseKeeper(renew, settings.stage_lease_s, f"job {job_id}'s run", "another run took the job over",
                       f"voxe-stage-{job_id}")


def ingest_lease(scene_id: str, token: str, settings: Settings) -> LeaseKeeper:
    """The lease of the run that holds the scene's ingest (``worker.ingest``), kept while it runs and the scene is
    processing: one failed meanwhile (its key revoked) or deleted is held no more, and its ingest stops."""
    renew = _held_row_renewal(lambda: update(Scene).where(Scene.id == scene_id, Scene.ingest_token == token,
                                                          Scene.state == PROCESSING),
                              settings.stage_lease_s, "ingest_lease_until")
    return LeaseKeeper(renew, settings.stage_lease_s, f"scene {scene_id}'s ingest", "another run took it over",
                       f"voxe-ingest-{scene_id}")


def load_reconstruction(rec_id: str) -> Reconstruction | None:
    with session_scope() as session:
        return session.get(Reconstruction, rec_id)


# --------------------------------------------------------------------------- models
_GUIDANCE_CACHE: OrderedDict[tuple[str, str], object] = OrderedDict()  # least recently used first


def resolve_model(model: str, settings: Settings) -> str:
    """A hub id or local folder as given; ``tiny`` builds the smoke-test model once on this machine."""
    if model != TINY_MODEL:
        return model
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    return str(build_once(settings, "tiny-stable-diffusion", "model_index.json", build_tiny_stable_diffusion))


def build_once(settings: Settings, name: str, marker: str, build) -> Path:
    """``<model_dir>/<name>``, written by ``build(folder)`` once per machine (smoke-test models).

    Processes serialise on a file lock; the folder is built aside and renamed into
    place, so ``marker`` inside it means it is complete.
    """
    root = Path(settings.model_dir).resolve()
    target = root / name
    if (target / marker).is_file():
        return target
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".tiny.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (target / marker).is_file():
            tmp = Path(tempfile.mkdtemp(dir=root, prefix=".tiny-"))
            try:
                build(tmp)
                os.rename(tmp, target)
            finally:  # a failed build leaves no half-written folder behind
                shutil.rmtree(tmp, ignore_errors=True)
    return target


def get_guidance(model: str, device: str, settings: Settings, job: Job | None = None):
    """One StableDiffusionGuidance per (model, device) per worker process, loaded on first use.

    At most ``settings.guidance_cache_size`` stay loaded (2: a local job's SDS and attention models):
    before one more loads, the least recently used is freed, so a worker serving other models
    does not keep every one it ever loaded. A first-use download shows on ``job``'s message
    ("downloading <model> (N GB)") while its run still holds it, as its progress does.
    """
    from voxe_core.guidance.sds import StableDiffusionGuidance

    key = (model, device)
    if key in _GUIDANCE_CACHE:
        _GUIDANCE_CACHE.move_to_end(key)
        return _GUIDANCE_CACHE[key]
    while len(_GUIDANCE_CACHE) >= settings.guidance_cache_size:
        _free_least_recent_guidance()
    path = resolve_model(model, settings)
    log.info("loading guidance model %s on %s", path, device)
    on_message = (lambda text: update_job(job.id, held_by=job.run_token, message=text)) if job is not None else None
    _GUIDANCE_CACHE[key] = StableDiffusionGuidance.from_pretrained(
        path, device=device, on_message=on_message, name=model, cuda_graphs=None if settings.cuda_graphs else False,
        compile_encoder=None if settings.compile_encoder else False)
    return _GUIDANCE_CACHE[key]


def say_smoke_test_model(job: Job, stage: str, role: str, model: str) -> str | None:
    """Where ``model`` is a folder ``voxe build-tiny-model`` wrote (random weights; ``tiny`` is labelled by its name
    already), a ``warning`` event of ``stage`` saying so and the sentence in the job's ``result.smoke_test[role]``:
    the job records showed the folder's path alone (the API may not see the folder; this worker loads it). Returns
    the sentence, for the grid the stage writes (as ``voxe edit``'s), or None."""
    from voxe_core.guidance.loading import SMOKE_TEST_MODEL_NOTE, smoke_test_model

    if model == TINY_MODEL or not smoke_test_model(model):
        return None
    note = f"SMOKE TEST: the {role} model {model!r} is {SMOKE_TEST_MODEL_NOTE}"
    record_warning(job.id, stage, note)
    _change_result(job.id, lambda result: {**result, "smoke_test": {**result.get("smoke_test", {}), role: note}})
    return note


def _free_least_recent_guidance() -> None:
    """Drop the least recently used guidance and give its memory back (on CUDA, the allocator's cache too)."""
    model, device = _GUIDANCE_CACHE.popitem(last=False)[0]  # the guidance itself kept by no name here
    log.info("freeing guidance model %s on %s", model, device)
    give_back_freed_memory()


def give_back_freed_memory() -> None:
    """Collect the reference cycles of models just let go, then (on CUDA) give the allocator's cached blocks back."""
    import gc

    import torch

    gc.collect()  # the modules' reference cycles, before the allocator can give their blocks back
    if torch.cuda.is_initialized():
        torch.cuda.empty_cache()
