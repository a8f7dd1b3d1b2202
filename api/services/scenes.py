"""Scenes: an upload checked and stored at once, its ingest queued; listing, lookup, deletion."""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from fastapi import HTTPException, status
from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.auth import Idempotency, check_upload_bytes, lock_live_key
from api.http_semantics import ID_SHOWN, try_again_soon
from api.paging import PageQuery, PageRows, read_page
from api.uploads import UploadError, stage_upload, staging_folder
from voxe_core.mesh_input import MESH_INPUT_SUFFIXES
from voxe_service.models import FAILED, QUEUED, RUNNING, ApiKey, Job, Reconstruction, Scene, new_id
from voxe_service.queue import QUEUE_UNAVAILABLE, TaskQueue
from voxe_service.scenes import fail_scene, lock_scene
from voxe_service.settings import Settings
from voxe_service.storage import Storage, job_key, reconstruction_storage_key, scene_key
from voxe_service.texts import listed

log = logging.getLogger("voxe.api")


@dataclass
class Upload:
    """What a POST /v1/scenes sent: one zip, or files named by their paths, an optional display name and a mesh's
    shading mode."""

    archive: BinaryIO | None
    archive_name: str | None
    files: list[tuple[str, BinaryIO]]
    name: str | None
    mesh_shading: str | None = None
    mesh_up_axis: str | None = None

    def default_name(self, scene_format: str) -> str:
        """The name of a scene of ``scene_format`` sent with none: its zip's file name, or its mesh's, or the one
        folder its files are in, without suffix and control characters; "" where there is none (a folder's files
        sent loose) or it is blank (a zip "   .zip": stored, it had been the blank name a 422 refuses when sent). A
        mesh or a folder sent as files (curl's ``-F files=@spot.obj``) had been named "scene-<id>", a zip alone by
        its name."""
        if self.archive is not None:
            stem = Path(self.archive_name or "").stem
        else:
            paths = [PurePosixPath(name.replace("\\", "/")) for name, _ in self.files]
            meshes = [path for path in paths if path.suffix.lower() in MESH_INPUT_SUFFIXES]
            folders = {path.parts[0] for path in paths if len(path.parts) > 1}
            if scene_format == "mesh" and len(meshes) == 1:  # (a dataset's own mesh, COLMAP's fused.ply, names none)
                stem = meshes[0].stem
            elif len(folders) == 1 and all(len(path.parts) > 1 for path in paths):
                stem = folders.pop()
            else:
                stem = ""
        name = "".join(c for c in stem if c.isprintable())[:255]
        return name if name.strip() else ""

    def digests(self) -> tuple[str, str | None]:
        """sha256 of what the upload asks for (field names, file names and bytes), not of its multipart framing; a
        field added later counts only when sent, so a retry across an upgrade still matches its first request. Then
        the digest an earlier version recorded for it where that differs (the Idempotency record's
        ``earlier_sha256``), else None.

        The archive's file name counts where it names the scene (no ``name`` sent): the same bytes as guitar.zip
        had replayed the scene named "mic" from mic.zip. With a name sent it names nothing, so it does not count
        (a client may send a temporary file's name). Before, it did not count at all: that digest is the earlier
        one, so a record written then still replays its bytes sent under another file name."""
        fields = (self.name, self.mesh_shading) + ((self.mesh_up_axis,) if self.mesh_up_axis is not None else ())
        named_by_file = self.archive is not None and not self.name
        current = hashlib.sha256(repr(fields).encode())
        earlier = current.copy() if named_by_file else None
        archive = f"archive:{self.archive_name or ''}" if named_by_file else "archive"
        parts = [(archive, self.archive)] if self.archive is not None else [(f"files:{n}", h) for n, h in self.files]
        for label, handle in parts:
            current.update(b"\0" + label.encode() + b"\0")
            if earlier is not None:  # (the archive: the only part)
                earlier.update(b"\0archive\0")
            while chunk := handle.read(1 << 20):
                current.update(chunk)
                if earlier is not None:
                    earlier.update(chunk)
            handle.seek(0)
        return current.hexdigest(), earlier.hexdigest() if earlier is not None else None


def get_scene(*, session: Session, key: ApiKey, scene_id: str) -> Scene:
    """The key's scene; another key's scene is as absent as a missing one."""
    scene = session.get(Scene, scene_id)
    if scene is None or scene.owner_key_id != key.id:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {listed([scene_id], width=ID_SHOWN)} not found")
    return scene


def create_scene(*, session: Session, settings: Settings, storage: Storage, queue: TaskQueue, key: ApiKey,
                 upload: Upload, idempotency_key: str | None) -> tuple[Scene, bool]:
    """Check, store and record an upload, then queue its ingest; (the scene, whether this was a replay).

    Cheap checks answer 4xx at once with nothing stored; the scene is ``processing`` until a
    worker's ingest has decoded it.
    """
    idem = None
    if idempotency_key:
        digest, earlier = upload.digests()
        idem = Idempotency(idempotency_key, digest, "scenes", earlier_sha256=earlier)
    if idem is not None and (replayed := idem.replayed(session, key, Scene)) is not None:
        return replayed, True
    if (replayed := _replayed_or_room_checked(session, settings, key, idem, 0)) is not None:  # full: before unpacking
        return replayed, True
    session.commit()  # its connection back to the pool while the upload is unpacked and stored (minutes for GBs)
    with staging_folder(settings.work_dir) as staging:
        try:
            staged = stage_upload(
                staging, upload.archive, upload.files, settings.max_extracted_bytes, settings.max_upload_files,
                settings.validation_downsample, settings.max_compression_ratio, settings.max_image_pixels,
                upload.mesh_shading, upload.mesh_up_axis, upload.archive_name,
            )
        except UploadError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        # The bytes to store are known now: an upload over the quota is refused before they are stored (they had
        # been written, GBs to S3, then deleted); the check under the key's lock below still decides a race.
        size = staged.archive.stat().st_size
        if (replayed := _replayed_or_room_checked(session, settings, key, idem, size)) is not None:
            return replayed, True
        session.commit()  # the connection back to the pool while the archive is stored
        scene_id = new_id()
        storage_key = scene_key(scene_id, staged.archive_name)
        try:
            stored = storage.put_file(storage_key, staged.archive, "application/zip")
            scene = Scene(
                id=scene_id, owner_key_id=key.id,
                name=upload.name or upload.default_name(staged.format) or f"scene-{scene_id[:8]}",
                format=staged.format, image_count=staged.image_count, width=staged.width, height=staged.height,
                splits=staged.splits, storage_key=storage_key, size_bytes=stored.size, sha256=stored.sha256,
            )
            lock_live_key(session, key)
            session.add(scene)
            if idem is not None:
                idem.record(session, key, scene_id)
            session.flush()
            check_upload_bytes(session, key, settings, stored.size, including_new=True)
            session.commit()
        except BaseException as exc:
            session.rollback()
            storage.discard(storage_key)  # logged, not raised over the answer (a 429 naming the quota, say)
            if idem is not None and isinstance(exc, IntegrityError):  # a concurrent retry created it first
                if (replayed := idem.replayed(session, key, Scene)) is not None:
                    return replayed, True
            raise
    _queue_ingest(session, storage, queue, scene, key, idem)
    return scene, False


def _replayed_or_room_checked(session: Session, settings: Settings, key: ApiKey, idem: Idempotency | None,
                              adding: int) -> Scene | None:
    """``check_upload_bytes`` before the upload is stored; None when there is room. When it refuses a retry whose
    first request committed meanwhile (that request's scene is what fills the quota), that scene, to replay: the
    retry had been answered 429 for its own upload (under the key's lock, later, the twin's record wins)."""
    try:
        check_upload_bytes(session, key, settings, adding)
    except HTTPException:
        if idem is not None and (replayed := idem.replayed(session, key, Scene)) is not None:
            return replayed
        raise
    return None


def _queue_ingest(session: Session, storage: Storage, queue: TaskQueue, scene: Scene, key: ApiKey,
                  idem: Idempotency | None) -> None:
    """Hand the ingest to the broker. When it is down (503) the upload was never accepted: its scene, bytes and
    Idempotency-Key go, so nothing is listed and a retry with the key uploads it anew. But the scene was listed
    while the broker took its time to refuse: a job accepted on it meanwhile keeps it, failed with the reason (as
    its ingest would have), and the job fails naming it; the key goes even so (kept, it had answered the retry the
    503 asks for 200 with that failed scene)."""
    scene_id = scene.id
    try:
        task_id = queue.send_ingest(scene_id)
    except Exception:  # noqa: BLE001 - broker down: nothing will ingest it
        log.exception("could not queue the ingest of scene %s", scene_id)  # the broker's own words: the log's
        reason = f"could not queue the ingest: {QUEUE_UNAVAILABLE}"
        lock_scene(session, scene_id)  # before counting, as delete_scene does: a job is counted here or refused there
        if session.scalar(select(func.count()).select_from(Job).where(Job.scene_id == scene_id)):
            fail_scene(session, scene_id, reason)
        else:
            session.delete(scene)
        if idem is not None:
            idem.forget(session, key)
        session.commit()
        storage.discard_prefixes(scene_key(scene_id))
        raise try_again_soon(reason) from None
    # Conditional: the scene was listed while the broker took the ingest, and a DELETE meanwhile had made this
    # write fail with a 500 (the deletion stands: the ingest finds the scene gone and keeps nothing).
    if session.execute(update(Scene).where(Scene.id == scene_id).values(task_id=task_id)).rowcount != 1:
        session.rollback()
        raise HTTPException(status.HTTP_409_CONFLICT, f"scene {scene_id!r} was deleted (DELETE /v1/scenes/{scene_id}) "
                                                      "before its upload answered; nothing of it is kept")
    if idem is not None:  # only now may a retry replay it (Idempotency.replayed)
        idem.answered(session, key)
    session.commit()


def list_scenes(*, session: Session, key: ApiKey, page: PageQuery) -> PageRows:
    """A page of the key's scenes, newest first, and how many there are."""
    return read_page(session, "/v1/scenes", Scene, [Scene.owner_key_id == key.id], page)


def list_reconstructions(*, session: Session, key: ApiKey, scene_id: str) -> list[Reconstruction]:
    """The scene's reconstructions some job uses. A refused submission (quota, models, a broker down) may leave
    the row it made for its parameters (made in its own transaction, race-free): it waits unlisted until a job
    with those parameters uses it."""
    get_scene(session=session, key=key, scene_id=scene_id)
    used = select(Job.id).where(Job.reconstruction_id == Reconstruction.id).exists()
    return list(session.scalars(select(Reconstruction).where(Reconstruction.scene_id == scene_id, used)
                                .order_by(Reconstruction.created_at)))


def delete_scene(*, session: Session, storage: Storage, key: ApiKey, scene_id: str) -> None:
    """Delete the scene with its jobs, reconstructions and stored objects; 409 while a job is queued or running.

    A processing scene can be deleted too: its ingest finds it gone and keeps nothing. The jobs' webhook deliveries go
    with them, those pending never sent (as the README says: their job, its URLs and their state are gone).
    """
    scene = get_scene(session=session, key=key, scene_id=scene_id)
    # Locked before counting, as creating a job locks it after writing its row (add_jobs): a job created meanwhile
    # is either counted here (409) or refused there (404), never accepted and then deleted with the scene.
    if lock_scene(session, scene_id) is None:  # another DELETE's, committed meanwhile: it had been a 204 here too
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id!r} not found (deleted meanwhile)")
    active, stopping = session.execute(select(func.count(), func.count().filter(Job.cancel_requested))
                                       .where(Job.scene_id == scene_id, Job.state.in_((QUEUED, RUNNING)))).one()
    if active and not stopping:
        raise HTTPException(status.HTTP_409_CONFLICT,
                            f"scene {scene_id!r} has {active} queued or running job(s); cancel them first")
    if active:  # canceled, running until their worker's next cancel check: "cancel them first" had misled
        then = "" if stopping == active else f"cancel the other {active - stopping}, then "
        raise HTTPException(status.HTTP_409_CONFLICT,
                            f"scene {scene_id!r} has {active} queued or running job(s), {stopping} of them canceled "
                            f"and still stopping (a running job stops within a few iterations): {then}delete the "
                            "scene once they have ended")
    job_ids = list(session.scalars(select(Job.id).where(Job.scene_id == scene_id)))
    rec_ids = list(session.scalars(select(Reconstruction.id).where(Reconstruction.scene_id == scene_id)))
    session.delete(scene)  # jobs, artifacts and reconstructions go with it (ON DELETE CASCADE)
    session.commit()
    # Rows first, then objects: a crash in between leaves unreferenced objects, never dangling rows.
    storage.discard_prefixes(scene_key(scene_id), *map(job_key, job_ids), *map(reconstruction_storage_key, rec_ids))


def refuse_unless_usable(scene: Scene) -> None:
    """409 for a failed scene: no job can run on it (the reason is named); processing and ready are fine."""
    if scene.state == FAILED:
        raise HTTPException(status.HTTP_409_CONFLICT, f"scene {scene.id!r} failed processing: {scene.error}; "
                                                      "upload it again")
