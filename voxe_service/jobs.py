"""A job's lifecycle as the API, the reaper and the workers all write it: terminal states and the event timeline.

Every state change is a conditional UPDATE (the row must still be unfinished, and whatever
else the caller saw), so concurrent writers never overwrite each other's ending, and each
change that took effect is recorded as a :class:`~voxe_service.models.JobEvent` in the same
transaction.
"""

from __future__ import annotations

from collections.abc import Iterable

from sqlalchemy import delete, func, select, update
from sqlalchemy.orm import Session

from voxe_service import webhooks
from voxe_service.models import TERMINAL_STATES, Artifact, Job, JobEvent, utcnow
from voxe_service.storage import get_storage, job_key


def record_event(session: Session, job_id: str, kind: str, *, stage: str | None = None,
                 iteration: int | None = None, worker: str | None = None, detail: str | None = None) -> None:
    """Add one event to the job's timeline, and its webhook delivery if the job wants one (both committed with
    the caller's transaction), under the job's row lock.

    Event streams read each job's events past the last id they sent. PostgreSQL numbers an event as it is written,
    so an event numbered while another writer of the job had yet to commit became visible after one numbered later,
    and a stream (or a timeline read handing over to one) that had read past that number never sent it. The job's
    row is locked first and held until the commit, so a job's events commit in id order: ``FOR NO KEY UPDATE``, the
    lock its UPDATE takes (a writer that changed the job first holds it already, and waits for nothing more), which
    lets rows naming the job be written meanwhile. SQLite lets one writer in at a time anyway.
    """
    session.execute(select(Job.id).where(Job.id == job_id).with_for_update(key_share=True))
    event = JobEvent(job_id=job_id, kind=kind, stage=stage, iteration=iteration, worker_hostname=worker,
                     detail=detail, at=utcnow())
    session.add(event)
    session.flush()  # the event's id, which its delivery names
    webhooks.enqueue(session, job_id, event)


def finish_jobs(session: Session, job_ids: Iterable[str], state: str, *, message: str | None = None,
                error: str | None = None, where: Iterable = ()) -> list[str]:
    """Move the unfinished jobs among ``job_ids`` (that also match ``where``) to the terminal ``state``.

    Returns the ids that changed, each with a ``state`` event carrying the error or message. A caller ending jobs
    canceled withdraws their unfinished stage's artifacts (:func:`withdraw_unfinished_stage_artifacts`). The hold of
    a run of the job goes with the ending (``run_token``): a run still going (stalled past its lease, its process
    alive) finds the job no longer its own, and publishes or records nothing more into it (``RunSuperseded``).
    """
    ids = list(job_ids)
    if not ids:
        return []
    now = utcnow()
    changed = session.execute(
        update(Job).where(Job.id.in_(ids), Job.state.not_in(TERMINAL_STATES), *where)
        .values(state=state, finished_at=now, updated_at=now, eta_seconds=None, message=message, error=error,
                run_token=None, run_lease_until=None)
        .returning(Job.id, Job.stage)
    ).all()
    for job_id, stage in changed:
        record_event(session, job_id, state, stage=stage, detail=error or message)
    return [job_id for job_id, _ in changed]


def withdraw_unfinished_stage_artifacts(session: Session, job_id: str) -> list[str]:
    """Delete the rows of the artifacts the job's unfinished stage published, by this run of it or an earlier one
    (those announced on the timeline since the last ``stage_completed``), as the job ends canceled; return their
    storage keys, for the caller to delete once this transaction is committed.

    A job canceled during a stage lists none of that stage's outputs (an export's turntable without its mesh),
    only those of the stages it completed. Previews stay: progress images, announced as ``preview`` events, no
    stage's output. Rows first, in the ending's transaction: a worker dying before the bytes go leaves only bytes no
    row lists (deleted with the job), never a listed artifact whose bytes are gone.
    """
    since = select(func.coalesce(func.max(JobEvent.id), 0)).where(
        JobEvent.job_id == job_id, JobEvent.kind == "stage_completed").scalar_subquery()
    published = select(JobEvent.detail).where(JobEvent.job_id == job_id, JobEvent.kind == "artifact",
                                              JobEvent.id > since)
    return list(session.scalars(delete(Artifact).where(Artifact.job_id == job_id, Artifact.name.in_(published))
                                .returning(Artifact.key)))


def discard_withdrawn(job_id: str, keys: Iterable[str], settings=None) -> None:
    """Delete the stored bytes of the job's withdrawn artifacts, once the withdrawal is committed: only the job's own
    (an initial grid's bytes are the shared reconstruction's)."""
    for key in keys:
        if key.startswith(job_key(job_id, "")):
            get_storage(settings).discard(key)
