"""A scene's lifecycle: processing (stored, its ingest queued) -> ready, or failed with the reason.

Jobs created on a processing scene are recorded but not sent: they wait, costing no worker,
until the ingest marks the scene ready and dispatches them (or fails them with the scene's
reason). The handover is race-free: the API reads the scene's state under a lock on its row
(:func:`lock_scene`, after writing the job), and the ingest changes the state and collects the
waiting jobs in one transaction (:func:`mark_ready`), so every job is sent exactly once, by
whichever side saw the scene ready.
"""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from voxe_service.jobs import finish_jobs
from voxe_service.models import EVALUATE, FAILED, PROCESSING, QUEUED, READY, Job, Scene, utcnow


def lock_scene(session: Session, scene_id: str) -> Scene | None:
    """The scene's current row, locked until the transaction ends (PostgreSQL: FOR UPDATE).

    SQLite has no row locks: call it after the transaction's first write, which holds the
    database's write lock, so no other writer can change the state before the commit.
    """
    return session.scalars(select(Scene).where(Scene.id == scene_id).with_for_update()
                           .execution_options(populate_existing=True)).first()


def waiting_jobs(session: Session, scene_id: str, include_evaluations: bool = False) -> list[Job]:
    """Queued jobs of the scene never handed to the broker (the ingest sends the edits; evaluations follow)."""
    query = select(Job).where(Job.scene_id == scene_id, Job.state == QUEUED, Job.task_id.is_(None))
    if not include_evaluations:
        query = query.where(Job.mode != EVALUATE)
    return list(session.scalars(query.order_by(Job.created_at, Job.id)))


def mark_ready(session: Session, scene_id: str, **values) -> list[Job] | None:
    """processing -> ready with ``values`` (sizes, the final archive); the jobs to dispatch now.

    None when the scene is no longer processing (deleted, or failed by the reaper meanwhile).
    """
    now = utcnow()
    changed = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING)
                              .values(state=READY, error=None, updated_at=now, **values))
    if changed.rowcount != 1:
        return None
    return waiting_jobs(session, scene_id)


def fail_scene(session: Session, scene_id: str, reason: str, where=()) -> bool:
    """processing -> failed with ``reason`` (its stored bytes no longer count: ``size_bytes`` 0); the jobs
    waiting on it fail naming it. False when the scene was not processing (or not as ``where`` says)."""
    changed = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING, *where)
                              .values(state=FAILED, error=reason, size_bytes=0, updated_at=utcnow()))
    if changed.rowcount != 1:
        return False
    waiting = waiting_jobs(session, scene_id, include_evaluations=True)
    finish_jobs(session, [j.id for j in waiting], FAILED,
                error=f"the scene's upload failed processing: {reason}")
    return True
