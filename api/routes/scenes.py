"""/v1/scenes: upload (validated before anything is stored), list, get, delete."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, UploadFile, status
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from api.deps import get_session, settings_dep, storage_dep
from api.models import QUEUED, RUNNING, Job, Reconstruction, Scene, new_id
from api.schemas import Page, ReconstructionOut, SceneOut
from api.settings import Settings
from api.storage import Storage
from api.uploads import UploadError, ingest

log = logging.getLogger("voxe.api")
router = APIRouter(prefix="/v1/scenes", tags=["scenes"])

_ERRORS = {404: {"description": "no such scene"}}


def scene_out(scene: Scene) -> SceneOut:
    return SceneOut.model_validate(scene, from_attributes=True)


def get_scene_or_404(session: Session, scene_id: str) -> Scene:
    scene = session.get(Scene, scene_id)
    if scene is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id!r} not found")
    return scene


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SceneOut,
    responses={413: {"description": "upload over the size limit"},
               422: {"description": "not a valid dataset; the message names the file and frame"}},
    summary="Upload a posed image set",
)
def create_scene(
    archive: UploadFile | None = File(
        None, description="a zip of a NeRF-synthetic folder (transforms_train.json, ...) or an instant-ngp "
                          "folder (transforms.json); the folder may be the archive root or its only top-level folder"),
    files: list[UploadFile] | None = File(
        None, description="alternatively the dataset's files, each named by its path in the dataset folder "
                          "(e.g. transforms.json, images/0001.png)"),
    name: str | None = Form(None, max_length=255, description="display name (default: the upload's name)"),
    session: Session = Depends(get_session),
    settings: Settings = Depends(settings_dep),
    storage: Storage = Depends(storage_dep),
) -> SceneOut:
    uploaded = [(f.filename or "", f.file) for f in files or []]
    try:
        result, staging = ingest(
            Path(settings.work_dir) / "uploads", archive.file if archive is not None else None, uploaded,
            settings.max_extracted_bytes, settings.max_upload_files, settings.validation_downsample,
        )
    except UploadError as exc:
        raise HTTPException(exc.status, str(exc)) from None
    scene_id = new_id()
    key = f"scenes/{scene_id}/dataset.zip"
    try:
        stored = storage.put_file(key, result.archive, "application/zip")
        default_name = Path(archive.filename or "").stem if archive is not None else ""
        scene = Scene(
            id=scene_id, name=name or default_name or f"scene-{scene_id[:8]}", format=result.format,
            image_count=result.image_count, width=result.width, height=result.height, splits=result.splits,
            storage_key=key, size_bytes=stored.size, sha256=stored.sha256,
        )
        session.add(scene)
        session.commit()
    except BaseException:
        session.rollback()
        storage.delete(key)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return scene_out(scene)


@router.get("", response_model=Page[SceneOut], summary="List scenes, newest first")
def list_scenes(
    limit: int = Query(20, ge=1, le=200),
    offset: int = Query(0, ge=0),
    session: Session = Depends(get_session),
) -> Page[SceneOut]:
    total = session.scalar(select(func.count()).select_from(Scene)) or 0
    rows = session.scalars(select(Scene).order_by(Scene.created_at.desc(), Scene.id).limit(limit).offset(offset))
    return Page[SceneOut](items=[scene_out(s) for s in rows], total=total, limit=limit, offset=offset)


@router.get("/{scene_id}", response_model=SceneOut, responses=_ERRORS)
def get_scene(scene_id: str, session: Session = Depends(get_session)) -> SceneOut:
    return scene_out(get_scene_or_404(session, scene_id))


@router.get("/{scene_id}/reconstructions", response_model=list[ReconstructionOut], responses=_ERRORS,
            summary="The scene's cached reconstructions (one per reconstruction-parameter set)")
def list_reconstructions(scene_id: str, session: Session = Depends(get_session)) -> list[ReconstructionOut]:
    get_scene_or_404(session, scene_id)
    rows = session.scalars(select(Reconstruction).where(Reconstruction.scene_id == scene_id)
                           .order_by(Reconstruction.created_at))
    return [ReconstructionOut.model_validate(r, from_attributes=True) for r in rows]


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses={**_ERRORS, 409: {"description": "the scene has queued or running jobs"}})
def delete_scene(
    scene_id: str, session: Session = Depends(get_session), storage: Storage = Depends(storage_dep)
) -> None:
    scene = get_scene_or_404(session, scene_id)
    active = session.scalar(select(func.count()).select_from(Job)
                            .where(Job.scene_id == scene_id, Job.state.in_((QUEUED, RUNNING))))
    if active:
        raise HTTPException(status.HTTP_409_CONFLICT,
                            f"scene {scene_id!r} has {active} queued or running job(s); cancel them first")
    job_ids = list(session.scalars(select(Job.id).where(Job.scene_id == scene_id)))
    rec_ids = list(session.scalars(select(Reconstruction.id).where(Reconstruction.scene_id == scene_id)))
    session.delete(scene)  # jobs, artifacts and reconstructions go with it (ON DELETE CASCADE)
    session.commit()
    # Rows first, then objects: a crash in between leaves unreferenced objects, never dangling rows.
    prefixes = [f"scenes/{scene_id}/"] + [f"jobs/{j}/" for j in job_ids] + [f"reconstructions/{r}/" for r in rec_ids]
    for prefix in prefixes:
        try:
            storage.delete_prefix(prefix)
        except Exception:  # noqa: BLE001
            log.warning("could not delete stored objects under %s", prefix, exc_info=True)
