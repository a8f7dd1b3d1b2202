"""The database under real concurrency, on SQLite and on PostgreSQL (the deployment's database): migrations
in place, the reconstruction claim raced by workers, the per-key quota raced by submissions, and the handover
of jobs waiting on a scene to the scene's ingest raced by new submissions."""

from __future__ import annotations

import importlib.util
import threading
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from fastapi import HTTPException

from service_helpers import reset_service_caches, service_env

ROOT = Path(__file__).resolve().parents[1]

RACERS = 8
ROUNDS = 30


@pytest.fixture
def db(tmp_path, monkeypatch, database_url):
    """A migrated private database (SQLite, then PostgreSQL); the settings."""
    for key, value in service_env(tmp_path, database_url=database_url).items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from voxe_service.db import run_migrations
    from voxe_service.settings import get_settings

    run_migrations(get_settings().database_url)
    yield get_settings()
    reset_service_caches()


def race(target, n: int = RACERS) -> list:
    """Run ``target(i)`` in ``n`` threads released together; their results (an exception is a result)."""
    barrier, results = threading.Barrier(n), [None] * n

    def run(i):
        barrier.wait()
        try:
            results[i] = target(i)
        except Exception as exc:  # noqa: BLE001 - returned for the test to judge
            results[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    return results


def add_scene(state: str = "ready") -> str:
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Scene

    with session_scope() as session:
        scene = Scene(name="s", format="nerf_synthetic", image_count=1, width=8, height=8, splits=["train"],
                      storage_key="scenes/s/dataset.zip", size_bytes=1, sha256="0" * 64, state=state,
                      task_id="ingest", owner_key_id=LOCAL_KEY_ID)
        session.add(scene)
        session.flush()
        return scene.id


def add_job(scene_id: str) -> str:
    """A queued job on the scene; its id."""
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Job

    with session_scope() as session:
        job = Job(scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global", edit_words=[],
                  params={}, sds_model="tiny", attention_model="tiny", device="cpu")
        session.add(job)
        session.flush()
        return job.id


class RecordingQueue:
    """The real sender's chains, recorded instead of published: which job each chain starts with."""

    def __init__(self):
        from voxe_service.queue import TaskQueue, create_celery_app

        self.queue = TaskQueue(create_celery_app())
        self.sent: list[str] = []
        self._lock = threading.Lock()

    def stage_chain(self, *args, **kwargs):
        return self.queue.stage_chain(*args, **kwargs)

    def send(self, signature) -> str:
        with self._lock:
            self.sent.append(signature.tasks[0].args[0])
        return f"task-{len(self.sent)}"


# ------------------------------------------------------------------------------------------ migrations
READY_SCENE_ROW = (  # a ready scene as written from 0004 (scenes' states) on
    "INSERT INTO scenes (id, owner_key_id, name, format, image_count, width, height, splits, storage_key, size_bytes, "
    "sha256, state, created_at, updated_at) VALUES ('s1', 'local', 'old', 'nerf_synthetic', 3, 8, 8, '[\"train\"]', "
    "'scenes/s1/dataset.zip', 10, 'x', 'ready', '2026-01-01 00:00:00+00', '2026-01-01 00:00:00+00')")


def job_row_of_0007(state: str, job_id: str = "j1") -> str:
    """A job of scene s1 in ``state`` as written from 0007 (its re-send count) on."""
    return ("INSERT INTO jobs (id, scene_id, owner_key_id, prompt, mode, edit_words, params, sds_model, "
            "attention_model, device, state, iteration, total, losses, cancel_requested, completed_stages, requeues, "
            f"created_at, updated_at) VALUES ('{job_id}', 's1', 'local', 'a mic', 'global', '[]', '{{}}', 'tiny', "
            f"'tiny', 'cpu', '{state}', 0, 0, '{{}}', false, '[]', 0, '2026-01-01 00:00:00+00', "
            "'2026-01-01 00:00:00+00')")


def test_a_database_of_the_previous_head_upgrades_in_place(database_url):
    """Rows written before scenes had states keep their data and become ready; downgrading gives them back."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    config, engine = database_at(
        database_url, "0003_evaluation",
        "INSERT INTO scenes (id, owner_key_id, name, format, image_count, width, height, splits, storage_key, "
        "size_bytes, sha256, created_at) VALUES ('s1', 'local', 'old', 'nerf_synthetic', 3, 8, 8, '[\"train\"]', "
        "'scenes/s1/dataset.zip', 10, 'x', '2026-01-01 00:00:00+00')",
        "INSERT INTO jobs (id, scene_id, owner_key_id, prompt, mode, edit_words, params, sds_model, attention_model, "
        "device, state, iteration, total, losses, cancel_requested, completed_stages, created_at, updated_at) VALUES "
        "('j1', 's1', 'local', 'a mic', 'global', '[]', '{}', 'tiny', 'tiny', 'cpu', 'succeeded', 0, 0, '{}', false, "
        "'[]', '2026-01-01 00:00:00+00', '2026-01-01 00:00:00+00')",
        "INSERT INTO idempotency_records (owner_key_id, endpoint, idempotency_key, request_sha256, resource_id, "
        "created_at) VALUES ('local', 'jobs', 'k1', 'x', 'j1', '2026-01-01 00:00:00+00')")
    command.upgrade(config, "head")
    with engine.begin() as conn:
        row = conn.execute(text("SELECT state, error, task_id, updated_at, created_at, size_bytes FROM scenes")).one()
        assert (row.state, row.error, row.task_id, row.size_bytes) == ("ready", None, None, 10)
        assert conn.execute(text("SELECT backbone FROM scenes")).scalar_one() is None  # 0008: auto from the images
        assert conn.execute(text("SELECT ingest_attempts FROM scenes")).scalar_one() == 0  # 0010: never interrupted
        assert str(row.updated_at) == str(row.created_at)
        conn.execute(text("INSERT INTO job_events (job_id, kind, at) VALUES ('j1', 'succeeded', "
                          "'2026-01-01 00:00:00+00')"))
        job = conn.execute(text("SELECT run_token, run_lease_until, requeues FROM jobs")).one()
        assert tuple(job) == (None, None, 0)  # 0007: held by no run, never sent again
        assert not conn.execute(text("SELECT pending FROM idempotency_records")).scalar_one()  # 0011: answered
    command.check(config)  # the upgraded schema is exactly the models'
    command.downgrade(config, "0003_evaluation")
    with engine.begin() as conn:
        assert conn.execute(text("SELECT name FROM scenes")).scalar_one() == "old"
        assert conn.execute(text("SELECT state FROM jobs")).scalar_one() == "succeeded"
    tables = inspect(engine)
    assert "job_events" not in tables.get_table_names()
    assert "state" not in {c["name"] for c in tables.get_columns("scenes")}


def test_webhook_deliveries_written_before_their_receiver_was_recorded_get_their_urls(database_url):
    """0012 records each delivery's receiver (scheme, host and port), which the sender's cap counts by: those
    already written get their URL's, a URL that cannot be read so standing for itself; downgrading drops it."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    urls = ["https://Hooks.Example.com/jobs/j1?try=1", "http://hooks.example.com:8080/a", "http://[::1]:9000/x",
            "https://[::1/broken"]
    config, engine = database_at(
        database_url, "0011_idempotency_pending",
        READY_SCENE_ROW,
        job_row_of_0007("running"))
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO webhook_deliveries (id, job_id, event_id, event_type, url, payload, state, "
                          "attempts, next_attempt_at, created_at) VALUES (:id, 'j1', :n, 'job.warning', :url, '{}', "
                          "'pending', 0, '2026-01-01 00:00:00+00', '2026-01-01 00:00:00+00')"),
                     [{"id": f"d{n}", "n": n, "url": url} for n, url in enumerate(urls)])
    command.upgrade(config, "head")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT origin FROM webhook_deliveries ORDER BY id")).scalars().all() == [
            "https://hooks.example.com:443", "http://hooks.example.com:8080", "http://[::1]:9000",
            "https://[::1/broken"]
    command.check(config)
    command.downgrade(config, "0011_idempotency_pending")
    assert "origin" not in {c["name"] for c in inspect(engine).get_columns("webhook_deliveries")}
    engine.dispose()


def test_byte_sizes_past_2_gib_are_stored(db):
    """A 2 GiB upload is allowed (VOXE_MAX_UPLOAD_BYTES) and a key may store 50 GiB: PostgreSQL's 32-bit integer
    had refused such a scene and artifact ("integer out of range")."""
    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, Artifact, Job, Reconstruction, Scene

    big = 5 * 1024**3 + 1
    scene_id = add_scene()
    with session_scope() as session:
        session.get(Scene, scene_id).size_bytes = big
        job = Job(scene_id=scene_id, owner_key_id=LOCAL_KEY_ID, prompt="a mic", mode="global", edit_words=[],
                  params={}, sds_model="tiny", attention_model="tiny", device="cpu")
        session.add(job)
        session.flush()
        session.add(Artifact(job_id=job.id, name="big.bin", key="k", size=big, content_type="x", sha256="0" * 64,
                             kind="grid"))
        session.add(Reconstruction(scene_id=scene_id, params_key="p", params={}, grid_size=big))
        job_id = job.id
    with session_scope() as session:
        assert session.get(Scene, scene_id).size_bytes == big
        assert session.get(Job, job_id).artifacts[0].size == big
        assert session.query(Reconstruction).one().grid_size == big


def test_api_replicas_starting_at_once_migrate_a_fresh_database_one_after_another(database_url):
    """Four processes upgrade one fresh database at once, as API replicas starting together do: all succeed and
    the schema is the models' (on PostgreSQL all but one had failed on a duplicate key, in 3 of 5 trials)."""
    import os
    import subprocess
    import sys

    from alembic import command

    from service_helpers import REPO
    from voxe_service.db import alembic_config

    migrate = f"from voxe_service.db import run_migrations; run_migrations({database_url!r})"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    replicas = [subprocess.Popen([sys.executable, "-c", migrate], env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True) for _ in range(4)]
    try:
        outcomes = [(replica.wait(120), replica.stdout.read()) for replica in replicas]
    finally:
        for replica in replicas:
            replica.kill()  # (those still running after the wait)
            replica.wait()
            replica.stdout.close()
    assert all(status == 0 for status, _ in outcomes), [out[-600:] for status, out in outcomes if status]
    command.check(alembic_config(database_url))


def test_a_fresh_sqlite_file_is_migrated_into_wal_mode(tmp_path):
    """run_migrations leaves a new SQLite file in WAL mode, before any service connection opens it: the first
    connections of the service (a request's threads, the API and a worker) had each turned it from rollback mode to
    WAL at connect, and one of two doing so at once got "database is locked" with no busy wait (1 in ~150 trials
    of eight threads; the CI failure of test_racing_first_reads_of_a_keys_webhook_secret_all_get_the_stored_one)."""
    import sqlite3

    from voxe_service.db import run_migrations

    run_migrations(f"sqlite:///{tmp_path / 'voxe.db'}")
    connection = sqlite3.connect(tmp_path / "voxe.db")  # (a plain connection: it asks for no mode itself)
    try:
        assert connection.execute("PRAGMA journal_mode").fetchone() == ("wal",)
    finally:
        connection.close()


def test_a_sqlite_uri_filename_gets_its_folder_and_lock_where_sqlite_opens_it(tmp_path, monkeypatch):
    """``sqlite:///file:./var/x.db?uri=true`` (SQLite's URI filename): the folder made and the migration lock are
    those of ./var/x.db, the file SQLite opens; a folder named 'file:.' had been made (and the lock put there) and
    ./var left missing, SQLite then failing "unable to open database file"."""
    from sqlalchemy import create_engine, inspect

    from voxe_service.db import run_migrations

    monkeypatch.chdir(tmp_path)
    url = "sqlite:///file:./var/x.db?uri=true"
    run_migrations(url)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["var"]
    assert {"x.db", "x.db.migrate.lock"} <= {p.name for p in (tmp_path / "var").iterdir()}
    engine = create_engine(url)
    try:
        assert "jobs" in inspect(engine).get_table_names()
    finally:
        engine.dispose()


def test_ply_artifacts_recorded_as_octet_stream_get_their_model_type_and_back(database_url):
    """0016 gives PLY artifacts recorded before the worker named their type model/ply, as it records them now; other
    artifacts keep theirs; downgrading gives the PLY ones back octet-stream. One an earlier worker publishes after it
    ran keeps octet-stream until the revision is run again (its docstring says so)."""
    from alembic import command
    from sqlalchemy import text

    from service_helpers import database_at

    config, engine = database_at(
        database_url, "0015_owner_index_prefix",
        READY_SCENE_ROW,
        job_row_of_0007("succeeded"))
    recorded = {"mesh.ply": "application/octet-stream", "UPPER.PLY": "application/octet-stream",
                "mesh.obj": "model/obj", "grid.safetensors": "application/octet-stream"}
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO artifacts (job_id, name, key, size, content_type, sha256, kind, created_at) "
                          "VALUES ('j1', :name, :name, 1, :type, 'x', 'mesh', '2026-01-01 00:00:00+00')"),
                     [{"name": name, "type": kind} for name, kind in recorded.items()])

    def types() -> dict[str, str]:
        with engine.connect() as conn:
            return dict(conn.execute(text("SELECT name, content_type FROM artifacts")).all())

    command.upgrade(config, "head")
    assert types() == {**recorded, "mesh.ply": "model/ply", "UPPER.PLY": "model/ply"}
    command.check(config)
    command.downgrade(config, "0015_owner_index_prefix")
    assert types() == recorded
    command.upgrade(config, "head")
    with engine.begin() as conn:  # an earlier worker's, after the API migrated (as its docstring says: it stays)
        conn.execute(text("INSERT INTO artifacts (job_id, name, key, size, content_type, sha256, kind, created_at) "
                          "VALUES ('j1', 'late.ply', 'late.ply', 1, 'application/octet-stream', 'x', 'mesh', "
                          "'2026-01-01 00:00:00+00')"))
    assert types()["late.ply"] == "application/octet-stream"
    spec = importlib.util.spec_from_file_location("migration_0016", ROOT / "voxe_service" / "migrations" / "versions"
                                                  / "0016_ply_content_type.py")
    migration = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(migration)
    for _ in range(2):  # the docstring's remedy, run by hand (twice: it changes nothing more)
        with engine.begin() as conn:
            conn.execute(text(migration.RETYPE_TO_PLY))
        assert types() == {**recorded, "mesh.ply": "model/ply", "UPPER.PLY": "model/ply", "late.ply": "model/ply"}
    engine.dispose()


@pytest.mark.parametrize("before, column", [("0016_ply_content_type", "lost_ingest_resends"),
                                            ("0017_lost_ingest_resends", "ingest_storage_outages")])
def test_a_scenes_ingest_count_upgrades_from_none_and_back(database_url, before, column):
    """0017 counts the re-sends of a scene's ingest whose message was taken as lost (the reaper doubles its wait by
    them), 0018 the runs of its ingest a storage outage stopped (doubling their pause): a scene written before either
    was never sent again or stopped so (0); downgrading drops the count, the scene kept."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    config, engine = database_at(
        database_url, before,
        "INSERT INTO scenes (id, owner_key_id, name, format, image_count, width, height, splits, storage_key, "
        "size_bytes, sha256, state, task_id, ingest_attempts, created_at, updated_at) VALUES ('s1', 'local', 'old', "
        "'nerf_synthetic', 3, 8, 8, '[\"train\"]', 'scenes/s1/dataset.zip', 10, 'x', 'processing', 'ingest', 0, "
        "'2026-01-01 00:00:00+00', '2026-01-01 00:00:00+00')")
    command.upgrade(config, "head")
    with engine.connect() as conn:
        assert conn.execute(text(f"SELECT state, {column} FROM scenes")).one() == ("processing", 0)
    command.check(config)
    command.downgrade(config, before)
    with engine.connect() as conn:
        assert conn.execute(text("SELECT state, task_id FROM scenes")).one() == ("processing", "ingest")
    assert column not in {c["name"] for c in inspect(engine).get_columns("scenes")}
    engine.dispose()


def test_jobs_not_ended_upgrade_to_resume_from_the_old_fixed_checkpoint_key_and_back(database_url):
    """0019 records the key of each job's live checkpoint (a key of its run's own). A job written before it that had
    not ended (queued: re-queued after an interrupted edit; running) stored its edit checkpoint at the one fixed key
    ``checkpoints/edit.safetensors``, which it now records, for its next run to resume from: without it the edit
    starts over, its progress lost. An ended job records none. Downgrading drops the column, the jobs kept."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at
    from voxe_service.models import CANCELED, FAILED, QUEUED, RUNNING, SUCCEEDED
    from voxe_service.storage import job_key

    states = (QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELED)
    config, engine = database_at(database_url, "0018_ingest_storage_outages", READY_SCENE_ROW,
                                 *(job_row_of_0007(state, job_id=f"j-{state}") for state in states))
    command.upgrade(config, "0019_job_checkpoint_key")
    with engine.connect() as conn:
        recorded = dict(conn.execute(text("SELECT id, checkpoint_key FROM jobs")).all())
    old_fixed_key = {f"j-{state}": job_key(f"j-{state}", "checkpoints/edit.safetensors") for state in (QUEUED, RUNNING)}
    assert recorded == {**dict.fromkeys(f"j-{state}" for state in states), **old_fixed_key}
    command.downgrade(config, "0018_ingest_storage_outages")
    with engine.connect() as conn:
        assert dict(conn.execute(text("SELECT id, state FROM jobs")).all()) == {f"j-{state}": state for state in states}
    assert "checkpoint_key" not in {c["name"] for c in inspect(engine).get_columns("jobs")}
    engine.dispose()


def test_a_jobs_storage_outage_count_upgrades_from_none_and_back(database_url):
    """0020 counts the runs of a job's stages a storage outage stopped in a column (they had been counted from the
    text of its ``requeued`` events), as 0018 does a scene's ingest's: a job written before it was never stopped so
    (0); downgrading drops the count, the job kept."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    config, engine = database_at(database_url, "0019_job_checkpoint_key", READY_SCENE_ROW,
                                 job_row_of_0007("running"))
    command.upgrade(config, "head")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT state, storage_outages FROM jobs")).one() == ("running", 0)
    command.check(config)
    command.downgrade(config, "0019_job_checkpoint_key")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT state, requeues FROM jobs")).one() == ("running", 0)
    assert "storage_outages" not in {c["name"] for c in inspect(engine).get_columns("jobs")}
    engine.dispose()


def test_keys_upgrade_to_never_expiring_and_back(database_url):
    """0021 gives a key an expiry (NULL: never, as every key written before it); one set is read back as written, and
    downgrading drops the column, the keys kept, tokens and quotas included."""
    from alembic import command
    from sqlalchemy import inspect, text
    from sqlalchemy.orm import Session

    from service_helpers import database_at
    from voxe_service.models import ApiKey

    config, engine = database_at(
        database_url, "0020_job_storage_outages",
        "INSERT INTO api_keys (id, name, token_sha256, max_active_jobs, created_at) VALUES ('abc123abc123', 'alice', "
        "'ff', 3, '2026-01-01 00:00:00+00')")
    command.upgrade(config, "head")
    with engine.begin() as conn:
        assert conn.execute(text("SELECT expires_at FROM api_keys WHERE id = 'abc123abc123'")).one() == (None,)
        conn.execute(text("INSERT INTO api_keys (id, name, token_sha256, created_at, expires_at) VALUES "
                          "('def456def456', 'bob', 'ee', '2026-01-01 00:00:00+00', '2027-01-01 00:00:00+00')"))
    command.check(config)
    with Session(engine) as session:  # read back through the model: an aware UTC datetime on either database
        assert session.get(ApiKey, "def456def456").expires_at == datetime(2027, 1, 1, tzinfo=timezone.utc)
    command.downgrade(config, "0020_job_storage_outages")
    with engine.connect() as conn:
        assert dict(conn.execute(text("SELECT id, name FROM api_keys WHERE id != 'local'")).all()) == {
            "abc123abc123": "alice", "def456def456": "bob"}
        assert conn.execute(text("SELECT token_sha256, max_active_jobs FROM api_keys WHERE id = 'abc123abc123'")
                            ).one() == ("ff", 3)
    assert "expires_at" not in {c["name"] for c in inspect(engine).get_columns("api_keys")}
    engine.dispose()


def test_scenes_upgrade_to_no_warnings_kept_and_back(database_url):
    """0022 keeps a scene's ingest warnings (NULL: a scene ingested before it, whose were not kept); a list written is
    read back through the model as written, and downgrading drops the column, the scenes kept."""
    from alembic import command
    from sqlalchemy import inspect, text
    from sqlalchemy.orm import Session

    from service_helpers import database_at
    from voxe_service.models import Scene

    config, engine = database_at(database_url, "0021_key_expiry", READY_SCENE_ROW)
    command.upgrade(config, "head")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT state, warnings FROM scenes")).one() == ("ready", None)
    command.check(config)
    said = ["m.obj: the material library its mtllib names, 'model.mtl', is not found beside it; the mesh loads "
            "without its materials"]
    with Session(engine) as session:
        assert session.get(Scene, "s1").warnings is None
        session.get(Scene, "s1").warnings = said
        session.commit()
    with Session(engine) as session:
        assert session.get(Scene, "s1").warnings == said
    command.downgrade(config, "0021_key_expiry")
    with engine.connect() as conn:
        assert conn.execute(text("SELECT name, state, storage_key FROM scenes")).one() == (
            "old", "ready", "scenes/s1/dataset.zip")
    assert "warnings" not in {c["name"] for c in inspect(engine).get_columns("scenes")}
    engine.dispose()


def test_jobs_of_0004_upgrade_to_webhooks_off_and_back(database_url):
    """0005 adds the webhook columns (NULL: no webhook) and the deliveries outbox; downgrading drops them."""
    from alembic import command
    from sqlalchemy import inspect, text

    from service_helpers import database_at

    config, engine = database_at(
        database_url, "0004_ingest_and_events",
        READY_SCENE_ROW,
        "INSERT INTO jobs (id, scene_id, owner_key_id, prompt, mode, edit_words, params, sds_model, attention_model, "
        "device, state, iteration, total, losses, cancel_requested, completed_stages, created_at, updated_at) VALUES "
        "('j1', 's1', 'local', 'a mic', 'global', '[]', '{}', 'tiny', 'tiny', 'cpu', 'succeeded', 0, 0, '{}', false, "
        "'[]', '2026-01-01 00:00:00+00', '2026-01-01 00:00:00+00')")
    command.upgrade(config, "0005_webhooks")
    with engine.begin() as conn:
        assert conn.execute(text("SELECT webhook_url, webhook_events FROM jobs")).one() == (None, None)
        conn.execute(text("INSERT INTO webhook_deliveries (id, job_id, event_id, event_type, url, payload, state, "
                          "attempts, created_at) VALUES ('msg_1', 'j1', 1, 'job.succeeded', 'https://example.com/h', "
                          "'{}', 'pending', 0, '2026-01-01 00:00:00+00')"))
    command.downgrade(config, "0004_ingest_and_events")
    tables = inspect(engine)
    assert "webhook_deliveries" not in tables.get_table_names()
    assert "webhook_url" not in {c["name"] for c in tables.get_columns("jobs")}
    assert "webhook_secret" not in {c["name"] for c in tables.get_columns("api_keys")}
    engine.dispose()


def test_no_index_leads_another(database_url):
    """A non-unique index whose columns lead another index, a unique constraint or the primary key serves no lookup
    the longer one does not, and costs every insert an update: the owner_key_id indexes of jobs and scenes had, once
    0014 indexed (owner_key_id, created_at, id), and the job_id (scene_id) indexes of artifacts, webhook_deliveries
    and reconstructions, the lead of their unique constraints, since 0001 and 0005. Every table is checked; 0015
    drops them; downgrading it gives them back."""
    from alembic import command
    from sqlalchemy import create_engine, inspect

    from voxe_service.db import alembic_config

    config = alembic_config(database_url)
    command.upgrade(config, "head")
    engine = create_engine(database_url)
    schema = inspect(engine)
    tables = schema.get_table_names()
    assert {"jobs", "scenes", "artifacts", "webhook_deliveries", "reconstructions"} <= set(tables)
    leading = []
    for table in tables:
        indexes = schema.get_indexes(table)
        keys = {index["name"]: index["column_names"] for index in indexes}
        keys |= {unique["name"]: unique["column_names"] for unique in schema.get_unique_constraints(table)}
        keys[None] = schema.get_pk_constraint(table)["constrained_columns"]
        leading += [(table, index["name"], name) for index in indexes if not index["unique"]
                    for name, columns in keys.items()
                    if name != index["name"] and columns[:len(index["column_names"])] == index["column_names"]]
    assert leading == []
    command.downgrade(config, "0014_listing_order")
    schema = inspect(engine)
    for table, name in [("jobs", "ix_jobs_owner_key_id"), ("scenes", "ix_scenes_owner_key_id"),
                        ("artifacts", "ix_artifacts_job_id"), ("webhook_deliveries", "ix_webhook_deliveries_job_id"),
                        ("reconstructions", "ix_reconstructions_scene_id")]:
        assert name in {index["name"] for index in schema.get_indexes(table)}
    engine.dispose()


# ------------------------------------------------------------------------------------------ the reconstruction claim
def test_exactly_one_of_many_racing_workers_claims_a_reconstruction(db):
    """The conditional UPDATE lets one claim win per round, however many workers race it at once."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job, Reconstruction, utcnow
    from worker import runtime

    scene = add_scene()
    with session_scope() as session:
        rec = Reconstruction(scene_id=scene, params_key="k", params={})
        session.add(rec)
        session.flush()
        rec_id = rec.id
        jobs = [Job(scene_id=scene, owner_key_id="local", prompt="a mic", mode="global", params={}, sds_model="tiny",
                    attention_model="tiny", device="cpu", reconstruction_id=rec_id) for _ in range(RACERS)]
        session.add_all(jobs)
        session.flush()
        job_ids = [j.id for j in jobs]
    for round_ in range(6):
        wins = race(lambda i: runtime.try_claim_reconstruction(rec_id, job_ids[i], f"host-{i}", db,
                                                                allow_failed=True))
        assert not [w for w in wins if isinstance(w, Exception)], wins
        assert wins.count(True) == 1, (round_, wins)
        winner = runtime.load_reconstruction(rec_id)
        assert winner.owner_job_id == job_ids[wins.index(True)] and winner.run_count == round_ + 1
        if round_ % 2:  # the fitter handed it back (canceled) ...
            runtime.set_reconstruction(rec_id, winner.owner_job_id, state="pending", owner_job_id=None,
                                       lease_until=None)
        else:  # ... or its lease lapsed (a dead worker): either way the next round races for it again
            with session_scope() as session:
                session.execute(update(Reconstruction).where(Reconstruction.id == rec_id)
                                .values(lease_until=utcnow() - timedelta(seconds=1)))


def test_exactly_one_of_many_racing_messages_runs_a_stage(db, monkeypatch):
    """A stage's message delivered to many workers at once: one run takes the job; each other one, seeing the
    holder renew its lease, is dropped (StageHeld), and only one ``stage_started`` is on the timeline."""
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import Job, JobEvent
    from worker import runtime

    monkeypatch.setattr(db, "stage_lease_s", 2.0)  # renewed every 0.5 s: a busy CPU does not let it lapse
    scene = add_scene()
    for round_ in range(3):
        with session_scope() as session:
            job = Job(scene_id=scene, owner_key_id="local", prompt="a mic", mode="global", params={},
                      sds_model="tiny", attention_model="tiny", device="cpu", completed_stages=["reconstruct"])
            session.add(job)
            session.flush()
            job_id = job.id
        dropped = threading.Semaphore(0)

        def run(i):
            try:
                held = runtime.begin_stage(job_id, "edit", f"host-{i}", "cpu", db)
            except runtime.StageHeld:
                dropped.release()
                return "dropped"
            with runtime.stage_lease(job_id, held.run_token, db):  # renewing until every other run gave up
                for _ in range(RACERS - 1):
                    assert dropped.acquire(timeout=30)
            return held.run_token

        outcomes = race(run)
        tokens = [o for o in outcomes if o != "dropped"]
        assert len(tokens) == 1 and isinstance(tokens[0], str), (round_, outcomes)
        with session_scope() as session:
            assert session.get(Job, job_id).run_token == tokens[0]
            started = session.scalars(select(JobEvent.kind).where(JobEvent.job_id == job_id)).all()
        assert started == ["stage_started"], (round_, started)


def test_a_stage_begins_while_job_creation_holds_its_keys_row(db):
    """PostgreSQL: job creation holds the API key's row (the quota lock) while it writes jobs, one of which a
    worker may already be starting. begin_stage takes the job in one UPDATE that changes no foreign key, so it
    needs nothing of the key's row; a claim followed by a second UPDATE of the same row re-checked the foreign
    keys, waited for the key's row, and deadlocked with a creation waiting for the job's row (seen in CI)."""
    from sqlalchemy import create_engine, text

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import runtime

    if not db.database_url.startswith("postgresql"):
        pytest.skip("SQLite has no row locks: one writer at a time")
    scene = add_scene()
    with session_scope() as session:
        job = Job(scene_id=scene, owner_key_id="local", prompt="a mic", mode="global", params={}, sds_model="tiny",
                  attention_model="tiny", device="cpu")
        session.add(job)
        session.flush()
        job_id = job.id
    engine = create_engine(db.database_url)
    try:
        with engine.connect() as creation:
            creation.execute(text("SELECT id FROM api_keys WHERE id = 'local' FOR UPDATE")).all()  # held
            began: list = []
            worker = threading.Thread(
                target=lambda: began.append(runtime.begin_stage(job_id, "reconstruct", "w@host", "cpu", db)))
            worker.start()
            worker.join(20)
            waited = worker.is_alive()
            creation.rollback()  # (lets a waiting begin_stage finish)
            worker.join(60)
            assert not waited, "begin_stage waited for the API key's row"
            assert began[0].state == "running" and began[0].run_token
    finally:
        engine.dispose()


# ------------------------------------------------------------------------------------------ the quota lock
def test_concurrent_submissions_never_exceed_the_keys_quota(db):
    """Twice as many submissions as the key may have active jobs, all at once: exactly the quota is accepted."""
    from sqlalchemy import func, select, update

    from api.schemas import JobCreate
    from api.services.jobs import create_job
    from voxe_service.db import get_sessionmaker, session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, Job

    quota = RACERS // 2
    with session_scope() as session:
        session.execute(update(ApiKey).where(ApiKey.id == LOCAL_KEY_ID).values(max_active_jobs=quota))
    scenes = [add_scene(), add_scene("processing")]  # sent at once, and waiting for an ingest: both count
    queue = RecordingQueue()

    def submit(i):
        with get_sessionmaker()() as session:
            key = session.get(ApiKey, LOCAL_KEY_ID)
            body = JobCreate(scene_id=scenes[i % 2], prompt="a wood carving of a mic")
            return create_job(session=session, settings=db, queue=queue, key=key, body=body, idempotency_key=None)[0].id

    for round_ in range(2):
        results = race(submit)
        accepted = [r for r in results if isinstance(r, str)]
        refused = [r for r in results if isinstance(r, HTTPException)]
        assert len(accepted) == quota and len(refused) == RACERS - quota, results
        assert {r.status_code for r in refused} == {429}
        with session_scope() as session:
            active = session.scalar(select(func.count()).select_from(Job).where(Job.state == "queued"))
            assert active == quota, round_
            session.execute(update(Job).values(state="canceled"))  # the next round starts from none active
    assert len(set(queue.sent)) == len(queue.sent)  # no job was sent twice


def test_an_upload_landing_while_a_mesh_ingest_checks_its_rendered_size_never_exceeds_the_keys_quota(db, tmp_path,
                                                                                                      monkeypatch):
    """A mesh's ingest checks its rendered views' size against the key's upload quota, then stores it; an upload
    landing between the two was checked against the mesh's old size. On SQLite, whose ``FOR UPDATE`` locks nothing,
    both were accepted, the key stored past its quota; the key's lock now holds the upload back until the ingest has
    stored its size, and the upload is refused (429), as on PostgreSQL."""
    from types import SimpleNamespace

    from sqlalchemy import func, select, update

    from api.services import scenes as scene_service
    from voxe_service import quotas
    from voxe_service.db import get_sessionmaker, session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, Scene
    from voxe_service.storage import get_storage
    from worker import ingest

    with session_scope() as session:
        session.execute(update(ApiKey).where(ApiKey.id == LOCAL_KEY_ID).values(max_upload_bytes=100))
        mesh = Scene(name="mesh", format="mesh", image_count=1, width=8, height=8, splits=["train"],
                     storage_key="scenes/m/upload.obj", size_bytes=10, sha256="0" * 64, state="processing",
                     task_id="ingest", ingest_token="run", owner_key_id=LOCAL_KEY_ID)
        session.add(mesh)
        session.flush()
        mesh_id = mesh.id
    (tmp_path / "upload.zip").write_bytes(b"x" * 50)
    monkeypatch.setattr(scene_service, "stage_upload", lambda *args: SimpleNamespace(
        archive=tmp_path / "upload.zip", archive_name="dataset.zip", format="nerf_synthetic", image_count=1, width=8,
        height=8, splits=["train"]))
    answers = []

    def upload():
        with get_sessionmaker()() as session:
            try:
                answers.append(scene_service.create_scene(
                    session=session, settings=db, storage=get_storage(db),
                    queue=SimpleNamespace(send_ingest=lambda scene_id: "task"), key=session.get(ApiKey, LOCAL_KEY_ID),
                    upload=scene_service.Upload(archive=None, archive_name=None, files=[], name="upload"),
                    idempotency_key=None)[0].state)
            except HTTPException as exc:
                answers.append(exc.status_code)

    uploading = threading.Thread(target=upload)
    stored_bytes = quotas.stored_bytes

    def upload_lands_after_the_read(session, key_id, excluding=None):
        counted = stored_bytes(session, key_id, excluding)
        if excluding == mesh_id:  # the ingest's read
            uploading.start()
            uploading.join(1)  # (held back by the key's lock, it waits for the ingest's commit)
        return counted

    monkeypatch.setattr(quotas, "stored_bytes", upload_lands_after_the_read)
    assert ingest._ready(mesh_id, "run", {"size_bytes": 60}, get_storage(db), db, None)["state"] == "ready"
    uploading.join(60)
    assert answers == [429]
    with session_scope() as session:
        stored = session.execute(select(Scene.name, Scene.state, Scene.size_bytes)).all()
        assert session.scalar(select(func.sum(Scene.size_bytes))) == 60
    assert [tuple(row) for row in stored] == [("mesh", "ready", 60)]


# ------------------------------------------------------------------------------------------ waiting for a scene
def test_jobs_racing_a_scenes_ingest_are_each_sent_exactly_once(db):
    """Submissions while the ingest marks the scene ready: whichever side saw it ready sends a job, never both,
    and no job is left unsent."""
    from sqlalchemy import select, update

    from api.schemas import JobCreate
    from api.services.jobs import create_job
    from voxe_service.db import get_sessionmaker, session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, Job
    from voxe_service.queue import dispatch_job
    from voxe_service.scenes import mark_ready

    with session_scope() as session:
        session.execute(update(ApiKey).where(ApiKey.id == LOCAL_KEY_ID).values(max_active_jobs=1000))
    for round_ in range(ROUNDS):
        scene = add_scene("processing")
        queue = RecordingQueue()

        def act(i):
            with get_sessionmaker()() as session:
                if i == 0:  # the ingest: ready, then send the jobs that waited
                    waiting = mark_ready(session, scene)
                    session.commit()
                    for job in waiting:
                        dispatch_job(session, queue, job)
                    return "ready"
                key = session.get(ApiKey, LOCAL_KEY_ID)
                body = JobCreate(scene_id=scene, prompt="a wood carving of a mic")
                return create_job(session=session, settings=db, queue=queue, key=key, body=body,
                                  idempotency_key=None)[0].id

        results = race(act)
        assert not [r for r in results if isinstance(r, Exception)], results
        job_ids = sorted(r for r in results if r != "ready")
        assert sorted(queue.sent) == job_ids, (round_, queue.sent, job_ids)  # each once, none missing
        with session_scope() as session:
            unsent = session.scalars(select(Job.id).where(Job.scene_id == scene, Job.task_id.is_(None))).all()
        assert unsent == [], round_


def test_reapers_reading_a_lost_ingest_at_once_send_it_once(db, monkeypatch):
    """API processes reap side by side: each that read a scene whose ingest message is taken as lost had sent a copy
    (sent, then recorded if the row was unchanged). The re-send is claimed first: one sends it, and records it."""
    from types import SimpleNamespace

    from sqlalchemy import update

    import api.reaper as reaper
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow

    sent, lock = [], threading.Lock()

    def send_ingest(scene_id):
        with lock:
            sent.append(scene_id)
            return f"task-{len(sent)}"

    monkeypatch.setattr(reaper, "get_queue", lambda: SimpleNamespace(send_ingest=send_ingest))
    all_read, broker_waiting = threading.Barrier(RACERS), reaper._sql_broker_waiting

    def once_all_read(url):  # (read after the scenes: every reaper has read them before any sends)
        all_read.wait(60)
        return broker_waiting(url)

    monkeypatch.setattr(reaper, "_sql_broker_waiting", once_all_read)
    for round_ in range(ROUNDS // 6):
        scene = add_scene("processing")
        with session_scope() as session:
            session.execute(update(Scene).where(Scene.id == scene).values(
                updated_at=utcnow() - timedelta(seconds=2 * db.job_lost_message_timeout_s)))
        del sent[:]
        results = race(lambda i: reaper.reap_orphaned_scenes(db))
        assert results == [[]] * RACERS, results
        assert sent == [scene], round_
        with session_scope() as session:
            row = session.get(Scene, scene)
            assert (row.task_id, row.lost_ingest_resends) == ("task-1", 1)


def test_reading_the_sql_brokers_waiting_messages_gives_its_connection_back(db):
    """kombu's channel never closes its session: each read of the broker's waiting messages kept a connection checked
    out until the session was collected, and reapers reading at once (8 API processes' passes) ran the broker's pool
    dry, each read then timing out after 30 s, none sending the lost ingest they had all read."""
    import gc

    from voxe_service.broker import Channel, waiting_tasks

    gc.disable()  # (what had returned them)
    try:
        for _ in range(3):
            waiting_tasks(db.broker_url)
        engine, _sessions = Channel._engines[db.broker_url.removeprefix("sqla+")]  # (kombu's engine of the URL)
        assert engine.pool.checkedout() == 0
    finally:
        gc.enable()


def test_a_malformed_waiting_message_is_skipped_said_once_and_the_others_read(tmp_path, caplog):
    """A single message not of Celery's shape in the SQL broker's table had raised out of waiting_tasks: the reaper
    took the broker as unreadable, and no queued job's message as lost, until a worker took that message."""
    import json
    import logging
    from base64 import b64encode

    from kombu import Connection

    from voxe_service.broker import register, waiting_tasks

    url = f"sqla+sqlite:///{tmp_path / 'broker.db'}"
    register()

    def task_message(task, args, chain=None):
        body = b64encode(json.dumps([args, {}, {"chain": chain}]).encode()).decode()
        return {"body": body, "headers": {"task": task}, "properties": {}}

    with Connection(url) as conn:
        channel = conn.default_channel
        channel._put("voxe", task_message("voxe.edit", ["j1"], chain=[{"task": "voxe.export", "args": ["j1"]}]))
        for malformed in ({"body": "not base64 at all!"}, {"headers": {}}, task_message("voxe.edit", 5),
                          {"body": b64encode(b"[[], {}, []]").decode(), "headers": {"task": "voxe.edit"}}):
            channel._put("voxe", malformed)
        channel._put("voxe", task_message("voxe.reconstruct", ["j2"]))
        channel.session.add(channel.message_cls(payload="{not json", queue=channel._get_or_create("voxe")))
        channel.session.commit()
        channel.session.close()
    with caplog.at_level(logging.WARNING, logger="voxe.broker"):
        for _ in range(2):
            assert waiting_tasks(url) == {("voxe.edit", "j1"), ("voxe.export", "j1"), ("voxe.reconstruct", "j2")}
    skipped = [r.getMessage() for r in caplog.records if "is no Celery task message" in r.getMessage()]
    assert len(skipped) == 5 and all(m.endswith(": skipped") for m in skipped), skipped


def _processes_at_once(target, n: int) -> list[str | None]:
    """``target()`` in ``n`` forked processes released together (the API and workers starting): each one's error,
    None where it succeeded."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    barrier, results = context.Barrier(n), context.Queue()

    def run():
        barrier.wait()
        try:
            target()
            results.put(None)
        except Exception as exc:  # noqa: BLE001 - the racer's error is its result
            results.put(f"{type(exc).__name__}: {exc}"[:300])

    processes = [context.Process(target=run) for _ in range(n)]
    for process in processes:
        process.start()
    errors = [results.get(timeout=60) for _ in processes]
    for process in processes:
        process.join(timeout=60)
    return errors


def test_processes_opening_a_fresh_sql_broker_at_once_all_open_it_in_wal_mode(tmp_path):
    """The API and a worker open the SQL broker's new file at once on a fresh install: kombu makes its tables as each
    first opens it, and one of two doing so at once was refused "table kombu_queue already exists" (25 of 30 trials
    of four processes), or "database is locked" turning it to WAL. They set it up one at a time (as the metadata
    database's migrations), the file left in WAL mode."""
    import sqlite3

    from kombu import Connection

    from voxe_service.broker import register

    register()
    for trial in range(5):
        path = tmp_path / f"broker{trial}.db"

        def first_open():
            with Connection(f"sqla+sqlite:///{path}") as conn:
                conn.default_channel.session.close()  # (the channel's first session opens the database)

        assert _processes_at_once(first_open, 4) == [None] * 4
        connection = sqlite3.connect(path)  # (a plain connection: it asks for no mode itself)
        try:
            assert connection.execute("PRAGMA journal_mode").fetchone() == ("wal",)
            assert {"kombu_queue", "kombu_message"} <= {name for (name,) in connection.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
        finally:
            connection.close()


def test_processes_opening_a_fresh_sql_broker_on_postgresql_at_once_all_open_it(postgres_server):
    """The SQL broker on PostgreSQL (sqla+postgresql+psycopg://): kombu makes its tables as each process first opens
    the database, and of the API and workers starting at once on a fresh database one was refused (a duplicate key
    in pg_type as two made the same table). They make them one at a time."""
    from kombu import Connection

    from voxe_service.broker import register

    register()
    for trial in range(5):
        url = f"sqla+{postgres_server.create_database()}"

        def first_open():
            with Connection(url) as conn:
                conn.default_channel.session.close()  # (the channel's first session opens the database)

        assert _processes_at_once(first_open, 4) == [None] * 4


def test_a_stuck_holder_of_the_database_setup_lock_fails_a_start_naming_it_after_the_wait(postgres_server, monkeypatch,
                                                                                            caplog):
    """pg_advisory_lock waits without limit: a session holding the setup lock and never letting go (a process hung in
    its migration, a psql left open) had held every API and worker start, migrations and the SQL broker's first
    open alike, silently for good. The wait now says who holds the lock as it begins, and after SETUP_LOCK_WAIT_S
    fails naming the lock, the holder's pid and how long it waited; once the holder lets go, a start goes on."""
    import logging
    import time

    from sqlalchemy import create_engine, text
    from sqlalchemy.pool import NullPool

    from voxe_service import db
    from voxe_service.db import SETUP_LOCK, database_setup, run_migrations

    url = postgres_server.create_database()
    holder_engine = create_engine(url, poolclass=NullPool)  # (its session, and the lock, end as it closes)
    monkeypatch.setattr(db, "SETUP_LOCK_WAIT_S", 1.5)
    try:
        with holder_engine.connect() as holder:
            holder.execute(text("SET application_name = 'stuck-migration'"))
            holder.execute(text("SELECT pg_advisory_lock(:key)"), {"key": SETUP_LOCK})
            pid = holder.execute(text("SELECT pg_backend_pid()")).scalar_one()
            started = time.monotonic()
            with caplog.at_level(logging.WARNING, logger="voxe.db"):
                with pytest.raises(RuntimeError, match=rf"gave up after waiting 2 s for the database setup lock "
                                                       rf"\(PostgreSQL advisory lock {SETUP_LOCK}\), held by the "
                                                       rf"session of pid {pid} \(application 'stuck-migration'"):
                    run_migrations(url)
            assert 1.5 <= time.monotonic() - started < 10
            assert (f"waiting for the database setup lock (PostgreSQL advisory lock {SETUP_LOCK}), held by the "
                    f"session of pid {pid} (application 'stuck-migration'") in caplog.text
            assert "giving up after 2 s" in caplog.text
        with database_setup(url):  # the holder gone: taken at once
            pass
        run_migrations(url)
    finally:
        holder_engine.dispose()


def test_processes_first_using_a_queue_of_the_sql_broker_at_once_all_use_its_one_row(tmp_path):
    """kombu makes a queue's row as a process first sends to or reads it: of the API and a worker doing so at once on
    a fresh broker, one was refused "UNIQUE constraint failed: kombu_queue.name" (9 of 30 trials of four). It reads
    the row the other made."""
    from kombu import Connection

    from voxe_service.broker import register

    register()
    url = f"sqla+sqlite:///{tmp_path / 'broker.db'}"
    with Connection(url) as conn:
        conn.default_channel.session.close()  # (the tables made)
    for trial in range(5):
        def first_use(queue=f"voxe{trial}"):
            with Connection(url) as conn:
                channel = conn.default_channel
                try:
                    channel._get_or_create(queue)
                finally:
                    channel.session.close()

        assert _processes_at_once(first_use, 4) == [None] * 4
    with Connection(url) as conn:
        channel = conn.default_channel
        names = [queue.name for queue in channel.session.query(channel.queue_cls)]
        channel.session.close()
    assert sorted(names) == [f"voxe{trial}" for trial in range(5)]


# ------------------------------------------------------------------------------------------ the connection pool
def test_racing_first_reads_of_a_keys_webhook_secret_all_get_the_stored_one(db):
    """Requests that have each read the key without a webhook secret make it at once (GET /v1/webhooks/secret, a
    job with a webhook): one makes it, every one returns it (each had written its own, last writer winning)."""
    from voxe_service.db import get_sessionmaker
    from voxe_service.models import LOCAL_KEY_ID, ApiKey
    from voxe_service.webhooks import key_secret

    all_read = threading.Barrier(RACERS)

    def first_read(_):
        with get_sessionmaker()() as session:
            key = session.get(ApiKey, LOCAL_KEY_ID)
            assert key.webhook_secret is None
            all_read.wait(60)  # (a racer that failed before it: the others go on, their error told, not hung)
            secret = key_secret(session, key)
            session.commit()
            return secret

    secrets = race(first_read)
    with get_sessionmaker()() as session:
        stored = session.get(ApiKey, LOCAL_KEY_ID).webhook_secret
    assert secrets == [stored] * RACERS, secrets


def test_racing_rotations_of_a_keys_webhook_secret_all_answer_the_one_kept(db):
    """Rotations at once (two POST /v1/webhooks/secret/rotate, or one beside the admin's rotate-webhook-secret) each
    answered the secret it wrote, the last writer's kept: the others' callers held a secret that never signed
    anything. One writes its secret, every one answers it, and it is not the one they all replaced."""
    from api.services.jobs import rotate_webhook_secret
    from voxe_service.db import get_sessionmaker
    from voxe_service.models import LOCAL_KEY_ID, ApiKey
    from voxe_service.webhooks import key_secret

    with get_sessionmaker()() as session:
        old = key_secret(session, session.get(ApiKey, LOCAL_KEY_ID))
        session.commit()
    all_read = threading.Barrier(RACERS)

    def rotate(_):
        with get_sessionmaker()() as session:
            key = session.get(ApiKey, LOCAL_KEY_ID)
            assert key.webhook_secret == old
            all_read.wait(60)  # (a racer that failed before it: the others go on, their error told, not hung)
            return rotate_webhook_secret(session=session, key=key)

    secrets = race(rotate)
    with get_sessionmaker()() as session:
        stored = session.get(ApiKey, LOCAL_KEY_ID).webhook_secret
    assert stored != old and secrets == [stored] * RACERS, secrets


def test_a_process_holds_at_most_its_configured_connections_then_waits_its_timeout(tmp_path, monkeypatch,
                                                                                     database_url):
    """VOXE_DATABASE_POOL_SIZE + VOXE_DATABASE_MAX_OVERFLOW bound one process's connections (the deployment's sum
    must fit the server's max_connections); one more waits VOXE_DATABASE_POOL_TIMEOUT_S, then fails, and gets a
    connection once one is returned."""
    import time

    from sqlalchemy import text
    from sqlalchemy.exc import TimeoutError as PoolTimeout

    for key, value in {**service_env(tmp_path, database_url=database_url), "VOXE_DATABASE_POOL_SIZE": "2",
                       "VOXE_DATABASE_MAX_OVERFLOW": "1", "VOXE_DATABASE_POOL_TIMEOUT_S": "0.5"}.items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from voxe_service.db import get_engine

    engine = get_engine()
    try:
        held = [engine.connect() for _ in range(3)]
        for connection in held:
            assert connection.execute(text("select 1")).scalar() == 1
        started = time.monotonic()
        with pytest.raises(PoolTimeout):
            engine.connect()
        assert 0.5 <= time.monotonic() - started < 5
        held.pop().close()
        with engine.connect() as connection:
            assert connection.execute(text("select 2")).scalar() == 2
        for connection in held:
            connection.close()
    finally:
        engine.dispose()
        reset_service_caches()


def test_a_failed_statement_does_not_carry_the_secrets_it_binds(database_url):
    """SQLAlchemy's error text names a statement's bound values: a failed UPDATE of a webhook delivery had logged its
    last_error with the webhook_url's credentials. The statement is named, its values are not."""
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    from voxe_service.db import make_engine

    engine = make_engine(database_url)
    try:
        with pytest.raises(DBAPIError) as failed, engine.connect() as connection:
            connection.execute(text("UPDATE no_such_table SET last_error = :error"),
                               {"error": "webhook_url 'https://bob:s3cr3t@hooks.example.com/' cannot be sent to"})
    finally:
        engine.dispose()
    assert "UPDATE no_such_table" in str(failed.value) and "s3cr3t" not in str(failed.value), failed.value


def test_a_postgresql_that_accepts_and_never_answers_is_an_outage_within_the_connect_timeout(monkeypatch):
    """A hung or partitioned PostgreSQL (the TCP connection made, no answer ever): libpq has no connect timeout of
    its own, so a connect had waited for ever, each request holding its thread (and every /readyz leaving one
    behind). Now a URL without ``connect_timeout`` gets POSTGRES_CONNECT_TIMEOUT_S, and the connect fails as an
    outage (the API's 503), its migrations at startup too; one the URL sets is kept."""
    import time

    from sqlalchemy import text
    from sqlalchemy.exc import OperationalError

    from service_helpers import outcome_within, silent_server
    from voxe_service import db as db_module
    from voxe_service.db import connect_timeout_args, database_outage, make_engine, run_migrations

    assert "connect_timeout" not in connect_timeout_args("postgresql+psycopg://u@db/voxe?connect_timeout=3")
    assert connect_timeout_args("sqlite:///./var/voxe.db") == {}
    monkeypatch.setattr(db_module, "POSTGRES_CONNECT_TIMEOUT_S", 2)

    def query(engine):
        with engine.connect() as connection:
            return connection.execute(text("SELECT 1")).scalar()

    with silent_server() as (port, accepted):
        url = f"postgresql+psycopg://voxe@127.0.0.1:{port}/voxe"
        engine, started = make_engine(url), time.monotonic()
        try:
            outcome = outcome_within(lambda: query(engine), 30)
            assert outcome, "the connect still waited on the silent server after 30 s"
            assert database_outage(outcome[0]) and "timeout" in str(outcome[0]), outcome
            assert accepted and time.monotonic() - started < 15
            started = time.monotonic()  # the API's first connect: its migrations at startup
            with pytest.raises(OperationalError, match="timeout"):
                run_migrations(url)
            assert time.monotonic() - started < 15
        finally:
            engine.dispose()


def test_the_services_postgresql_connections_give_up_on_a_server_whose_machine_went_away(postgres_server):
    """libpq has no read timeout and the system's keepalives first probe after 2 hours: a query whose PostgreSQL
    machine crashed or was cut off (the request taken, no answer, no reset ever) waited that long. The service's
    connections now keep TCP keepalives and a TCP user timeout (a black-holed server: "Connection timed out" within
    a minute, not waited for), each setting the URL gives its own kept."""
    def tcp_settings(url: str) -> dict:
        from voxe_service.db import make_engine

        engine = make_engine(url)
        try:
            with engine.connect() as connection:
                given = connection.connection.dbapi_connection.info.get_parameters()
        finally:
            engine.dispose()
        return {key: given.get(key) for key in ("keepalives", "keepalives_idle", "keepalives_interval",
                                                "keepalives_count", "tcp_user_timeout")}

    url = postgres_server.create_database()
    assert tcp_settings(url) == {"keepalives": "1", "keepalives_idle": "30", "keepalives_interval": "10",
                                 "keepalives_count": "3", "tcp_user_timeout": "60000"}
    assert tcp_settings(f"{url}?keepalives_idle=5&tcp_user_timeout=20000") == {
        "keepalives": "1", "keepalives_idle": "5", "keepalives_interval": "10", "keepalives_count": "3",
        "tcp_user_timeout": "20000"}


# ------------------------------------------------------------------------------------------ the event timeline
def test_an_event_recorded_while_another_writer_holds_its_job_commits_after_it(db):
    """Event streams read each job's events past the last id they sent. PostgreSQL numbers an event as it is
    written, so a checkpoint event (no job write before it) recorded while the reaper's transaction had numbered
    its own 'requeued' and not yet committed became visible first, with the higher id: a stream that read it
    then never sent the reaper's. Every event writer now holds the job's row until it commits."""
    from sqlalchemy import select, update

    from voxe_service.db import get_sessionmaker, session_scope
    from voxe_service.jobs import record_event
    from voxe_service.models import Job, JobEvent, utcnow
    from worker import runtime

    job_id = add_job(add_scene())
    reaper = get_sessionmaker()()
    try:  # the reaper's way: the job written, then its event numbered, the commit still to come
        reaper.execute(update(Job).where(Job.id == job_id).values(updated_at=utcnow()))
        record_event(reaper, job_id, "requeued")
        checkpoint = threading.Thread(target=runtime.record_job_event, args=(job_id, "checkpoint"),
                                      kwargs={"iteration": 200})
        checkpoint.start()
        checkpoint.join(1.0)
        with session_scope() as reader:  # what a stream's poll sees meanwhile: nothing past the reaper's number
            visible = reader.scalars(select(JobEvent.kind).where(JobEvent.job_id == job_id)).all()
        assert checkpoint.is_alive() and visible == [], visible
        reaper.commit()
    finally:
        reaper.close()
    checkpoint.join(30)
    with session_scope() as session:
        kinds = session.scalars(select(JobEvent.kind).where(JobEvent.job_id == job_id).order_by(JobEvent.id)).all()
    assert kinds == ["requeued", "checkpoint"]


def test_a_stream_misses_no_event_numbered_before_one_committed_first(db):
    """An event stream sends each job's events past the last id it sent. On PostgreSQL an event numbered by one
    writer and committed after a later-numbered one of another writer of the job (here the API canceling it)
    was never sent: the stream read the cancel, ended with it, and a reconnect (Last-Event-ID) or a timeline read
    handing over to a stream had missed it as well. ``record_event`` holds the job's row until the writer commits,
    whatever the writer wrote before, so a job's events commit in id order. (SQLite lets one writer in at a time.)"""
    import asyncio
    from contextlib import aclosing

    from api.events import EventHub
    from api.routes.jobs import progress_view
    from voxe_client.client import parse_sse
    from voxe_service.db import get_sessionmaker, session_scope
    from voxe_service.jobs import finish_jobs, record_event
    from voxe_service.models import CANCELED, QUEUED, Job

    job_id = add_job(add_scene())
    writer = get_sessionmaker()()  # a writer that wrote nothing of the job before its event
    ended = []

    def cancel():  # the API's way with a queued job
        with session_scope() as session:
            ended.extend(finish_jobs(session, [job_id], CANCELED, message="canceled", where=[Job.state == QUEUED]))

    async def interleave():
        """The checkpoint numbered first; the cancel written meanwhile, and the stream polling, for a second; then
        the checkpoint committed."""
        record_event(writer, job_id, "checkpoint", iteration=200)
        canceling = asyncio.create_task(asyncio.to_thread(cancel))
        await asyncio.sleep(1.0)
        writer.commit()
        await canceling

    async def main():
        hub = EventHub(0.05, progress_view)
        try:
            sent = []
            async with aclosing(hub.stream(job_id, "local")) as stream:
                writing = asyncio.create_task(interleave())
                async for chunk in stream:
                    sent += [event["event"] for event in parse_sse(chunk.splitlines()) if event["id"] is not None]
                await writing
            return sent
        finally:
            await hub.close()

    try:
        sent = asyncio.run(asyncio.wait_for(main(), 30))
    finally:
        writer.close()
    assert ended == [job_id]
    assert sent == ["checkpoint", "canceled"], sent


def _error_of_a_statement_binding(engine, secret: str) -> str:
    """The text of the error a failing statement that binds ``secret`` raises on ``engine``."""
    from sqlalchemy import text
    from sqlalchemy.exc import DBAPIError

    with pytest.raises(DBAPIError) as failed, engine.connect() as conn:
        conn.execute(text("INSERT INTO no_such_table (token) VALUES (:token)"), {"token": secret})
    return str(failed.value)


def test_the_sql_brokers_and_alembics_engines_leave_bound_values_out_of_their_errors(database_url, monkeypatch):
    """The metadata engines hid a statement's bound values from their errors (and logs), but kombu's engine of a SQL
    broker other than SQLite (a message's body: a task's arguments) and the engine alembic migrates with did not.
    Both hide them now."""
    import sqlalchemy
    from alembic import command
    from types import SimpleNamespace

    from voxe_service.broker import Channel
    from voxe_service.db import alembic_config

    client = SimpleNamespace(hostname=database_url, transport_options={"polling_interval": 1.0})
    broker_engine = Channel._engine_from_config(SimpleNamespace(connection=SimpleNamespace(client=client)))
    migrating, engine_from_config = [], sqlalchemy.engine_from_config
    monkeypatch.setattr(sqlalchemy, "engine_from_config",
                        lambda *args, **kwargs: migrating.append(engine_from_config(*args, **kwargs)) or migrating[-1])
    command.upgrade(alembic_config(database_url), "head")
    assert len(migrating) == 1
    try:
        for engine in (broker_engine, migrating[0]):
            error = _error_of_a_statement_binding(engine, "whsec_s3cret")
            assert "no_such_table" in error and "whsec_s3cret" not in error, error
    finally:
        broker_engine.dispose()
        migrating[0].dispose()
