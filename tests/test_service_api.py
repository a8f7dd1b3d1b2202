"""Fast in-process tests of the HTTP API (FastAPI TestClient; no worker runs, queued tasks just wait)."""

from __future__ import annotations

import base64
import contextlib
import io
import json
import re
import shutil
import threading
import zipfile
from pathlib import Path

import pytest
import torch
from fastapi.testclient import TestClient

from captures import pose_at, square_capture, write_colmap_model
from needs import SPOT, require_data
from service_helpers import (
    MIC, TINY_FIT, ingest, reset_service_caches as _reset, service_env, small_mic, zip_folder,
)


@pytest.fixture
def root(request, tmp_path, monkeypatch):
    """A private service environment under ``tmp_path``: SQLite, or PostgreSQL for tests parametrized with
    ``@pytest.mark.parametrize("root", ["sqlite", "postgres"], indirect=True)``."""
    database_url = None
    if getattr(request, "param", "sqlite") == "postgres":
        database_url = request.getfixturevalue("postgres_server").create_database()
    for key, value in service_env(tmp_path, database_url=database_url).items():
        monkeypatch.setenv(key, value)
    _reset()
    yield tmp_path
    _reset()


BOTH_DATABASES = pytest.mark.parametrize("root", ["sqlite", "postgres"], indirect=True)


@pytest.fixture
def client(root):
    from api.main import create_app

    with TestClient(create_app()) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    require_data(MIC)
    return small_mic(tmp_path_factory.mktemp("data") / "mic_small")


def upload_zip(client, path: Path, name: str = "scene.zip"):
    with open(path, "rb") as handle:
        return client.post("/v1/scenes", files={"archive": (name, handle, "application/zip")})


def make_scene(client, dataset, tmp_path) -> dict:
    """Upload the dataset and run its ingest (no worker runs here): the scene, ready."""
    response = upload_zip(client, zip_folder(dataset, tmp_path / "ok.zip", prefix="mic_small"))
    assert response.status_code == 201, response.text
    assert response.json()["state"] == "processing"
    assert ingest(response.json()["id"])["state"] == "ready"
    return client.get(f"/v1/scenes/{response.json()['id']}").json()


def stored_files(root: Path) -> list[str]:
    storage = root / "storage"
    return sorted(p.relative_to(storage).as_posix() for p in storage.rglob("*") if p.is_file()) if storage.exists() else []


def staged(root: Path) -> list[str]:
    uploads = root / "work" / "uploads"
    return sorted(p.name for p in uploads.iterdir()) if uploads.exists() else []


JOB = {"prompt": "a mic wearing big sunglasses", "mode": "local", "edit_words": ["sunglasses"]}


def reconstruction_rows(scene_id: str) -> list[str]:
    """The scene's reconstruction rows in the database, used or not (the API lists only those jobs use)."""
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction

    with session_scope() as session:
        return sorted(session.scalars(select(Reconstruction.id).where(Reconstruction.scene_id == scene_id)))


# ------------------------------------------------------------------------------------------ scenes
def test_openapi_documents_the_v1_surface(client):
    spec = client.get("/openapi.json").json()
    for path in ("/v1/scenes", "/v1/scenes/{scene_id}", "/v1/jobs", "/v1/jobs/{job_id}",
                 "/v1/jobs/{job_id}/cancel", "/v1/jobs/{job_id}/artifacts", "/v1/jobs/{job_id}/artifacts/{name}",
                 "/v1/jobs/{job_id}/events", "/healthz", "/readyz"):
        assert path in spec["paths"], path
    params = spec["components"]["schemas"]["JobParams"]["properties"]
    assert params["iterations"]["default"] == 8000 and params["guidance_scale"]["default"] == 100.0
    assert client.get("/healthz").json() == {"status": "ok"}


def test_upload_zip_and_files(client, dataset, root):
    scene = make_scene(client, dataset, root)
    assert scene["state"] == "ready" and scene["error"] is None and scene["warnings"] == []
    assert scene["format"] == "nerf_synthetic" and scene["image_count"] == 3
    assert (scene["width"], scene["height"]) == (800, 800) and scene["splits"] == ["train"]
    assert scene["name"] == "scene"  # the archive's name
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    assert staged(root) == []

    files = [("files", (p.relative_to(dataset).as_posix(), open(p, "rb"))) for p in sorted(dataset.rglob("*"))
             if p.is_file()]
    try:
        response = client.post("/v1/scenes", files=files, data={"name": "from files"})
    finally:
        for _, (_, handle) in files:
            handle.close()
    assert response.status_code == 201, response.text
    assert response.json()["name"] == "from files" and response.json()["image_count"] == 3

    page = client.get("/v1/scenes", params={"limit": 1, "offset": 1}).json()
    assert page["total"] == 2 and len(page["items"]) == 1 and page["items"][0]["id"] == scene["id"]
    assert client.get(f"/v1/scenes/{scene['id']}").json() == scene


def test_a_scene_is_processing_until_its_ingest_and_jobs_on_it_wait_without_a_message_in_the_broker(
        client, dataset, root):
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    response = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small"))
    assert response.status_code == 201, response.text
    scene = response.json()
    # The cheap checks filled in what the json and the image headers say; decoding is the ingest's.
    assert (scene["state"], scene["error"], scene["image_count"], scene["width"]) == ("processing", None, 3, 800)
    assert client.get(f"/v1/scenes/{scene['id']}").json()["state"] == "processing"
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert job["state"] == "queued" and job["message"] == (f"waiting for the scene {scene['id']} to be processed "
                                                           "(its upload is being decoded)")
    with session_scope() as session:
        assert session.get(Job, job["id"]).task_id is None  # not sent: no worker is held waiting for the scene
        assert session.get(Scene, scene["id"]).task_id is not None  # the ingest's message is in the broker

    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    ready = client.get(f"/v1/scenes/{scene['id']}").json()
    assert ready == {**scene, "state": "ready", "backbone": "relu_field", "warnings": []}
    sent = client.get(f"/v1/jobs/{job['id']}").json()
    assert sent["state"] == "queued" and sent["message"] is None
    with session_scope() as session:
        assert session.get(Job, job["id"]).task_id is not None  # the ingest sent the job that waited
    assert ingest(scene["id"])["skipped"] == f"scene {scene['id']} is ready"  # a redelivered ingest does nothing
    later = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert later["message"] is None  # on a ready scene: sent at once
    with session_scope() as session:
        assert session.get(Job, later["id"]).task_id is not None


def test_jobs_waiting_on_an_ingest_whose_broker_refuses_them_stay_queued_for_the_reaper(client, dataset, root,
                                                                                        monkeypatch):
    """The ingest sends the jobs that waited for their scene; a broker refusing then (a Redis restarting) had failed
    them for good. They stay queued with no task id, which the reaper sends once the broker is back."""
    from kombu.exceptions import OperationalError

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import TaskQueue

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()

    def refused(self, signature):
        raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")

    monkeypatch.setattr(TaskQueue, "send", refused)
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    waiting = client.get(f"/v1/jobs/{job['id']}").json()
    assert (waiting["state"], waiting["error"]) == ("queued", None)
    with session_scope() as session:
        assert session.get(Job, job["id"]).task_id is None


def test_an_ingest_stopped_by_a_cold_shutdown_goes_back_to_the_queue_keeping_the_upload(client, dataset, root,
                                                                                         monkeypatch):
    """A solo-pool worker's cold shutdown cancels its task by raising in it: that had failed the scene and deleted
    its upload. Now the message is rejected back to the queue, and the next ingest decodes the scene."""
    from celery.exceptions import Reject
    from celery.worker import state

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage
    from worker import ingest as ingest_module

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    decode = ingest_module.decode

    def cancelled_by_the_shutdown(*args):
        monkeypatch.setattr(state, "should_terminate", 0)  # set by Celery's cold shutdown (its exit code)
        raise NotImplementedError("<class 'celery.concurrency.solo.TaskPool'> does not implement kill_job")

    monkeypatch.setattr(ingest_module, "decode", cancelled_by_the_shutdown)
    with pytest.raises(Reject) as rejected:  # (called as the task does: Celery's apply would swallow the Reject)
        ingest_module.ingest_scene(scene["id"], get_settings(), get_storage(get_settings()), "w@host")
    assert rejected.value.requeue
    assert client.get(f"/v1/scenes/{scene['id']}").json()["state"] == "processing"
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    with session_scope() as session:  # not a run the upload killed: it does not count towards the limit
        assert session.get(Scene, scene["id"]).ingest_attempts == 0
    monkeypatch.setattr(state, "should_terminate", None)  # the next worker
    monkeypatch.setattr(ingest_module, "decode", decode)
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}


@pytest.mark.parametrize("stopped", ["taking the scene", "recording it ready"])
def test_an_ingest_stopped_by_a_database_outage_goes_back_to_the_queue(client, dataset, root, monkeypatch, stopped):
    """A locked (or unreachable) database had failed the ingest's task, its message acknowledged: with its worker
    alive the reaper never failed the scene, which stayed processing for good, and the job waiting on it queued.
    Now the message goes back to the queue and the redelivery readies the scene; a run that took the scene counts
    (what answers as an outage every time must not decode the upload for ever)."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import ingest as ingest_module
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    name = {"taking the scene": "session_scope", "recording it ready": "mark_ready"}[stopped]
    real, calls = getattr(ingest_module, name), []

    def locked_once(*args, **kwargs):
        calls.append(name)
        if len(calls) == 1:
            raise OperationalError("UPDATE scenes", {}, sqlite3.OperationalError("database is locked"))
        return real(*args, **kwargs)

    monkeypatch.setattr(ingest_module, name, locked_once)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    result = tasks.ingest_task.apply(args=(scene["id"],))
    assert result.state == "REJECTED" and result.result.requeue
    assert result.result.reason == (f"the ingest of scene {scene['id']} stopped by a database outage (the database "
                                    "cannot be reached or is locked)")
    assert client.get(f"/v1/scenes/{scene['id']}").json()["state"] == "processing"
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    with session_scope() as session:  # a run that could not take the scene counts nothing
        assert session.get(Scene, scene["id"]).ingest_attempts == (0 if stopped == "taking the scene" else 1)
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "queued"


def test_an_ingest_stopped_by_a_storage_outage_goes_back_to_the_queue_keeping_the_upload(client, dataset, root,
                                                                                          monkeypatch):
    """The storage unreachable or throttled as the ingest fetches the upload (after botocore's retries) had failed
    the scene and deleted the upload, a valid one, for good: the message goes back to the queue and the redelivery
    readies the scene. Met at every run, it does not use up the ingest's attempts (an outage every scene meets alike
    had failed the scenes ingesting through it at VOXE_JOB_MAX_REQUEUES, as it had the running jobs): the scene
    waits, its pause doubling at each run up to its bound, and is readied once the storage answers again."""
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import ingest as ingest_module
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()

    def throttled(self, key, dest):
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when fetching {key}")

    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as outage:
        outage.setattr(type(get_storage()), "get_file", throttled)
        result = tasks.ingest_task.apply(args=(scene["id"],))
    assert result.state == "REJECTED" and result.result.requeue
    assert result.result.reason == (f"the ingest of scene {scene['id']} stopped by a storage outage (S3 bucket 'voxe': "
                                    f"SlowDown when fetching scenes/{scene['id']}/dataset.zip)")
    assert client.get(f"/v1/scenes/{scene['id']}").json()["state"] == "processing"
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    with session_scope() as session:
        stopped = session.get(Scene, scene["id"])
        assert (stopped.ingest_attempts, stopped.ingest_storage_outages) == (0, 1)
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}

    again = upload_zip(client, zip_folder(dataset, root / "again.zip", prefix="mic_small")).json()
    pauses = []
    monkeypatch.setattr(ingest_module.time, "sleep", pauses.append)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 1.0)
    with monkeypatch.context() as outage:
        outage.setattr(type(get_storage()), "get_file", throttled)
        states = [tasks.ingest_task.apply(args=(again["id"],)).state for _ in range(9)]  # the limit is 3
    assert client.get(f"/v1/scenes/{again['id']}").json()["state"] == "processing"
    with session_scope() as session:
        waiting = session.get(Scene, again["id"])
        assert (waiting.ingest_attempts, waiting.ingest_storage_outages) == (0, 9)
    assert states == ["REJECTED"] * 9 and pauses == [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 64.0, 64.0]
    assert tasks.ingest_task.apply(args=(again["id"],)).result == {"scene_id": again["id"], "state": "ready"}


def test_an_ingest_a_storage_outage_stops_past_its_bound_fails_the_scene_naming_it(client, dataset, root,
                                                                                 monkeypatch):
    """An upload whose stored object answers 5xx every time (after botocore's retries) was fetched for ever: a
    storage outage uses up none of the ingest's attempts. Below VOXE_STORAGE_OUTAGE_MAX_RETRIES such runs each goes
    back to the queue as before; the next run an outage stops fails the scene, naming the outage and how many times
    it stopped the ingest, and its upload goes."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    bound = get_settings().storage_outage_max_retries
    with session_scope() as session:
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(ingest_storage_outages=bound - 1))

    def broken_object(self, key, dest):
        raise StorageUnavailable(f"S3 bucket 'voxe': InternalError (503) when fetching {key}")

    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    monkeypatch.setattr(type(get_storage()), "get_file", broken_object)
    given_back = tasks.ingest_task.apply(args=(scene["id"],))
    assert given_back.state == "REJECTED" and given_back.result.requeue
    with session_scope() as session:
        assert session.get(Scene, scene["id"]).ingest_storage_outages == bound
    assert tasks.ingest_task.apply(args=(scene["id"],)).get() == {"scene_id": scene["id"], "state": "failed"}
    failed = client.get(f"/v1/scenes/{scene['id']}").json()
    assert failed["state"] == "failed"
    assert failed["error"] == (f"ingest: stopped by a storage outage (S3 bucket 'voxe': InternalError (503) when "
                               f"fetching scenes/{scene['id']}/dataset.zip); storage outages stopped it {bound + 1} "
                               f"times ({bound} retries, the limit: VOXE_STORAGE_OUTAGE_MAX_RETRIES={bound})")
    assert stored_files(root) == []


def test_an_ingest_on_a_worker_whose_disk_is_full_goes_back_to_the_queue_keeping_the_upload(client, dataset, root,
                                                                                           monkeypatch):
    """One worker's scratch disk full as it unpacks an upload (killed runs' folders, another job's grids) had failed
    the scene and deleted its upload, a valid one, for good: every upload that worker took was lost. A full disk is
    the machine's state, not the upload's fault: the message goes back to the queue, counted as an outage's return
    is (a disk full at every run fails the scene at the limit, naming it: it had named "killed: out of memory?"
    first), and the redelivery readies the scene. While it waits, the scene says what stopped its last run."""
    import errno
    import os

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()

    def full(archive, dest):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dest))

    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as disk:
        disk.setattr(datasets, "unpack", full)
        result = tasks.ingest_task.apply(args=(scene["id"],))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    full_disk = f"the worker's disk full (OSError: [Errno {errno.ENOSPC}] {os.strerror(errno.ENOSPC)})"
    assert result.result.reason == f"the ingest of scene {scene['id']} stopped by {full_disk}"
    listed = client.get(f"/v1/scenes/{scene['id']}").json()
    assert (listed["state"], listed["error"]) == ("processing", full_disk)
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    with session_scope() as session:
        assert session.get(Scene, scene["id"]).ingest_attempts == 1
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    assert client.get(f"/v1/scenes/{scene['id']}").json()["error"] is None

    again = upload_zip(client, zip_folder(dataset, root / "again.zip", prefix="mic_small")).json()
    with monkeypatch.context() as disk:
        disk.setattr(datasets, "unpack", full)
        states = [tasks.ingest_task.apply(args=(again["id"],)).state for _ in range(5)]
    assert states == ["REJECTED"] * 4 + ["SUCCESS"]
    failed = client.get(f"/v1/scenes/{again['id']}").json()
    assert (failed["state"], failed["error"]) == ("failed", f"ingest: stopped 4 times, the last by {full_disk}: no "
                                                  "fault of the upload (upload it again once that is mended); it was "
                                                  "sent again 3 time(s) already, the limit (VOXE_JOB_MAX_REQUEUES=3)")


def test_a_cold_shutdown_in_an_ingests_outage_pause_sends_its_message_back(client, dataset, root, monkeypatch):
    """The pause before an ingest stopped by an outage goes back to the queue (up to minutes) is where a worker
    stopped meanwhile cancels it, raising in the task: that went through, the message acknowledged as failed and the
    scene left processing. The message goes back as the pause had sent it."""
    from celery.worker import state

    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import ingest as ingest_module
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()

    def throttled(self, key, dest):
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when fetching {key}")

    def cancelled_by_the_shutdown(_seconds):
        monkeypatch.setattr(state, "should_terminate", 0)  # set by Celery's cold shutdown (its exit code)
        raise NotImplementedError("<class 'celery.concurrency.solo.TaskPool'> does not implement kill_job")

    with monkeypatch.context() as outage:
        outage.setattr(type(get_storage()), "get_file", throttled)
        outage.setattr(ingest_module.time, "sleep", cancelled_by_the_shutdown)
        result = tasks.ingest_task.apply(args=(scene["id"],))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert result.result.reason == (f"the ingest of scene {scene['id']} stopped by a storage outage (S3 bucket 'voxe': "
                                    f"SlowDown when fetching scenes/{scene['id']}/dataset.zip)")
    monkeypatch.setattr(state, "should_terminate", None)  # the next worker
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}


ARCHIVE_DAMAGE = {  # what the storage may do to a stored archive: cut it short, rot a bit, keep a write's tail
    "truncated": lambda data: data[:len(data) // 2],
    "a byte flipped": lambda data: bytes(byte ^ 0xFF if i == len(data) // 2 else byte for i, byte in enumerate(data)),
    "padded": lambda data: data + bytes(100),
}


@pytest.mark.parametrize("damage", ARCHIVE_DAMAGE)
def test_a_scene_archive_damaged_in_the_storage_fails_naming_the_scene_and_the_checksums(client, dataset, root,
                                                                                         damage):
    """The archive's size and SHA-256 recorded when it was stored are checked as a worker fetches it: one damaged in
    the storage had failed its ingest as "BadZipFile: File is not a zip file" (or a CRC of some image), or been
    ingested (bytes after its end); a job's unpack, the same. Both fail naming the scene and both checksums, and
    leave no download or unpacked folder behind."""
    import hashlib

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.settings import get_settings
    from voxe_service.storage import StorageError, get_storage
    from worker import runtime

    def damaged(scene: dict) -> str:
        """Damage the scene's stored archive; what the error is to say of it."""
        key = f"scenes/{scene['id']}/dataset.zip"
        path = get_storage().path(key)
        data = ARCHIVE_DAMAGE[damage](path.read_bytes())
        path.write_bytes(data)
        return (f"{key}: the stored bytes are not the ones recorded ({scene['size_bytes']} bytes, SHA-256 "
                f"{scene['sha256']}; the storage holds {len(data)} bytes, SHA-256 {hashlib.sha256(data).hexdigest()}"
                "): truncated or corrupted in the storage")

    uploaded = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    words = damaged(uploaded)
    assert ingest(uploaded["id"]) == {"scene_id": uploaded["id"], "state": "failed"}
    failed = client.get(f"/v1/scenes/{uploaded['id']}").json()
    assert (failed["state"], failed["error"]) == ("failed", f"ingest: StorageError: scene {uploaded['id']}'s upload "
                                                            f"{words}")

    ready = make_scene(client, dataset, root)
    words = damaged(ready)
    with session_scope() as session:
        scene = session.get(Scene, ready["id"])
    with pytest.raises(StorageError) as fetched:
        with runtime.scene_dataset(scene, get_settings(), get_storage()):
            pass
    assert str(fetched.value) == f"scene {ready['id']}'s archive {words}"
    # nothing unpacked is kept (the cache's lock file, made as room is made before the download, is no dataset)
    assert [p.name for p in (root / "work" / "scenes").iterdir() if p.name != runtime.EVICTION_LOCK] == []


@pytest.mark.parametrize("locks", [True, False])
def test_an_ingest_removes_the_folders_its_scenes_killed_runs_left_and_keeps_a_live_runs(client, dataset, root,
                                                                                        monkeypatch, locks):
    """An ingest killed mid-run (out of memory on its upload) leaves its unpacked upload (up to
    VOXE_MAX_EXTRACTED_BYTES), which had stayed until the scene failed: in a crash loop, one per run. The scene's
    next run on the machine removes those whose lock died with their process as it starts; a live run's folder (its
    lock held) and other scenes' stay. Where the filesystem has no locks, nothing is removed and the ingest runs."""
    import errno
    import fcntl
    import subprocess
    import sys
    from types import SimpleNamespace

    from voxe_service import scratch
    from voxe_service.settings import get_settings
    from worker import ingest as ingest_module

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    work = Path(get_settings().work_dir) / "ingest"
    holding = ("import fcntl, sys, time; owner = open(sys.argv[1], 'ab'); fcntl.flock(owner, fcntl.LOCK_EX); "
               "print('locked', flush=True); time.sleep(600)")

    def run_in(folder: Path) -> subprocess.Popen:
        """A process holding ``folder`` as an ingest run does (voxe_service.scratch)."""
        folder.mkdir(parents=True)
        (folder / "archive.zip").write_bytes(b"an unpacked upload")
        process = subprocess.Popen([sys.executable, "-c", holding, str(folder / ".owner")], stdout=subprocess.PIPE,
                                   text=True)
        assert process.stdout.readline() == "locked\n"
        return process

    killed = run_in(work / f"{scene['id']}-killed01")
    killed.kill()
    killed.wait()
    live, other = f"{scene['id']}-live0001", f"{'1' * 32}-other001"
    (work / other).mkdir()
    seen, decode = [], ingest_module.decode

    def decode_seeing(*args):
        seen.extend(p.name for p in work.iterdir() if p.is_dir())
        return decode(*args)

    def no_locks(*args):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(ingest_module, "decode", decode_seeing)
    if not locks:
        monkeypatch.setattr(scratch, "fcntl", SimpleNamespace(flock=no_locks, LOCK_EX=fcntl.LOCK_EX,
                                                              LOCK_NB=fcntl.LOCK_NB))
    running = run_in(work / live)
    try:
        assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    finally:
        running.kill()
        running.wait()
    kept = [live, other] + ([] if locks else [f"{scene['id']}-killed01"])
    own = set(seen) - set(kept)  # as the run decoded: the killed run's folder gone already
    assert set(kept) <= set(seen) and len(own) == 1 and own.pop().startswith(f"{scene['id']}-")
    assert sorted(p.name for p in work.iterdir() if p.is_dir()) == sorted(kept)


def test_an_ingest_that_cannot_make_its_folder_still_removes_the_killed_runs_and_holds_no_descriptor(
        client, dataset, root, monkeypatch):
    """A disk filled by killed runs' folders: the new run's own folder cannot be made (ENOSPC). The dead folders
    are removed first, so the disk frees itself, and no descriptor is left holding a lock (it had kept them judged
    live by every later run until this worker process died)."""
    import errno
    import os
    import tempfile

    from voxe_service.settings import get_settings
    from worker import tasks

    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    work = Path(get_settings().work_dir) / "ingest"
    (work / f"{scene['id']}-killed01").mkdir(parents=True)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    def open_in_work() -> list[str]:
        """The paths under ``work`` this process holds a descriptor on (a count of all of them had also seen the
        database pool's connections, which the ingest's lease keeper may open)."""
        paths = []
        for fd in os.listdir("/proc/self/fd"):
            try:
                paths.append(os.readlink(f"/proc/self/fd/{fd}"))
            except OSError:  # closed since listed
                pass
        return [path for path in paths if path.startswith(str(work.resolve()))]

    monkeypatch.setattr(tempfile, "mkdtemp", full)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    result = tasks.ingest_task.apply(args=(scene["id"],))  # (the machine's state: the message goes back)
    assert result.state == "REJECTED" and "No space left" in result.result.reason
    assert list(work.iterdir()) == [] and open_in_work() == []


def test_a_work_dir_that_cannot_hold_uploads_stops_the_api_at_its_start_naming_the_variable(root, monkeypatch):
    """VOXE_WORK_DIR naming a file had let the API start and answer every upload 500 (its staging folder unmade)."""
    from api.main import create_app
    from voxe_service.settings import SettingsError

    not_a_folder = root / "work-file"
    not_a_folder.write_text("")
    monkeypatch.setenv("VOXE_WORK_DIR", str(not_a_folder))
    _reset()
    with pytest.raises(SettingsError, match=rf"^bad service settings: VOXE_WORK_DIR='{not_a_folder}': cannot make "
                                            rf"the upload staging folder '{not_a_folder / 'uploads'}': Not a directory"):
        with TestClient(create_app()):
            pass
    # an uploads folder there already, where no folder can be made (read-only to the API's user: as root, which
    # reads past permissions, making one is made to refuse as it would)
    work = root / "work-ro"
    (work / "uploads").mkdir(parents=True)
    monkeypatch.setenv("VOXE_WORK_DIR", str(work))
    mkdir = Path.mkdir

    def read_only_uploads(self, *args, **kwargs):
        if self.parent == work / "uploads":
            raise PermissionError(13, "Permission denied")
        return mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only_uploads)
    _reset()
    with pytest.raises(SettingsError, match=rf"^bad service settings: VOXE_WORK_DIR='{work}': cannot make the upload "
                                            rf"staging folder '{work / 'uploads'}': Permission denied"):
        with TestClient(create_app()):
            pass


def test_a_starting_api_process_removes_the_staging_folders_no_live_process_holds(root, monkeypatch):
    """An API process killed mid-upload (OOM, SIGKILL, a deploy) left its staging folder in work/uploads for good. A
    starting one removes those whose lock (flock on .owner) no process holds; an upload in progress in another
    process sharing the work folder keeps its folder, and one whose folder was swept before it locked it makes
    another."""
    import tempfile

    from api import uploads
    from api.main import create_app
    from voxe_service import scratch

    work = root / "work"
    with uploads.staging_folder(work) as live:
        killed = work / "uploads" / "upload-killed"  # its process's lock went with the process
        (killed / "data").mkdir(parents=True)
        (killed / ".owner").touch()
        (killed / "data" / "big.bin").write_bytes(b"x" * 1000)
        (work / "uploads" / "upload-unlocked").mkdir()  # its process died before it made its lock file
        with TestClient(create_app()):
            assert staged(root) == [live.name]
    # Another process sweeping a folder between its making and its locking: the upload makes another.
    make, open_file, made, opened = tempfile.mkdtemp, open, [], []

    def made_then_swept(**kwargs):
        made.append(Path(make(**kwargs)))
        if len(made) == 1:
            assert uploads.sweep_staging(work) == 1
        return str(made[-1])

    def opened_then_swept(path, *args):
        opened.append(handle := open_file(path, *args))
        if len(opened) == 1:  # (the sweep's own open is the second)
            assert uploads.sweep_staging(work) == 1
        return handle

    for name, swept in (("tempfile.mkdtemp", made_then_swept), ("open", opened_then_swept)):
        with monkeypatch.context() as patch:
            patch.setattr(scratch if name == "open" else tempfile, name.split(".")[-1], swept, raising=False)
            with uploads.staging_folder(work) as replaced:
                assert staged(root) == [replaced.name]
        assert staged(root) == []
    assert len(made) == 2 and len(opened) == 3
    # A filesystem without locks (some NFS / CIFS mounts, ENOLCK): uploads go on, and the sweep removes nothing
    import errno
    import fcntl

    def no_locks(*_args):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with uploads.staging_folder(work) as unlocked:
        assert uploads.sweep_staging(work) == 0 and staged(root) == [unlocked.name]
    assert staged(root) == []


def test_a_processing_scene_can_be_deleted_and_its_ingest_keeps_nothing(client, dataset, root):
    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"]
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert client.delete(f"/v1/scenes/{scene['id']}").status_code == 409  # a job waits on it
    client.post(f"/v1/jobs/{job['id']}/cancel")
    assert client.delete(f"/v1/scenes/{scene['id']}").status_code == 204
    assert ingest(scene["id"])["skipped"] == f"scene {scene['id']} is gone"
    assert stored_files(root) == [] and client.get(f"/v1/scenes/{scene['id']}").status_code == 404


@BOTH_DATABASES
def test_a_scene_deleted_before_its_upload_answers_is_a_409_and_keeps_nothing(client, dataset, root, monkeypatch):
    """The scene is listed while the broker takes its ingest, so a DELETE can come first: the upload then says so
    (it had been a 500 from the task id's write), and neither the scene, its bytes nor a replay of its key stay."""
    from voxe_service.queue import TaskQueue

    send_ingest, deleted = TaskQueue.send_ingest, []

    def deleted_meanwhile(self, scene_id):
        deleted.append(client.delete(f"/v1/scenes/{scene_id}").status_code)
        return send_ingest(self, scene_id)

    monkeypatch.setattr(TaskQueue, "send_ingest", deleted_meanwhile)
    archive, retry = zip_folder(dataset, root / "ok.zip", prefix="mic_small"), {"Idempotency-Key": "once"}
    with open(archive, "rb") as handle:
        response = client.post("/v1/scenes", files={"archive": ("scene.zip", handle, "application/zip")}, headers=retry)
    assert deleted == [204] and response.status_code == 409, response.text
    assert "was deleted (DELETE /v1/scenes/" in response.json()["detail"]
    assert client.get("/v1/scenes").json()["total"] == 0 and stored_files(root) == [] and staged(root) == []
    with open(archive, "rb") as handle:
        replay = client.post("/v1/scenes", files={"archive": ("scene.zip", handle, "application/zip")}, headers=retry)
    assert replay.status_code == 409 and "has been deleted; use a new key" in replay.json()["detail"]


def test_a_job_deleted_with_its_scene_before_its_creation_answers_is_a_409(client, dataset, root, monkeypatch):
    """A job is listed once recorded, so while the broker takes it the job can be canceled and its scene deleted:
    POST /v1/jobs and POST /v1/evaluations then say so (re-reading the deleted job had been a 500)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import TaskQueue

    send, deleted = TaskQueue.send, []

    def canceled_and_deleted_meanwhile(self, *args, **kwargs):
        (queued,) = client.get("/v1/jobs", params={"state": "queued"}).json()["items"]
        assert client.post(f"/v1/jobs/{queued['id']}/cancel").status_code == 200
        deleted.append(client.delete(f"/v1/scenes/{queued['scene_id']}").status_code)
        return send(self, *args, **kwargs)

    edited, scene = make_scene(client, dataset, root), make_scene(client, dataset, root)
    edit = client.post("/v1/jobs", json={"scene_id": edited["id"], **JOB}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="succeeded"))
    monkeypatch.setattr(TaskQueue, "send", canceled_and_deleted_meanwhile)
    evaluation = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic"})
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers={"Idempotency-Key": "once"})
    assert deleted == [204, 204]
    for response in (evaluation, job):
        assert response.status_code == 409, response.text
        assert "was canceled and deleted with its scene before its creation answered" in response.json()["detail"]
    assert client.get("/v1/jobs").json()["total"] == 0 and stored_files(root) == []


def test_a_job_canceled_while_its_creation_sends_it_keeps_the_message_of_its_cancel(client, dataset, root, monkeypatch):
    """The send's record of the task id had overwritten the canceled job's message with none."""
    from voxe_service.queue import TaskQueue

    send = TaskQueue.send

    def canceled_meanwhile(self, *args, **kwargs):
        (queued,) = client.get("/v1/jobs", params={"state": "queued"}).json()["items"]
        assert client.post(f"/v1/jobs/{queued['id']}/cancel").json()["message"] == "canceled while queued"
        return send(self, *args, **kwargs)

    scene = make_scene(client, dataset, root)
    monkeypatch.setattr(TaskQueue, "send", canceled_meanwhile)
    created = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB})
    assert created.status_code == 201, created.text
    job = client.get(f"/v1/jobs/{created.json()['id']}").json()
    assert (job["state"], job["message"]) == ("canceled", "canceled while queued")


def test_a_cancel_whose_job_is_deleted_with_its_scene_meanwhile_is_a_404(client, dataset, root, monkeypatch):
    """Canceling a canceled job again while its scene is deleted: the answer re-read a deleted row, a 500."""
    from api.services import jobs as job_service

    scene = make_scene(client, dataset, root)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert client.post(f"/v1/jobs/{job['id']}/cancel").json()["state"] == "canceled"
    request_cancel, deleted = job_service.request_cancel, []

    def deleted_meanwhile(**kwargs):
        request_cancel(**kwargs)
        deleted.append(client.delete(f"/v1/scenes/{scene['id']}").status_code)

    monkeypatch.setattr(job_service, "request_cancel", deleted_meanwhile)
    response = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert deleted == [204] and response.status_code == 404, response.text
    assert response.json()["detail"] == f"job {job['id']!r} not found"


def test_canceling_a_sweeps_edit_that_waits_for_its_scene_fails_its_evaluation_with_it(client, dataset, root):
    """The evaluation rides in its edit's chain: canceling the edit while its scene was processing had left it
    queued, never sent (its message still 'waiting for the scene'), holding a quota slot and the scene, until the
    reaper failed it as never handed to the broker. It fails as the chain's evaluate stage fails it."""
    scene = upload_zip(client, zip_folder(dataset, root / "ok.zip", prefix="mic_small")).json()
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene["id"], "object": "microphone"}]}).json()
    canceled, other = sweep["entries"][:2]
    assert client.post(f"/v1/jobs/{canceled['edit_job_id']}/cancel").json()["state"] == "canceled"
    evaluation = client.get(f"/v1/jobs/{canceled['evaluation_job_id']}").json()
    assert evaluation["state"] == "failed" and evaluation["error"] == (
        f"evaluate: source job {canceled['edit_job_id']} canceled: canceled while queued")
    assert client.get(f"/v1/jobs/{other['evaluation_job_id']}").json()["state"] == "queued"
    assert ingest(scene["id"])["state"] == "ready"
    assert client.get(f"/v1/sweeps/{sweep['id']}").json()["counts"] == {"canceled": 1, "failed": 1, "queued": 10}


def test_the_api_process_imports_no_worker_code():
    """The API sends tasks by name: building the app and a sender imports nothing of worker/."""
    import subprocess
    import sys

    from service_helpers import REPO

    code = ("import sys\n"
            "from api.main import create_app\n"
            "create_app()\n"
            "from voxe_service.queue import get_queue\n"
            "get_queue()\n"
            "print(sorted(m for m in sys.modules if m == 'worker' or m.startswith('worker.')))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def _zip_bytes(entries: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return buffer.getvalue()


def _dataset_entries(dataset: Path, drop: str | None = None, json_text: str | None = None) -> dict[str, bytes]:
    entries = {p.relative_to(dataset).as_posix(): p.read_bytes() for p in dataset.rglob("*") if p.is_file()}
    if drop:
        entries.pop(drop)
    if json_text is not None:
        entries["transforms_train.json"] = json_text.encode()
    return entries


@pytest.mark.parametrize("case, expected", [
    ("not a zip", "not a readable zip"),
    ("traversal", "'..' path components are not allowed"),
    ("absolute", "absolute paths are not allowed"),
    ("missing image", "transforms_train.json frame 1 ('./train/r_4'): image not found (tried train/r_4, train/r_4.png, "
                      "train/r_4.jpg, train/r_4.jpeg)"),
    ("broken json", "transforms_train.json: invalid JSON"),
    ("no dataset", "the upload is neither a dataset nor a mesh (it holds 'readme.txt'): send a dataset folder or "
                   ".zip (transforms_train.json: NeRF-synthetic; transforms.json: instant-ngp / nerfstudio; a COLMAP "
                   "model sparse/0/ or sparse/ beside images/), or one mesh (.obj, .ply)"),
])
def test_bad_upload_is_422_and_leaves_nothing(client, dataset, root, case, expected):
    if case == "not a zip":
        body = b"this is not a zip"
    elif case == "traversal":
        body = _zip_bytes({**_dataset_entries(dataset), "../evil.txt": b"x"})
    elif case == "absolute":
        body = _zip_bytes({**_dataset_entries(dataset), "/etc/evil.txt": b"x"})
    elif case == "missing image":
        body = _zip_bytes(_dataset_entries(dataset, drop="train/r_4.png"))
    elif case == "broken json":
        body = _zip_bytes(_dataset_entries(dataset, json_text='{"frames": [}'))
    else:
        body = _zip_bytes({"readme.txt": b"hello"})
    response = client.post("/v1/scenes", files={"archive": ("bad.zip", body, "application/zip")})
    assert response.status_code == 422, response.text
    assert expected in response.json()["detail"], response.json()
    assert "/tmp" not in response.json()["detail"] and str(root) not in response.json()["detail"]
    assert client.get("/v1/scenes").json()["total"] == 0
    assert stored_files(root) == [] and staged(root) == []


def test_a_zip_that_is_none_is_refused_naming_the_file_sent(client, dataset, root):
    """An upload's zip that cannot be read is named by its file name as sent, as a file sent loose is: the 422 had
    said only "archive is not a readable zip file", whichever file of several a user had picked."""
    misplaced = _zip_bytes(_dataset_entries(dataset)).replace(zipfile.stringCentralDir, b"XX\x01\x02")
    for body, reason in ((b"this is not a zip", "no end of central directory record"),
                         (misplaced, "its central directory is not where its end record says")):
        response = client.post("/v1/scenes", files={"archive": ("bad.zip", body, "application/zip")})
        assert response.status_code == 422, response.text
        assert response.json()["detail"] == f"archive 'bad.zip' is not a readable zip file: {reason}"
    assert client.get("/v1/scenes").json()["total"] == 0
    assert stored_files(root) == [] and staged(root) == []


def test_a_transforms_json_written_on_windows_uploads(client, dataset, root):
    """The upload check reads its file_path's '\\' separators as '/', as the loader does (and instant-ngp)."""
    meta = json.loads((dataset / "transforms_train.json").read_text())
    for frame in meta["frames"]:
        frame["file_path"] = frame["file_path"].replace("/", "\\")
    body = _zip_bytes(_dataset_entries(dataset, json_text=json.dumps(meta)))
    response = client.post("/v1/scenes", files={"archive": ("windows.zip", body, "application/zip")})
    assert response.status_code == 201, response.text
    assert (response.json()["image_count"], response.json()["width"]) == (3, 800)
    assert ingest(response.json()["id"])["state"] == "ready"


def _colmap_capture(tmp_path: Path, second_model: str = "PINHOLE") -> Path:
    root = square_capture(tmp_path)
    params = [12.0, 12.0, 8.0, 6.0] + [0.0] * (8 if second_model == "FULL_OPENCV" else 0)
    write_colmap_model(root / "sparse" / "0", [("OPENCV", 16, 12, [12.0, 12.0, 8.0, 6.0, 0.02, 0.0, 0.0, 0.0]),
                                               (second_model, 16, 12, params)],
                       [(f"{i}.png", i % 2, pose_at(i)) for i in range(3)])
    (root / "dense").mkdir()
    (root / "dense" / "fused.ply").write_bytes(b"ply\n")  # COLMAP's dense output: beside a model it is no mesh
    return root


def test_colmap_and_nerfstudio_uploads(client, root):
    good = _colmap_capture(root / "good")
    response = upload_zip(client, zip_folder(good, root / "colmap.zip", prefix="capture"))
    assert response.status_code == 201, response.text
    scene = response.json()
    assert (scene["format"], scene["image_count"], scene["width"], scene["height"]) == ("colmap", 3, 16, 12)
    assert ingest(scene["id"])["state"] == "ready"

    bad = _colmap_capture(root / "bad", second_model="FULL_OPENCV")
    response = upload_zip(client, zip_folder(bad, root / "bad.zip"))
    assert response.status_code == 422
    assert response.json()["detail"] == ("invalid dataset: sparse/0/images.bin frame 1 ('images/1.png'): camera 2 has "
                                         "COLMAP model FULL_OPENCV, which is not supported (use one of SIMPLE_PINHOLE, "
                                         "PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, SIMPLE_RADIAL_FISHEYE, "
                                         "RADIAL_FISHEYE, OPENCV_FISHEYE)")
    shutil.rmtree(good / "sparse")
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": pose_at(i).tolist()} for i in range(3)]
    frames[2]["camera_model"] = "OPENCV_FISHEYE"
    meta = {"camera_model": "OPENCV", "fl_x": 12.0, "k1": 0.02, "frames": frames}
    (good / "transforms.json").write_text(json.dumps(meta))
    response = upload_zip(client, zip_folder(good, root / "ns.zip"))
    assert response.status_code == 422
    assert response.json()["detail"] == ("invalid dataset: transforms.json frame 2 ('images/2.png'): camera_model "
                                         "OPENCV_FISHEYE differs from frame 0's OPENCV; the fisheye and the OPENCV "
                                         "model cannot be mixed in one capture")
    assert client.get("/v1/scenes").json()["total"] == 1 and staged(root) == []


def test_mesh_shading_is_checked_at_upload(client, dataset, root):
    body = zip_folder(dataset, root / "mic.zip").read_bytes()
    for field, unknown, valid in (("mesh_shading", "flat", "baked"), ("mesh_up_axis", "w", "z")):
        response = client.post("/v1/scenes", files={"archive": ("mic.zip", body, "application/zip")},
                               data={field: unknown})
        assert response.status_code == 422 and response.json()["detail"][0]["loc"] == ["body", field]
        response = client.post("/v1/scenes", files={"archive": ("mic.zip", body, "application/zip")},
                               data={field: valid})
        assert response.status_code == 422 and f"{field} applies to mesh uploads only" in response.json()["detail"]
    assert client.get("/v1/scenes").json()["total"] == 0 and staged(root) == []


def test_upload_needs_exactly_one_source(client):
    response = client.post("/v1/scenes", files={"name": (None, "nothing")})
    assert response.status_code == 422 and "either one zip" in response.json()["detail"]
    assert client.post("/v1/scenes").status_code == 422  # no body: an empty form, as above
    response = client.post("/v1/scenes", files={"name": (None, "no\x00thing")})  # checked first, and never stored
    assert response.status_code == 422 and response.json()["detail"][0]["loc"] == ["body", "name"]


def test_a_scene_name_sent_with_control_characters_or_blank_is_a_422_naming_it(client):
    """A name sent in the form kept a newline or ESC (stored and listed as sent, where a name taken from the zip's file
    name has them stripped), and a name of spaces was stored. Both are a 422 naming the field and saying what is
    wrong; a name of any script, with spaces inside, is taken as sent."""
    for name, said in (("two\nlines", "contains control characters"), ("\x1b[31mred", "contains control characters"),
                       ("tab\there", "contains control characters"), ("no\x00thing", "contains control characters"),
                       ("   ", "is blank"), ("\u3000", "is blank")):
        response = client.post("/v1/scenes", files={"name": (None, name)})
        assert response.status_code == 422, name
        (error,) = response.json()["detail"]
        assert error["loc"] == ["body", "name"] and f"the name {said}" in error["msg"], (name, error)
    for name in ("a café 🎩", " padded "):  # (then refused for sending no dataset: the name passed)
        response = client.post("/v1/scenes", files={"name": (None, name)})
        assert response.status_code == 422 and "either one zip" in response.json()["detail"], name
    assert client.get("/v1/scenes").json()["total"] == 0


def test_upload_over_the_limit_is_413(root, monkeypatch, dataset):
    monkeypatch.setenv("VOXE_MAX_UPLOAD_BYTES", "1000")
    _reset()
    from api.main import create_app

    with TestClient(create_app()) as client:
        response = upload_zip(client, zip_folder(dataset, root / "big.zip"))
        assert response.status_code == 413 and "VOXE_MAX_UPLOAD_BYTES" in response.json()["detail"]
        archive = (root / "big.zip").read_bytes()
        boundary = "limit-test"
        multipart = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"archive\"; filename=\"big.zip\"\r\n"
                     f"Content-Type: application/zip\r\n\r\n").encode() + archive + f"\r\n--{boundary}--\r\n".encode()
        chunked = [  # no Content-Length: the limit is found while the body streams in
            ("/v1/scenes", f"multipart/form-data; boundary={boundary}", multipart),
            ("/v1/jobs", "application/json", b'{"scene_id": "x", "prompt": "' + b"a" * 2000 + b'"}'),
        ]
        for url, content_type, body in chunked:
            response = client.post(url, content=iter([body[:500], body[500:]]), headers={"content-type": content_type})
            assert "content-length" not in response.request.headers
            assert response.status_code == 413 and "VOXE_MAX_UPLOAD_BYTES" in response.json()["detail"], url
        assert client.get("/v1/scenes").json()["total"] == 0


def test_the_413_is_serialised_as_every_other_answer(root, monkeypatch):
    """The upload limit's 413 had been written with json.dumps' spaces ({"detail": "..."}), unlike every other answer
    (FastAPI's compact JSON): a client comparing bodies, or a cache keying on them, saw two forms of one API."""
    monkeypatch.setenv("VOXE_MAX_JSON_BODY_BYTES", "100")
    _reset()
    from api.main import create_app

    with TestClient(create_app()) as client:
        for content in (b"x" * 200, iter([b"x" * 60, b"x" * 60])):  # by Content-Length; counted while streaming
            response = client.post("/v1/jobs", content=content, headers={"content-type": "application/json"})
            detail = ("JSON body (any body but an upload's multipart form) over the limit of 100 bytes "
                      "(VOXE_MAX_JSON_BODY_BYTES)")
            assert response.status_code == 413
            assert response.content == json.dumps({"detail": detail}, separators=(",", ":")).encode()
            assert response.headers["content-type"] == "application/json"
            assert int(response.headers["content-length"]) == len(response.content)
        other = client.get("/v1/jobs/nope")
        assert other.status_code == 404 and b'{"detail":"' in other.content  # the form every answer has


# ------------------------------------------------------------------------------------------ jobs
@pytest.mark.parametrize("body, location", [
    ({"bogus": 1}, ["body", "bogus"]),
    ({"params": {"iteratons": 10}}, ["body", "params", "iteratons"]),
    ({"params": {"reconstruction": {"presett": "fast"}}}, ["body", "params", "reconstruction", "presett"]),
    ({"params": {"export": {"frames": 3}}}, ["body", "params", "export", "frames"]),
])
def test_unknown_fields_are_422_naming_the_field(client, dataset, root, body, location):
    scene = make_scene(client, dataset, root)
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, **body})
    assert response.status_code == 422
    errors = response.json()["detail"]
    assert any(e["loc"] == location and e["type"] == "extra_forbidden" for e in errors), errors


@pytest.mark.parametrize("body, message", [
    ({"edit_words": ["hat"]}, "edit word 'hat' does not occur in the prompt"),
    ({"edit_words": []}, "edit_words is required for a local edit"),
    ({"prompt": "a mic, wearing sunglasses", "edit_words": [","]}, "edit word ',' names nothing"),
    ({"edit_words": [" \t"]}, "an edit word is blank"),
    # the model lowers the prompt's final capital sigma to \u03c3, not to the final \u03c2 the word has
    ({"prompt": "\u0395\u039d\u0391\u03a3 \u03a3\u039a\u03a5\u039b\u039f\u03a3 wearing a hat",
      "edit_words": ["\u03c3\u03ba\u03c5\u03bb\u03bf\u03c2"]}, "does not occur in the prompt"),
    ({"prompt": "\u4e00\u53ea\u6234\u5e3d\u5b50\u7684\u72d7", "edit_words": ["\u5e3d\u5b50"]},
     "separate the edit word from the words around it with spaces in the prompt"),
    ({"prompt": "a mic wearing a dog\u2019s hat", "edit_words": ["dog's hat"]},
     "its apostrophes and quotes must be the prompt's own"),
    ({"mode": "global"}, "edit_words apply to local edits only"),
    ({"edit_words": ["a mic wearing big sunglasses"]}, "cover the whole prompt"),
    ({"prompt": "   "}, "no words"),
    ({"prompt": "a <|endoftext|> hat on a mic"}, "the prompt contains '<|endoftext|>', which the model reads as"),
    ({"prompt": "<|startoftext|>a mic wearing sunglasses<|endoftext|>"},
     "the prompt contains '<|startoftext|>' and '<|endoftext|>'"),
    ({"edit_words": ["sunglasses<|endoftext|>"]}, "an edit word contains '<|endoftext|>'"),
    ({"params": {"refine": {"lift_start": "constant"}}}, "refine: lift_start='constant' with iterations=0"),
])
def test_bad_edit_words_are_422(client, dataset, root, body, message):
    scene = make_scene(client, dataset, root)
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, **body})
    assert response.status_code == 422
    assert message in json.dumps(response.json()), response.json()


@pytest.mark.parametrize("prompt, edit_word", [
    ("a mic wearing a caf\u00e9 hat", "cafe\u0301 hat"),  # composed prompt, decomposed word: one text in NFC
    ("a mic wearing a cafe\u0301 hat", "Caf\u00e9 hat"),
    ("a dog's mic wearing sunglasses", "dog"),  # the model reads "dog" "'s"
    ("a sunglasses-wearing mic", "sunglasses"),  # and "sunglasses" "-" "wearing"
    ("a \U0001f3a9 on a mic", "\U0001f3a9"),  # a symbol the model reads (it had been 'an edit word has no words')
    ("a dog wearing a \u2665 necklace", "\u2665"),
])
def test_an_edit_word_the_model_finds_in_the_prompt_is_accepted(client, dataset, root, prompt, edit_word):
    """The API had matched words of its own ([\\w'-]+, not normalised): these were 422s saying the word 'does not
    occur in the prompt', which the refinement's tokenizer finds there."""
    scene = make_scene(client, dataset, root)
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": prompt, "mode": "local",
                                             "edit_words": [edit_word]})
    assert response.status_code == 201, response.json()


def test_a_prompt_or_object_is_accepted_when_it_names_something_as_the_model_reads_it(client, dataset, root):
    """An emoji or currency sign alone names what to edit into (as it names the object beside an edit word), and
    punctuation alone names nothing: the API had refused the first as having 'no words' and accepted the second
    (its words were [\\w'-]+: "---" was one). A contraction's ending alone names nothing either, and the 422 says
    so: it had named punctuation and marks only, though the pattern takes "'s"."""
    scene = make_scene(client, dataset, root)
    for text, names in (("\U0001f436", True), ("\U0001f436 \U0001f3a9", True), ("$", True), ("---", False),
                        ("'", False), ("_", False), ("^^", False), ("'s", False), ("'ll 's-", False)):
        job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": text})
        assert job.status_code == (201 if names else 422), (text, job.json())
        evaluation = client.post("/v1/evaluations", json={"job_ids": ["nope"], "object": text})
        assert evaluation.status_code == (404 if names else 422), (text, evaluation.json())  # (404: no such job)
        if not names:
            for refusal in (job, evaluation):
                assert "has no words: nothing in it names anything" in refusal.text, (text, refusal.json())
                assert "or a contraction's ending such as 's alone do not" in refusal.text, (text, refusal.json())


def test_parameter_ranges_are_checked(client, dataset, root):
    scene = make_scene(client, dataset, root)
    for params in ({"iterations": -1}, {"render_size": 4}, {"guidance_scale": 0}, {"regulariser": "l3"},
                   {"reconstruction": {"preset": "slow"}}, {"downsample": 0}, {"resample": "lanczos"}):
        response = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": params})
        assert response.status_code == 422, params


def test_jobs_share_a_reconstruction_per_parameter_set_and_cancel_when_queued(client, dataset, root):
    scene = make_scene(client, dataset, root)
    first = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": {"downsample": 8}}).json()
    second = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a yarn doll of a mic",
                                           "params": {"downsample": 8, "iterations": 10}}).json()
    other = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": {"downsample": 4}}).json()
    boxed = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB,
                                          "params": {"downsample": 8, "resample": "box"}}).json()
    assert first["state"] == "queued" and first["params"]["iterations"] == 8000
    assert first["params"]["resample"] == "bilinear"
    assert first["reconstruction"]["id"] == second["reconstruction"]["id"] != other["reconstruction"]["id"]
    assert boxed["reconstruction"]["id"] not in (first["reconstruction"]["id"], other["reconstruction"]["id"])
    assert first["models"]["sds"] == "tiny (smoke test, random weights)"
    assert second["models"]["attention"] is None  # global edits never use the attention model
    assert len(client.get(f"/v1/scenes/{scene['id']}/reconstructions").json()) == 3

    canceled = client.post(f"/v1/jobs/{first['id']}/cancel")
    assert canceled.status_code == 200 and canceled.json()["state"] == "canceled"
    assert canceled.json()["finished_at"] is not None
    assert client.post(f"/v1/jobs/{first['id']}/cancel").json()["state"] == "canceled"
    listing = client.get("/v1/jobs", params={"state": "queued", "scene_id": scene["id"]}).json()
    assert listing["total"] == 3 and {j["id"] for j in listing["items"]} == {second["id"], other["id"], boxed["id"]}


def test_the_job_listing_is_newest_first_and_pages_by_limit_and_offset(client, dataset, root):
    """As its summary says; the listings' other tests had checked counts and sets only, so an oldest-first order or
    an offset ignored had passed."""
    scene = make_scene(client, dataset, root)
    ids = [client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": f"a mic made of {stuff}"}).json()["id"]
           for stuff in ("wood", "glass", "gold")]
    assert [j["id"] for j in client.get("/v1/jobs").json()["items"]] == ids[::-1]
    page = client.get("/v1/jobs", params={"scene_id": scene["id"], "limit": 1, "offset": 1}).json()
    assert (page["total"], [j["id"] for j in page["items"]]) == (3, [ids[1]])


def listed(client, path: str, **params) -> tuple[list[str], dict]:
    page = client.get(path, params=params)
    assert page.status_code == 200, page.text
    return [row["id"] for row in page.json()["items"]], page.json()


@BOTH_DATABASES
def test_a_job_added_between_page_reads_is_neither_repeated_nor_skipped_by_the_cursor(client, dataset, root):
    """Paging by offset, a job created while the first page was shown shifted the next: "older" repeated the first
    page's last job. The cursor names that row, so the next page starts after it wherever it now stands."""
    scene = make_scene(client, dataset, root)

    def new_job(stuff: str) -> str:
        return client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": f"a mic made of {stuff}"}).json()["id"]

    ids = [new_job(stuff) for stuff in ("wood", "glass", "gold")]  # oldest first
    first, page = listed(client, "/v1/jobs", limit=2)
    assert first == ids[:0:-1] and page["next_cursor"] and page["offset"] == 0
    added = new_job("silver")
    by_offset, _ = listed(client, "/v1/jobs", limit=2, offset=2)
    assert by_offset == [ids[1], ids[0]]  # the original behaviour: the first page's last job again
    second, after = listed(client, "/v1/jobs", limit=2, cursor=page["next_cursor"])
    assert second == [ids[0]] and after["next_cursor"] is None  # the last page
    assert (after["total"], after["offset"]) == (4, 3)  # its place in the list as it is now (the added one first)
    assert listed(client, "/v1/jobs", limit=2)[0] == [added, ids[2]]
    filtered, page = listed(client, "/v1/jobs", limit=1, state="queued", scene_id=scene["id"])
    assert listed(client, "/v1/jobs", limit=3, state="queued", scene_id=scene["id"],
                  cursor=page["next_cursor"])[0] == [ids[2], ids[1], ids[0]]


@BOTH_DATABASES
def test_the_cursor_orders_jobs_created_at_the_same_instant_by_id(client, dataset, root):
    """Jobs whose created_at is the same (a sweep's, written together) are each listed once, paged by cursor."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene = make_scene(client, dataset, root)
    ids = [client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": f"a mic {n}"}).json()["id"]
           for n in range(4)]
    with session_scope() as session:  # all at the first one's instant
        session.execute(update(Job).values(created_at=session.get(Job, ids[0]).created_at))
    seen, cursor = [], None
    while True:
        rows, page = listed(client, "/v1/jobs", limit=1, **({"cursor": cursor} if cursor else {}))
        seen += rows
        if (cursor := page["next_cursor"]) is None:
            break
    assert seen == sorted(ids, reverse=True)


def test_a_scene_deleted_between_page_reads_does_not_make_the_cursor_skip_one(client, dataset, root):
    """By offset, a scene of the first page deleted meanwhile moved the next page past a scene never shown."""
    archive = zip_folder(dataset, root / "ok.zip", prefix="mic_small")
    ids = [upload_zip(client, archive).json()["id"] for _ in range(3)]  # oldest first
    first, page = listed(client, "/v1/scenes", limit=2)
    assert first == ids[:0:-1]
    assert client.delete(f"/v1/scenes/{ids[2]}").status_code == 204
    assert listed(client, "/v1/scenes", limit=2, offset=2)[0] == []  # the original behaviour: ids[0] skipped
    second, after = listed(client, "/v1/scenes", limit=2, cursor=page["next_cursor"])
    assert second == [ids[0]] and (after["offset"], after["total"], after["next_cursor"]) == (1, 2, None)


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/scenes"])
def test_a_cursor_not_of_the_listing_or_sent_with_an_offset_is_a_422_naming_it(client, dataset, root, path):
    archive = zip_folder(dataset, root / "ok.zip", prefix="mic_small")
    for _ in range(2):
        assert upload_zip(client, archive).status_code == 201
    scenes_cursor = listed(client, "/v1/scenes", limit=1)[1]["next_cursor"]
    jobs_cursor = base64.urlsafe_b64encode(
        base64.urlsafe_b64decode(scenes_cursor + "==").replace(b"/v1/scenes", b"/v1/jobs")).decode().rstrip("=")
    cursor, foreign, listing_of_foreign = ((jobs_cursor, scenes_cursor, "/v1/scenes") if path == "/v1/jobs"
                                          else (scenes_cursor, jobs_cursor, "/v1/jobs"))
    assert client.get(path, params={"cursor": cursor}).status_code == 200
    for sent, detail in (
            ({"cursor": "bm90IGEgY3Vyc29y"}, f"cursor 'bm90IGEgY3Vyc29y' is not a cursor of GET {path}: send a "
                                             "page's next_cursor unchanged"),
            ({"cursor": "!!"}, f"cursor '!!' is not a cursor of GET {path}: send a page's next_cursor unchanged"),
            ({"cursor": foreign},
             f"cursor '{foreign[:40]}...' is a cursor of GET {listing_of_foreign}, not of GET {path}"),
            ({"cursor": cursor, "offset": 0}, "send either cursor or offset, not both: a cursor names where its page "
                                              "starts")):
        response = client.get(path, params=sent)
        assert (response.status_code, response.json()["detail"]) == (422, detail), sent
    too_long = client.get(path, params={"cursor": "a" * 201})
    assert too_long.status_code == 422 and "cursor" in too_long.text


LENIENT_INTEGERS = ("1_0", "%2B5", "+5", "%205", "5%20", "5.0", "%095")  # _, sign, space (+ in a query), tab, fraction


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/scenes"])
def test_an_integer_query_parameter_not_written_in_digits_is_a_422_naming_it(client, path):
    """Pydantic's lax reading of a query string had taken limit=1_0 as 10, +5 or " 5" as 5 and 5.0 as 5: a typo
    (or a value meant otherwise) answered as if it were plain digits. Only digits (an optional minus) are read now."""
    for parameter in ("limit", "offset"):
        for sent in LENIENT_INTEGERS:
            response = client.get(f"{path}?{parameter}={sent}")
            assert response.status_code == 422, (parameter, sent, response.text)
            [error] = response.json()["detail"]
            assert (error["loc"], error["type"]) == (["query", parameter], "int_parsing"), (parameter, sent)
            assert error["msg"] == ("Input should be an integer written in the digits 0-9 (a leading - allowed), "
                                    "nothing else")


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/scenes"])
def test_integer_query_parameters_in_digits_are_read(client, path):
    """Plain digits, leading zeros included, are read as before; a negative one is told its bound."""
    page = client.get(f"{path}?limit=007&offset=0")
    assert page.status_code == 200 and page.json()["offset"] == 0
    below = client.get(f"{path}?limit=-1").json()["detail"]
    assert [(e["loc"], e["type"]) for e in below] == [(["query", "limit"], "greater_than_equal")]


CRAFTED_CURSORS = {
    "id a lone surrogate": '["/v1/jobs","2026-12-06T13:00:00+00:00","\\ud800"]',
    "listing a lone surrogate": '["\\ud800","2026-12-06T13:00:00+00:00","' + "0" * 32 + '"]',
    "id holding NUL": '["/v1/jobs","2026-12-06T13:00:00+00:00","' + "0" * 15 + '\\u0000' + "0" * 16 + '"]',
    "id not of the ids' form": '["/v1/jobs","2026-12-06T13:00:00+00:00","' + "A" * 32 + '"]',
}


@BOTH_DATABASES
@pytest.mark.parametrize("crafted", CRAFTED_CURSORS)
def test_a_crafted_cursor_is_a_422_naming_it_on_either_database(client, root, crafted):
    """A lone surrogate had failed the database's encoding (or, in the listing's name, the 422's) and a NUL
    PostgreSQL's: 500s. The cursor's id must be of the ids' form and its listing one the API lists."""
    cursor = base64.urlsafe_b64encode(CRAFTED_CURSORS[crafted].encode()).decode().rstrip("=")
    response = client.get("/v1/jobs", params={"cursor": cursor})
    assert (response.status_code, response.json()["detail"]) == (
        422, f"cursor '{cursor[:40]}...' is not a cursor of GET /v1/jobs: send a page's next_cursor unchanged")


def add_ready_scene(n: int) -> str:
    """A ready scene of the local key, written straight to the database (as another request's upload commits it);
    its id."""
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Scene

    with session_scope() as session:
        scene = Scene(name="s", format="nerf_synthetic", image_count=1, width=8, height=8, splits=["train"],
                      storage_key=f"scenes/{n}/d.zip", size_bytes=1, sha256="0" * 64, state="ready",
                      task_id="ingest", owner_key_id=LOCAL_KEY_ID)
        session.add(scene)
        session.flush()
        return scene.id


@contextlib.contextmanager
def a_scene_added_after_the_listings_count(n: int):
    """Within it, the first statement counting scenes is followed, before the listing reads on, by another
    connection's scene ``n``; yields the statements it followed (one, once it has)."""
    from sqlalchemy import event

    from voxe_service.db import get_engine

    counted = []

    def another_upload_after_the_first_count(_conn, _cursor, statement, *_args):
        if not counted and "count(*)" in statement and "scenes" in statement:
            counted.append(statement)
            upload = threading.Thread(target=add_ready_scene, args=(n,))  # another request's, on its own connection
            upload.start()
            upload.join()

    event.listen(get_engine(), "after_cursor_execute", another_upload_after_the_first_count)
    try:
        yield counted
    finally:
        event.remove(get_engine(), "after_cursor_execute", another_upload_after_the_first_count)


@BOTH_DATABASES
def test_a_scene_created_while_a_cursor_page_is_counted_leaves_its_offset_within_the_total(client, root):
    """The total and the cursor's offset had been two statements: a scene created between them gave an offset past
    the total (the UI showed "4–4 of 3"). They are one now."""
    for n in range(3):
        add_ready_scene(n)
    cursor = listed(client, "/v1/scenes", limit=2)[1]["next_cursor"]
    with a_scene_added_after_the_listings_count(3) as counted:
        rows, page = listed(client, "/v1/scenes", limit=2, cursor=cursor)
    assert counted and len(listed(client, "/v1/scenes")[0]) == 4  # the scene was added while the page was read
    assert (page["offset"], len(rows), page["total"]) == (2, 1, 3)  # as the list stood at the counts


@BOTH_DATABASES
def test_a_scene_created_while_an_offset_page_is_read_shifts_neither_its_rows_nor_its_total(client, root):
    """By offset, the total and the page had been two statements: a scene created between them shifted the page by
    one (its first row one the page before had shown) against a total without it. A page past the end still
    counts the list as it stood."""
    for n in range(3):
        add_ready_scene(n)
    ids = listed(client, "/v1/scenes")[0]  # newest first
    with a_scene_added_after_the_listings_count(3) as counted:
        rows, page = listed(client, "/v1/scenes", limit=2, offset=1)
    assert counted and len(listed(client, "/v1/scenes")[0]) == 4  # the scene was added while the page was read
    assert (rows, page["total"], page["next_cursor"]) == (ids[1:], 3, None)  # as the list stood at the count
    with a_scene_added_after_the_listings_count(4) as counted:
        rows, page = listed(client, "/v1/scenes", limit=2, offset=9)
    assert counted and (rows, page["total"], page["offset"], page["next_cursor"]) == ([], 4, 9, None)


@BOTH_DATABASES
def test_a_listing_page_costs_little_more_python_than_its_plain_query_and_count(client, root):
    """read_page's one statement had been ordered by its aliased page's columns, which every call adapted to the
    page: three to four times the Python of a plain page query and its count (~2 ms a page; the database's time
    unchanged). Function calls are counted, not timed: a shared machine's timings vary."""
    import cProfile
    import pstats
    from functools import partial

    from sqlalchemy import func, select

    from api.paging import PageQuery, read_page
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Job

    scene_id = add_ready_scene(0)
    with session_scope() as session:
        session.add_all([Job(scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global",
                             edit_words=[], params={}, sds_model="tiny", attention_model="tiny", device="cpu")
                         for _ in range(4)])
    filters, newest_first = [Job.owner_key_id == LOCAL_KEY_ID], (Job.created_at.desc(), Job.id.desc())

    def calls(read) -> int:
        with session_scope() as session:
            read(session)  # its statements compiled and cached, as a running service holds them
            profile = cProfile.Profile()
            profile.runcall(read, session)
        return pstats.Stats(profile).total_calls

    def plain(session):
        session.scalar(select(func.count()).select_from(Job).where(*filters))
        session.scalars(select(Job).where(*filters).order_by(*newest_first).offset(1).limit(3)).all()

    with session_scope() as session:
        newest = session.execute(select(Job.created_at, Job.id).where(*filters).order_by(*newest_first)).first()
    yardstick = calls(plain)
    for page in (PageQuery(limit=2, offset=1, after=None), PageQuery(limit=2, offset=0, after=tuple(newest))):
        assert calls(partial(read_page, listing="/v1/jobs", model=Job, filters=filters, page=page)) < 2 * yardstick


@pytest.mark.parametrize("api", ["of cursors", "from before cursors"])
def test_the_load_bench_lists_each_job_once_while_jobs_are_added(client, root, api):
    """bench/service_load.py counts a submitted job it does not list as lost. It had paged by offset: a job created
    while it listed shifted the next page by one, listing the first page's last job twice. It pages by each page's
    next_cursor now, as a client does; an API from before cursors (a --baseline-tree's, answering none, and where no
    job is added meanwhile) still by offset."""
    import asyncio
    import runpy

    import httpx

    from service_helpers import REPO
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Job

    def add_jobs(count: int) -> list[str]:
        with session_scope() as session:
            jobs = [Job(scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global", edit_words=[],
                        params={}, sds_model="tiny", attention_model="tiny", device="cpu") for _ in range(count)]
            session.add_all(jobs)
            session.flush()
            return [job.id for job in jobs]

    class BenchClient:
        """The bench's HTTP client, on the test client: with cursors, a job is submitted once the first page is
        answered; from before them, the pages name no next_cursor."""

        def __init__(self):
            self.pages = 0

        async def get(self, path: str, params: dict) -> httpx.Response:
            page = client.get(path, params=params).json()
            self.pages += 1
            if api == "from before cursors":
                del page["next_cursor"]
            elif self.pages == 1:
                add_jobs(1)
            return httpx.Response(200, json=page)

    scene_id = add_ready_scene(0)
    jobs = add_jobs(201)  # two pages of the bench's 200
    listed_job_ids = runpy.run_path(str(REPO / "bench" / "service_load.py"))["listed_job_ids"]
    bench_client = BenchClient()
    ids = asyncio.run(listed_job_ids(bench_client))
    assert (bench_client.pages, len(ids), set(ids)) == (2, 201, set(jobs))


def test_a_job_downsampling_past_its_scenes_images_is_refused_before_it_is_queued(client, dataset, root):
    """A scene of small images is ready (its ingest decodes them at full size); a job asking a downsample larger than
    them had been accepted and failed in the worker's fit. The scene's size is known from its upload's checks."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    scene = make_scene(client, dataset, root)
    with session_scope() as session:  # as an upload of 16x24 images records them
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(width=16, height=24))
    refused = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": {"downsample": 32}})
    assert refused.status_code == 422 and refused.json()["detail"] == (
        f"params.downsample 32 is larger than scene {scene['id']!r}'s images (16x24): at most 16")
    assert client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": {"downsample": 16}}).status_code == 201


def test_canceling_a_job_that_ends_as_the_request_comes_is_a_conflict(client, dataset, root, monkeypatch):
    """The job was running when read and succeeded before the cancel's update: that had answered 200 with the
    succeeded job, where a finished job's cancel is a 409."""
    from sqlalchemy import update

    from api.services import jobs as job_service
    from voxe_service.models import Job

    scene = make_scene(client, dataset, root)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    request_cancel = job_service.request_cancel

    def finished_first(*, session, job_ids):
        session.execute(update(Job).where(Job.id.in_(job_ids)).values(state="succeeded"))
        request_cancel(session=session, job_ids=job_ids)

    monkeypatch.setattr(job_service, "request_cancel", finished_first)
    answer = client.post(f"/v1/jobs/{job['id']}/cancel")
    assert answer.status_code == 409 and answer.json()["detail"] == f"job {job['id']!r} already succeeded"


@BOTH_DATABASES
def test_reconstruction_creation_is_race_free(client, dataset, root):
    from api.services.jobs import reconstruction_for
    from voxe_service.db import get_sessionmaker
    from voxe_service.models import Reconstruction, Scene

    scene = make_scene(client, dataset, root)
    params = {"downsample": 2, "max_images": None, "reconstruction": {"preset": "fast"}}
    ids, errors = [], []
    barrier = threading.Barrier(8)

    def create():
        try:
            with get_sessionmaker()() as session:
                row = session.get(Scene, scene["id"])
                barrier.wait()
                ids.append(reconstruction_for(session=session, scene=row, params=params).id)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=create) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(set(ids)) == 1 and len(ids) == 8
    with get_sessionmaker()() as session:
        assert session.query(Reconstruction).count() == 1


def test_unknown_ids_are_404(client):
    missing = "0" * 32
    assert client.get(f"/v1/scenes/{missing}").status_code == 404
    assert client.get(f"/v1/scenes/{missing}/reconstructions").status_code == 404
    assert client.delete(f"/v1/scenes/{missing}").status_code == 404
    assert client.get(f"/v1/jobs/{missing}").status_code == 404
    assert client.post(f"/v1/jobs/{missing}/cancel").status_code == 404
    assert client.get(f"/v1/jobs/{missing}/artifacts").status_code == 404
    assert client.get(f"/v1/jobs/{missing}/artifacts/preview.png").status_code == 404
    response = client.post("/v1/jobs", json={"scene_id": missing, **JOB})
    assert response.status_code == 404 and missing in response.json()["detail"]


# ------------------------------------------------------------------------------------------ artifacts
def _job_with_artifact(client, dataset, root, data: bytes) -> tuple[str, str]:
    from voxe_service.db import session_scope
    from voxe_service.models import Artifact
    from voxe_service.storage import get_storage

    scene = make_scene(client, dataset, root)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    stored = get_storage().put_bytes(f"jobs/{job['id']}/render_000.png", data)
    with session_scope() as session:
        session.add(Artifact(job_id=job["id"], name="render_000.png", key=stored.key, size=stored.size,
                             sha256=stored.sha256, content_type="image/png", kind="render"))
    # A file in storage that is not in the job's artifact list is never served.
    get_storage().put_bytes(f"jobs/{job['id']}/secret.txt", b"secret")
    return job["id"], scene["id"]


def _job_row(owner_key_id: str = "local") -> str:
    """A succeeded job on a ready scene, written straight to the database (no dataset, no ingest): its id."""
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    with session_scope() as session:
        scene = Scene(owner_key_id=owner_key_id, name="s", format="nerf_synthetic", image_count=3, width=800,
                      height=800, splits=["train"], storage_key="scenes/s/dataset.zip", size_bytes=1, sha256="0" * 64,
                      state="ready")
        session.add(scene)
        session.flush()
        job = Job(scene_id=scene.id, owner_key_id=owner_key_id, prompt="a mic", mode="global", params={},
                  sds_model="tiny", attention_model="tiny", device="cpu", state="succeeded")
        session.add(job)
        session.flush()
        return job.id


def _published_render(root) -> tuple[str, str]:
    """A job (``_job_row``) whose render_000.png (5,000 bytes of "A") the worker published: its id and the download's
    URL."""
    from worker.runtime import publish_artifact

    job_id = _job_row()
    (root / "render_000.png").write_bytes(b"A" * 5000)
    publish_artifact(job_id, "render_000.png", root / "render_000.png", "render")
    return job_id, f"/v1/jobs/{job_id}/artifacts/render_000.png"


def test_mesh_artifacts_are_served_as_their_model_types(client, root):
    """mesh.ply had been served as application/octet-stream beside its siblings' model/gltf-binary and model/obj: a
    browser or a viewer given the URL saw an unknown binary. No PLY type is registered; model/ply is the one 3D
    viewers (f3d) and other services declare, in the model/ family of the others."""
    from worker.runtime import publish_artifacts

    job_id = _job_row()
    files = {"mesh.ply": b"ply\nformat ascii 1.0\nend_header\n", "mesh.glb": b"glTF", "mesh.obj": b"v 0 0 0\n",
             "mesh.mtl": b"newmtl m\n"}
    for name, data in files.items():
        (root / name).write_bytes(data)
    publish_artifacts(job_id, [(name, root / name, "mesh") for name in files])
    expected = {"mesh.ply": "model/ply", "mesh.glb": "model/gltf-binary", "mesh.obj": "model/obj",
                "mesh.mtl": "model/mtl"}
    listing = client.get(f"/v1/jobs/{job_id}/artifacts").json()
    assert {a["name"]: a["content_type"] for a in listing} == expected
    for name, content_type in expected.items():
        for request in (client.get, client.head):
            served = request(f"/v1/jobs/{job_id}/artifacts/{name}")
            assert served.status_code == 200 and served.headers["content-type"] == content_type, (request, name)
            assert served.headers["content-disposition"] == f'inline; filename="{name}"'


def test_artifact_download_ranges_and_names(client, dataset, root):
    import hashlib

    data = bytes(range(256)) * 40  # 10240 bytes
    job_id, _ = _job_with_artifact(client, dataset, root, data)
    url = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    listing = client.get(f"/v1/jobs/{job_id}/artifacts").json()
    assert listing == [{**listing[0], "name": "render_000.png", "size": len(data),
                        "sha256": hashlib.sha256(data).hexdigest(), "url": url}]
    full = client.get(url)
    assert full.status_code == 200 and full.content == data and full.headers["accept-ranges"] == "bytes"
    for header, expected, first, last in (("bytes=0-99", data[:100], 0, 99),
                                          ("bytes=10000-", data[10000:], 10000, 10239),
                                          ("bytes=-40", data[-40:], 10200, 10239),
                                          ("bytes=10200-999999", data[10200:], 10200, 10239),
                                          ("bytes=10-" + "9" * 5000, data[10:], 10, 10239),  # past int()'s digits
                                          ("bytes=-" + "9" * 5000, data, 0, 10239)):
        part = client.get(url, headers={"Range": header})
        assert part.status_code == 206 and part.content == expected, header
        assert part.headers["content-range"] == f"bytes {first}-{last}/{len(data)}"
        assert int(part.headers["content-length"]) == len(expected)
    for header in ("bytes=10240-", "bytes=50-10", "bytes=abc", "bytes=-0", "bytes=" + "1" * 5000 + "-"):
        bad = client.get(url, headers={"Range": header})
        assert bad.status_code == 416, header
        assert bad.headers["content-range"] == f"bytes */{len(data)}"
    assert client.get(url, headers={"Range": "bytes=0-1,5-6"}).content == data  # several ranges: whole file
    head = client.head(url)
    assert head.status_code == 200 and head.headers["content-length"] == str(len(data)) and head.content == b""
    for name in ("secret.txt", "..%2Fsecret.txt", "..%2F..%2Fscenes", "%2Fetc%2Fpasswd", "render_000.png%00",
                 "%2E%2E%2Fsecret.txt", "RENDER_000.PNG"):
        assert client.get(f"/v1/jobs/{job_id}/artifacts/{name}").status_code == 404, name
    # NUL never reaches the database (PostgreSQL text cannot hold it): a path naming nothing, a bad query
    assert client.get(f"/v1/jobs/{job_id}%00/artifacts").status_code == 404
    nul_query = client.get("/v1/jobs?scene_id=%00")
    assert nul_query.status_code == 422 and "NUL" in nul_query.json()["detail"]
    (stored,) = [f for f in stored_files(root) if f.endswith("render_000.png")]
    (root / "storage" / stored).unlink()  # lost from the storage (a bucket's lifecycle rule, an operator)
    gone = client.get(url)
    assert gone.status_code == 404 and gone.json()["detail"] == "artifact 'render_000.png' is missing from storage"
    assert client.head(url).status_code == 404  # as the GET (it had answered 200 and a length)


def test_head_answers_wherever_get_does_with_its_headers_and_no_body(client, dataset, tmp_path):
    """``curl -I`` on a job's URL: HEAD had been 405 on every GET route but an artifact's download. An event stream's
    HEAD ends with its headers, though its job goes on."""
    scene = make_scene(client, dataset, tmp_path)
    job = client.post("/v1/jobs", json={**JOB, "scene_id": scene["id"]}).json()
    for url in ("/healthz", "/v1/jobs", f"/v1/jobs/{job['id']}", f"/v1/jobs/{job['id']}/artifacts",
                f"/v1/scenes/{scene['id']}", "/v1/jobs/no-such-job"):
        got, head = client.get(url), client.head(url)
        assert (head.status_code, head.content) == (got.status_code, b""), url
        for header in ("content-length", "content-type", "x-content-type-options"):
            assert head.headers[header] == got.headers[header], (url, header)
    stream = client.head(f"/v1/jobs/{job['id']}/events", headers={"Accept": "text/event-stream"})
    assert stream.status_code == 200 and stream.content == b""
    assert stream.headers["content-type"].startswith("text/event-stream")
    assert client.options(f"/v1/jobs/{job['id']}").headers["allow"] == "GET, HEAD, OPTIONS"
    refused = client.head(f"/v1/jobs/{job['id']}/cancel")  # no GET there: no HEAD either
    assert refused.status_code == 405 and refused.headers["allow"] == "OPTIONS, POST"


def test_every_v1_answer_is_kept_out_of_shared_caches_and_the_webhook_secret_out_of_every_cache(client, root):
    """A /v1 answer is one key's, but its key may come in X-API-Key, which shared caches do not know (RFC 9111 §3.5
    keeps only answers to Authorization out of them), and no answer said Cache-Control: a proxy caching by URL had
    answered one key's job listing, or its webhook secret, to the next key. Each is now private (and revalidated, an
    artifact's by its ETag), the secret not stored at all; an event stream's ``no-cache`` is private too."""
    job_id, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    answers = {"listing": client.get("/v1/jobs"), "job": client.get(f"/v1/jobs/{job_id}"),
               "HEAD": client.head(f"/v1/jobs/{job_id}"), "artifact": client.get(url),
               "range": client.get(url, headers={"Range": "bytes=0-9"}),
               "304": client.get(url, headers={"If-None-Match": etag}), "404": client.get("/v1/jobs/no-such-job"),
               "422": client.get("/v1/jobs?limit=0"), "405": client.delete(f"/v1/jobs/{job_id}"),
               "stream": client.get(f"/v1/jobs/{job_id}/events", headers={"Accept": "text/event-stream"})}
    for what, answer in answers.items():
        assert answer.headers.get("cache-control") == "private, no-cache", (what, answer.status_code)
    secret = client.get("/v1/webhooks/secret")
    assert secret.status_code == 200 and secret.headers.get("cache-control") == "no-store"
    assert "cache-control" not in client.get("/healthz").headers  # no key's: anyone's to cache


def test_a_v1_internal_error_is_kept_out_of_shared_caches_too(root, monkeypatch):
    """An unhandled error's 500 is answered outside every middleware, so on /v1 it had no Cache-Control, though every
    /v1 answer is said to have one: a proxy could keep one key's 500 for the next key."""
    from api.main import create_app
    from api.routes import jobs as jobs_route

    def fails(**_):
        raise RuntimeError("a bug")

    monkeypatch.setattr(jobs_route.jobs, "get_job", fails)
    with TestClient(create_app(), raise_server_exceptions=False) as failing:
        answer = failing.get("/v1/jobs/any")
        assert answer.status_code == 500 and answer.headers.get("cache-control") == "private, no-cache"
        assert "cache-control" not in failing.get("/no-such-page").headers  # (a 404 off /v1: anyone's)


def test_a_body_sent_to_an_operation_that_takes_none_is_a_documented_415_and_does_nothing(client):
    """A cancel or a deletion sent with a body (``{"reason": ...}``, ``{"force": true}``) had ignored it silently:
    the caller could believe it was read. Such a body is a 415 naming the operation, nothing done; an empty one (no
    body, Content-Length 0) is none, and a GET's body is still ignored (RFC 9110 gives it no meaning)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    job_id = _job_row()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id).values(state="queued"))
    scene_id = client.get(f"/v1/jobs/{job_id}").json()["scene_id"]
    spec = client.get("/openapi.json").json()
    for method, path, url in (("POST", "/v1/jobs/{job_id}/cancel", f"/v1/jobs/{job_id}/cancel"),
                              ("POST", "/v1/sweeps/{sweep_id}/cancel", "/v1/sweeps/s1/cancel"),
                              ("DELETE", "/v1/scenes/{scene_id}", f"/v1/scenes/{scene_id}")):
        refused = client.request(method, url, content=b'{"reason": "not needed"}',
                                 headers={"Content-Type": "application/json"})
        assert refused.status_code == 415, (method, url, refused.text)
        assert refused.json()["detail"] == (f"{method} {path} takes no body: send none (got 24 bytes of "
                                            "application/json)")
        assert "415" in spec["paths"][path][method.lower()]["responses"], (method, path)
    assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "queued"
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 200
    assert client.request("GET", f"/v1/jobs/{job_id}/events", content=b"ignored").status_code == 200
    canceled = client.post(f"/v1/jobs/{job_id}/cancel", headers={"Content-Length": "0"})
    assert canceled.status_code == 200 and canceled.json()["state"] == "canceled"


def test_a_body_sent_to_an_operation_that_takes_none_is_refused_unread(client):
    """The 415 had read the body whole first, and a DELETE's escaped the 1 MiB limit (POST, PUT and PATCH only): a
    64 MiB body sent to DELETE /v1/scenes/{id} was held in memory before its refusal. Its Content-Length says a body
    is there; one sent in chunks is read to its first non-empty chunk; a DELETE over the limit is its 413."""

    scene_id = client.get(f"/v1/jobs/{_job_row()}").json()["scene_id"]
    path = f"/v1/scenes/{scene_id}"

    def delete(framing: list[tuple[bytes, bytes]], chunks: list[bytes]) -> tuple[int, str | None, int]:
        """(status, detail, bytes the app read) of a DELETE sending ``chunks`` framed by ``framing``'s headers."""
        scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.4"}, "http_version": "1.1",
                 "method": "DELETE", "scheme": "http", "path": path, "raw_path": path.encode(), "root_path": "",
                 "query_string": b"", "client": ("127.0.0.1", 1), "server": ("testserver", 80),
                 "headers": [(b"host", b"testserver"), (b"content-type", b"application/json"), *framing]}
        messages = iter([*({"type": "http.request", "body": chunk, "more_body": True} for chunk in chunks),
                         {"type": "http.request", "body": b"", "more_body": False}])
        read, sent = [], []

        async def receive():
            message = next(messages, {"type": "http.disconnect"})
            read.append(len(message.get("body", b"")))
            return message

        async def send(message):
            sent.append(message)

        client.portal.call(client.app, scope, receive, send)
        (status,) = [m["status"] for m in sent if m["type"] == "http.response.start"]
        body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
        return status, json.loads(body)["detail"] if body else None, sum(read)

    mib, chunked = 1 << 20, [(b"transfer-encoding", b"chunked")]
    large = [b"x" * mib] * 64
    assert delete(chunked, [b"", *large]) == (415, "DELETE /v1/scenes/{scene_id} takes no body: send none (got a "
                                                   "chunked body of application/json)", mib)
    assert delete([(b"content-length", str(64 * mib).encode())], large) == (
        413, f"JSON body (any body but an upload's multipart form) over the limit of {mib} bytes "
             "(VOXE_MAX_JSON_BODY_BYTES)", 0)
    assert delete([(b"content-length", b"24")], [b'{"reason": "not needed"}']) == (
        415, "DELETE /v1/scenes/{scene_id} takes no body: send none (got 24 bytes of application/json)", 0)
    assert client.get(path).status_code == 200
    assert delete(chunked, [b"", b""]) == (204, None, 0)  # chunks, all empty: no body
    assert client.get(path).status_code == 404


def test_the_event_stream_is_negotiated_by_the_accept_media_type_and_its_weight(client):
    """text/event-stream had been found in Accept as a substring: ``text/event-stream;q=0`` (anything but a stream)
    got a stream, and ``Text/Event-Stream`` (media types are case-insensitive) the JSON timeline. Then any q above 0
    streamed, also where application/json was weighted higher: now the stream needs a q at least JSON's (named, or
    through application/* or */*). A q not in RFC 9110's form (.5) had counted as 1, opening a stream ranked below
    JSON. Both answers say ``Vary: Accept`` (they had said nothing, so a cache could serve one for the other)."""
    url = f"/v1/jobs/{_job_row()}/events"
    for accept, streamed in (("text/event-stream", True), ("Text/Event-Stream", True),
                             ("application/json, text/event-stream; q=0.5", False),
                             ("application/json, text/event-stream;q=0.1", False),
                             ("application/json;q=0.5, text/event-stream;q=0.5", True),
                             ("application/json;q=0.4, text/event-stream;q=0.5", True),
                             ("application/*;q=0.6, text/event-stream;q=0.5", False),
                             ("text/event-stream;q=0.5, */*;q=0.1", True), ("*/*, text/event-stream;q=0.9", False),
                             ("text/event-stream;q=0, application/json", False), ("text/event-stream; Q=0.000", False),
                             ("text/event-streams", False), ("*/*", False),
                             # a q written otherwise is read as a number within [0, 1]; no number counts as absent
                             ("application/json;q=0.9, text/event-stream;q=.5", False),
                             ("application/json, text/event-stream;q=0.0001", False),
                             ("application/json;q=0.5, text/event-stream;q=7", True),
                             ("application/json;q=0.5, text/event-stream;q=-1", False),
                             ("application/json;q=0.5, text/event-stream;q=high", True),
                             ("application/json;q=0.5, text/event-stream;q=nan", True)):
        response = client.get(url, headers={"Accept": accept})
        assert response.status_code == 200, accept
        assert response.headers["content-type"].startswith("text/event-stream") is streamed, accept
        assert response.headers.get("vary") == "Accept", accept
    assert client.head(url, headers={"Accept": "text/event-stream"}).headers.get("vary") == "Accept"
    assert client.head(url).headers.get("vary") == "Accept"
    split = client.get(url, headers=[("Accept", "application/json"), ("Accept", "text/event-stream")])
    assert split.headers["content-type"].startswith("text/event-stream")


def _replace_artifact(job_id: str, data: bytes) -> None:
    """Replace the job's render_000.png as the worker's publish_artifact does (a republished preview): the bytes under
    a new key, the row switched to it, the old object deleted."""
    import uuid

    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import Artifact
    from voxe_service.storage import get_storage

    stored = get_storage().put_bytes(f"jobs/{job_id}/v-{uuid.uuid4().hex[:12]}/render_000.png", data)
    with session_scope() as session:
        artifact = session.scalars(select(Artifact).where(Artifact.job_id == job_id)).one()
        old, (artifact.key, artifact.size, artifact.sha256) = artifact.key, (stored.key, stored.size, stored.sha256)
    get_storage().delete(old)


def test_conditional_downloads_follow_if_range_and_if_none_match(client, dataset, root):
    """If-Range was ignored: a download resumed after its artifact was replaced (a republished preview) spliced the
    old bytes' head to the new bytes' tail. Now an If-Range other than the current ETag (a weak one, a date: no
    Last-Modified is sent) gets the whole file with 200 (RFC 9110 §13.1.5), and an If-None-Match naming the
    current ETag a 304 (§13.1.2)."""
    old, new = b"A" * 5000, b"B" * 6000
    job_id, _ = _job_with_artifact(client, dataset, root, old)
    url = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    first = client.get(url, headers={"Range": "bytes=0-2499"})
    etag = first.headers["etag"]
    resumed = client.get(url, headers={"Range": "bytes=2500-", "If-Range": etag})
    assert resumed.status_code == 206 and first.content + resumed.content == old
    _replace_artifact(job_id, new)
    current = client.head(url).headers["etag"]
    for validator in (etag, f"W/{current}", "Sat, 01 Jan 2000 00:00:00 GMT"):
        whole = client.get(url, headers={"Range": "bytes=2500-", "If-Range": validator})
        assert whole.status_code == 200 and whole.content == new and "content-range" not in whole.headers, validator
        assert whole.headers["etag"] == current
    assert client.get(url, headers={"Range": "bytes=2500-", "If-Range": current}).content == new[2500:]
    for request in (client.get, client.head):
        for held in (current, f'"other", W/{current}', "*"):
            unchanged = request(url, headers={"If-None-Match": held})
            assert unchanged.status_code == 304 and unchanged.content == b"" and unchanged.headers["etag"] == current
        assert request(url, headers={"If-None-Match": etag}).status_code == 200  # an older version: the file
    documented = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]
    for method in ("get", "head"):
        assert {"200", "206", "304", "404", "416"} <= set(documented[method]["responses"]), method
        assert {"Range", "if-range", "if-none-match"} <= {p["name"] for p in documented[method]["parameters"]}


def test_if_match_refuses_a_replaced_artifact_with_412(client, dataset, root):
    """If-Match was ignored: a download fetched in parts, each asking If-Match with the first part's ETag (RFC 9110
    §13.1.1), was given the replaced artifact's bytes for its later parts, a spliced file. Now a 412 unless If-Match
    names the current ETag (strong comparison) or is *."""
    old, new = b"A" * 5000, b"B" * 6000
    job_id, _ = _job_with_artifact(client, dataset, root, old)
    url = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    etag = client.head(url).headers["etag"]
    part = client.get(url, headers={"Range": "bytes=2500-", "If-Match": f'"other", {etag}'})
    assert part.status_code == 206 and part.content == old[2500:]
    _replace_artifact(job_id, new)
    current = client.head(url).headers["etag"]
    for request in (client.get, client.head):
        for held in (etag, f"W/{current}"):
            refused = request(url, headers={"Range": "bytes=2500-", "If-Match": held})
            assert refused.status_code == 412, (request, held)
        assert request(url, headers={"If-Match": "*", "If-None-Match": current}).status_code == 304
    detail = client.get(url, headers={"If-Match": etag}).json()["detail"]
    assert detail == (f"If-Match {etag!r} does not name artifact 'render_000.png''s current ETag {current}: it was "
                      "replaced (download it again from the start)")
    assert client.get(url, headers={"Range": "bytes=5000-", "If-Match": current}).content == new[5000:]
    documented = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]
    for method in ("get", "head"):
        assert "412" in documented[method]["responses"] and "if-match" in {
            p["name"] for p in documented[method]["parameters"]}, method


def test_a_416_names_a_long_range_cut_short(client, root):
    """A Range of thousands of digits had come back whole in the 416's message (as long as the server's header
    limit allows)."""
    _, url = _published_render(root)
    for header in ("bytes=" + "1" * 5000 + "-", "bytes=" + "x" * 5000, "bytes=-0" + "0" * 5000):
        refused = client.get(url, headers={"Range": header})
        assert refused.status_code == 416 and len(refused.json()["detail"]) < 120, header[:20]
        assert repr(header[:60] + "...") in refused.json()["detail"]
    assert client.get(url, headers={"Range": "bytes=9000-"}).json()["detail"] == (
        "range 'bytes=9000-' is outside the 5000-byte file")


def test_a_range_ending_before_it_starts_says_so_and_an_empty_files_suffix_range_gets_the_file(client, root):
    """bytes=3000-2000 had been a 416 saying the range "is outside the 5000-byte file", which it is not, and
    bytes=-0 an "empty suffix range" however large the file. A suffix range of an empty artifact is satisfiable (RFC
    9110 §14.1.1: by the empty file) and had been a 416: a client resuming every download with bytes=-N failed on an
    empty one. It gets the empty file (200: no Content-Range can say 0 bytes)."""
    from worker.runtime import publish_artifact

    job_id, url = _published_render(root)
    for request in (client.get, client.head):
        backwards = request(url, headers={"Range": "bytes=3000-2000"})
        assert backwards.status_code == 416 and backwards.headers["content-range"] == "bytes */5000", request
        nothing = request(url, headers={"Range": "bytes=-0"})
        assert nothing.status_code == 416 and nothing.headers["content-range"] == "bytes */5000", request
    assert client.get(url, headers={"Range": "bytes=3000-2000"}).json()["detail"] == (
        "range 'bytes=3000-2000' ends before it starts: send bytes=first-last with last >= first")
    assert client.get(url, headers={"Range": "bytes=-0"}).json()["detail"] == (
        "range 'bytes=-0' is a suffix of 0 bytes: it selects none")
    (root / "empty.log").write_bytes(b"")
    publish_artifact(job_id, "empty.log", root / "empty.log", "log")
    empty = f"/v1/jobs/{job_id}/artifacts/empty.log"
    for request in (client.get, client.head):
        whole = request(empty, headers={"Range": "bytes=-100"})
        assert (whole.status_code, whole.content, whole.headers["content-length"]) == (200, b"", "0"), request
        assert "content-range" not in whole.headers
        start = request(empty, headers={"Range": "bytes=0-"})  # (no first byte: unsatisfiable)
        assert start.status_code == 416 and start.headers["content-range"] == "bytes */0", request


def test_an_empty_artifact_missing_from_storage_is_a_404_as_any_other(client, root):
    """An empty artifact's object lost from the storage had been served 200 and empty (its GET and HEAD read no
    object), where an artifact of any other size missing so is a 404 "missing from storage": one rule, whatever the
    size."""
    from worker.runtime import publish_artifact

    job_id, _ = _published_render(root)
    (root / "empty.log").write_bytes(b"")
    publish_artifact(job_id, "empty.log", root / "empty.log", "log")
    for stored in stored_files(root):  # both lost from the storage (a bucket's lifecycle rule, an operator)
        (root / "storage" / stored).unlink()
    for name in ("empty.log", "render_000.png"):
        url = f"/v1/jobs/{job_id}/artifacts/{name}"
        for headers in ({}, {"Range": "bytes=-100"}):
            gone = client.get(url, headers=headers)
            assert gone.status_code == 404, (name, headers)
            assert gone.json()["detail"] == f"artifact {name!r} is missing from storage"
            assert client.head(url, headers=headers).status_code == 404, (name, headers)


def test_an_artifact_stored_shorter_than_listed_is_a_500_naming_both_sizes_before_any_byte(client, root):
    """An object cut short in the storage (5,000 bytes listed, 3,000 stored) had been streamed as 200 with the listed
    Content-Length and dropped at its end, every resume from there the same: a client's error read as an outage. The
    answer, before any byte, says the stored object is damaged, to GET and HEAD, with a Range too."""
    job_id, url = _published_render(root)
    (stored,) = [f for f in stored_files(root) if f.endswith("render_000.png")]
    (root / "storage" / stored).write_bytes(b"A" * 3000)
    for request in (client.get, client.head):
        for headers in ({}, {"Range": "bytes=3000-"}, {"Range": "bytes=0-99"}):
            damaged = request(url, headers=headers)
            assert damaged.status_code == 500, (request, headers)
            if request == client.get:
                assert damaged.json()["detail"] == ("artifact 'render_000.png' is stored with 3000 bytes, not the "
                                                    "5000 it is listed with: its stored object is damaged")


DATE = "Wed, 21 Oct 2015 07:28:00 GMT"


def test_a_range_or_if_range_sent_on_two_lines_is_read_as_both_not_as_its_first(client, root):
    """A second Range or If-Range line had been dropped: bytes=0-1 then bytes=5-6 served bytes 0-1, where a proxy
    reading the last line expects bytes 5-6, and a current ETag then an old one resumed the download. Range is a list,
    its lines combined as RFC 9110 §5.3 does: two ranges are several (the whole file, as one line listing them).
    If-Range holds one value, so two lines are a 422 naming it: combined, a date (which holds a comma) then anything
    had been read as that date alone, a 200 (then as the whole file)."""
    _, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    for request in (client.get, client.head):
        two_ranges = request(url, headers=[("Range", "bytes=0-1"), ("Range", "bytes=5-6")])
        assert (two_ranges.status_code, two_ranges.headers["content-length"]) == (200, "5000"), request
        assert "content-range" not in two_ranges.headers
        for validators in ((etag, '"old"'), ('"old"', etag), (etag, DATE), (DATE, etag), (DATE, DATE)):
            refused = request(url, headers=[("Range", "bytes=0-1"), *(("If-Range", v) for v in validators)])
            assert refused.status_code == 422, (request, validators)
            if request is client.get:
                assert refused.json()["detail"] == "If-Range was sent on 2 lines: it holds one value, send it once"
        assert request(url, headers=[("Range", "bytes=0-1"), ("If-Range", etag)]).status_code == 206
        assert request(url, headers=[("If-Range", etag), ("If-Range", DATE)]).status_code == 200  # no Range: ignored


def test_a_last_event_id_sent_on_two_lines_is_a_422_not_its_first_line(client):
    """Last-Event-ID 5 then 9 had resumed the stream after event 5 (repeating 6 to 9 to a client whose proxy read
    the last line), and 5 then "soon" had streamed too, though one line is no event id. Read as one value (RFC 9110
    §5.3), two ids are none: a 422 saying the header holds one value (it is no list to combine)."""
    url = f"/v1/jobs/{_job_row()}/events"
    for lines in (("5", "9"), ("5", "soon"), ("5", "5")):
        refused = client.get(url, headers=[("Accept", "text/event-stream"), *(("Last-Event-ID", v) for v in lines)])
        assert refused.status_code == 422, lines
        assert refused.json()["detail"] == "Last-Event-ID was sent on 2 lines: it holds one value, send it once"
    with client.stream("GET", url, headers={"Accept": "text/event-stream", "Last-Event-ID": "0"}) as one:
        assert one.status_code == 200  # (the job has ended: its stream ends at the hub's first poll)


def test_a_last_event_id_past_the_jobs_newest_event_is_a_422_not_a_stream_without_its_events(client):
    """A stream resumed after an id no stream of the job sent (another job's, a restored database's), past the job's
    newest event, had sent none of its events, its end included, for as long as the job ran (ids count the whole
    table's): the client heard only snapshots, and no 'succeeded'. It is a 422 saying so; the job's own newest id (or
    an earlier one) still resumes, and the JSON timeline ignores the header."""
    from voxe_client.client import parse_sse
    from voxe_service.db import session_scope
    from voxe_service.models import JobEvent

    job_id, sse = _job_row(), {"Accept": "text/event-stream"}
    with session_scope() as session:
        events = [JobEvent(job_id=job_id, kind=kind) for kind in ("stage_started", "succeeded")]
        session.add_all(events)
        session.flush()
        newest = events[-1].id
    url = f"/v1/jobs/{job_id}/events"
    for past in (newest + 1, newest + 10**6):
        refused = client.get(url, headers={**sse, "Last-Event-ID": str(past)})
        assert refused.status_code == 422, past
        assert refused.json()["detail"] == (
            f"Last-Event-ID {past} is past job {job_id}'s newest event ({newest}): no stream of it sent that id; "
            "resume after an id its stream sent, or leave Last-Event-ID out for the whole timeline")
    with client.stream("GET", url, headers={**sse, "Last-Event-ID": str(newest - 1)}) as resumed:
        assert resumed.status_code == 200
        assert [event["id"] for event in parse_sse(resumed.iter_lines()) if event["id"]] == [str(newest)]
    assert len(client.get(url, headers={"Last-Event-ID": str(newest + 1)}).json()) == 2
    none_yet = client.get(f"/v1/jobs/{_job_row()}/events", headers={**sse, "Last-Event-ID": "1"})
    assert none_yet.status_code == 422 and "newest event (it has none yet)" in none_yet.json()["detail"]


def test_a_long_cursor_or_last_event_id_refused_is_quoted_said_cut(client):
    """A refused cursor or Last-Event-ID had been quoted as its first 40 characters with nothing saying more was
    sent: a 60-character one read as though the client had sent those 40. The cut is said ("...") as every other
    message quoting a client's text says it (voxe_service.texts.listed)."""
    sent = "c" * 40 + "d" * 20
    refused = client.get("/v1/jobs", params={"cursor": sent})
    assert refused.json()["detail"] == (f"cursor '{'c' * 40}...' is not a cursor of GET /v1/jobs: send a page's "
                                        "next_cursor unchanged")
    whole = client.get("/v1/jobs", params={"cursor": "c" * 40}).json()["detail"]
    assert whole.startswith(f"cursor '{'c' * 40}' is not")  # none cut: none said
    job_id = _job_row()
    refused = client.get(f"/v1/jobs/{job_id}/events", headers={"Accept": "text/event-stream",
                                                                "Last-Event-ID": "1" * 40 + "x" * 20})
    assert (refused.status_code, refused.json()["detail"]) == (
        422, f"Last-Event-ID must be the id of an event (an integer from 0 to {2**63 - 1}), not '{'1' * 40}...'")


def test_a_header_refused_is_quoted_as_the_client_wrote_it_not_as_latin_1(client, root):
    """The server reads a header's bytes as Latin-1: a Last-Event-ID of a full-width "３" (UTF-8) had been quoted in
    its 422 as 'ï¼\\x93', a Range's, If-Range's or If-Match's text so in their 416/422s. They are quoted as sent;
    bytes that are not UTF-8 are quoted as read."""
    refused = client.get(f"/v1/jobs/{_job_row()}/events", headers={"Accept": "text/event-stream",
                                                                     "Last-Event-ID": "３".encode()})
    assert (refused.status_code, refused.json()["detail"]) == (
        422, f"Last-Event-ID must be the id of an event (an integer from 0 to {2**63 - 1}), not '３'")
    not_utf8 = client.get(f"/v1/jobs/{_job_row()}/events", headers={"Accept": "text/event-stream",
                                                                      "Last-Event-ID": b"\xe9"})
    assert not_utf8.status_code == 422 and not_utf8.json()["detail"].endswith(", not 'é'")
    _, url = _published_render(root)
    said = {"Range": "malformed range 'bytes=é-'", "If-Match": "If-Match 'é' is not an entity tag",
            "If-Range": "If-Range 'é' is neither"}
    for header, words in said.items():
        sent = {"Range": "bytes=4000-", header: ("bytes=é-" if header == "Range" else "é").encode()}
        answer = client.get(url, headers=sent)
        assert answer.status_code in (416, 422) and words in answer.json()["detail"], (header, answer.text)


def test_a_scene_deleted_by_another_request_meanwhile_is_a_404_not_a_second_204(client, monkeypatch):
    """Two DELETEs of one scene at once had both answered 204: the second read the scene, waited for the first's lock,
    found its row gone and deleted nothing (a warning in the log). It is a 404, as any DELETE after the first is."""
    from api.services import scenes
    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    scene_id = add_ready_scene(0)
    lock_scene = scenes.lock_scene

    def deleted_by_another_request_first(session, locking):
        with session_scope() as other:
            other.delete(other.get(Scene, locking))
        return lock_scene(session, locking)

    monkeypatch.setattr(scenes, "lock_scene", deleted_by_another_request_first)
    second = client.delete(f"/v1/scenes/{scene_id}")
    assert second.status_code == 404 and second.json()["detail"] == (
        f"scene {scene_id!r} not found (deleted meanwhile)")


def test_an_idempotency_key_sent_twice_is_a_422_and_creates_nothing(client):
    """Two Idempotency-Key lines had created the job under the first, silently: a retry through a proxy keeping the
    last (or the client's own retry logic adding another) then made a second job."""
    scene_id = client.get(f"/v1/jobs/{_job_row()}").json()["scene_id"]
    body = json.dumps({"scene_id": scene_id, **JOB}).encode()
    for path in ("/v1/jobs", "/v1/sweeps"):
        sent = {"/v1/jobs": body, "/v1/sweeps": json.dumps({"scenes": [{"scene_id": scene_id, "object": "mic"}]})}
        response = client.post(path, content=sent[path], headers=[("Content-Type", "application/json"),
                                                                   ("Idempotency-Key", "a"), ("Idempotency-Key", "b")])
        assert response.status_code == 422, (path, response.text)
        assert response.json()["detail"] == "Idempotency-Key header sent more than once: send one key"
    assert client.get("/v1/jobs").json()["total"] == 1  # only _job_row's
    assert client.post("/v1/jobs", content=body, headers={"Content-Type": "application/json",
                                                          "Idempotency-Key": "a"}).status_code == 201


def test_a_blank_idempotency_key_is_told_blank_not_its_length(client):
    """An Idempotency-Key of only spaces had been answered "must be 1-255 characters, got 0": the client had sent
    three characters, and 0 counted what was left once they were stripped. A blank key is told blank now; an
    over-long one its length, as before."""
    scene_id = client.get(f"/v1/jobs/{_job_row()}").json()["scene_id"]
    body = {"scene_id": scene_id, **JOB}
    for blank in ("", "   ", "\t"):
        response = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": blank})
        assert response.status_code == 422, (blank, response.text)
        assert response.json()["detail"] == ("Idempotency-Key header is blank (empty or only spaces): send a key of "
                                             "1-255 characters, or leave the header out")
    response = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "k" * 256})
    assert response.status_code == 422
    assert response.json()["detail"] == "Idempotency-Key header must be 1-255 characters, got 256"
    assert client.get("/v1/jobs").json()["total"] == 1  # only _job_row's


def test_conditional_headers_read_every_line_and_refuse_a_bare_tag(client, root):
    """An If-Match or If-None-Match sent as several lines (RFC 9110 §5.3) had been read from its first line only: the
    current ETag on the second line got a 412, or a whole download for a 304. A bare tag (the listing's sha256, not
    quoted as the ETag header gives it) never matched: If-Match answered 412 "it was replaced", If-None-Match the
    whole file. Now every line counts, and an element that is not an entity tag is a 422 naming the header; * sent
    on two lines had been a 422 "lists * with entity tags" though it listed none: it is *."""
    job_id, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    sha256 = client.get(f"/v1/jobs/{job_id}/artifacts").json()[0]["sha256"]
    for request in (client.get, client.head):
        unchanged = request(url, headers=[("If-None-Match", '"old"'), ("If-None-Match", f"W/{etag}")])
        assert unchanged.status_code == 304, request
        part = request(url, headers=[("Range", "bytes=4000-"), ("If-Match", '"old"'), ("If-Match", etag)])
        assert part.status_code == 206 and part.headers["content-range"] == "bytes 4000-4999/5000", request
        assert request(url, headers={"If-None-Match": ""}).status_code == 200  # an empty list holds no tag
        for header, value in (("If-Match", sha256), ("If-None-Match", sha256), ("If-Match", f'"old", {sha256}'),
                              ("If-None-Match", f'W/{sha256}'), ("If-Match", f'{etag} x')):
            refused = request(url, headers={header: value})
            assert refused.status_code == 422, (request, header, value)
        assert request(url, headers={"If-Match": '*, "old"'}).status_code == 422
        assert request(url, headers=[("If-None-Match", "*"), ("If-None-Match", "*")]).status_code == 304
        assert request(url, headers=[("Range", "bytes=4000-"), ("If-Match", "*"), ("If-Match", "*")]).status_code == 206
    detail = client.get(url, headers={"If-None-Match": sha256}).json()["detail"]
    assert detail == (f"If-None-Match {sha256!r} is not an entity tag: send ETags quoted, as the ETag header gives "
                      'them ("<sha256>" or W/"<sha256>"), or *')
    assert client.get(url, headers={"If-Match": '"a,b", ' + etag}).status_code == 200  # a quoted tag may hold a comma
    documented = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]
    assert all("422" in documented[method]["responses"] for method in ("get", "head"))


def test_an_if_range_that_is_neither_an_entity_tag_nor_a_date_is_a_422_naming_it(client, root):
    """If-Range holding the listing's sha256 unquoted never matched: a resumed download silently got the whole file
    again (If-Match and If-None-Match answer it with a 422). Now it is a 422 naming If-Range when a Range is sent;
    without one If-Range is ignored (RFC 9110 §13.1.5), and a date, in any of HTTP's three forms, is still a date. A
    date followed by anything is none (parsedate_tz had read the date at its start: a 200)."""
    _, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    sha256 = etag.strip('"')
    for request in (client.get, client.head):
        for bare in (sha256, f" {sha256} ", "", f"{etag}, {etag}", f"{DATE} garbage", f"{DATE}, {etag}"):
            refused = request(url, headers={"Range": "bytes=4000-", "If-Range": bare})
            assert refused.status_code == 422, (request, bare)
        assert request(url, headers={"If-Range": sha256}).status_code == 200  # no Range: ignored
        assert request(url, headers={"Range": "bytes=4000-", "If-Range": etag}).status_code == 206
        for date in ("Sun, 06 Nov 1994 08:49:37 GMT", "Sunday, 06-Nov-94 08:49:37 GMT", "Sun Nov  6 08:49:37 1994"):
            whole = request(url, headers={"Range": "bytes=4000-", "If-Range": date})
            assert whole.status_code == 200 and whole.headers["content-length"] == "5000", (request, date)
    assert client.get(url, headers={"Range": "bytes=4000-", "If-Range": sha256}).json()["detail"] == (
        f"If-Range {sha256!r} is neither an entity tag nor a date: send the ETag quoted, as the ETag header gives it "
        '("<sha256>")')


def test_if_match_is_told_it_compares_strongly_and_an_empty_one_is_named(client, root):
    """If-Match's 422 for a bare tag advised W/"<sha256>", but If-Match compares strongly (RFC 9110 §13.1.1): a W/
    tag, even the current ETag's, got 412 "it was replaced", as did an empty If-Match, both untrue. Now the advice
    offers W/ to If-None-Match only, a weak-only If-Match is a 412 saying a W/ tag never matches, and an empty one a
    422 naming it."""
    _, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    sha256 = etag.strip('"')
    assert client.get(url, headers={"If-Match": sha256}).json()["detail"] == (
        f"If-Match {sha256!r} is not an entity tag: send ETags quoted, as the ETag header gives them (\"<sha256>\"), "
        "or *")
    for request in (client.get, client.head):
        for weak in (f"W/{etag}", f'W/"old", W/{etag}'):
            assert request(url, headers={"If-Match": weak}).status_code == 412, (request, weak)
        for empty in ("", " , "):
            assert request(url, headers={"If-Match": empty}).status_code == 422, (request, empty)
    weak = client.get(url, headers={"If-Match": f"W/{etag}"}).json()["detail"]
    assert weak == (f"If-Match compares strongly: a W/ tag never matches, and If-Match {'W/' + etag!r} lists no other "
                    "(send the ETag as the ETag header gives it, without W/)")
    assert client.get(url, headers={"If-Match": " , "}).json()["detail"] == (
        'If-Match is empty: send ETags quoted, as the ETag header gives them ("<sha256>"), or *')
    assert client.get(url, headers={"If-Match": f"W/{etag}, {etag}"}).status_code == 200  # its strong tag matches


def test_an_if_match_of_weak_and_strong_tags_is_told_why_none_matched(client, root):
    """An If-Match listing W/ tags beside strong ones that all failed had been told the artifact "was replaced",
    also where its W/ tag was the current ETag (nothing was replaced: the W/ kept it from matching). The 412 now
    names the current ETag sent as W/, or else says the strong tags name an older version and W/ ones never match."""
    from voxe_service.texts import listed

    _, url = _published_render(root)
    etag = client.head(url).headers["etag"]
    current_weak = client.get(url, headers={"If-Match": f'W/{etag}, "old"'})
    assert current_weak.status_code == 412
    sent = listed(['"old"', f"W/{etag}"], width=70)
    assert current_weak.json()["detail"] == (
        f"If-Match compares strongly: a W/ tag never matches, and If-Match {sent} "
        f"names artifact 'render_000.png''s current ETag {etag} only with W/ (send the ETag as the ETag header gives "
        "it, without W/)")
    older = client.get(url, headers={"If-Match": 'W/"older", "old"'})
    assert older.status_code == 412
    sent = listed(['"old"', 'W/"older"'], width=70)
    assert older.json()["detail"] == (
        f"If-Match {sent} does not name artifact 'render_000.png''s "
        f"current ETag {etag}: it was replaced (download it again from the start); its W/ tags never match (If-Match "
        "compares strongly)")


def test_a_download_racing_its_artifacts_replacement_serves_the_new_bytes(client, dataset, root, monkeypatch):
    """An artifact replaced between the route's read of its row and its open of the object (the old one deleted)
    had answered 404 "missing from storage" though the next GET was 200: the row is read again once."""
    import hashlib

    from voxe_service.storage import LocalStorage

    job_id, _ = _job_with_artifact(client, dataset, root, b"A" * 5000)
    url = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    open_object, replacing = LocalStorage._open, []

    def replaced_first(self, key):
        if replacing:
            _replace_artifact(job_id, replacing.pop())
        return open_object(self, key)

    monkeypatch.setattr(LocalStorage, "_open", replaced_first)
    for request, data in ((client.head, b"B" * 6000), (client.get, b"C" * 7000)):
        replacing.append(data)
        response = request(url)
        assert response.status_code == 200 and not replacing
        assert response.headers["x-checksum-sha256"] == hashlib.sha256(data).hexdigest()
        assert response.headers["content-length"] == str(len(data)) and response.content in (b"", data)


def test_a_download_whose_client_leaves_mid_stream_holds_no_file(client, dataset, root):
    """A client gone mid-stream (curl stopped, a download manager's probe): Starlette drops the body's iterator
    unclosed, and the artifact's file stayed open until a garbage collection (with the collector off: forever)."""
    import asyncio
    import gc
    import os

    from starlette.requests import ClientDisconnect

    job_id, _ = _job_with_artifact(client, dataset, root, b"x" * 300_000)
    path = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.4"}, "http_version": "1.1",
             "method": "GET", "scheme": "http", "path": path, "raw_path": path.encode(), "root_path": "",
             "query_string": b"", "headers": [(b"host", b"testserver")], "client": ("127.0.0.1", 1),
             "server": ("testserver", 80)}

    async def receive():
        await asyncio.sleep(60)

    async def send(message):
        if message["type"] == "http.response.body":
            raise OSError("the client closed the connection")  # as uvicorn's send does

    async def download():
        with pytest.raises(ClientDisconnect):
            await client.app(scope, receive, send)

    gc.disable()
    try:
        client.portal.call(download)
        held = [os.path.realpath(f"/proc/self/fd/{fd}") for fd in os.listdir("/proc/self/fd")]
    finally:
        gc.enable()
    assert [file for file in held if file.startswith(str(root.resolve() / "storage"))] == []


def test_a_storage_that_cannot_be_reached_is_a_503_with_retry_after(client, dataset, root):
    """A storage outage (S3 refusing connections) answered a bare 500 where a database outage answers 503 with
    Retry-After: the request may be sent again. A missing object is no outage (the routes' 404)."""
    import boto3
    from botocore.config import Config

    from api.deps import storage_dep
    from api.http_semantics import unavailability
    from service_helpers import free_port
    from voxe_service.storage import ObjectNotFound, S3Storage, StorageError

    job_id, _ = _job_with_artifact(client, dataset, root, b"x" * 100)
    refusing = boto3.client("s3", endpoint_url=f"http://127.0.0.1:{free_port()}", region_name="us-east-1",
                            aws_access_key_id="testing", aws_secret_access_key="testing",
                            config=Config(retries={"max_attempts": 1}))
    client.app.dependency_overrides[storage_dep] = lambda: S3Storage("voxe", client=refusing, create_bucket=False)
    url = f"/v1/jobs/{job_id}/artifacts/render_000.png"
    upload = zip_folder(dataset, root / "unstored.zip", prefix="mic_small")
    for response in (client.get(url), client.head(url), upload_zip(client, upload)):
        assert response.status_code == 503 and response.headers["retry-after"] == "5", response.request.method
    assert client.get(url).json()["detail"] == "the storage cannot be reached or is busy; try again in 5 s"
    # faults a retry would meet again stay 500s: a missing object, a bad key, a missing bucket, access denied
    assert unavailability(ObjectNotFound("jobs/x/y.png")) is None
    assert unavailability(StorageError("invalid storage key 'jobs/j/../x.png'")) is None
    from botocore.exceptions import ClientError

    for code, status, outage in (("SlowDown", 503, True), ("InternalError", 500, True), ("AccessDenied", 403, False)):
        error = ClientError({"Error": {"Code": code}, "ResponseMetadata": {"HTTPStatusCode": status}}, "GetObject")
        with pytest.raises(StorageError) as raised, S3Storage("voxe", client=refusing, create_bucket=False) \
                ._as_storage_errors():
            raise error
        assert (unavailability(raised.value) is not None) == outage, code
    documented = client.get("/openapi.json").json()["paths"]["/v1/jobs/{job_id}/artifacts/{name}"]["get"]["responses"]
    assert "the database or the storage is busy or unreachable" in documented["503"]["description"]


@BOTH_DATABASES
def test_a_download_holds_no_database_connection_while_it_streams(client, dataset, root, monkeypatch):
    """A download had held its request's pooled connection (on PostgreSQL, a transaction open) until its client read
    the last byte: two slow ones with a pool of 2 made every other request wait and fail 503. The pool is sampled
    a few times as the body streams (a background poll may hold a connection for an instant, never for all)."""
    import time

    from voxe_service.db import get_engine
    from voxe_service.storage import get_storage

    data = bytes(range(256)) * 40
    job_id, _ = _job_with_artifact(client, dataset, root, data)
    storage_class = type(get_storage())
    open_range, least_held = storage_class.open_range, []

    def sampled(self, key, start=0, end=None):
        chunks = open_range(self, key, start, end)

        def streamed():
            samples = []
            for _ in range(5):
                samples.append(get_engine().pool.checkedout())
                time.sleep(0.01)
            least_held.append(min(samples))
            yield from chunks
        return streamed()

    monkeypatch.setattr(storage_class, "open_range", sampled)
    response = client.get(f"/v1/jobs/{job_id}/artifacts/render_000.png")
    assert response.status_code == 200 and response.content == data
    assert least_held == [0]


@BOTH_DATABASES
def test_delete_scene(client, dataset, root):
    job_id, scene_id = _job_with_artifact(client, dataset, root, b"png")
    response = client.delete(f"/v1/scenes/{scene_id}")
    assert response.status_code == 409 and "queued or running" in response.json()["detail"]
    client.post(f"/v1/jobs/{job_id}/cancel")
    assert client.delete(f"/v1/scenes/{scene_id}").status_code == 204
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 404
    assert client.get(f"/v1/jobs/{job_id}").status_code == 404
    assert stored_files(root) == []


@BOTH_DATABASES
def test_deleting_a_scene_whose_canceled_jobs_are_still_stopping_says_to_wait_for_them(client, root):
    """A running job canceled stays running until its worker's next cancel check: deleting its scene meanwhile had
    been a 409 saying "cancel them first", to a caller who just had (the cancel had answered 200)."""
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene_id = add_ready_scene(0)
    with session_scope() as session:
        jobs = [Job(scene_id=scene_id, owner_key_id="local", prompt="a mic", mode="global", params={},
                    sds_model="tiny", attention_model="tiny", device="cpu", state="running") for _ in range(2)]
        session.add_all(jobs)
        session.flush()
        first, second = (job.id for job in jobs)
    assert client.post(f"/v1/jobs/{first}/cancel").json()["state"] == "running"  # (until the worker checks)
    one_left = client.delete(f"/v1/scenes/{scene_id}")
    assert one_left.status_code == 409 and one_left.json()["detail"] == (
        f"scene {scene_id!r} has 2 queued or running job(s), 1 of them canceled and still stopping (a running job "
        "stops within a few iterations): cancel the other 1, then delete the scene once they have ended")
    client.post(f"/v1/jobs/{second}/cancel")
    stopping = client.delete(f"/v1/scenes/{scene_id}")
    assert stopping.status_code == 409 and stopping.json()["detail"] == (
        f"scene {scene_id!r} has 2 queued or running job(s), 2 of them canceled and still stopping (a running job "
        "stops within a few iterations): delete the scene once they have ended")
    assert client.get(f"/v1/scenes/{scene_id}").status_code == 200


@BOTH_DATABASES
def test_a_job_for_a_scene_deleted_while_it_is_created_is_404(client, dataset, root):
    """The steps of creating a job after its scene's lookup, met by a scene deleted in between: a 404 naming it,
    and no row left (the scene's deletion locks it before counting jobs, so no accepted job goes with it)."""
    from fastapi import HTTPException

    from api.services import jobs as job_service
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, Job, Scene
    from voxe_service.settings import get_settings

    scene = make_scene(client, dataset, root)
    with session_scope() as session:
        gone = session.get(Scene, scene["id"])
        session.expunge(gone)
    assert client.delete(f"/v1/scenes/{scene['id']}").status_code == 204
    with session_scope() as session:
        with pytest.raises(HTTPException, match="was deleted while the job was created") as lookup:
            job_service.reconstruction_for(session=session, scene=gone, params={})
        job = Job(scene_id=scene["id"], owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global", params={},
                  sds_model="tiny", attention_model="tiny", device="cpu", state="queued")
        with pytest.raises(HTTPException, match="was deleted while the job was created") as adding:
            job_service.add_jobs(session=session, key=session.get(ApiKey, LOCAL_KEY_ID), settings=get_settings(),
                                 jobs=[job])
    assert lookup.value.status_code == adding.value.status_code == 404
    assert client.get("/v1/jobs").json()["total"] == 0


def test_readiness_reports_the_missing_worker(client):
    response = client.get("/readyz")
    assert response.status_code == 503
    checks = response.json()["checks"]
    assert checks["database"]["ok"] and checks["broker"]["ok"] and checks["storage"]["ok"]
    assert checks["worker"] == {"ok": False, "method": "database heartbeat", "workers": []}


def test_sql_broker_takes_a_polling_interval(tmp_path):
    from kombu import Connection

    from voxe_service.broker import register

    register()
    url = f"sqla+sqlite:///{tmp_path / 'broker.db'}"
    with Connection(url, transport_options={"polling_interval": 0.05, "connect_args": {"timeout": 30}}) as conn:
        assert conn.transport.polling_interval == 0.05
        with conn.SimpleQueue("q") as queue:
            queue.put({"n": 1})
            assert queue.get(timeout=2).payload == {"n": 1}


def test_celery_app_configuration(root):
    from voxe_service.queue import create_celery_app

    app = create_celery_app()
    conf = app.conf
    assert conf.task_acks_late and conf.task_reject_on_worker_lost and conf.worker_prefetch_multiplier == 1
    assert conf.task_time_limit > conf.task_soft_time_limit
    assert conf.broker_transport_options["polling_interval"] == 0.5
    assert app.amqp.router.route({}, "voxe.edit")["queue"].name == "gpu"


def test_redis_visibility_timeout_exceeds_the_hard_time_limit(root, monkeypatch):
    monkeypatch.setenv("VOXE_BROKER_URL", "redis://127.0.0.1:1/0")
    _reset()
    from voxe_service.queue import create_celery_app

    conf = create_celery_app().conf
    assert conf.broker_transport_options["visibility_timeout"] > conf.task_time_limit


def test_missing_model_fails_the_job_with_a_clear_message(root, monkeypatch, dataset):
    """Default (real) model ids without downloaded weights: the job fails naming the model and the fix."""
    monkeypatch.delenv("VOXE_SDS_MODEL")
    monkeypatch.delenv("VOXE_ATTENTION_MODEL")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(root / "empty-hf-home"))
    _reset()
    from sqlalchemy import update

    from api.main import create_app
    from voxe_core.constants import SDS_MODEL_ID
    from voxe_core.guidance.loading import download_command
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import tasks

    with TestClient(create_app()) as client:
        scene = make_scene(client, dataset, root)
        job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a yarn doll of a mic"}).json()
        assert job["models"]["sds"] == SDS_MODEL_ID
        with session_scope() as session:  # as if the reconstruction stage had run
            session.execute(update(Job).where(Job.id == job["id"]).values(completed_stages=["reconstruct"]))
        result = tasks.edit_task.apply(args=(job["id"],)).get()
        assert result["state"] == "failed"
        failed = client.get(f"/v1/jobs/{job['id']}").json()
        assert failed["state"] == "failed" and failed["finished_at"]
        for part in (SDS_MODEL_ID, "not available offline", f"`{download_command(SDS_MODEL_ID)}`", "HF_HOME",
                     "VOXE_SDS_MODEL=tiny"):
            assert part in failed["error"], failed["error"]
        # The rest of the chain sees a finished job and does nothing.
        assert "skipped" in tasks.export_task.apply(args=(job["id"],)).get()
        events = client.get(f"/v1/jobs/{job['id']}/events").json()
        assert [(e["kind"], e["stage"]) for e in events] == [("stage_started", "edit"), ("failed", "edit")]
        assert events[1]["detail"] == failed["error"] and events[0]["worker_hostname"]


# ------------------------------------------------------------------------------------------ reconstruction sharing
def _two_jobs(client, dataset, root):
    scene = make_scene(client, dataset, root)
    body = {"scene_id": scene["id"], "prompt": "a yarn doll of a mic"}
    a, b = client.post("/v1/jobs", json=body).json(), client.post("/v1/jobs", json=body).json()
    assert a["reconstruction"]["id"] == b["reconstruction"]["id"]
    return a, b, a["reconstruction"]["id"]


@BOTH_DATABASES
def test_reconstruction_claims(client, dataset, root):
    """Exactly one job fits; a lapsed lease or a released claim lets another take over."""
    from datetime import timedelta

    from voxe_service.models import utcnow
    from voxe_service.settings import get_settings
    from worker import runtime

    a, b, rec_id = _two_jobs(client, dataset, root)
    settings = get_settings()
    assert runtime.try_claim_reconstruction(rec_id, a["id"], "host-a", settings, allow_failed=True)
    assert not runtime.try_claim_reconstruction(rec_id, b["id"], "host-b", settings, allow_failed=True)
    assert runtime.try_claim_reconstruction(rec_id, a["id"], "host-a", settings, allow_failed=True)  # redelivered
    runtime.set_reconstruction(rec_id, a["id"], lease_until=utcnow() - timedelta(seconds=1))  # a's worker died
    assert runtime.try_claim_reconstruction(rec_id, b["id"], "host-b", settings, allow_failed=False)
    assert not runtime.try_claim_reconstruction(rec_id, a["id"], "host-a", settings, allow_failed=True)
    runtime.set_reconstruction(rec_id, b["id"], state="pending", owner_job_id=None, lease_until=None)  # b canceled
    assert runtime.try_claim_reconstruction(rec_id, a["id"], "host-a", settings, allow_failed=False)
    assert runtime.load_reconstruction(rec_id).run_count == 4
    runtime.set_reconstruction(rec_id, a["id"], state="failed", lease_until=None)
    assert not runtime.try_claim_reconstruction(rec_id, b["id"], "host-b", settings, allow_failed=False)  # waiters fail
    assert runtime.try_claim_reconstruction(rec_id, b["id"], "host-b", settings, allow_failed=True)  # new jobs retry


def test_a_job_waits_for_the_fit_another_job_runs(client, dataset, root):
    import time

    import torch
    from sqlalchemy import update

    from voxe_core.grid import VoxelGrid
    from voxe_core.presets import reconstruct_config, reconstruction_params
    from voxe_core.progress import StageCancelled
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    a, b, rec_id = _two_jobs(client, dataset, root)
    settings = get_settings()
    assert runtime.try_claim_reconstruction(rec_id, a["id"], "host-a", settings, allow_failed=True)
    with session_scope() as session:
        session.execute(update(Job).values(state="running"))
    outcome = {}

    def wait_as_b():
        try:
            tasks._reconstruct(runtime.load_job(b["id"]), settings, "cpu", get_storage())
            outcome["ok"] = True
        except BaseException as exc:  # noqa: BLE001
            outcome["error"] = exc

    thread = threading.Thread(target=wait_as_b)
    thread.start()
    deadline = time.monotonic() + 60  # until b has recorded that it waits (however busy the machine is)
    while not (client.get(f"/v1/jobs/{b['id']}").json()["message"] or "").startswith("waiting") \
            and time.monotonic() < deadline:
        time.sleep(0.05)
    assert thread.is_alive()  # waiting: the fit it waits for is a's, and a never ran it
    waiting = client.get(f"/v1/jobs/{b['id']}").json()
    assert waiting["message"].startswith(f"waiting for the scene's reconstruction {rec_id} (fitted by job {a['id']})")
    # Weighed as the fit it waits for (voxe_service.progress.FitWork), with the edit that fit leads to.
    fitted = reconstruct_config(reconstruction_params(waiting["params"]), backbone="relu_field")
    assert waiting["result"]["fit"] == {"backbone": "relu_field", "steps": fitted.total_iterations,
                                        "rays_per_step": fitted.rays_per_step}
    assert waiting["result"]["edit_schedule"]["iterations"] == 8000

    grid = VoxelGrid(8)
    with torch.no_grad():
        grid.features[2:6, 2:6, 2:6, 0] = 50.0
    grid.save(root / "g.safetensors")
    stored = get_storage().put_file(f"reconstructions/{rec_id}/grid.safetensors", root / "g.safetensors")
    runtime.set_reconstruction(rec_id, a["id"], state="succeeded", grid_key=stored.key, grid_size=stored.size,
                               grid_sha256=stored.sha256)
    thread.join(20)
    assert outcome == {"ok": True}
    job = client.get(f"/v1/jobs/{b['id']}").json()
    assert job["reconstruction"]["reused"] is True and job["reconstruction"]["run_count"] == 1
    names = [x["name"] for x in client.get(f"/v1/jobs/{b['id']}/artifacts").json()]
    assert names == ["initial_grid.safetensors", "preview.png"]

    # A waiting job that is canceled stops waiting.
    c = client.post("/v1/jobs", json={"scene_id": a["scene_id"], "prompt": "a mic", "params": {"downsample": 5}}).json()
    d = client.post("/v1/jobs", json={"scene_id": a["scene_id"], "prompt": "a mic", "params": {"downsample": 5}}).json()
    assert runtime.try_claim_reconstruction(c["reconstruction"]["id"], c["id"], "host-c", settings, True)
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == d["id"]).values(state="running", cancel_requested=True))
    with pytest.raises(StageCancelled):
        tasks._reconstruct(runtime.load_job(d["id"]), settings, "cpu", get_storage())


def _two_tiny_fits(client, dataset, root) -> tuple[str, str, str]:
    """Two jobs sharing one tiny reconstruction (fast to fit for real): their ids and the reconstruction's."""
    scene = make_scene(client, dataset, root)
    a, b = (client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic", "params": TINY_FIT}).json()
            for _ in range(2))
    assert a["reconstruction"]["id"] == b["reconstruction"]["id"]
    return a["id"], b["id"], a["reconstruction"]["id"]


def test_a_finished_fits_checkpoint_the_storage_cannot_delete_fails_nothing(client, dataset, root, monkeypatch):
    """G_i stored and recorded, the fit's checkpoint is deleted as cleanup: a delete the storage refused then (S3
    throttling its DELETE) had failed the owner's job, its fit succeeded."""
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import runtime, tasks

    a, _, rec_id = _two_tiny_fits(client, dataset, root)
    storage_class, deleted = type(get_storage()), []
    real_delete = storage_class.delete

    def refused_for_checkpoints(self, key):
        deleted.append(key)
        if key.startswith(f"reconstructions/{rec_id}/checkpoint-"):  # (its owner's run's own)
            raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when deleting {key}")
        return real_delete(self, key)

    monkeypatch.setattr(storage_class, "delete", refused_for_checkpoints)
    get_storage().put_bytes(f"reconstructions/{rec_id}/checkpoint-an-earlier-run.safetensors", b"its fit's state")
    assert tasks.reconstruct_task.apply(args=(a,)).get()["state"] == "done"
    assert f"reconstructions/{rec_id}/checkpoint-an-earlier-run.safetensors" in deleted
    assert runtime.load_reconstruction(rec_id).state == "succeeded"
    job = client.get(f"/v1/jobs/{a}").json()
    assert (job["state"], job["error"], job["completed_stages"]) == ("running", None, ["reconstruct"])


@pytest.mark.parametrize("failing_renewal", [1, 2])  # the fit's total recorded, then its first progress
def test_a_fit_goes_on_through_a_lease_renewal_the_database_refuses_once(client, dataset, root, monkeypatch,
                                                                          failing_renewal):
    """One renewal of the fit's lease meeting a database error (locked, a dropped connection) while the lease still
    runs is skipped, the next one renews: it had failed the shared fit, and with it every job waiting on it."""
    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    a, b, rec_id = _two_tiny_fits(client, dataset, root)
    real, renewals = runtime.renew_lease, []

    def flaky_renewal(*args, **kwargs):
        renewals.append(kwargs)
        if len(renewals) == failing_renewal:
            raise OperationalError("UPDATE reconstructions", {}, Exception("database is locked"))
        return real(*args, **kwargs)

    monkeypatch.setattr(runtime, "renew_lease", flaky_renewal)
    assert tasks.reconstruct_task.apply(args=(a,)).get()["state"] == "done"
    assert len(renewals) > failing_renewal  # renewed again after the refused one
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.error, rec.run_count) == ("succeeded", a, None, 1)
    assert tasks.reconstruct_task.apply(args=(b,)).get()["state"] == "done"
    assert client.get(f"/v1/jobs/{b}").json()["reconstruction"]["reused"] is True


def test_an_owner_that_cannot_renew_its_fits_lease_before_it_runs_out_hands_the_fit_back(client, dataset, root,
                                                                                          monkeypatch):
    """The database refuses every renewal of the owner's first claim: past the lease another job may have taken the
    fit over, so the owner stops (LeaseLost) and hands it back rather than failing it, then claims it again (no job
    took it meanwhile) and fits it once its renewals go through."""
    import time

    import voxe_core.reconstruct
    from sqlalchemy.exc import OperationalError

    from voxe_service.settings import get_settings
    from worker import runtime, tasks

    a, b, rec_id = _two_tiny_fits(client, dataset, root)
    monkeypatch.setattr(get_settings(), "reconstruction_lease_s", 1.0)
    real_claim, real_renewal, real_fit = (runtime.try_claim_reconstruction, runtime.renew_lease,
                                          voxe_core.reconstruct.reconstruct)
    claims = []

    def claim(rec_id, *args, **kwargs):
        rec = runtime.load_reconstruction(rec_id)
        claims.append((rec.state, rec.owner_job_id, rec.error))
        return real_claim(rec_id, *args, **kwargs)

    def renewal(*args, **kwargs):
        if len(claims) == 1:  # an outage for as long as the first claim runs
            raise OperationalError("UPDATE reconstructions", {}, Exception("connection refused"))
        return real_renewal(*args, **kwargs)

    def slow_fit(*args, **kwargs):
        if len(claims) == 1:
            time.sleep(1.5)  # past the lease: its progress finds the lease run out
        return real_fit(*args, **kwargs)

    monkeypatch.setattr(runtime, "try_claim_reconstruction", claim)
    monkeypatch.setattr(runtime, "renew_lease", renewal)
    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", slow_fit)
    assert tasks.reconstruct_task.apply(args=(a,)).get()["state"] == "done"
    assert claims == [("pending", None, None), ("pending", None, None)]  # handed back, not failed
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.run_count) == ("succeeded", a, 2)
    assert tasks.reconstruct_task.apply(args=(b,)).get()["state"] == "done"


@pytest.mark.parametrize("stop", ["time limit", "database outage", "storage outage", "full disk"])
def test_an_owner_stopped_by_its_time_limit_or_a_database_outage_hands_the_fit_to_the_waiting_jobs(
        client, dataset, root, monkeypatch, stop):
    """The owner's soft time limit is its job's (that job fails, naming it), and a database or storage outage or
    its worker's disk full is no fault of the fit's: each hands the shared fit back, and a job waiting on it fits
    it, where each had failed the fit and every job waiting on it. An outage or a full disk is no fault of the
    owner's job either: its message goes back to the queue, and its redelivery takes the fit the other job
    stored."""
    import errno

    from celery.exceptions import SoftTimeLimitExceeded
    from sqlalchemy.exc import OperationalError

    from voxe_service.settings import get_settings
    from voxe_service.storage import StorageUnavailable
    from worker import runtime, tasks

    a, b, rec_id = _two_tiny_fits(client, dataset, root)
    real_fit = tasks._fit_grid

    def stopped_fit(*args, **kwargs):
        if stop == "time limit":
            raise SoftTimeLimitExceeded()
        if stop == "storage outage":  # storing a checkpoint, say
            raise StorageUnavailable("the storage cannot be reached: connect timeout")
        if stop == "full disk":  # writing one to the worker's scratch
            raise OSError(errno.ENOSPC, "No space left on device", "reconstruction_checkpoint.safetensors")
        raise OperationalError("UPDATE jobs", {}, Exception("server closed the connection unexpectedly"))

    monkeypatch.setattr(tasks, "_fit_grid", stopped_fit)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    result = tasks.reconstruct_task.apply(args=(a,))
    owner = client.get(f"/v1/jobs/{a}").json()
    if stop == "time limit":
        assert result.get()["state"] == "failed"
        assert owner["state"] == "failed" and owner["error"].startswith(
            f"reconstruct: time limit of {get_settings().task_soft_time_limit_s} s exceeded")
    else:
        assert result.state == "REJECTED" and result.result.requeue
        assert (owner["state"], owner["error"]) == ("running", None)
    said = {"time limit": None,  # (the owner's job failed saying so; the fit, no fault of it, has no error)
            "database outage": "a database outage (the database cannot be reached or is locked)",
            "storage outage": "a storage outage (the storage cannot be reached: connect timeout)",
            "full disk": "the worker's disk full (OSError: [Errno 28] No space left on device)"}[stop]
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.owner_run_token, rec.error) == (
        "pending", None, None, said and f"job {a}'s fit: stopped by {said}")
    monkeypatch.setattr(tasks, "_fit_grid", real_fit)
    assert tasks.reconstruct_task.apply(args=(b,)).get()["state"] == "done"
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.run_count) == ("succeeded", b, 2)
    if stop != "time limit":  # the owner's redelivered message
        assert tasks.reconstruct_task.apply(args=(a,)).get()["state"] == "done"
        assert client.get(f"/v1/jobs/{a}").json()["reconstruction"]["reused"] is True


# ------------------------------------------------------------------------------------------ mesh scenes
def _mesh_scene(client, monkeypatch) -> dict:
    """Spot uploaded as OBJ + texture, rendered by its ingest into 4 views of 32 px (fast)."""
    from voxe_service import datasets

    require_data(SPOT)
    monkeypatch.setattr(datasets, "MESH_VIEWS", 4)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    with open(SPOT / "spot_triangulated.obj", "rb") as obj, open(SPOT / "spot_texture.png", "rb") as png:
        response = client.post("/v1/scenes", files=[("files", ("spot.obj", obj)), ("files", ("spot.png", png))])
    assert response.status_code == 201, response.text
    assert response.json()["state"] == "processing"
    assert ingest(response.json()["id"])["state"] == "ready"
    return client.get(f"/v1/scenes/{response.json()['id']}").json()


def test_a_mesh_scene_job_voxelizes_the_uploaded_mesh_instead_of_fitting(client, root, monkeypatch):
    import voxe_core.reconstruct
    import torch

    from voxe_core.backbones import load_grid
    from voxe_core.mesh_input import VoxelizeConfig, load_mesh, voxelize
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = _mesh_scene(client, monkeypatch)
    assert scene["format"] == "mesh" and scene["image_count"] == 4
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a cow wearing a hat", "mode": "global",
                                        "params": {"reconstruction": {"resolution": 24}}}).json()

    def no_fit(*_args, **_kwargs):
        raise AssertionError("route auto on a mesh scene must not fit")

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", no_fit)
    assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
    done = client.get(f"/v1/jobs/{job['id']}").json()
    assert (done["iteration"], done["total"]) == (1, 1)
    # its peak memory, as a fit's (README, Memory: result.peak_memory_gb.{reconstruct,...}); the voxelize route had none
    assert done["result"]["peak_memory_gb"]["reconstruct"] > 0 and done["result"]["peak_memory_kind"] == "process_rss"
    rec = runtime.load_reconstruction(job["reconstruction"]["id"])
    assert rec.params["route"] == "voxelize" and (rec.iteration, rec.total) == (1, 1)
    grid = load_grid(get_storage().get_file(rec.grid_key, root / "g.safetensors"))
    voxelized = voxelize(load_mesh(SPOT / "spot_triangulated.obj", SPOT / "spot_texture.png"),
                         VoxelizeConfig(resolution=24))
    voxelized.save(root / "expected.safetensors")  # as the worker stores grids (sparse)
    expected = load_grid(root / "expected.safetensors")
    assert grid.resolution == expected.resolution == (24, 24, 24)
    assert torch.equal(grid.flat_features, expected.flat_features)
    assert torch.equal(grid.bbox_min, expected.bbox_min) and grid.density_scale == expected.density_scale
    names = [a["name"] for a in client.get(f"/v1/jobs/{job['id']}/artifacts").json()]
    assert names == ["initial_grid.safetensors", "preview.png"]


def test_the_voxelize_route_tells_its_job_what_the_mesh_loads_without_unless_the_scene_did(client, root, monkeypatch):
    """The voxelize route loads the scene's mesh again, and what it loads without (an OBJ's .mtl not sent) had been
    said in the worker's log alone: a job on a scene whose warnings were not kept (ingested before migration 0022) was
    never told. It is now a ``warning`` event of stage reconstruct; a job the scene's kept warnings told already is
    not told it twice."""
    from sqlalchemy import update

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import tasks

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    obj = ("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nusemtl red\nf 1 2 3\nf 1 3 4\nf 1 2 5\n")
    scene = client.post("/v1/scenes", files=[("files", ("cube/m.obj", obj.encode(), "text/plain"))]).json()
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    said = ("m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh loads "
            "without its materials")

    def voxelized(resolution: int) -> list[tuple[str, str]]:
        job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a cube", "mode": "global",
                                            "params": {"reconstruction": {"resolution": resolution}}}).json()
        assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
        assert client.get(f"/v1/jobs/{job['id']}").json()["reconstruction"]["state"] == "succeeded"
        events = client.get(f"/v1/jobs/{job['id']}/events").json()
        return [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning" and e["detail"] == said]

    assert voxelized(24) == [("ingest", said)]  # told at its creation, once
    with session_scope() as session:  # as a scene ingested before its warnings were kept
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(warnings=None))
    assert voxelized(16) == [("reconstruct", said)]


def test_a_voxelize_reload_that_fails_after_a_warning_still_tells_the_job_the_warning(client, root, monkeypatch):
    """The voxelize route's reload of a scene's mesh that raised a warning (an OBJ's .mtl not sent) and then failed
    had dropped the warning with the load: the job failed without being told what may explain it, where a failed
    ingest keeps its. The job is told it (a ``warning`` event of stage reconstruct) and fails."""
    from sqlalchemy import update

    from voxe_core.mesh_input import MeshError
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import ingest as worker_ingest, tasks

    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    assert ingest(scene["id"])["state"] == "ready"
    with session_scope() as session:  # as a scene ingested before its warnings were kept: no job is told them
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(warnings=None))

    def refused(mesh, shading):  # the load fails once the mesh loaded without its .mtl (a later worker's rule, say)
        raise MeshError("m.obj: refused on reload")

    monkeypatch.setattr(worker_ingest, "shade_mesh", refused)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a cube", "mode": "global",
                                        "params": {"reconstruction": {"resolution": 16}}}).json()
    tasks.reconstruct_task.apply(args=(job["id"],))
    done = client.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "failed" and "m.obj: refused on reload" in done["error"], done
    events = client.get(f"/v1/jobs/{job['id']}/events").json()  # (at ingest: that the scene's were not kept)
    assert [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning" and e["stage"] != "ingest"] == [
        ("reconstruct", "m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh "
                        "loads without its materials")]


def test_a_voxelize_reload_refusing_the_mesh_names_its_file_as_uploaded_as_the_ingest_does(client, root, monkeypatch):
    """A mesh this version refuses in a scene an older version's ingest let in fails the voxelize route's reload; its
    MeshError named the file as the worker keeps it ("mesh.obj: every triangle has zero area ...") where the ingest
    names it as uploaded ("m.obj: ...", without the worker's scratch path). The job's error names it as uploaded."""
    import contextlib

    from worker import runtime, tasks

    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    assert ingest(scene["id"])["state"] == "ready"
    unpacked = runtime.scene_dataset

    @contextlib.contextmanager
    def as_an_older_ingest_let_it_in(*args):  # its three vertices on a line
        with unpacked(*args) as dataset:
            (dataset / "mesh" / "mesh.obj").write_text("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
            yield dataset

    monkeypatch.setattr(runtime, "scene_dataset", as_an_older_ingest_let_it_in)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a cube", "mode": "global",
                                        "params": {"reconstruction": {"resolution": 16}}}).json()
    tasks.reconstruct_task.apply(args=(job["id"],))
    done = client.get(f"/v1/jobs/{job['id']}").json()
    said = "MeshError: m.obj: every triangle has zero area (repeated or collinear vertices); the mesh has no surface"
    assert (done["state"], done["error"], done["reconstruction"]["error"]) == ("failed", f"reconstruct: {said}", said)


def test_a_ply_texture_unread_is_told_to_a_job_once_in_the_same_words_at_each_load(client, root, monkeypatch):
    """A PLY whose TextureFile names a file of its folder that is no image: Pillow named the bytes trimesh handed it
    by their memory address ("cannot identify image file <_io.BytesIO object at 0x7f...>"), a new one at each load,
    so the voxelize route's reload said a warning the scene's kept warnings did not hold, and the job was told it
    twice (stage ingest, then reconstruct). It is said without the address, the same at every load, and told once."""
    from voxe_service import datasets
    from worker import tasks

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    ply = _square_ply("texcoord").replace(b"TextureFile old.png", b"TextureFile options.json")
    scene = client.post("/v1/scenes", files=[("files", ("square.ply", ply))])
    assert scene.status_code == 201, scene.text
    assert ingest(scene.json()["id"])["state"] == "ready"
    said = ("square.ply: the texture its header names (TextureFile) cannot be read (UnidentifiedImageError: cannot "
            "identify image file); the mesh loads without it")
    assert client.get(f"/v1/scenes/{scene.json()['id']}").json()["warnings"] == [said]
    job = client.post("/v1/jobs", json={"scene_id": scene.json()["id"], "prompt": "a square", "mode": "global",
                                        "params": {"reconstruction": {"resolution": 16}}}).json()
    assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
    events = client.get(f"/v1/jobs/{job['id']}/events").json()
    assert [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning"] == [("ingest", said)]


def test_a_mesh_scene_archive_keeps_the_uploaded_mesh(client, root, monkeypatch):
    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    scene = _mesh_scene(client, monkeypatch)
    with session_scope() as session:
        key = session.get(Scene, scene["id"]).storage_key
    assert re.fullmatch(rf"scenes/{scene['id']}/dataset-[0-9a-f]{{8}}\.zip", key)  # (its ingest run's own key)
    assert stored_files(root) == [key]  # the upload's archive was replaced
    with zipfile.ZipFile(root / "storage" / key) as archive:
        names = set(archive.namelist())
        assert archive.read("mesh/mesh.obj") == (SPOT / "spot_triangulated.obj").read_bytes()
        assert archive.read("mesh/texture.png") == (SPOT / "spot_texture.png").read_bytes()
    assert {"transforms_train.json", "train/r_003.png", "mesh/mesh.obj", "mesh/texture.png"} <= names


def _square_ply(texture_coordinates: str | None) -> bytes:
    """A square of two triangles in the plane y = 0 (the floor, up axis y), its header naming ``old.png``
    (TextureFile); ``texture_coordinates`` "texcoord" (per corner, ASCII), "s t" (per vertex, binary) or None
    (green vertex colours instead).
    The first triangle's UVs lie in the left half of the image, the second's in its right half."""
    import numpy as np
    import trimesh

    vertices, faces = [[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], [[0, 1, 2], [0, 2, 3]]
    if texture_coordinates == "texcoord":
        header = ("ply\nformat ascii 1.0\ncomment TextureFile old.png\nelement vertex 4\nproperty float x\n"
                  "property float y\nproperty float z\nelement face 2\nproperty list uchar int vertex_indices\n"
                  "property list uchar float texcoord\nend_header\n")
        return (header + "".join(" ".join(map(str, v)) + "\n" for v in vertices)
                + "3 0 1 2 6 0.25 0.5 0.25 0.5 0.25 0.5\n3 0 2 3 6 0.75 0.5 0.75 0.5 0.75 0.5\n").encode()
    # per vertex, each triangle its own vertices: the second's at u = 0.75
    vertices = np.array(vertices, dtype=float)[np.ravel(faces)]
    mesh = trimesh.Trimesh(vertices, np.arange(6).reshape(2, 3), process=False,
                           vertex_colors=None if texture_coordinates else np.tile([0, 255, 0, 255], (6, 1)))
    if texture_coordinates is not None:
        mesh.vertex_attributes["s"] = np.repeat([0.25, 0.75], 3)
        mesh.vertex_attributes["t"] = np.full(6, 0.5)
    body = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True)
    return body.replace(b"\nelement vertex", b"\ncomment TextureFile old.png\nelement vertex", 1)


def _red_and_blue_png() -> bytes:
    """A 4×4 image, its left half red, its right half blue."""
    from PIL import Image

    image = Image.new("RGB", (4, 4), (0, 0, 255))
    image.paste((255, 0, 0), (0, 0, 2, 4))
    buffer = io.BytesIO()
    image.save(buffer, "PNG")
    return buffer.getvalue()


@pytest.mark.parametrize("texture_coordinates", ["texcoord", "s t"])
def test_a_ply_uploaded_with_its_texture_is_rendered_textured(client, root, monkeypatch, texture_coordinates):
    """The image beside a PLY with texture coordinates is kept as its texture, whatever its header's TextureFile
    names, and the views are rendered in its colours: it had been dropped, the PLY rendered as an uncoloured mesh
    (its TextureFile not found, the ingest warning so)."""
    from voxe_core.data import load_scene
    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    monkeypatch.setattr(datasets, "MESH_VIEWS", 4)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    png = _red_and_blue_png()
    response = client.post("/v1/scenes", files=[("files", ("square.ply", _square_ply(texture_coordinates))),
                                                ("files", ("square.png", png))])
    assert response.status_code == 201, response.text
    assert ingest(response.json()["id"])["state"] == "ready"
    with session_scope() as session:
        key = session.get(Scene, response.json()["id"]).storage_key
    with zipfile.ZipFile(root / "storage" / key) as archive:
        assert archive.read("mesh/texture.png") == png
        assert json.loads(archive.read("mesh/names.json"))["texture.png"] == "square.png"
        archive.extractall(root / "scene")
    views = load_scene(root / "scene", "train")
    surface = views.images[views.alphas > 0.999]
    red = (surface[:, 0] > 0.99) & (surface[:, 2] < 0.01)
    blue = (surface[:, 2] > 0.99) & (surface[:, 0] < 0.01)
    assert float(surface[:, 1].max()) < 0.01 and int(red.sum()) > 50 and int(blue.sum()) > 50  # each triangle its half


@pytest.mark.parametrize("texture_coordinates, images, expected", [
    (None, ["scan.png"], "the PLY comes with an image ('scan.png') but its header declares no texture coordinates "
                         "(texcoord per face, or s t / u v / texture_u texture_v per vertex) to map it with; send the "
                         "image with a PLY that has them, or the PLY alone (its vertex or face colours)"),
    (None, ["a.png", "b.tga"], "the PLY comes with images ('a.png', 'b.tga') but its header declares no texture "
                               "coordinates"),
    ("texcoord", ["a.png", "b.jpg"], "the PLY comes with several images ('a.png', 'b.jpg'); send one texture"),
    ("s t", ["a.tga"], "the PLY comes with an image of a kind not read as a texture ('a.tga'); send its texture as "
                       ".png, .jpg, .jpeg"),
])
def test_an_image_a_ply_cannot_take_is_422_and_leaves_nothing(client, root, texture_coordinates, images, expected):
    """As beside an OBJ: several images, or one of a kind the loader does not read; and an image beside a PLY
    whose header declares no texture coordinates (it had been dropped without a word)."""
    response = client.post("/v1/scenes", files=[("files", ("square.ply", _square_ply(texture_coordinates))),
                           *[("files", (name, _red_and_blue_png())) for name in images]])
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith(expected)
    assert client.get("/v1/scenes").json()["total"] == 0
    assert stored_files(root) == [] and staged(root) == []


def test_a_ply_without_an_image_is_stored_alone_as_before(client, root):
    """Vertex colours, or texture coordinates without their image: the PLY alone, whatever its header's
    TextureFile names (a file not an image beside it is ignored)."""
    for texture_coordinates in (None, "texcoord"):
        response = client.post("/v1/scenes", files=[("files", ("square.ply", _square_ply(texture_coordinates))),
                                                    ("files", ("licence.txt", b"CC-BY"))])
        assert response.status_code == 201, response.text
        key = f"scenes/{response.json()['id']}/upload.zip"
        with zipfile.ZipFile(root / "storage" / key) as archive:
            assert archive.namelist() == ["mesh/mesh.ply", "mesh/names.json", "mesh/options.json"]


def test_a_broker_refusing_a_submission_keeps_nothing_and_a_retry_with_the_key_runs_it(client, dataset, root,
                                                                                        monkeypatch):
    """A 503 answers a request that was never accepted: before, the failed scene or job stayed listed, and a
    retry with the same Idempotency-Key replayed it as a 200 instead of submitting again."""
    from voxe_service.queue import TaskQueue

    scene = make_scene(client, dataset, root)
    archive = zip_folder(dataset, root / "again.zip", prefix="mic_small")
    body = {"scene_id": scene["id"], **JOB, "params": {"reconstruction": {"resolution": 64}}}

    def refuse(self, *args):
        raise ConnectionError("broker down")

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send", refuse)
        with open(archive, "rb") as handle:
            upload = client.post("/v1/scenes", files={"archive": ("s.zip", handle, "application/zip")},
                                 headers={"Idempotency-Key": "u1"})
        job = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "j1"})
    assert upload.status_code == job.status_code == 503, (upload.text, job.text)
    # The cause and when to retry; the broker's own words (SQL, a Redis address) stay in the log.
    assert upload.json()["detail"] == "could not queue the ingest: the job queue is unavailable; try again in 5 s"
    assert job.json()["detail"] == "could not queue the job: the job queue is unavailable; try again in 5 s"
    assert upload.headers["retry-after"] == job.headers["retry-after"] == "5"
    assert client.get("/v1/scenes").json()["total"] == 1 and client.get("/v1/jobs").json()["total"] == 0
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"] and staged(root) == []
    assert len(reconstruction_rows(scene["id"])) == 1  # the refused job made its row (in its own transaction) ...
    assert client.get(f"/v1/scenes/{scene['id']}/reconstructions").json() == []  # ... which no job uses: unlisted

    with open(archive, "rb") as handle:  # the broker is back: the same keys submit anew
        upload = client.post("/v1/scenes", files={"archive": ("s.zip", handle, "application/zip")},
                             headers={"Idempotency-Key": "u1"})
    job = client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "j1"})
    assert upload.status_code == job.status_code == 201, (upload.text, job.text)
    assert upload.json()["state"] == "processing" and job.json()["state"] == "queued"
    (rec,) = client.get(f"/v1/scenes/{scene['id']}/reconstructions").json()
    assert rec["id"] == job.json()["reconstruction"]["id"]  # the row the refused job made, used now


def _keyed_requests(client, dataset, root):
    """A scene made here, and two requests with an Idempotency-Key: another scene's upload (u1), a job on it (j1)."""
    scene = make_scene(client, dataset, root)
    archive = zip_folder(dataset, root / "again.zip", prefix="mic_small")

    def upload():
        with open(archive, "rb") as handle:
            return client.post("/v1/scenes", files={"archive": ("s.zip", handle, "application/zip")},
                               headers={"Idempotency-Key": "u1"})

    def create_job():
        return client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}, headers={"Idempotency-Key": "j1"})

    return scene, upload, create_job


@BOTH_DATABASES
def test_a_retry_while_the_broker_refuses_the_first_request_is_a_409_not_what_it_withdraws(client, dataset, root,
                                                                                          monkeypatch):
    """A retry with the same Idempotency-Key arriving while the first request waited on a broker that then refused
    had been answered 200 with the scene or job that request was withdrawing: deleted a moment later."""
    from voxe_service.queue import TaskQueue

    scene, upload, create_job = _keyed_requests(client, dataset, root)

    retried = {}

    def refuse_after_a_retry(retry):
        """A broker that refuses, slowly: the same request is sent again (once) while the first waits on it."""
        def refuse(self, *args):
            if retry not in retried:
                retried[retry] = retry()
            raise ConnectionError("broker down")
        return refuse

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send_ingest", refuse_after_a_retry(upload))
        broker_down.setattr(TaskQueue, "send", refuse_after_a_retry(create_job))
        assert upload().status_code == create_job().status_code == 503
    for retry, key, what in ((retried[upload], "u1", "scene"), (retried[create_job], "j1", "job")):
        assert retry.status_code == 409, retry.text
        assert retry.json()["detail"].startswith(f"the first request with Idempotency-Key {key!r} has not answered "
                                                 f"yet (the broker may still refuse its {what} ")
        assert retry.json()["detail"].endswith("); retry in a moment")
        assert retry.headers["retry-after"] == "1"
    assert client.get("/v1/scenes").json()["total"] == 1 and client.get("/v1/jobs").json()["total"] == 0
    assert stored_files(root) == [f"scenes/{scene['id']}/dataset.zip"] and staged(root) == []
    assert upload().status_code == create_job().status_code == 201  # the broker is back: the keys submit anew


def test_a_retry_after_its_first_request_died_unanswered_replays_the_job_once_the_reaper_sent_it(client, dataset,
                                                                                                root):
    """A request that died between recording its job and the broker's answer leaves its Idempotency-Key pending:
    retries are 409 while the job waits unsent, and replay it once the reaper has sent it."""
    from datetime import timedelta

    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import IdempotencyRecord, Job, utcnow
    from voxe_service.settings import get_settings

    scene = make_scene(client, dataset, root)
    body, headers = {"scene_id": scene["id"], **JOB}, {"Idempotency-Key": "j1"}
    created = client.post("/v1/jobs", json=body, headers=headers).json()
    with session_scope() as session:  # as that request left it
        session.execute(update(IdempotencyRecord).values(pending=True))
        session.execute(update(Job).values(task_id=None))
    assert client.post("/v1/jobs", json=body, headers=headers).status_code == 409
    settings = get_settings()
    reap_orphaned_jobs(settings, now=utcnow() + timedelta(seconds=2 * settings.job_stale_timeout_s))
    replayed = client.post("/v1/jobs", json=body, headers=headers)
    assert replayed.status_code == 200 and replayed.json()["id"] == created["id"]


@BOTH_DATABASES
def test_a_retry_reading_its_key_as_the_first_request_withdraws_it_is_a_409_to_retry_never_a_dead_key(
        client, dataset, root):
    """A retry had read its Idempotency-Key's record, then the scene or job it names: the first request's 503
    withdrawing both (its broker refused) committed between the two reads made it answer "has been deleted; use a
    new key" for a key free to run anew. Read in one statement, the retry sees both (409, retry in a moment) or
    neither (it runs anew)."""
    from sqlalchemy import delete, event, update

    from voxe_service.db import get_engine, session_scope
    from voxe_service.models import IdempotencyRecord, Job, Scene

    _, upload, create_job = _keyed_requests(client, dataset, root)

    for submit, model, key, what in ((upload, Scene, "u1", "scene"), (create_job, Job, "j1", "job")):
        first = submit()
        assert first.status_code == 201, first.text
        this_record = IdempotencyRecord.idempotency_key == key
        with session_scope() as session:  # as the first request leaves them while the broker has not answered
            session.execute(update(IdempotencyRecord).where(this_record).values(pending=True))
            session.execute(update(model).where(model.id == first.json()["id"]).values(task_id=None))
        withdrawn = []

        def withdraw_after_the_record_is_read(_conn, _cursor, statement, *_args):
            """The first request's 503 (its resource and record deleted, one commit), just after the retry's read."""
            if withdrawn or not statement.lstrip().startswith("SELECT") or "FROM idempotency_records" not in statement:
                return
            withdrawn.append(statement)
            with get_engine().begin() as other:
                other.execute(delete(model).where(model.id == first.json()["id"]))
                other.execute(delete(IdempotencyRecord).where(this_record))

        event.listen(get_engine(), "after_cursor_execute", withdraw_after_the_record_is_read)
        try:
            retry = submit()
        finally:
            event.remove(get_engine(), "after_cursor_execute", withdraw_after_the_record_is_read)
        assert withdrawn and retry.status_code == 409, retry.text
        assert retry.json()["detail"].startswith(f"the first request with Idempotency-Key {key!r} has not answered "
                                                 f"yet (the broker may still refuse its {what} ")
        again = submit()  # the key was withdrawn: it runs anew
        assert again.status_code == 201 and again.json()["id"] != first.json()["id"], again.text


def test_a_job_accepted_while_the_broker_refused_the_ingest_keeps_the_scene_failed(client, dataset, root,
                                                                                   monkeypatch):
    """The scene is listed while the broker takes its time to refuse its ingest: a job accepted on it meanwhile is
    not deleted with it (the 503 path deletes a scene only with no job); both fail naming the reason."""
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Job, Scene
    from voxe_service.queue import TaskQueue

    def accept_a_job_then_refuse(self, scene_id):
        with session_scope() as session:  # what a concurrent POST /v1/jobs commits on the processing scene
            session.add(Job(id="j" * 32, scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global",
                            params={}, sds_model="tiny", attention_model="tiny", device="cpu", state="queued"))
        raise ConnectionError("broker down")

    monkeypatch.setattr(TaskQueue, "send_ingest", accept_a_job_then_refuse)
    response = upload_zip(client, zip_folder(dataset, root / "s.zip", prefix="mic_small"))
    assert response.status_code == 503
    (scene,) = client.get("/v1/scenes").json()["items"]
    assert scene["state"] == "failed" and scene["error"] == "could not queue the ingest: the job queue is unavailable"
    job = client.get(f"/v1/jobs/{'j' * 32}").json()
    assert job["state"] == "failed" and job["error"] == f"the scene's upload failed processing: {scene['error']}"
    assert stored_files(root) == [] and staged(root) == []  # its bytes go either way
    with session_scope() as session:
        assert session.get(Scene, scene["id"]).size_bytes == 0


def test_an_upload_refused_503_whose_scene_a_job_kept_is_uploaded_anew_by_a_retry_with_its_key(client, dataset, root,
                                                                                                monkeypatch):
    """The 503 of an upload whose ingest the broker refused says "try again", and a retry with its Idempotency-Key
    submits it again. Where a job accepted on the listed scene meanwhile kept that scene (failed), the key had been
    kept with it: the retry, voxe_client's own after a 503, answered 200 with the failed scene, never uploaded."""
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Job
    from voxe_service.queue import TaskQueue

    send_ingest = TaskQueue.send_ingest

    def accept_a_job_then_refuse(self, scene_id):
        with session_scope() as session:  # what a concurrent POST /v1/jobs commits on the processing scene
            session.add(Job(id="j" * 32, scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global",
                            params={}, sds_model="tiny", attention_model="tiny", device="cpu", state="queued"))
        raise ConnectionError("broker down")

    archive = zip_folder(dataset, root / "s.zip", prefix="mic_small")

    def upload():
        with open(archive, "rb") as handle:
            return client.post("/v1/scenes", files={"archive": ("s.zip", handle, "application/zip")},
                               headers={"Idempotency-Key": "up-1"})

    monkeypatch.setattr(TaskQueue, "send_ingest", accept_a_job_then_refuse)
    assert upload().status_code == 503
    (kept,) = client.get("/v1/scenes").json()["items"]
    assert kept["state"] == "failed"  # kept for its job, as before
    monkeypatch.setattr(TaskQueue, "send_ingest", send_ingest)
    again = upload()
    assert again.status_code == 201, again.text
    assert again.json()["id"] != kept["id"] and again.json()["state"] == "processing"
    assert "idempotent-replayed" not in again.headers
    replay = upload()  # the key now names the scene this retry made
    assert replay.status_code == 200 and replay.json()["id"] == again.json()["id"]


def test_route_voxelize_on_an_image_scene_is_a_422_naming_the_field(client, dataset, root):
    scene = make_scene(client, dataset, root)
    body = {"scene_id": scene["id"], **JOB, "params": {"reconstruction": {"route": "voxelize"}}}
    response = client.post("/v1/jobs", json=body)
    assert response.status_code == 422
    assert response.json()["detail"] == (f"reconstruction.route 'voxelize' needs a scene uploaded as a mesh; scene "
                                          f"{scene['id']!r} is 'nerf_synthetic' images: use route 'fit' or 'auto'")
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene["id"], "object": "mic"}],
                                            "params": {"reconstruction": {"route": "voxelize"}}})
    assert sweep.status_code == 422 and "reconstruction.route 'voxelize'" in sweep.json()["detail"]
    assert reconstruction_rows(scene["id"]) == []  # nothing half made (the listing would hide an unused row)
    both = {"scene_id": scene["id"], **JOB, "params": {"reconstruction": {"route": "voxelize", "backbone": "scene"}}}
    errors = client.post("/v1/jobs", json=both).json()["detail"]
    assert any(e["loc"] == ["body", "params", "reconstruction"] and "backbone 'scene'" in e["msg"] for e in errors)


def test_route_auto_and_fit_keep_an_image_scenes_reconstruction_key():
    from voxe_core.presets import reconstruction_params

    plain = reconstruction_params({})
    assert "route" not in plain
    for route in ("auto", "fit"):
        assert reconstruction_params({"reconstruction": {"route": route}}) == plain
    assert reconstruction_params({}, mesh_scene=True) == {**plain, "route": "voxelize"}
    assert reconstruction_params({"reconstruction": {"route": "fit"}}, mesh_scene=True) == plain
    assert "route" not in reconstruction_params({"reconstruction": {"backbone": "scene"}}, mesh_scene=True)


def test_reconstruction_key_follows_the_recipe_not_only_the_parameters(monkeypatch):
    """A fit cached under an older fast() is not reused once the preset changes."""
    from voxe_core.reconstruct import ReconstructConfig

    from voxe_core.presets import reconstruction_key, reconstruction_params

    params = reconstruction_params({})
    before = reconstruction_key(params)
    assert reconstruction_key(reconstruction_params({})) == before  # deterministic
    fast = ReconstructConfig.fast
    monkeypatch.setattr(ReconstructConfig, "fast", classmethod(lambda cls, **kw: fast(**{"lr": 0.02, **kw})))
    assert reconstruction_key(params) != before


def test_reconstructions_stored_before_the_resample_option_load_box_filtered_images(monkeypatch):
    """A row written before ``resample`` existed resumes on the images it was fitted on."""
    import worker.inputs as inputs
    from voxe_core.data import load_scene
    from voxe_core.presets import reconstruction_params

    require_data(MIC)
    monkeypatch.setattr(inputs, "job_scene", lambda job: None)
    monkeypatch.setattr(inputs.runtime, "scene_dataset", lambda scene, settings, storage: contextlib.nullcontext(MIC))
    current = reconstruction_params({"downsample": 16, "max_images": 2})
    legacy = {k: v for k, v in current.items() if k != "resample"}
    assert current["resample"] == "bilinear"
    for params, resample in ((legacy, "box"), (current, "bilinear")):
        loaded = inputs.load_images(None, params, None, None).images
        assert torch.equal(loaded, load_scene(MIC, "train", 16, 2, resample=resample).images), resample


def test_reconstruction_iterations_that_fit_no_stage_count_are_a_422(client, dataset, root):
    scene = make_scene(client, dataset, root)
    # 4 values fit neither default preset "auto" may resolve to (fast: 3 stages, scene: 2).
    body = {"scene_id": scene["id"], **JOB, "params": {"reconstruction": {"iterations": [10, 20, 30, 40]}}}
    response = client.post("/v1/jobs", json=body)
    assert response.status_code == 422, response.json()
    assert "one value or one per stage (3 stages), got 4" in response.json()["detail"]
    assert reconstruction_rows(scene["id"]) == []  # nothing half made (the listing would hide an unused row)


def test_a_scene_backbone_fit_of_a_single_image_is_a_422_at_submission(client, dataset, root):
    """max_images 1 leaves the scene backbone one camera, which orbits no centre: the job had been accepted and its
    fit failed in the worker once the images were loaded. An object fit of one image, or a scene fit of two, runs."""
    scene = make_scene(client, dataset, root)

    def submit(backbone: str, max_images: int):
        params = {"max_images": max_images, "reconstruction": {"backbone": backbone}}
        return client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": params})

    refused = submit("scene", 1)
    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"].startswith("params.reconstruction: max_images 1 keeps a single image, whose one "
                                               "camera has no centre to orbit")
    assert reconstruction_rows(scene["id"]) == []
    assert submit("scene", 2).status_code == 201
    assert submit("relu_field", 1).status_code == 201


def test_a_scene_backbone_fit_of_a_one_image_scene_is_a_422_at_submission(client, root, tmp_path):
    """A scene of one photo leaves the scene backbone one camera whatever max_images says: its jobs had been
    accepted (max_images unset) and failed in the worker. Refused on the ready scene, jobs and sweeps alike (the
    sweep's fid_input 422 had advised fid_input false, which led there); a job waiting on its ingest fails as the
    ingest decides 'auto'."""
    one_photo = _opaque_copy(small_mic(tmp_path / "mic1", frames=1), tmp_path / "photo1")
    photo_zip = zip_folder(one_photo, tmp_path / "one.zip", prefix="mic_small")
    waiting = upload_zip(client, photo_zip).json()
    waiting_job = client.post("/v1/jobs", json={"scene_id": waiting["id"], **JOB})
    assert waiting_job.status_code == 201, waiting_job.text  # processing: its backbone not decided yet
    assert ingest(waiting["id"])["state"] == "ready"
    scene = client.get(f"/v1/scenes/{waiting['id']}").json()
    assert (scene["backbone"], scene["image_count"]) == ("scene", 1)
    why = ("params.reconstruction: the scene has a single training image, whose one camera has no centre to orbit: "
           "the scene backbone needs views from around the object (upload them): backbone 'auto' is 'scene' for "
           "this scene (its images are opaque photos)")
    failed = client.get(f"/v1/jobs/{waiting_job.json()['id']}").json()
    assert (failed["state"], failed["error"]) == ("failed", why)

    refused = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB})
    assert refused.status_code == 422 and refused.json()["detail"] == why
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene["id"], "object": "mic"}],
                                            "evaluation": {"fid_input": False}})
    assert sweep.status_code == 422 and sweep.json()["detail"] == why
    named = {"reconstruction": {"backbone": "relu_field"}}
    assert client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": named}).status_code == 201


def test_a_one_image_scene_ingested_before_backbones_were_recorded_fails_its_fit_naming_the_count(client, root,
                                                                                                   tmp_path):
    """A scene ingested before its backbone was recorded (NULL: "auto" is decided by the worker from the images it
    loads) passes the submission's check, which cannot resolve "auto"; the worker's check of the fit knew no image
    count, so a one-photo scene failed in the scene frame's own words, naming neither the count nor what "auto"
    became. It fails as a submission on a newer scene is refused, before any fitting."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import tasks

    one_photo = _opaque_copy(small_mic(tmp_path / "mic1", frames=1), tmp_path / "photo1")
    scene = upload_zip(client, zip_folder(one_photo, tmp_path / "one.zip", prefix="mic_small")).json()
    assert ingest(scene["id"])["state"] == "ready"
    with session_scope() as session:
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(backbone=None))
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": {"downsample": 16}})
    assert job.status_code == 201, job.text
    assert tasks.reconstruct_task.apply(args=(job.json()["id"],)).get()["state"] == "failed"
    failed = client.get(f"/v1/jobs/{job.json()['id']}").json()
    assert failed["error"] == ("reconstruct: ValueError: the scene has a single training image, whose one camera has "
                               "no centre to orbit: the scene backbone needs views from around the object (upload "
                               "them): backbone 'auto' is 'scene' for this scene (its images are opaque photos)")


def test_fid_input_against_a_single_input_image_is_a_422_at_submission(client, dataset, root):
    """FID_input compares the ring with the edits' fit's input images, and FID needs two: an evaluation of edits
    fitted from max_images 1 had been accepted and failed in the worker (a sweep's, after each edit had run)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene = make_scene(client, dataset, root)
    one_image = {"max_images": 1}
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene["id"], "object": "mic"}],
                                            "params": one_image})
    assert sweep.status_code == 422, sweep.text
    assert sweep.json()["detail"] == ("evaluation.fid_input needs at least 2 input images to compare the ring with "
                                      "(FID), but params.max_images 1 keeps 1: set evaluation.fid_input false, or "
                                      "fit from more images")
    assert client.get("/v1/jobs").json()["total"] == 0 and reconstruction_rows(scene["id"]) == []

    edit = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB, "params": one_image}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="succeeded"))
    evaluation = {"job_ids": [edit["id"]], "object": "mic"}
    refused = client.post("/v1/evaluations", json=evaluation)
    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"] == ("params.fid_input needs at least 2 input images to compare the ring with "
                                        f"(FID), but the edits' params.max_images 1 (job {edit['id']!r}) keeps 1: "
                                        "set params.fid_input false, or fit from more images")
    assert client.post("/v1/evaluations", json={**evaluation, "params": {"fid_input": False}}).status_code == 201
    two = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene["id"], "object": "mic"}],
                                          "params": {"max_images": 2}})
    assert two.status_code == 201, two.text


def test_an_object_name_whose_source_text_clip_cannot_read_is_a_422_naming_it(client, dataset, root):
    """The source text "a render of a <object>" is scored by CLIP, which reads 77 tokens: a 99-character object such
    as "a-a-...-a" (105 tokens with "a render of a" and the start and end tokens) had been accepted (201) and failed in the worker, after the models had loaded."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene = make_scene(client, dataset, root)
    edit = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="succeeded"))
    long_object = "-".join("a" * 50)
    refused = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": long_object})
    assert refused.status_code == 422, refused.text
    assert refused.json()["detail"] == (
        'object: the source text is at least 105 tokens as the model sees it ("a render of a a-a-a-a-a-a-a-a-...'
        'a-a-a-a-a-a-a-a"); its text encoder reads 77, its start and end tokens included: shorten the object name')
    assert client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "a" * 100}).status_code == 201


def test_an_evaluation_of_jobs_of_different_scenes_or_reconstructions_names_the_jobs_apart(client, dataset, root):
    """Up to 60 jobs are listed: the 422 had said only that some belong to different scenes (or reconstructions),
    not which."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene, other_scene = make_scene(client, dataset, root), make_scene(client, dataset, root)
    first, same, coarse, elsewhere = (
        client.post("/v1/jobs", json={"scene_id": scene_id, **JOB, "params": params}).json()
        for scene_id, params in ((scene["id"], {}), (scene["id"], {}), (scene["id"], {"downsample": 2}),
                                 (other_scene["id"], {})))
    with session_scope() as session:
        session.execute(update(Job).values(state="succeeded"))
    scenes = client.post("/v1/evaluations", json={"job_ids": [first["id"], same["id"], elsewhere["id"]],
                                                  "object": "mic"})
    assert scenes.status_code == 422, scenes.text
    assert scenes.json()["detail"] == (
        f"the jobs belong to different scenes: job {elsewhere['id']!r} edits scene {other_scene['id']!r}, job "
        f"{first['id']!r} scene {scene['id']!r}; an evaluation scores edits of one object")
    reconstructions = client.post("/v1/evaluations", json={"job_ids": [first["id"], same["id"], coarse["id"]],
                                                           "object": "mic"})
    assert reconstructions.status_code == 422, reconstructions.text
    assert reconstructions.json()["detail"] == (
        f"the jobs edit different reconstructions of the scene (reconstruction parameters differ): job "
        f"{coarse['id']!r} edits reconstruction {coarse['reconstruction']['id']!r}, job {first['id']!r} "
        f"{first['reconstruction']['id']!r}")


def test_an_evaluation_whose_scene_is_deleted_while_it_is_created_is_404(client, dataset, root, monkeypatch):
    """The scene (its reconstructions and jobs with it) deleted after the edit jobs were read: a 404 naming it, as
    a job's submission answers, and nothing recorded (the FID_input check's read of it had raised, a 500)."""
    from sqlalchemy import delete, func, select, update

    import api.services.evaluations as evaluations
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    scene = make_scene(client, dataset, root)
    edit = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="succeeded"))
    read_job = evaluations.get_job

    def read_then_scene_deleted(**kwargs):
        job = read_job(**kwargs)
        with session_scope() as other:  # a DELETE /v1/scenes/{id} committed meanwhile
            other.execute(delete(Scene).where(Scene.id == scene["id"]))
        return job

    monkeypatch.setattr(evaluations, "get_job", read_then_scene_deleted)
    response = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic"})
    assert response.status_code == 404, response.text
    assert response.json()["detail"] == f"scene {scene['id']!r} was deleted while the job was created"
    with session_scope() as session:
        assert session.scalar(select(func.count()).select_from(Job)) == 0


def _opaque_copy(dataset: Path, dest: Path) -> Path:
    """``dataset`` with its images flattened onto white, saved without alpha: photos, as a capture's are."""
    from PIL import Image

    shutil.copytree(dataset, dest)
    for path in dest.rglob("*.png"):
        with Image.open(path) as image:
            flat = Image.new("RGB", image.size, "white")
            flat.paste(image, mask=image.getchannel("A"))
        flat.save(path)
    return dest


def test_a_scenes_backbone_is_decided_at_processing_and_jobs_are_checked_against_it(client, dataset, root):
    """Three reconstruction iterations fit the object preset (3 stages), not the photos' (2): on a ready scene of
    photos they are a 422 saying what "auto" became; on one still processing, the job fails when its ingest
    decides, and a job whose parameters fit is sent."""
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    three = {"reconstruction": {"iterations": [2, 2, 3]}}
    objects = make_scene(client, dataset, root)
    assert objects["backbone"] == "relu_field"
    accepted = client.post("/v1/jobs", json={"scene_id": objects["id"], **JOB, "params": three})
    assert accepted.status_code == 201, accepted.text

    photos_zip = zip_folder(_opaque_copy(dataset, root / "photos"), root / "photos.zip", prefix="photos")
    processing = upload_zip(client, photos_zip).json()
    assert processing["backbone"] is None
    misfit = client.post("/v1/jobs", json={"scene_id": processing["id"], **JOB, "params": three}).json()
    fitting = client.post("/v1/jobs", json={"scene_id": processing["id"], **JOB,
                                            "params": {"reconstruction": {"iterations": [2, 3]}}}).json()
    assert ingest(processing["id"])["state"] == "ready"
    assert client.get(f"/v1/scenes/{processing['id']}").json()["backbone"] == "scene"
    why = ("iterations takes one value or one per stage (2 stages), got 3: backbone 'auto' is 'scene' for this "
           "scene (its images are opaque photos)")
    failed = client.get(f"/v1/jobs/{misfit['id']}").json()
    assert (failed["state"], failed["error"]) == ("failed", f"params.reconstruction: {why}")
    assert client.get(f"/v1/jobs/{fitting['id']}").json()["state"] == "queued"
    listed = {r["id"]: r for r in client.get(f"/v1/scenes/{processing['id']}/reconstructions").json()}
    never_fitted = listed[failed["reconstruction"]["id"]]  # says why, rather than waiting as if a job would fit it
    assert (never_fitted["state"], never_fitted["error"]) == ("failed", f"params.reconstruction: {why}")
    assert listed[client.get(f"/v1/jobs/{fitting['id']}").json()["reconstruction"]["id"]]["state"] == "pending"
    with session_scope() as session:
        assert session.get(Job, misfit["id"]).task_id is None  # never sent
        assert session.get(Job, fitting["id"]).task_id is not None

    refused = client.post("/v1/jobs", json={"scene_id": processing["id"], **JOB, "params": three})
    assert refused.status_code == 422 and refused.json()["detail"] == f"params.reconstruction: {why}"
    named = {"reconstruction": {**three["reconstruction"], "backbone": "relu_field"}}
    assert client.post("/v1/jobs", json={"scene_id": processing["id"], **JOB, "params": named}).status_code == 201

    # A sweep over both scenes is refused for the second before any reconstruction of the first is made.
    before = reconstruction_rows(objects["id"])
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": objects["id"], "object": "mic"},
                                                       {"scene_id": processing["id"], "object": "mic"}],
                                            "params": {"reconstruction": {"iterations": [3, 2, 3]}}})
    assert sweep.status_code == 422 and sweep.json()["detail"] == f"params.reconstruction: {why}"
    assert reconstruction_rows(objects["id"]) == before


def test_a_job_whose_scenes_ingest_decides_meanwhile_is_checked_under_the_scenes_lock(client, dataset, root,
                                                                                       monkeypatch):
    """The ingest ends between the submission's first look (processing: nothing to check yet) and the job's
    insertion, so its decision never sees the job: the job is checked under the scene's lock, a 422 naming what
    "auto" became, and nothing of it is kept."""
    from sqlalchemy import func, select, update

    import api.services.jobs as jobs_service
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    photos_zip = zip_folder(_opaque_copy(dataset, root / "photos"), root / "photos.zip", prefix="photos")
    processing = upload_zip(client, photos_zip).json()
    real_lock_scene = jobs_service.lock_scene

    def ingest_ends_first(session, scene_id):
        session.execute(update(Scene).where(Scene.id == scene_id).values(state="ready", backbone="scene"))
        return real_lock_scene(session, scene_id)

    monkeypatch.setattr(jobs_service, "lock_scene", ingest_ends_first)
    raced = client.post("/v1/jobs", json={"scene_id": processing["id"], **JOB,
                                          "params": {"reconstruction": {"iterations": [2, 2, 3]}}})
    assert raced.status_code == 422, raced.text
    assert raced.json()["detail"].endswith("got 3: backbone 'auto' is 'scene' for this scene (its images are "
                                           "opaque photos)")
    with session_scope() as session:
        assert session.scalar(select(func.count()).select_from(Job).where(Job.scene_id == processing["id"])) == 0


def test_migrations_match_the_models(database_url):
    from alembic import command

    from voxe_service.db import alembic_config, run_migrations

    url = database_url
    run_migrations(url)
    config = alembic_config(url)
    command.check(config)  # raises when the models have changes no migration covers


@pytest.mark.parametrize("root", ["sqlite", "postgres"], indirect=True)
def test_an_upload_holds_no_database_connection_while_it_is_unpacked_and_stored(client, dataset, root,
                                                                                 monkeypatch):
    """Unpacking and storing an upload takes as long as its bytes (minutes for GBs into S3): the request had held
    its pooled connection all along (on PostgreSQL a transaction open), so 15 concurrent uploads used up the
    pool and every other request waited 30 s and failed. The pool is sampled a few times at each step (a
    background poll may hold a connection for an instant, never for all of them)."""
    import time

    from api.services import scenes
    from voxe_service.db import get_engine
    from voxe_service.storage import get_storage

    least_held = {}

    def sampled(name, step):
        def wrapper(*args, **kwargs):
            samples = []
            for _ in range(5):
                samples.append(get_engine().pool.checkedout())
                time.sleep(0.01)
            least_held[name] = min(samples)
            return step(*args, **kwargs)
        return wrapper

    storage_class = type(get_storage())
    monkeypatch.setattr(scenes, "stage_upload", sampled("unpacking", scenes.stage_upload))
    monkeypatch.setattr(storage_class, "put_file", sampled("storing", storage_class.put_file))
    response = upload_zip(client, zip_folder(dataset, root / "held.zip", prefix="mic_small"))
    assert response.status_code == 201, response.text
    assert least_held == {"unpacking": 0, "storing": 0}


def test_a_ply_whose_face_count_is_a_digit_not_ascii_is_a_422_naming_its_line(client, root):
    """'²' is a digit to str.isdigit but no number to int(): a PLY whose header's face count was one had the
    upload's check raise a ValueError, a 500."""
    header = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
              "element face \u00b2\nproperty list uchar int vertex_indices\nend_header\n")
    body = (header + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").encode()
    response = client.post("/v1/scenes", files=[("files", ("tri.ply", body))])
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == ("tri.ply: its header's line 7, 'element face \u00b2', is not "
                                         "'element <name> <count>'")
    assert client.get("/v1/scenes").json()["total"] == 0


@pytest.mark.parametrize("surrogate", ["\ud800", "\udc80"])
def test_a_file_path_holding_a_lone_surrogate_is_a_422_naming_it(client, dataset, root, surrogate):
    """JSON's "\\udc80" reads as a lone surrogate that os.fsencode lets through (an undecodable byte's escape):
    the check's "image not found", naming the path, had held it, and the 422's JSON could not encode it (a 500)."""
    meta = json.loads((dataset / "transforms_train.json").read_text())
    meta["frames"][0]["file_path"] = f"./train/r_{surrogate}"
    body = _zip_bytes(_dataset_entries(dataset, json_text=json.dumps(meta)))
    response = client.post("/v1/scenes", files={"archive": ("surrogate.zip", body, "application/zip")})
    assert response.status_code == 422, response.text
    assert f"'file_path' holds {surrogate!r}, a lone surrogate" in response.json()["detail"]
    assert client.get("/v1/scenes").json()["total"] == 0 and staged(root) == []


def test_a_404_shows_a_long_requested_id_cut(client):
    """Regression: a 404 echoed the whole id of the request's path, a string of any length the client chose (an 8 kB
    path, an 8 kB message). Ids (32 characters) are shown whole; past 100 characters, cut."""
    job_id = _job_row()
    long = "x" * 5000
    shown = repr("x" * 100 + "...")
    for path, detail in ((f"/v1/jobs/{long}", f"job {shown} not found"),
                         (f"/v1/scenes/{long}", f"scene {shown} not found"),
                         (f"/v1/sweeps/{long}", f"sweep {shown} not found"),
                         (f"/v1/jobs/{job_id}/artifacts/{long}", f"job {job_id!r} has no artifact {shown}")):
        response = client.get(path)
        assert (response.status_code, response.json()["detail"]) == (404, detail), path
    assert client.get(f"/v1/jobs/{'a' * 32}").json()["detail"] == f"job {'a' * 32!r} not found"


def test_an_empty_scene_id_filter_is_a_422_naming_it(client):
    """Regression: GET /v1/jobs?scene_id= (a form's empty filter) answered an empty page, as if the key had no job,
    where it names no scene at all."""
    _job_row()
    refused = client.get("/v1/jobs?scene_id=")
    assert refused.status_code == 422
    assert [(error["loc"], error["type"]) for error in refused.json()["detail"]] == [(["query", "scene_id"],
                                                                                     "string_too_short")]
    assert client.get("/v1/jobs").json()["total"] == 1


def _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch) -> dict:
    """The scene of an OBJ (cube/m.obj) whose mtllib names model.mtl, not sent, rendered into 2 views of 32 px at its
    ingest; as created (processing)."""
    from voxe_service import datasets

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    obj = ("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nusemtl red\nf 1 2 3\nf 1 3 4\nf 1 2 5\n")
    response = client.post("/v1/scenes", files=[("files", ("cube/m.obj", obj.encode(), "text/plain"))])
    assert response.status_code == 201, response.text
    return response.json()


def test_a_mesh_loaded_without_the_mtl_its_obj_names_says_so_on_the_jobs_waiting_for_it(client, root, monkeypatch):
    """An OBJ whose mtllib names an .mtl not sent uploads (``voxe submit`` sends it so, warning) and loads grey: that
    had been said in the worker's log alone. The jobs waiting for the scene now get a ``warning`` event saying it."""
    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    events = client.get(f"/v1/jobs/{job['id']}/events").json()
    warnings = [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning"]
    assert warnings == [("ingest", "m.obj: the material library its mtllib names, 'model.mtl', is not found beside "
                                   "it; the mesh loads without its materials")]


def test_a_mesh_or_a_folder_sent_as_files_without_a_name_is_named_by_it_as_a_zip_is(client, dataset):
    """A scene sent with no name is named by its zip's file name; a mesh or a dataset folder sent as files (curl's
    ``-F files=@spot.obj``, a folder's files under its name) had been named "scene-<id>". Now by the mesh's file
    name or the one folder, suffix dropped; files sent loose name nothing."""
    obj = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\n"
    mesh = client.post("/v1/scenes", files=[("files", ("spot.v2.obj", obj, "text/plain"))])
    assert mesh.status_code == 201, mesh.text
    assert (mesh.json()["format"], mesh.json()["name"]) == ("mesh", "spot.v2")
    in_folder = client.post("/v1/scenes", files=[("files", ("meshes/cow.OBJ", obj, "text/plain"))])
    assert in_folder.json()["name"] == "cow"

    def sent_as_files(prefix: str) -> dict:
        files = [("files", (prefix + p.relative_to(dataset).as_posix(), p.read_bytes()))
                 for p in sorted(dataset.rglob("*")) if p.is_file()]
        response = client.post("/v1/scenes", files=files)
        assert response.status_code == 201, response.text
        return response.json()

    assert sent_as_files("mic_small/")["name"] == "mic_small"
    loose = sent_as_files("")
    assert loose["name"] == f"scene-{loose['id'][:8]}"
    given = client.post("/v1/scenes", files=[("files", ("spot.obj", obj, "text/plain"))], data={"name": "given"})
    assert given.json()["name"] == "given"


def test_a_scene_whose_file_name_is_blank_is_named_scene_id_not_blank(client):
    """A scene sent with no name is named by its file's name: one of spaces alone (a zip "   .zip", a mesh " .obj")
    had been stored as the name, a scene listed as nameless, the very name a 422 refuses when it is sent. Such a scene
    is named "scene-<id>", as one whose files name nothing."""
    obj = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\n"
    for file_name in ("   .obj", " .obj"):
        scene = client.post("/v1/scenes", files=[("files", (file_name, obj, "text/plain"))])
        assert scene.status_code == 201, scene.text
        assert scene.json()["name"] == f"scene-{scene.json()['id'][:8]}", file_name
    archive = _zip_bytes({"m.obj": obj})
    scene = client.post("/v1/scenes", files={"archive": ("   .zip", archive, "application/zip")})
    assert scene.status_code == 201, scene.text
    assert scene.json()["name"] == f"scene-{scene.json()['id'][:8]}"


def test_a_job_created_on_a_mesh_scene_once_ready_is_told_its_ingests_warnings(client, root, monkeypatch):
    """The ingest's warnings (an OBJ's .mtl not sent: the mesh loads grey) had been told to the jobs waiting for the
    scene alone: one created once it was ready was never told, nor did the scene say it. The scene keeps them (its
    ``warnings``) and a job created on it gets the same ``warning`` event; an evaluation is told none (the ingest's
    are told to edits)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job

    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    assert scene["warnings"] is None  # (processing)
    waiting = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB}).json()
    assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
    said = ("m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh loads "
            "without its materials")
    assert client.get(f"/v1/scenes/{scene['id']}").json()["warnings"] == [said]
    assert client.get("/v1/scenes").json()["items"][0]["warnings"] == [said]
    later = client.post("/v1/jobs", json={"scene_id": scene["id"], **JOB})
    assert later.status_code == 201, later.text

    def warned(job_id):
        events = client.get(f"/v1/jobs/{job_id}/events").json()
        return [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning"]

    assert warned(waiting["id"]) == warned(later.json()["id"]) == [("ingest", said)]
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == later.json()["id"]).values(state="succeeded"))
    evaluation = client.post("/v1/evaluations", json={"job_ids": [later.json()["id"]], "object": "cube"})
    assert evaluation.status_code == 201, evaluation.text
    assert warned(evaluation.json()["id"]) == []


@BOTH_DATABASES
@pytest.mark.parametrize("fails_in", ["the mesh", "the views"])
def test_a_mesh_scene_whose_ingest_fails_keeps_the_warnings_said_before(client, root, monkeypatch, fails_in):
    """A mesh scene whose ingest failed after its load had warned (an OBJ's .mtl not sent, then its triangles of no
    area, or its rendered views refused) had kept no ``warnings``: what may explain the failure was said nowhere.
    The failed scene keeps those said before it failed."""
    from voxe_service import datasets
    from worker import ingest as worker_ingest

    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    if fails_in == "the mesh":  # its three vertices on a line
        obj, error = ("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 2 0 0\nusemtl red\nf 1 2 3\n",
                      "invalid mesh: m.obj: every triangle has zero area")
    else:
        obj, error = "mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", "invalid dataset: views"

        def refused(root, downsample):
            raise worker_ingest.IngestError("invalid dataset: views")
        monkeypatch.setattr(worker_ingest, "decode", refused)
    scene = client.post("/v1/scenes", files=[("files", ("cube/m.obj", obj.encode(), "text/plain"))])
    assert scene.status_code == 201, scene.text
    assert ingest(scene.json()["id"]) == {"scene_id": scene.json()["id"], "state": "failed"}
    failed = client.get(f"/v1/scenes/{scene.json()['id']}").json()
    assert failed["state"] == "failed" and failed["error"].startswith(error), failed["error"]
    assert failed["warnings"] == ["m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; "
                                  "the mesh loads without its materials"]


def test_a_scene_processed_before_its_warnings_were_kept_says_null_as_the_readme_says(client, root, monkeypatch):
    """A scene ingested before migration 0022 kept no warnings (its column NULL): the API shows null, not [] (none
    said), and the README's scenes row, which had said "null until it is ready", now says what null means there."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    assert ingest(scene["id"])["state"] == "ready"
    with session_scope() as session:
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(warnings=None))
    assert client.get(f"/v1/scenes/{scene['id']}").json()["warnings"] is None
    assert client.get("/v1/scenes").json()["items"][0]["warnings"] is None
    row = next(line for line in (Path(__file__).parent.parent / "README.md").read_text().splitlines()
               if line.startswith("| `GET /v1/scenes`"))
    assert "null while it is processing and for a scene processed before they were kept (migration 0022: not known" in row


def test_a_job_on_a_mesh_scene_whose_warnings_were_not_kept_is_told_they_are_not_known(client, root, monkeypatch):
    """A mesh scene processed before its warnings were kept (migration 0022: NULL) told its jobs nothing, which reads
    as none; a job reusing another's voxelized fit never reloads the mesh, so it was never told the .mtl not sent (the
    job that fitted it was, at stage reconstruct). Each edit created on such a scene is told, at its creation, that
    they are not known; an image scene's NULL says nothing (its processing has no warnings to keep)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from worker import tasks

    scene = _upload_an_obj_naming_an_mtl_not_sent(client, monkeypatch)
    assert ingest(scene["id"])["state"] == "ready"
    with session_scope() as session:
        session.execute(update(Scene).where(Scene.id == scene["id"]).values(warnings=None))
    unknown = (f"scene {scene['id']} was processed before its warnings were kept: whether its mesh loads without "
               "something its files name (an OBJ's .mtl not sent, a PLY's TextureFile unread: the mesh loads grey) is "
               "not known; a fit by the voxelize route says it as it loads the mesh, a fit reused says nothing (upload "
               "the mesh again to be told)")
    said = ("m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh loads "
            "without its materials")
    body = {"scene_id": scene["id"], "prompt": "a cube", "mode": "global",
            "params": {"reconstruction": {"resolution": 16}}}

    def warned(job_id: str) -> list[tuple[str, str]]:
        events = client.get(f"/v1/jobs/{job_id}/events").json()
        return [(e["stage"], e["detail"]) for e in events if e["kind"] == "warning"]

    fitted = client.post("/v1/jobs", json=body).json()
    assert tasks.reconstruct_task.apply(args=(fitted["id"],)).get()["state"] == "done"
    assert warned(fitted["id"]) == [("ingest", unknown), ("reconstruct", said)]
    reusing = client.post("/v1/jobs", json=body).json()
    assert tasks.reconstruct_task.apply(args=(reusing["id"],)).get()["state"] == "done"
    assert client.get(f"/v1/jobs/{reusing['id']}").json()["reconstruction"]["reused"] is True
    assert warned(reusing["id"]) == [("ingest", unknown)]
    from api.services.jobs import told_warnings

    assert told_warnings(Scene(id="images", format="nerf_synthetic", warnings=None)) == []


def test_a_webhook_sender_polling_while_the_broker_refuses_a_new_job_delivers_none_of_its_warnings(root, monkeypatch):
    """A job created on a mesh scene whose ingest warned is told its warnings in the transaction that records it,
    committed before the broker is asked: a sender polling while the broker then refused (the job withdrawn, a 503)
    had claimed its ``job.warning`` delivery, and told the receiver of a job that never existed. A job never sent is
    held back from the sender until the broker takes it."""
    from api.main import create_app
    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import WebhookDelivery, utcnow
    from voxe_service.queue import TaskQueue
    from voxe_service.webhooks import InFlight, Shares, claim_due

    monkeypatch.setenv("VOXE_WEBHOOK_ALLOW_NETWORKS", "127.0.0.0/8")
    monkeypatch.setenv("VOXE_WEBHOOK_POLL_INTERVAL_S", "3600")  # the API's own sender waits: these claims play it
    _reset()
    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    obj = ("mtllib model.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nusemtl red\nf 1 2 3\nf 1 3 4\nf 1 2 5\n")

    def sender_claims() -> list[str]:
        with session_scope() as session:
            won = claim_due(session, utcnow(), 30, 8, Shares(8, 8), InFlight())
            return [session.get(WebhookDelivery, c.delivery_id).job_id for c in won]

    claimed, real_send = [], TaskQueue.send

    def sender_polls_then_refuse(self, *args):
        claimed.append(sender_claims())
        raise ConnectionError("broker down")

    with TestClient(create_app()) as client:
        scene = client.post("/v1/scenes", files=[("files", ("cube/m.obj", obj.encode(), "text/plain"))]).json()
        assert ingest(scene["id"]) == {"scene_id": scene["id"], "state": "ready"}
        body = {"scene_id": scene["id"], **JOB, "webhook_url": "http://127.0.0.1:9/hook",
                "webhook_events": ["warning"]}
        monkeypatch.setattr(TaskQueue, "send", sender_polls_then_refuse)
        refused = client.post("/v1/jobs", json=body)
        assert refused.status_code == 503, refused.text
        assert claimed == [[]]  # nothing of the job being created was claimed while the broker was asked
        with session_scope() as session:
            assert session.query(WebhookDelivery).count() == 0  # withdrawn with the job
        monkeypatch.setattr(TaskQueue, "send", real_send)
        job = client.post("/v1/jobs", json=body)
        assert job.status_code == 201, job.text
        assert sender_claims() == [job.json()["id"]]  # once the broker took it, its warning is the sender's


def test_behind_a_proxy_prefix_a_jobs_links_are_under_it(client, dataset, root):
    """``uvicorn --root-path /api`` behind a proxy serving the service at /api: a job's links (preview, artifacts,
    events, webhooks), an artifact's URL and a stream's preview_url had been /v1/jobs/... at the proxy's top, none of
    them this service's."""
    from sqlalchemy import update

    from voxe_client.client import parse_sse
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    job_id, _ = _job_with_artifact(client, dataset, root, b"png bytes")
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id).values(preview_artifact="render_000.png"))
    with TestClient(client.app, root_path="/api") as proxied:
        job = proxied.post(f"/api/v1/jobs/{job_id}/cancel").json()
        assert job == proxied.get(f"/api/v1/jobs/{job_id}").json()
        listed_job = next(j for j in proxied.get("/api/v1/jobs").json()["items"] if j["id"] == job_id)
        for shown in (job, listed_job):
            assert [shown[f] for f in ("preview_url", "artifacts_url", "events_url", "webhooks_url")] == [
                f"/api/v1/jobs/{job_id}/{part}" for part in ("artifacts/render_000.png", "artifacts", "events",
                                                             "webhooks")]
        [artifact] = proxied.get(job["artifacts_url"]).json()
        assert artifact["url"] == job["preview_url"] and proxied.get(artifact["url"]).content == b"png bytes"
        assert proxied.get(job["events_url"]).json()[-1]["kind"] == "canceled"
        assert proxied.get(job["webhooks_url"]).json() == []
        with proxied.stream("GET", job["events_url"], headers={"Accept": "text/event-stream"}) as stream:
            events = list(parse_sse(stream.iter_lines()))
        assert [e["data"]["preview_url"] for e in events if e["event"] == "progress"] == [job["preview_url"]]
    assert client.get(f"/v1/jobs/{job_id}").json()["preview_url"] == f"/v1/jobs/{job_id}/artifacts/render_000.png"
