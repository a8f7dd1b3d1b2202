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

from voxe_core.presets import check_fit
from voxe_service.db import locked
from voxe_service.jobs import finish_jobs
from voxe_service.models import (
    EVALUATE, FAILED, PROCESSING, QUEUED, R_FAILED, R_PENDING, READY, Job, Reconstruction, Scene, utcnow,
)
from voxe_service.queue import evaluations_waiting_on


def lock_scene(session: Session, scene_id: str) -> Scene | None:
    """The scene's current row, locked until the transaction ends (:func:`voxe_service.db.locked`), so no other
    writer can change its state before the commit."""
    return locked(session, Scene, scene_id)


def waiting_jobs(session: Session, scene_id: str, include_evaluations: bool = False) -> list[Job]:
    """Queued jobs of the scene never handed to the broker (the ingest sends the edits; evaluations follow)."""
    query = select(Job).where(Job.scene_id == scene_id, Job.state == QUEUED, Job.task_id.is_(None))
    if not include_evaluations:
        query = query.where(Job.mode != EVALUATE)
    return list(session.scalars(query.order_by(Job.created_at, Job.id)))


def mark_ready(session: Session, scene_id: str, where=(), **values) -> list[Job] | None:
    """processing -> ready with ``values`` (sizes, the final archive, the backbone "auto" means); the jobs to
    dispatch now, touched: the reaper leaves them to the ingest for ``VOXE_JOB_STALE_TIMEOUT_S`` (one waiting longer,
    behind a long ingest, had looked never sent to a pass before the ingest sent it, and was sent twice). A waiting job
    whose reconstruction parameters that backbone cannot take (what a 422 refuses on a ready scene) fails naming why,
    and so do the evaluations of its sweep that wait on it and its reconstruction (still pending: no job can ever fit
    it on this scene, and its listing says why).

    None when the scene is no longer processing (deleted, or failed by the reaper meanwhile), or not as ``where``
    says (another run of its ingest took it over).
    """
    now = utcnow()
    changed = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING, *where)
                              .values(state=READY, error=None, updated_at=now, **values))
    if changed.rowcount != 1:
        return None
    dispatch = []
    image_count = session.scalar(select(Scene.image_count).where(Scene.id == scene_id))  # (a mesh's: as rendered)
    for job in waiting_jobs(session, scene_id):
        try:
            check_fit(job.reconstruction.params, values.get("backbone"), image_count)
        except ValueError as exc:
            error = f"params.reconstruction: {exc}"
            finish_jobs(session, [job.id], FAILED, error=error)
            finish_jobs(session, evaluations_waiting_on(session, job), FAILED,
                        error=f"evaluate: source job {job.id} failed: {error}")
            session.execute(update(Reconstruction).where(Reconstruction.id == job.reconstruction_id,
                                                         Reconstruction.state == R_PENDING)
                            .values(state=R_FAILED, error=error, finished_at=now))
        else:
            dispatch.append(job)
    if dispatch:
        session.execute(update(Job).where(Job.id.in_([job.id for job in dispatch])).values(updated_at=now))
    return dispatch


def fail_scene(session: Session, scene_id: str, reason: str, where=(), warnings: list[str] | None = None) -> bool:
    """processing -> failed with ``reason`` and the ``warnings`` its ingest said before it failed (None: not known,
    its upload never loaded); its stored bytes no longer count (``size_bytes`` 0); the jobs
    waiting on it fail naming it, and so do their reconstructions (pending: no job can ever fit them on this
    scene; they had stayed pending for good). False when the scene was not processing (or not as ``where``
    says)."""
    now, said = utcnow(), {} if warnings is None else {"warnings": warnings}  # (None left SQL NULL, not JSON null)
    changed = session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING, *where)
                              .values(state=FAILED, error=reason, size_bytes=0, updated_at=now, **said))
    if changed.rowcount != 1:
        return False
    error = f"the scene's upload failed processing: {reason}"
    finish_jobs(session, [j.id for j in waiting_jobs(session, scene_id, include_evaluations=True)], FAILED,
                error=error)
    session.execute(update(Reconstruction).where(Reconstruction.scene_id == scene_id,
                                                 Reconstruction.state == R_PENDING)
                    .values(state=R_FAILED, error=error, finished_at=now))
    return True
