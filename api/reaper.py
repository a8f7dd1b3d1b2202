"""The reaper: fail jobs that nothing will ever finish, so no job stays "running" or "queued" for ever.

A job is orphaned when

* it is ``running``, its record has not changed for ``VOXE_JOB_STALE_TIMEOUT_S`` (a running
  stage writes progress twice a second) and its worker has not written a heartbeat for as long
  (the worker is gone: killed, its machine lost). A worker that comes back under the same name
  heartbeats again and re-queues its jobs itself (SQL broker); Redis redelivers after its
  visibility timeout -- either way the job is not orphaned while that can still happen in time;
* or it is ``queued`` with no task id for as long: the API stopped between recording the job
  and handing its chain to the broker, so no message exists.

The API runs :func:`reap_orphaned_jobs` at startup and then every ``VOXE_REAPER_INTERVAL_S`` in a
background thread (:class:`Reaper`). Every update is conditional on the row still being what the
reaper saw, so several API processes may reap side by side and a worker that reports in at the
last moment wins.
"""

from __future__ import annotations

import logging
import threading
from datetime import datetime, timedelta

from sqlalchemy import or_, select, update

from api.db import session_scope
from api.models import FAILED, QUEUED, RUNNING, Job, WorkerHeartbeat, utcnow
from api.settings import Settings

log = logging.getLogger("voxe.reaper")


def _fail(session, job_id: str, seen_updated_at: datetime, seen_state: str, error: str, now: datetime) -> bool:
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == seen_state, Job.updated_at == seen_updated_at)
        .values(state=FAILED, error=error, finished_at=now, updated_at=now, eta_seconds=None)
    )
    return result.rowcount == 1


def reap_orphaned_jobs(settings: Settings, now: datetime | None = None) -> list[str]:
    """Mark orphaned jobs failed with the reason; returns their ids."""
    now = now or utcnow()
    timeout = settings.job_stale_timeout_s
    cutoff = now - timedelta(seconds=timeout)
    reaped = []
    with session_scope() as session:
        alive = select(WorkerHeartbeat.hostname).where(WorkerHeartbeat.last_seen >= cutoff)
        running = session.execute(
            select(Job.id, Job.stage, Job.worker_hostname, Job.updated_at).where(
                Job.state == RUNNING, Job.updated_at < cutoff,
                or_(Job.worker_hostname.is_(None), Job.worker_hostname.not_in(alive)),
            )
        ).all()
        for job in running:
            error = (f"worker {job.worker_hostname or '(unknown)'} stopped while the job was in {job.stage}: "
                     f"no heartbeat and no progress for {timeout:.0f} s, and the task was not redelivered "
                     f"(VOXE_JOB_STALE_TIMEOUT_S)")
            if _fail(session, job.id, job.updated_at, RUNNING, error, now):
                reaped.append(job.id)
        never_sent = session.execute(
            select(Job.id, Job.updated_at).where(Job.state == QUEUED, Job.task_id.is_(None), Job.updated_at < cutoff)
        ).all()
        for job in never_sent:
            error = (f"the job was never handed to the broker (the API stopped while creating it); "
                     f"failed after {timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S): create it again")
            if _fail(session, job.id, job.updated_at, QUEUED, error, now):
                reaped.append(job.id)
    for job_id in reaped:
        log.warning("reaper: job %s failed as orphaned", job_id)
    return reaped


def _delete_checkpoints(job_ids: list[str], settings: Settings) -> None:
    from api.storage import get_storage
    from worker.runtime import job_key

    storage = get_storage(settings)
    for job_id in job_ids:
        try:
            storage.delete_prefix(job_key(job_id, "checkpoints/"))
        except Exception:  # noqa: BLE001 - leftover checkpoints are harmless
            log.warning("reaper: could not delete the checkpoints of job %s", job_id, exc_info=True)


class Reaper:
    """Runs :func:`reap_orphaned_jobs` now and every ``reaper_interval_s`` until :meth:`stop`."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="voxe-reaper", daemon=True)

    def start(self) -> Reaper:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                _delete_checkpoints(reap_orphaned_jobs(self.settings), self.settings)
            except Exception:  # noqa: BLE001 - a failed pass is retried on the next one
                log.warning("reaper pass failed", exc_info=True)
            self._stop.wait(self.settings.reaper_interval_s)
