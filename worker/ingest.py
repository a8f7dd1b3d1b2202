"""The ingest stage of an upload: decode every image (and load and render a mesh) off the request path.

The API stored what passed its cheap checks and left the scene ``processing``
(``api/uploads.py``). Here the stored archive is unpacked, a mesh upload is rendered into
``MESH_VIEWS`` upper-hemisphere views (``voxe_core.mesh_input.write_mesh_dataset``) and
packed with the mesh as the scene's dataset archive, and the dataset is loaded in full
with ``voxe_core.data.load_scene`` at ``VOXE_VALIDATION_DOWNSAMPLE``, which also decides what
reconstruction backbone "auto" means for the scene (recorded: jobs are checked against it). Then
the scene is ``ready`` and the jobs waiting on it are dispatched (those whose reconstruction
parameters its backbone cannot take fail, naming why), or ``failed`` with the message of the
error (file and frame, as the API's 422s) and the jobs waiting on it fail naming it.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
import uuid
import warnings
from datetime import timedelta
from pathlib import Path
from typing import NamedTuple

from celery.exceptions import Reject
from sqlalchemy import or_, update
from sqlalchemy.exc import SQLAlchemyError

from voxe_core.backbones import detect_backbone
from voxe_core.constants import TEXTURE_SUFFIXES
from voxe_core.data import DatasetError, load_scene
from voxe_core.mesh_input import MESH_INPUT_SUFFIXES, MeshError, MeshWarning, load_mesh, shade_mesh, write_mesh_dataset
from voxe_service import datasets
from voxe_service.db import DATABASE_UNAVAILABLE, database_outage, session_scope
from voxe_service.jobs import record_event
from voxe_service.models import FAILED, PROCESSING, Scene, utcnow
from voxe_service.queue import (QueueUnavailable, TaskResult, dispatch_job, get_queue, requeue_limit_error,
                                storage_outage_limit_error)
from voxe_service.quotas import ingest_over_quota
from voxe_service.scenes import fail_scene, mark_ready
from voxe_service.scratch import locked_folder, sweep_unlocked
from voxe_service.settings import Settings
from voxe_service.storage import Storage, StorageUnavailable, StoredObject, scene_key
from worker.runtime import (LeaseKeeper, LeaseLost, failure_text, fetch, ingest_lease, pause_after_outage,
                            scene_archive, storage_or_disk_outage, worker_in_cold_shutdown)

log = logging.getLogger("voxe.worker")


class IngestError(ValueError):
    """The upload is not a usable dataset; the message is the scene's failure reason."""


def load_stored_mesh(dataset: Path):
    """The mesh a mesh scene's archive keeps under ``mesh/`` (as the API packed it), as ``load_mesh`` reads it with
    the up axis, shading and frame its upload asked (``mesh/options.json``; "y", "auto" and frame 1 for archives
    packed before them, whose views were rendered so): the render route (this ingest) and the voxelize route
    (``worker.tasks``) both read the mesh through here, so a scene's grid stays in its views' frame."""
    kept = dataset / datasets.MESH_FOLDER
    meshes = [p for p in sorted(kept.glob("mesh.*")) if p.suffix in MESH_INPUT_SUFFIXES]
    if len(meshes) != 1:
        raise MeshError(f"the scene's archive holds no {datasets.MESH_FOLDER}/mesh.obj or .ply (not uploaded as a mesh?)")
    textures = [p for p in sorted(kept.glob("texture.*")) if p.suffix in TEXTURE_SUFFIXES]
    options = kept / datasets.MESH_OPTIONS
    options = json.loads(options.read_text()) if options.is_file() else {}
    mesh = load_mesh(meshes[0], textures[0] if textures else None, options.get("up_axis", "y"),
                     frame=options.get("frame", 1))
    return shade_mesh(mesh, options.get("shading", "auto"))


def load_stored_mesh_telling(dataset: Path, told: list[str]):
    """:func:`load_stored_mesh`'s mesh; what it loaded without, its ``MeshWarning``s (an OBJ's .mtl not sent, which
    had been said in the worker's log alone), appended to ``told``, files named as uploaded, without the worker's
    scratch path: those said before a ``MeshError`` too (a failed ingest keeps them: they may be why), which names
    them so as well (the voxelize route's reload had said "mesh.obj", the name the worker keeps). Any other warning
    is shown as it would have been (the worker's log): recorded with them, it had been dropped unsaid."""
    kept = dataset / datasets.MESH_FOLDER
    try:
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always", MeshWarning)
            return load_stored_mesh(dataset)
    except MeshError as exc:  # (Pillow's messages carry the worker's scratch path)
        raise MeshError(_as_uploaded(_relative_message(exc, kept), kept)) from None
    finally:
        for other in said:
            if other.category is not MeshWarning:
                warnings.showwarning(other.message, other.category, other.filename, other.lineno)
        told.extend(_as_uploaded(_relative_message(w.message, kept), kept) for w in said if w.category is MeshWarning)


def render_mesh(root: Path, told: list[str]) -> None:
    """Render the mesh kept in ``root/mesh/`` into a NeRF-synthetic dataset in ``root`` (mesh input route (a)); what
    it loaded without appended to ``told`` (:func:`load_stored_mesh_telling`)."""
    try:
        mesh = load_stored_mesh_telling(root, told)
    except MeshError as exc:  # (named as uploaded)
        raise IngestError(f"invalid mesh: {exc}") from None
    write_mesh_dataset(mesh, root, datasets.MESH_VIEWS, datasets.MESH_VIEW_SIZE)


def _as_uploaded(message: str, kept: Path) -> str:
    """A message naming the kept files (``mesh.obj: ...``) by the names they were uploaded under."""
    names = kept / datasets.MESH_NAMES
    for stored, uploaded in (json.loads(names.read_text()) if names.is_file() else {}).items():
        message = re.sub(rf"(?<![\w.]){re.escape(stored)}\b", lambda _match, name=uploaded: name, message)
    return message


def _relative_message(exc: Exception, root: Path) -> str:
    message = str(exc)
    for prefix in sorted({str(root.resolve()), str(root)}, key=len, reverse=True):
        message = message.replace(prefix + os.sep, "").replace(prefix, "<upload>")
    return message


class Decoded(NamedTuple):
    count: int
    """The training split's number of images."""
    backbone: str
    """What reconstruction backbone "auto" means for the scene (``detect_backbone`` over every training image)."""


def decode(root: Path, downsample: int) -> Decoded:
    """Load the dataset folder's training split in full (every image decoded)."""
    try:
        try:
            scene = load_scene(root, "train", downsample=downsample, confine_paths=True)
        except DatasetError as exc:
            if "smaller than downsample" not in str(exc):
                raise
            scene = load_scene(root, "train", downsample=1, confine_paths=True)
    except DatasetError as exc:
        raise IngestError(f"invalid dataset: {_relative_message(exc, root)}") from None
    return Decoded(len(scene), detect_backbone(scene.alphas))


def ingest_scene(scene_id: str, settings: Settings, storage: Storage, hostname: str | None) -> TaskResult:
    """Take the scene's ingest (processing only), decode it, then mark it ready or failed.

    The run holds the scene under a lease (``Scene.ingest_token``, renewed while it runs), as a stage's run holds
    its job (``worker.runtime.begin_stage``): a duplicate message (the reaper's re-send, a broker's redelivery) waits
    for the lease to run out, then takes the scene over, or is dropped once the holder renews it, so two workers never
    ingest one scene at once; only the holder marks it ready or failed. Every run that takes the scene counts
    (``Scene.ingest_attempts``); one finding more than ``job_max_requeues`` runs before it interrupted (their worker
    processes killed, e.g. out of memory on this upload) fails the scene instead: an upload that kills its workers
    must not loop, as a job must not (``requeue_interrupted``).

    An outage of the database (down, locked) or of the storage (unreachable, throttled), or the worker's disk full, is
    no fault of the upload: the message goes back to the queue after a pause that doubles with each run
    (``runtime.OUTAGE_PAUSE_S``: 5, 10, 20 s ...), and its redelivery starts over. A database's, acknowledged as a
    failed task, had left the scene processing for good (its worker alive, the reaper never failed it) and the jobs
    waiting on it queued; a storage's, or one worker's full disk, had failed the scene and deleted its upload. A run
    that took the scene counts, as a stage's give-back counts: what answers as an outage every time (a full disk, a
    statement timeout) fails the scene at the limit, naming it, rather than decoding the upload again for ever; one
    that could not take it (the database down) does not, nor does one a storage outage stopped (counted in
    ``Scene.ingest_storage_outages`` instead, for its pause), as a stage's does not: an outage every scene met alike
    had failed the scenes ingesting through a few minutes of throttling. Past ``storage_outage_max_retries`` of
    those the next fails the scene, naming the outage: a storage object answering 5xx every time had been fetched for
    ever.
    """
    interrupted, storage_outages, token = None, 0, uuid.uuid4().hex
    try:
        taken = _take(scene_id, token, hostname, settings)
        if isinstance(taken, str):
            return {"scene_id": scene_id, "skipped": taken}
        upload, interrupted, storage_outages, stopped_by = taken
        with ingest_lease(scene_id, token, settings) as lease:
            return _ingest(scene_id, token, upload, interrupted, stopped_by, lease, settings, storage)
    except (*DATABASE_UNAVAILABLE, StorageUnavailable, LeaseLost, OSError) as exc:
        if isinstance(exc, LeaseLost):
            if lease.lost:  # another run holds the scene: what it stores is the scene's, this run writes nothing
                if _ended(scene_id):  # (or none: the scene was deleted or failed meanwhile)
                    return {"scene_id": scene_id, "skipped": f"scene {scene_id} was deleted or failed meanwhile"}
                log.warning("scene %s: %s; this run stops", scene_id, exc)
                return {"scene_id": scene_id, "skipped": str(exc)}
            cause = f"a database outage ({exc})"  # (its renewals could not reach the database)
        elif (why := database_outage(exc)) is not None:
            cause = f"a database outage ({why})"
        elif (cause := storage_or_disk_outage(exc)) is None:
            raise
        storage_outage = isinstance(exc, StorageUnavailable)
        if storage_outage and (error := storage_outage_limit_error(storage_outages, settings,
                                                                   f"ingest: stopped by {cause}")):
            _fail(scene_id, token, error, storage)
            return {"scene_id": scene_id, "state": "failed"}
        log.warning("scene %s: the ingest stopped by %s; its message goes back to the queue", scene_id, cause)
        _give_back(scene_id, token, stopped_by=cause, storage_outage=storage_outage)
        pause_after_outage((interrupted or 0) + (storage_outages if storage_outage else 0))
        raise Reject(f"the ingest of scene {scene_id} stopped by {cause}", requeue=True) from exc


def _take(scene_id: str, token: str, hostname: str | None, settings: Settings
          ) -> tuple[StoredObject, int, int, str | None] | str:
    """Take the processing scene's ingest for the run ``token``: (its archive as recorded, the runs that took it
    before, the runs a storage outage stopped, what stopped the last of them when it gave the scene back:
    :func:`_give_back`); why not, when it is no
    longer processing or another run holds it and renews its lease. The cause read is cleared: a run killed after
    it leaves none, and must not be said to have met it."""
    held = None  # the hold (token, lease end) this run waits out
    while True:
        with session_scope() as session:
            scene = session.get(Scene, scene_id)
            if scene is None or scene.state != PROCESSING:
                return f"scene {scene_id} is {scene.state if scene else 'gone'}"
            now = utcnow()
            hold = (scene.ingest_token, scene.ingest_lease_until)
            if scene.ingest_token is None or scene.ingest_lease_until < now:
                # (read before the update changes them)
                upload, before, stopped_by = scene_archive(scene), scene.ingest_attempts, scene.error
                storage_outages = scene.ingest_storage_outages
                taken = session.execute(update(Scene).where(
                    Scene.id == scene_id, Scene.state == PROCESSING, Scene.updated_at == scene.updated_at,
                    or_(Scene.ingest_token.is_(None), Scene.ingest_lease_until < now)).values(
                    worker_hostname=hostname, ingest_attempts=Scene.ingest_attempts + 1, ingest_token=token, error=None,
                    ingest_lease_until=now + timedelta(seconds=settings.stage_lease_s), updated_at=now)).rowcount
                if taken == 1:
                    return upload, before, storage_outages, stopped_by
                continue  # taken (or changed) since it was read: read it again
        if held is not None and hold != held:
            return f"scene {scene_id}: another run holds its ingest (this message is a duplicate)"
        held = hold
        time.sleep(settings.stage_lease_s / 8)


def _ingest(scene_id: str, token: str, upload: StoredObject, interrupted: int, stopped_by: str | None,
            lease: LeaseKeeper, settings: Settings, storage: Storage) -> TaskResult:
    """The ingest of the scene this run (``token``, its hold kept by ``lease``) took, its archive ``upload`` as
    recorded, after ``interrupted`` runs before it, the last stopped by ``stopped_by`` (an outage, a full disk) when
    it said so; at the limit the scene fails naming it, the upload no fault of it (it had said "killed: out of
    memory?" first, a full disk met at every run last). A mesh's rendered dataset is stored under a key of this
    run's own (:func:`run_archive_key`): a run that lost its hold, stalled past the check before it stores, never
    overwrites the archive another run recorded (every job's fetch had then failed its SHA-256 check)."""
    # The runs before this one, less the first: how often the ingest was sent again.
    why = (f"ingest: stopped {interrupted} times, the last by {stopped_by}: no fault of the upload (upload it again "
           "once that is mended)" if stopped_by else
           f"ingest: interrupted {interrupted} times, its worker process dying each time (killed: out of memory?), a "
           "database outage or a full disk stopping it")
    if error := requeue_limit_error(interrupted - 1, settings, why):
        _fail(scene_id, token, error, storage)
        return {"scene_id": scene_id, "state": "failed"}
    mesh_upload = upload.key == scene_key(scene_id, datasets.UPLOAD_ARCHIVE)
    work = Path(settings.work_dir) / "ingest"
    # The folders the scene's killed runs on this machine left (each up to VOXE_MAX_EXTRACTED_BYTES; a crash loop had
    # kept them all until the scene failed), removed before this run's is made: a full disk frees itself.
    if removed := sweep_unlocked(work, f"{scene_id}-*"):
        log.info("scene %s: removed %d folder(s) its killed ingests left", scene_id, removed)
    values: dict = {}
    loaded_without: list[str] | None = None  # (None: the upload never loaded, what it loads without not known)
    with locked_folder(work, f"{scene_id}-") as scratch:
        try:
            archive = fetch(storage, upload, scratch / "archive.zip", f"scene {scene_id}'s upload {upload.key}")
            _still_held(lease)
            root = datasets.unpack(archive, scratch / "data")
            loaded_without = []
            if mesh_upload:
                _still_held(lease)
                render_mesh(root, loaded_without)
            _still_held(lease)
            count, values["backbone"] = decode(root, settings.validation_downsample)
            if mesh_upload:  # the rendered dataset (and the mesh beside it) becomes the scene's archive
                _still_held(lease)
                archive = scratch / datasets.DATASET_ARCHIVE
                datasets.package(root, archive)
                stored = storage.put_file(run_archive_key(scene_id, token), archive, "application/zip")
                size = datasets.MESH_VIEW_SIZE
                values.update(storage_key=stored.key, size_bytes=stored.size, sha256=stored.sha256, image_count=count,
                              width=size, height=size, splits=["train", "test"])
        except Exception as exc:  # noqa: BLE001 - every failure becomes the scene's reason ...
            if worker_in_cold_shutdown():  # ... but a cold shutdown's (it had failed the scene and deleted its upload)
                _give_back(scene_id, token, uncount=True)
                raise Reject(f"the ingest of scene {scene_id} stopped by the worker's shutdown", requeue=True) from exc
            if isinstance(exc, LeaseLost) or storage_or_disk_outage(exc):  # ... a storage outage's or a
                raise  # full disk's, no fault of the upload either, and a lost hold's (the scene another run's to end)
            reason = str(exc) if isinstance(exc, IngestError) else f"ingest: {failure_text(exc)}"
            if not isinstance(exc, IngestError):
                log.exception("scene %s: ingest failed", scene_id)
            _fail(scene_id, token, reason, storage, loaded_without)
            return {"scene_id": scene_id, "state": "failed"}
    return _ready(scene_id, token, values, storage, settings, upload.key if mesh_upload else None, loaded_without)


def _still_held(lease: LeaseKeeper) -> None:
    """Between the ingest's steps: its hold renewed, or LeaseLost once the scene is no longer this run's to ingest (its
    key revoked, which fails it; deleted; another run took it over), as a canceled job's stage stops at its next
    check: a revoked key's ingest had decoded (and rendered) the upload to the end for a scene no key can use."""
    lease.renew()
    lease.check()


def run_archive_key(scene_id: str, token: str) -> str:
    """The key the run ``token`` stores a mesh scene's rendered dataset under (``scenes/<id>/dataset-<run>.zip``);
    scenes made ready before it keep theirs at ``scenes/<id>/dataset.zip``, read as recorded."""
    return scene_key(scene_id, f"{Path(datasets.DATASET_ARCHIVE).stem}-{token[:8]}.zip")


def _give_back(scene_id: str, token: str, uncount: bool = False, stopped_by: str | None = None,
               storage_outage: bool = False) -> None:
    """Give the run's hold back as its message goes back to the queue, so its redelivery takes the scene at once
    (not after the lease). ``uncount``: a run a worker's shutdown stopped is not one the upload killed: it does not
    count towards the limit (four deploys had failed a scene as "killed: out of memory?"). Only where the shutdown
    raises in the task (the solo pool's); a prefork pool's children are ended from outside, and their runs still
    count. The lease is left run out, not none: should the message be lost on its way back, the reaper sends the
    ingest again (it never takes a scene with no lease for one whose run stopped). ``stopped_by``: the outage or
    full disk that stopped the run, kept as the scene's error while it is processing (the next run reads it).
    ``storage_outage``: a storage outage stopped it, which every scene meets alike: uncounted too, it is counted in
    ``Scene.ingest_storage_outages``, doubling the pause before the next such run's message goes back."""
    values = dict(ingest_token=None, ingest_lease_until=utcnow(), error=stopped_by)
    if uncount or storage_outage:
        values["ingest_attempts"] = Scene.ingest_attempts - 1  # (this run's, counted as it took the scene)
    if storage_outage:
        values["ingest_storage_outages"] = Scene.ingest_storage_outages + 1
    try:
        with session_scope() as session:
            session.execute(update(Scene).where(Scene.id == scene_id, Scene.state == PROCESSING,
                                                Scene.ingest_token == token).values(**values))
    except SQLAlchemyError:  # (an outage) the message goes back all the same: its redelivery waits out the lease
        log.warning("scene %s: could not give back the ingest's hold", scene_id, exc_info=True)


def _fail(scene_id: str, token: str, reason: str, storage: Storage, warnings_said: list[str] | None = None) -> bool:
    """Fail the processing scene this run (``token``) holds and discard its stored bytes, keeping ``warnings_said``
    (what its load said before the failure) as its ``warnings``; False (nothing discarded) when it was no longer
    processing, or no longer held by this run."""
    with session_scope() as session:
        failed = fail_scene(session, scene_id, reason, where=[Scene.ingest_token == token], warnings=warnings_said)
    if failed:  # its bytes are of no use to any job: free the key's upload quota
        storage.discard_prefixes(scene_key(scene_id))
        log.warning("scene %s failed: %s", scene_id, reason)
    return failed


def _ready(scene_id: str, token: str, values: dict, storage: Storage, settings: Settings,
           replaced_key: str | None, warnings_said: list[str] = ()) -> TaskResult:
    """processing -> ready and its waiting jobs sent, each told ``warnings_said`` (a ``warning`` event of stage
    "ingest"; kept as the scene's ``warnings``, which the API tells the jobs created later); a mesh whose rendered
    views put its key over the upload quota (checked with the key locked, in the transaction that would store the new
    size) fails instead."""
    with session_scope() as session:
        over = "size_bytes" in values and ingest_over_quota(session, scene_id, values["size_bytes"], settings)
        waiting = None if over else mark_ready(session, scene_id, where=[Scene.ingest_token == token],
                                               warnings=list(warnings_said), **values)
        if waiting is None:
            session.rollback()
        else:
            for job in waiting:
                for text in warnings_said:
                    record_event(session, job.id, "warning", stage="ingest", detail=text)
            session.commit()
            queue = get_queue()  # the waiting jobs first: should this worker stop before, the reaper sends them
            for job in waiting:
                try:
                    dispatch_job(session, queue, job, fail_refused=False)
                except QueueUnavailable:  # left queued with no task id: the reaper sends it once the broker is back
                    log.warning("scene %s: could not dispatch job %s", scene_id, job.id)
    if over:
        if not _fail(scene_id, token, over, storage, list(warnings_said)):
            _discard_refused(scene_id, values.get("storage_key"), storage)
        return {"scene_id": scene_id, "state": "failed"}
    if waiting is None:
        if _discard_refused(scene_id, values.get("storage_key"), storage):
            return {"scene_id": scene_id, "skipped": f"scene {scene_id} was deleted or failed meanwhile"}
        return {"scene_id": scene_id, "skipped": f"scene {scene_id}: another run took its ingest over"}
    if replaced_key:  # the mesh upload, now packaged
        storage.discard(replaced_key)
    if values.get("storage_key"):
        _discard_earlier_runs(scene_id, values["storage_key"], storage)
    log.info("scene %s ready; dispatched %d waiting job(s)", scene_id, len(waiting))
    return {"scene_id": scene_id, "state": "ready"}


def _discard_refused(scene_id: str, stored_key: str | None, storage: Storage) -> bool:
    """Discard what a run whose result was refused leaves of no use, and say whether the scene ended: all its bytes
    when it was deleted or failed meanwhile; else (another run took the ingest over) only ``stored_key``, the
    dataset this run rendered under its own key, the upload and the other run's archive kept."""
    if _ended(scene_id):
        storage.discard_prefixes(scene_key(scene_id))
        return True
    if stored_key:
        storage.discard(stored_key)
    return False


def _discard_earlier_runs(scene_id: str, recorded_key: str, storage: Storage) -> None:
    """Discard the rendered datasets earlier runs stored under keys of their own (:func:`run_archive_key`) and never
    had recorded (stopped between storing and marking the scene ready: a database outage, a killed worker), now that
    ``recorded_key`` is the scene's: none else can be, and the upload quota counts only the recorded one. An earlier
    run cannot discard its own there: its mark may have committed with the answer lost."""
    runs_prefix = run_archive_key(scene_id, "").removesuffix(".zip")  # scenes/<id>/dataset-
    for key in storage.list(runs_prefix):
        if key != recorded_key:
            storage.discard(key)


def _ended(scene_id: str) -> bool:
    """Whether the scene was deleted or failed (its stored bytes of no use), rather than taken over by another run of
    its ingest (processing, or made ready by it)."""
    with session_scope() as session:
        scene = session.get(Scene, scene_id)
        return scene is None or scene.state == FAILED
