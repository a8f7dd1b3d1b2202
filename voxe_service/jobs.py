"""A job's lifecycle as the API, the reaper and the workers all write it: terminal states and the event timeline.

Every state change is a conditional UPDATE (the row must still be unfinished, and whatever
else the caller saw), so concurrent writers never overwrite each other's ending, and each
change that took effect is recorded as a :class:`~voxe_service.models.JobEvent` in the same
transaction.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from sqlalchemy import delete, event, func, select, update
from sqlalchemy.orm import Session, SessionTransaction

from voxe_service import webhooks
from voxe_service.models import CANCELED, TERMINAL_STATES, ApiKey, Artifact, Job, JobEvent, utcnow
from voxe_service.settings import Settings
from voxe_service.storage import get_storage, job_key

log = logging.getLogger("voxe.jobs")

_WITHDRAWN, _COMMITTED = "voxe_withdrawn", "voxe_withdrawn_committed"
"""``session.info`` keys: the withdrawn artifacts' keys of each open transaction of the session, whose bytes go once
it commits ({transaction: [(keys, settings)]}), and those of the outermost transaction committed, as it closes."""


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
                error: str | None = None, where: Iterable = (), settings: Settings | None = None) -> list[str]:
    """Move the unfinished jobs among ``job_ids`` (that also match ``where``) to the terminal ``state``.

    Returns the ids that changed, each with a ``state`` event carrying the error or message. Jobs ended canceled
    have their unfinished stage's artifacts withdrawn here, so no caller can forget it: the rows in this transaction
    (:func:`_withdraw_unfinished_stage_artifacts`), the bytes once it commits, from the storage of ``settings`` (the
    process's by default), and never where it rolls back. The hold of a run of the job goes with the ending
    (``run_token``): a run still going (stalled past its lease, its process alive) finds the job no longer its own,
    and publishes or records nothing more into it (``RunSuperseded``).
    """
    ids = list(job_ids)
    if not ids:
        return []
    now = utcnow()
    changed = []
    for message, some in _naming_a_revoke(session, ids, state, message).items():
        changed += session.execute(
            update(Job).where(Job.id.in_(some), Job.state.not_in(TERMINAL_STATES), *where)
            .values(state=state, finished_at=now, updated_at=now, eta_seconds=None, message=message, error=error,
                    run_token=None, run_lease_until=None)
            .returning(Job.id, Job.stage, Job.message)
        ).all()
    for job_id, stage, message in changed:
        record_event(session, job_id, state, stage=stage, detail=error or message)
        if state == CANCELED:
            _discard_once_committed(session, job_id, _withdraw_unfinished_stage_artifacts(session, job_id), settings)
    return [job_id for job_id, _, _ in changed]


def _naming_a_revoke(session: Session, ids: list[str], state: str, message: str | None) -> dict[str | None, list[str]]:
    """{message: job ids}: ``message`` for each job, and for one canceled whose API key is revoked ``message``
    naming the revoke. ``revoke-key`` flags a running job canceled, and its run or the reaper ends it: it had ended
    "canceled during edit", its webhook's receiver left to think someone had canceled it."""
    if state != CANCELED or message is None:
        return {message: ids}
    revoked = dict(session.execute(select(Job.id, ApiKey.id).join(ApiKey, ApiKey.id == Job.owner_key_id)
                                   .where(Job.id.in_(ids), ApiKey.revoked_at.is_not(None))).all())
    messages: dict[str | None, list[str]] = {}
    for job_id in ids:
        said = message if job_id not in revoked else f"{message}: its API key {revoked[job_id]} was revoked"
        messages.setdefault(said, []).append(job_id)
    return messages


def _withdraw_unfinished_stage_artifacts(session: Session, job_id: str) -> list[str]:
    """Delete the rows of the artifacts the job's unfinished stage published, by this run of it or an earlier one
    (those announced on the timeline since the last ``stage_completed``), as :func:`finish_jobs` ends the job
    canceled; return their storage keys, whose bytes go once this transaction is committed.

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


def _discard_once_committed(session: Session, job_id: str, keys: list[str], settings: Settings | None) -> None:
    """Hold the job's own withdrawn keys (an initial grid's bytes are the shared reconstruction's) for the commit of
    the transaction (or savepoint) they were withdrawn in. (On SQLite, pysqlite's legacy transaction control makes a
    savepoint opened first in a transaction the transaction itself, its release a commit: an ending there rolled
    back later stays, its bytes left listed by no row. The service opens no savepoints.)"""
    if own := [key for key in keys if key.startswith(job_key(job_id, ""))]:
        transaction = session.get_nested_transaction() or session.get_transaction()
        session.info.setdefault(_WITHDRAWN, {}).setdefault(transaction, []).append((own, settings))


@event.listens_for(Session, "after_commit")
def _hold_committed_withdrawals(session: Session) -> None:
    """A savepoint's withdrawals wait for its parent's commit; the outermost commit's go as it closes."""
    pending = session.info.get(_WITHDRAWN)
    transaction = session.get_nested_transaction() or session.get_transaction()
    if pending and (withdrawn := pending.pop(transaction, None)):
        if transaction.nested:
            pending.setdefault(transaction.parent, []).extend(withdrawn)
        else:
            session.info.setdefault(_COMMITTED, []).extend(withdrawn)


@event.listens_for(Session, "after_transaction_end")
def _discard_committed_withdrawals(session: Session, transaction: SessionTransaction) -> None:
    """Delete the bytes a committed transaction withdrew, once it has closed (so nothing raised here can leave the
    session half-committed), and forget those of one that ended without committing (rolled back, or its session
    closed): no later commit of the session deletes bytes its rows still list. As cleanup after a committed ending,
    a storage failure is logged, never raised to its caller: the bytes stay behind, listed by no row, deleted with
    the job."""
    if pending := session.info.get(_WITHDRAWN):
        pending.pop(transaction, None)
    if transaction.parent is not None:
        return
    for keys, settings in session.info.pop(_COMMITTED, []):
        try:
            storage = get_storage(settings)
        except Exception:  # noqa: BLE001 - see the docstring
            log.warning("could not delete the withdrawn artifacts %s", keys, exc_info=True)
            continue
        for key in keys:
            storage.discard(key)  # (logs a failure)
