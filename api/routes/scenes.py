"""/v1/scenes: upload (validated before anything is stored), list, get, delete; each key sees only its own."""

from __future__ import annotations

import hashlib
import logging
import shutil
from pathlib import Path
from typing import BinaryIO

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, Response, UploadFile, status
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.auth import Idempotency, check_upload_bytes, current_key, idempotency_key, lock_key
from api.deps import get_session, settings_dep, storage_dep
from api.models import QUEUED, RUNNING, ApiKey, Job, Reconstruction, Scene, new_id
from api.schemas import Page, ReconstructionOut, SceneOut
from api.settings import Settings
from api.storage import Storage
from api.uploads import UploadError, ingest

log = logging.getLogger("voxe.api")
router = APIRouter(prefix="/v1/scenes", tags=["scenes"])

_ERRORS = {404: {"description": "no such scene (or another key's)"}}
MAX_OFFSET = 1_000_000_000


def scene_out(scene: Scene) -> SceneOut:
    return SceneOut.model_validate(scene, from_attributes=True)


def get_scene_or_404(session: Session, scene_id: str, key: ApiKey) -> Scene:
    """The key's scene; another key's scene is as absent as a missing one."""
    scene = session.get(Scene, scene_id)
    if scene is None or scene.owner_key_id != key.id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id!r} not found")
    return scene


def _upload_digest(archive: BinaryIO | None, files: list[tuple[str, BinaryIO]], name: str | None) -> str:
    """sha256 of what an upload asks for (field names, file names and bytes), not of its multipart framing."""
    digest = hashlib.sha256(repr(name).encode())
    parts = [("archive", archive)] if archive is not None else [(f"files:{n}", h) for n, h in files]
    for label, handle in parts:
        digest.update(b"\0" + label.encode() + b"\0")
        while chunk := handle.read(1 << 20):
            digest.update(chunk)
        handle.seek(0)
    return digest.hexdigest()


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SceneOut,
    responses={200: {"description": "a retry with the same Idempotency-Key: the scene it created"},
               401: {"description": "missing or invalid API key"},
               413: {"description": "upload over the size limit"},
               422: {"description": "not a valid dataset (the message names the file and frame), or an "
                                    "Idempotency-Key reused with a different upload"},
               429: {"description": "the key's upload quota is used up (Retry-After)"}},
    summary="Upload a posed image set (optionally with an Idempotency-Key header)",
)
def create_scene(
    request: Request,
    response: Response,
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
    key: ApiKey = Depends(current_key),
) -> SceneOut:
    """201 with the new scene; 200 with the original one for a retry carrying the same Idempotency-Key."""
    source = archive.file if archive is not None else None
    uploaded = [(f.filename or "", f.file) for f in files or []]
    idem_key = idempotency_key(request)
    idem = Idempotency(idem_key, _upload_digest(source, uploaded, name), "scenes") if idem_key else None
    if idem is not None and (replayed := idem.replayed(session, key, response, Scene)) is not None:
        return scene_out(replayed)
    check_upload_bytes(session, key, settings, 0)  # already over: answer before unpacking anything
    try:
        result, staging = ingest(
            Path(settings.work_dir) / "uploads", source, uploaded, settings.max_extracted_bytes,
            settings.max_upload_files, settings.validation_downsample, settings.max_compression_ratio,
            settings.max_image_pixels,
        )
    except UploadError as exc:
        raise HTTPException(exc.status, str(exc)) from None
    scene_id = new_id()
    storage_key = f"scenes/{scene_id}/dataset.zip"
    try:
        stored = storage.put_file(storage_key, result.archive, "application/zip")
        default_name = Path(archive.filename or "").stem[:255] if archive is not None else ""
        scene = Scene(
            id=scene_id, owner_key_id=key.id, name=name or default_name or f"scene-{scene_id[:8]}",
            format=result.format, image_count=result.image_count, width=result.width, height=result.height,
            splits=result.splits, storage_key=storage_key, size_bytes=stored.size, sha256=stored.sha256,
        )
        lock_key(session, key)
        session.add(scene)
        if idem is not None:
            idem.record(session, key, scene_id)
        session.flush()
        check_upload_bytes(session, key, settings, stored.size, including_new=True)
        session.commit()
    except BaseException as exc:
        session.rollback()
        storage.delete(storage_key)
        if idem is not None and isinstance(exc, IntegrityError):  # a concurrent retry created it first
            if (replayed := idem.replayed(session, key, response, Scene)) is not None:
                return scene_out(replayed)
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return scene_out(scene)


@router.get("", response_model=Page[SceneOut], summary="List scenes, newest first")
def list_scenes(
    limit: int = Query(20, ge=1, le=200),
    offset: int = Query(0, ge=0, le=MAX_OFFSET),
    session: Session = Depends(get_session),
    key: ApiKey = Depends(current_key),
) -> Page[SceneOut]:
    mine = Scene.owner_key_id == key.id
    total = session.scalar(select(func.count()).select_from(Scene).where(mine)) or 0
    rows = session.scalars(select(Scene).where(mine).order_by(Scene.created_at.desc(), Scene.id)
                           .limit(limit).offset(offset))
    return Page[SceneOut](items=[scene_out(s) for s in rows], total=total, limit=limit, offset=offset)


@router.get("/{scene_id}", response_model=SceneOut, responses=_ERRORS)
def get_scene(scene_id: str, session: Session = Depends(get_session), key: ApiKey = Depends(current_key)) -> SceneOut:
    return scene_out(get_scene_or_404(session, scene_id, key))


@router.get("/{scene_id}/reconstructions", response_model=list[ReconstructionOut], responses=_ERRORS,
            summary="The scene's cached reconstructions (one per reconstruction-parameter set)")
def list_reconstructions(
    scene_id: str, session: Session = Depends(get_session), key: ApiKey = Depends(current_key)
) -> list[ReconstructionOut]:
    get_scene_or_404(session, scene_id, key)
    rows = session.scalars(select(Reconstruction).where(Reconstruction.scene_id == scene_id)
                           .order_by(Reconstruction.created_at))
    return [ReconstructionOut.model_validate(r, from_attributes=True) for r in rows]


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses={**_ERRORS, 409: {"description": "the scene has queued or running jobs"}})
def delete_scene(
    scene_id: str, session: Session = Depends(get_session), storage: Storage = Depends(storage_dep),
    key: ApiKey = Depends(current_key),
) -> None:
    scene = get_scene_or_404(session, scene_id, key)
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
