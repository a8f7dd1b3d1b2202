"""Service settings as the deployment sets them: bad values refused at start naming the variable, the docker files
setting only variables the service reads, and the README naming every variable read with the settings' defaults."""

from __future__ import annotations

import logging
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from PIL import Image
from pydantic import TypeAdapter

from voxe_service.queue import INGEST_TASK, STAGE_TASKS, broker_transport_options
from voxe_service.settings import Settings, SettingsError, get_settings

ROOT = Path(__file__).resolve().parents[1]
PILLOW_MOST = 2 * Image.MAX_IMAGE_PIXELS  # larger: Pillow's DecompressionBombError
DEPLOYMENT_FILES = ("docker-compose.yml", "docker/env.example", "docker/api.Dockerfile", "docker/worker.Dockerfile")


@pytest.fixture
def fresh_settings(monkeypatch):
    get_settings.cache_clear()
    yield monkeypatch
    get_settings.cache_clear()


@pytest.mark.parametrize("variable, value, message", [
    ("VOXE_DEVICE", "gpu", "VOXE_DEVICE='gpu': String should match pattern"),  # torch.device failed in every job
    ("VOXE_STORAGE_BACKEND", "s4", "VOXE_STORAGE_BACKEND='s4': Input should be 'local' or 's3'"),
    ("VOXE_MAX_UPLOAD_BYTES", "lots", "VOXE_MAX_UPLOAD_BYTES='lots': Input should be a valid integer"),
    ("VOXE_WORKER_MAX_TASKS_PER_CHILD", "0", "VOXE_WORKER_MAX_TASKS_PER_CHILD='0': Input should be greater than"),
    ("VOXE_DATABASE_MAX_OVERFLOW", "-1", "VOXE_DATABASE_MAX_OVERFLOW='-1': Input should be greater than or equal to 0"),
    ("VOXE_GUIDANCE_CACHE_SIZE", "0", "VOXE_GUIDANCE_CACHE_SIZE='0': Input should be greater than or equal to 1"),
    # an empty folder had been the working directory (/app in the images: artifacts among the service's files)
    ("VOXE_STORAGE_DIR", "", "VOXE_STORAGE_DIR='': must name a folder (unset it for the default)"),
    ("VOXE_WORK_DIR", " ", "VOXE_WORK_DIR=' ': must name a folder"),
    # taken as no loopback host (authentication on) while .ci/serve listened on its default, 127.0.0.1
    ("VOXE_HOST", "", "VOXE_HOST='': must name the address the API listens on (unset it for the default, 127.0.0.1)"),
    # accepted, then every stage failed at its start: timedelta(seconds=inf) overflows
    ("VOXE_STAGE_LEASE_S", "inf", "VOXE_STAGE_LEASE_S='inf': Input should be a finite number"),
    # had failed only when first used, deep in SQLAlchemy, kombu or botocore
    ("VOXE_DATABASE_URL", "postgres://u:S3cret@db/voxe",  # the password not printed
     "VOXE_DATABASE_URL='postgres://***@db/voxe': not a SQLAlchemy database URL (Can't load plugin: "
     "sqlalchemy.dialects:postgres)"),
    # a driver not installed, or an asyncio one: accepted, then the API's start (or its first connection) had failed
    ("VOXE_DATABASE_URL", "mssql+pymssql://u:S3cret@db/voxe", "VOXE_DATABASE_URL='mssql+pymssql://***@db/voxe': the "
                                                              "driver of mssql+pymssql is not installed (No module "
                                                              "named 'pymssql'); e.g. sqlite:///./var/voxe.db or "
                                                              "postgresql+psycopg://user:password@host/db"),
    # (a scheme with a '_' had been shown as a path, '/postgresql+psycopg_async:/***')
    ("VOXE_DATABASE_URL", "postgresql+psycopg_async://u:S3cret@db/voxe?sslmode=require",
     "VOXE_DATABASE_URL='postgresql+psycopg_async://***@db/voxe?sslmode=***': postgresql+psycopg_async is an asyncio "
     "driver; the service connects synchronously: e.g. sqlite:///./var/voxe.db"),
    ("VOXE_BROKER_URL", "sqla+sqlite+aiosqlite:///./var/broker.db", "VOXE_BROKER_URL='sqla+sqlite+aiosqlite:///./var/"
                                                                    "broker.db': sqlite+aiosqlite is an asyncio driver; "
                                                                    "the service connects synchronously: e.g. "
                                                                    "sqla+sqlite:///./var/broker.db"),
    # a base64 password holds '/' and '+': it had been printed whole
    ("VOXE_DATABASE_URL", "postgres://u:S3cret/x+y@db/voxe", "VOXE_DATABASE_URL='postgres://***@db/voxe': not a "
                                                             "SQLAlchemy database URL"),
    # each connection's own empty database: the API's request threads had found no tables, the workers no jobs
    *(("VOXE_DATABASE_URL", url, "': an in-memory SQLite database is each connection's own, empty one, that no "
                                 "other thread or process (the workers) sees; name a file, e.g. sqlite:///./var/voxe.db")
      for url in ("sqlite://", "sqlite:///:memory:", "sqlite+pysqlite:///:memory:",
                  "sqlite:///file:voxe?mode=memory&cache=shared&uri=true",
                  # SQLite's URI filenames of a private database (accepted; the API had found no tables)
                  "sqlite:///file::memory:?uri=true", "sqlite:///file:?uri=true",
                  "sqlite:///file:voxe.db?vfs=memdb&uri=true")),
    # a folder, not a file: accepted, the API's start had failed "unable to open database file", naming no setting
    ("VOXE_DATABASE_URL", "sqlite:////tmp", "VOXE_DATABASE_URL='sqlite:////tmp': names the folder '/tmp', not a "
                                           "database file; name a file in it, e.g. sqlite:///./var/voxe.db"),
    ("VOXE_BROKER_URL", "sqla+sqlite:///./var/", "VOXE_BROKER_URL='sqla+sqlite:///./var/': names the folder 'var', "
                                                 "not a database file; name a file in it, e.g. "
                                                 "sqla+sqlite:///./var/broker.db"),
    # the SQL broker's database, checked as the metadata's: accepted, the API had queued every job in a database of its
    # own that no worker read, or failed each submission as kombu first opened it
    *(("VOXE_BROKER_URL", url, f"VOXE_BROKER_URL={url!r}: an in-memory SQLite database is each connection's own, "
                               f"empty one, that no other thread or process (the workers) sees; name a file, e.g. "
                               f"{url.partition('+')[0]}+sqlite:///./var/broker.db")
      for url in ("sqla+sqlite://", "sqlalchemy+sqlite:///:memory:")),
    ("VOXE_BROKER_URL", "sqla+postgres://u:S3cret@db/voxe",
     "VOXE_BROKER_URL='sqla+postgres://***@db/voxe': not 'sqla+' and a SQLAlchemy database URL (Can't load plugin: "
     "sqlalchemy.dialects:postgres); e.g. sqla+sqlite:///./var/broker.db or sqla+postgresql+psycopg://user:"),
    ("VOXE_BROKER_URL", "valkey://:S3cret/x@cache:6379/0", "VOXE_BROKER_URL='valkey://***@cache:6379/0': not a "
                                                           "broker URL"),
    # no ':' after the user, an '@' in the user, no ':' after the scheme, a password in the query: printed whole
    ("VOXE_DATABASE_URL", "postgres://bob@S3cret@db/voxe", "VOXE_DATABASE_URL='postgres://***@db/voxe': not a "
                                                           "SQLAlchemy database URL"),
    ("VOXE_DATABASE_URL", "postgres://ops@corp:S3cret@db/voxe", "VOXE_DATABASE_URL='postgres://***@db/voxe': not a "
                                                                "SQLAlchemy database URL"),
    ("VOXE_DATABASE_URL", "postgresql//bob:S3cret@db/voxe", "VOXE_DATABASE_URL='/postgresql/***': not a SQLAlchemy "
                                                            "database URL"),
    ("VOXE_DATABASE_URL", "postgres://db/voxe?password=S3cret", "VOXE_DATABASE_URL='postgres://db/voxe?password=***': "
                                                                "not a SQLAlchemy database URL"),
    ("VOXE_BROKER_URL", "valkey://bob@S3cret@cache:6379/0", "VOXE_BROKER_URL='valkey://***@cache:6379/0': not a "
                                                            "broker URL"),
    ("VOXE_BROKER_URL", "redis//:S3cret@cache:6379/0", "VOXE_BROKER_URL='/redis/***': not a broker URL"),
    ("VOXE_BROKER_URL", "sqla+sqlite+aiosqlite:///./S3cret@b.db", "VOXE_BROKER_URL='sqla+sqlite+aiosqlite:///./***': "
                                                                   "sqlite+aiosqlite is an asyncio driver"),
    ("VOXE_BROKER_URL", "redis//localhost:6379", "VOXE_BROKER_URL='redis//localhost:6379': not a broker URL"),
    # the '@host' forgotten: the password read as a port, printed in the value and in SQLAlchemy's (or urllib's) error
    ("VOXE_DATABASE_URL", "postgresql://bob:S3cret/db", "VOXE_DATABASE_URL='postgresql://***': no host: what follows "
                                                        "its ':' is no port number (a password whose '@host' was left "
                                                        "out?); e.g. sqlite:///./var/voxe.db"),
    ("VOXE_DATABASE_URL", "postgresql+psycopg://bob:S3cret/x?sslmode=require", "VOXE_DATABASE_URL='postgresql+psycopg"
                                                                               "://***': no host"),
    ("VOXE_BROKER_URL", "sqla+postgresql://bob:S3cret/db", "VOXE_BROKER_URL='sqla+postgresql://***': no host: what "
                                                           "follows its ':' is no port number"),
    ("VOXE_BROKER_URL", "redis://:S3cret/0", "VOXE_BROKER_URL='redis://***': no host: what follows its ':' is no "
                                             "port number (a password whose '@host' was left out?); e.g. redis://"),
    # an empty model had been a model's name, failing as each job loaded it
    *((variable, value, f"{variable}={value!r}: must name a model: a hub id, a local folder, or tiny (unset it for "
                        "the default)")
      for variable in ("VOXE_SDS_MODEL", "VOXE_ATTENTION_MODEL", "VOXE_CLIP_MODEL") for value in ("", "  ")),
    # recorded in a job's column: accepted, then every submission had failed storing it (a 500 on PostgreSQL)
    *((variable, "/models/" + "m" * 600, "characters, the most a job records (608 given)")
      for variable in ("VOXE_SDS_MODEL", "VOXE_ATTENTION_MODEL")),
    ("VOXE_S3_ENDPOINT_URL", "minio:9000", "VOXE_S3_ENDPOINT_URL='minio:9000': an S3 endpoint is an http://"),
    # accepted, then botocore's bare "Invalid endpoint: http://" (or "not a valid URI") at the storage's first use
    ("VOXE_S3_ENDPOINT_URL", "http://", "VOXE_S3_ENDPOINT_URL='http://': an S3 endpoint is an http:// or https:// "
                                        "URL naming a host"),
    ("VOXE_S3_ENDPOINT_URL", "http://:9000", "VOXE_S3_ENDPOINT_URL='http://:9000': an S3 endpoint is"),
    ("VOXE_S3_ENDPOINT_URL", "http://minio:90000", "VOXE_S3_ENDPOINT_URL='http://minio:90000': an S3 endpoint is"),
    # credentials botocore never sends and prints in its errors (in the logs, and /readyz)
    *(("VOXE_S3_ENDPOINT_URL", endpoint, "VOXE_S3_ENDPOINT_URL='http://***@minio:9000': an S3 endpoint holds no "
                                         "credentials: they come from AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY")
      for endpoint in ("http://ak:S3cret@minio:9000", "http://S3cret@minio:9000")),
    # a host botocore refuses ("Invalid endpoint"), as a compose service named with an underscore is
    *(("VOXE_S3_ENDPOINT_URL", endpoint, f"VOXE_S3_ENDPOINT_URL={endpoint!r}: an S3 endpoint is an http:// or https:// "
                                         "URL naming a host (an IP address, or names of letters, digits and hyphens "
                                         "joined by dots)")
      for endpoint in ("http://minio_1:9000", "http://mi nio:9000", "http://-minio:9000", "http://[::1", "http://a..b")),
    # taken, then botocore's bare "Provided region_name ... doesn't match a supported format" at the storage's first use
    *(("VOXE_S3_REGION", region, f"VOXE_S3_REGION={region!r}: an S3 region is up to 63 letters, digits and hyphens")
      for region in ("eu west 1", "eu-west-1 ", "eu_west_1", "-eu", "r" * 64)),
    # taken, S3 then storing every object under "../x/", "a//b/" or "./" ("/x" quietly read as "x/")
    *(("VOXE_S3_PREFIX", prefix, f"VOXE_S3_PREFIX={prefix!r}: a key prefix is folder names of letters, digits, dots, "
                                 "hyphens and underscores joined by '/' (none of them '.' or '..', no '/' in front), "
                                 "e.g. voxe/prod")
      for prefix in ("../x", "/x", "a//b", ".", "x/..", "x//", "my prefix")),
    ("VOXE_TASK_SOFT_TIME_LIMIT_S", "30000", "VOXE_TASK_SOFT_TIME_LIMIT_S (30000 s) must be below "
                                             "VOXE_TASK_TIME_LIMIT_S (12600 s)"),
    # above Pillow's own limit, an image under the setting had been refused as "huge, over the limit"
    ("VOXE_MAX_IMAGE_PIXELS", "300000000", f"VOXE_MAX_IMAGE_PIXELS='300000000': must be at most {PILLOW_MOST} "
                                           "pixels, the most Pillow opens"),
])
def test_a_bad_setting_is_refused_at_start_naming_its_variable(fresh_settings, variable, value, message):
    """pydantic had named the field (storage_backend), not the variable a deployment sets."""
    fresh_settings.setenv(variable, value)
    with pytest.raises(SettingsError, match=r"^bad service settings: ") as error:
        get_settings()
    assert message in str(error.value) and "S3cret" not in str(error.value), str(error.value)


def test_the_image_pixel_limit_may_reach_the_most_pillow_opens(fresh_settings):
    fresh_settings.setenv("VOXE_MAX_IMAGE_PIXELS", str(PILLOW_MOST))
    assert get_settings().max_image_pixels == PILLOW_MOST


def test_s3_storage_needs_a_bucket_name(fresh_settings):
    fresh_settings.setenv("VOXE_STORAGE_BACKEND", "s3")
    for bucket in ("", "a/b"):  # botocore had refused them at the first upload (an empty one, 33 lines deep)
        fresh_settings.setenv("VOXE_S3_BUCKET", bucket)
        get_settings.cache_clear()
        with pytest.raises(SettingsError, match=f"VOXE_S3_BUCKET='{bucket}' is not an S3 bucket name"):
            get_settings()
    for bucket in ("voxe-artifacts.eu", "Legacy_Bucket"):  # path-style stores take botocore's wider rule
        fresh_settings.setenv("VOXE_S3_BUCKET", bucket)
        get_settings.cache_clear()
        assert get_settings().s3_bucket == bucket


def test_a_model_setting_is_read_without_the_spaces_around_it(fresh_settings):
    """A pasted ' CompVis/stable-diffusion-v1-4 ' had been kept whole: no hub id nor folder, so every worker reported
    it missing (advising to download it) and every job was refused."""
    for variable in ("VOXE_SDS_MODEL", "VOXE_ATTENTION_MODEL", "VOXE_CLIP_MODEL", "VOXE_FID_MODEL"):
        fresh_settings.setenv(variable, " CompVis/stable-diffusion-v1-4  ")
    fresh_settings.setenv("VOXE_FID_MODEL", "  ")  # an empty FID model is its default, the file in VOXE_MODEL_DIR
    settings = get_settings()
    assert (settings.sds_model, settings.attention_model, settings.clip_model, settings.fid_model) == (
        "CompVis/stable-diffusion-v1-4", "CompVis/stable-diffusion-v1-4", "CompVis/stable-diffusion-v1-4", "")


def test_a_model_as_long_as_a_jobs_column_is_accepted_and_one_longer_refused():
    from voxe_service.models import Job

    for setting in ("sds_model", "attention_model"):
        longest = Job.__table__.columns[setting].type.length
        assert getattr(Settings(**{setting: "m" * longest}), setting) == "m" * longest
        with pytest.raises(ValueError, match=f"at most {longest} characters, the most a job records"):
            Settings(**{setting: "m" * (longest + 1)})


def test_a_device_as_long_as_a_jobs_column_is_accepted_and_one_longer_refused(fresh_settings):
    """Recorded in jobs.device: 'cuda:' and 28 digits had been accepted, then every submission failed storing it
    (a 500 on PostgreSQL)."""
    from voxe_service.models import Job

    longest = Job.__table__.columns["device"].type.length
    device = "cuda:" + "1" * (longest - len("cuda:"))
    assert Settings(device=device).device == device
    fresh_settings.setenv("VOXE_DEVICE", device + "1")
    with pytest.raises(SettingsError, match=f"VOXE_DEVICE='{device}1': at most {longest} characters, the most a job "
                                            rf"records \({longest + 1} given\)"):
        get_settings()


def _jobs_after_migrating(url: str) -> int:
    """The jobs in the database at ``url`` once migrated: it opens where the settings say (a fresh one holds 0)."""
    from voxe_service.db import make_engine, run_migrations

    run_migrations(url)
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return connection.exec_driver_sql("SELECT count(*) FROM jobs").scalar_one()
    finally:
        engine.dispose()


def test_sqlite_files_under_the_home_folder_are_opened_there(fresh_settings, tmp_path):
    """SQLite opens '~/vx/voxe.db' as written, under a folder '~' of the working directory: the API had failed to
    start ("unable to open database file"), its folders and migration lock made under the home folder."""
    from voxe_service.broker import waiting_tasks

    home = tmp_path / "home"
    fresh_settings.setenv("HOME", str(home))
    fresh_settings.chdir(tmp_path)
    fresh_settings.setenv("VOXE_DATABASE_URL", "sqlite:///~/vx/voxe.db")
    fresh_settings.setenv("VOXE_BROKER_URL", "sqla+sqlite:///~/vx/broker.db?timeout=5")
    settings = get_settings()
    assert (settings.database_url, settings.broker_url) == (f"sqlite:///{home}/vx/voxe.db",
                                                            f"sqla+sqlite:///{home}/vx/broker.db?timeout=5")
    assert _jobs_after_migrating(settings.database_url) == 0
    assert waiting_tasks(settings.broker_url) == set()
    assert {path.name for path in (home / "vx").iterdir()} >= {"voxe.db", "broker.db"}
    assert not (tmp_path / "~").exists()


def test_a_sqlite_uri_filename_under_the_home_folder_is_opened_there(fresh_settings, tmp_path):
    """``sqlite:///file:~/vx/voxe.db?uri=true``: the folder and the migration lock were made under the home folder
    (settings.sqlite_file expands the '~'), but SQLite was handed the URI as written and opened './~/vx/voxe.db'
    ("unable to open database file"). The '~' is expanded in the URL too, as a plain file name's."""
    from voxe_service.settings import sqlite_file

    home = tmp_path / "home"
    fresh_settings.setenv("HOME", str(home))
    fresh_settings.chdir(tmp_path)
    fresh_settings.setenv("VOXE_DATABASE_URL", "sqlite:///file:~/vx/voxe.db?uri=true")
    settings = get_settings()
    assert sqlite_file(settings.database_url) == home / "vx" / "voxe.db"
    assert _jobs_after_migrating(settings.database_url) == 0
    assert {path.name for path in (home / "vx").iterdir()} >= {"voxe.db", "voxe.db.migrate.lock"}
    assert not (tmp_path / "~").exists()


def test_folders_under_the_home_folder_are_made_there(fresh_settings, tmp_path):
    """VOXE_STORAGE_DIR=~/voxe (as env files and compose pass it: no shell expands it) had stored every artifact under
    a folder named '~' in the working directory; the work and model folders alike."""
    from voxe_service.storage import get_storage

    home = tmp_path / "home"
    fresh_settings.setenv("HOME", str(home))
    fresh_settings.chdir(tmp_path)
    for variable in ("VOXE_STORAGE_DIR", "VOXE_WORK_DIR", "VOXE_MODEL_DIR"):
        fresh_settings.setenv(variable, f"~/{variable.lower()}")
    settings = get_settings()
    assert (settings.storage_dir, settings.work_dir, settings.model_dir) == (
        home / "voxe_storage_dir", home / "voxe_work_dir", home / "voxe_model_dir")
    get_storage(settings).put_bytes("jobs/j/a.txt", b"kept")
    assert (home / "voxe_storage_dir" / "jobs" / "j" / "a.txt").read_bytes() == b"kept"
    assert not (tmp_path / "~").exists()


@pytest.mark.parametrize("variable,value", [("VOXE_STORAGE_DIR", "~{user}/voxe"),
                                            ("VOXE_DATABASE_URL", "sqlite:///~{user}/voxe.db"),
                                            ("VOXE_BROKER_URL", "sqla+sqlite:///file:~{user}/broker.db?uri=true")])
def test_a_home_folder_of_a_user_the_machine_does_not_know_is_a_settings_error(fresh_settings, variable, value):
    """``VOXE_STORAGE_DIR=~nouser/x`` or ``VOXE_DATABASE_URL=sqlite:///~nouser/x.db`` (a user the machine does not
    know) had stopped the start with "RuntimeError: Could not determine home directory", naming no setting."""
    value = value.format(user="voxe-no-such-user")
    fresh_settings.setenv(variable, value)
    with pytest.raises(SettingsError, match=f"{variable}='.*': " + re.escape("'~voxe-no-such-user' is no home folder "
                                                                           "this machine knows (no such user); name "
                                                                           "the folder itself")):
        get_settings()


def test_a_folder_setting_is_read_without_the_spaces_around_it(fresh_settings, tmp_path):
    """VOXE_STORAGE_DIR=' ./var/storage' (pasted, or quoted with a space) had stored every artifact under a folder
    named ' .' of the working directory, and '~/voxe ' under '~/voxe ' (a trailing space in its name)."""
    from voxe_service.storage import get_storage

    fresh_settings.setenv("HOME", str(tmp_path / "home"))
    fresh_settings.chdir(tmp_path)
    fresh_settings.setenv("VOXE_STORAGE_DIR", " ./var/storage ")
    fresh_settings.setenv("VOXE_WORK_DIR", "\t~/work ")
    fresh_settings.setenv("VOXE_MODEL_DIR", f"  {tmp_path / 'models'}\n")
    settings = get_settings()
    assert (settings.storage_dir, settings.work_dir, settings.model_dir) == (
        Path("var/storage"), tmp_path / "home" / "work", tmp_path / "models")
    get_storage(settings).put_bytes("jobs/j/a.txt", b"kept")
    assert (tmp_path / "var" / "storage" / "jobs" / "j" / "a.txt").read_bytes() == b"kept"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["var"]


def test_a_worker_refuses_at_start_a_cuda_device_its_machine_lacks(tmp_path):
    """VOXE_DEVICE=cuda:N past this machine's GPUs (or on one with none) had started the worker, then failed every job
    it took ('Torch not compiled with CUDA enabled', 'invalid device ordinal'); the worker now stops at its start, as
    `celery -A worker.celery_app worker` imports its app."""
    import torch

    from service_helpers import service_env

    def start(device: str) -> subprocess.CompletedProcess:
        env = {**os.environ, **service_env(tmp_path), "VOXE_DEVICE": device, "PYTHONPATH": str(ROOT)}
        return subprocess.run([sys.executable, "-c", "import worker.celery_app"], cwd=ROOT, env=env,
                              capture_output=True, text=True, timeout=120)

    count = torch.cuda.device_count()
    refused = start("cuda:4096")
    have = (f"this machine has {count} CUDA device" if count else
            "CUDA is unavailable on this machine (torch sees no CUDA device); name one it has, or cpu, or auto (CUDA "
            "when available)")
    assert refused.returncode == 1 and refused.stderr.startswith(
        f"Vox-E worker: bad service settings: VOXE_DEVICE='cuda:4096': {have}"), refused.stderr
    started = start("cpu" if not count else f"cuda:{count - 1}")
    assert started.returncode == 0, started.stderr


@pytest.mark.parametrize("command", [
    ["-m", "uvicorn", "api.main:app", "--port", "0"],
    ["-m", "celery", "-A", "worker.celery_app", "worker", "-Q", "gpu"],
], ids=["api", "worker"])
def test_the_api_and_the_worker_refuse_a_bad_setting_in_one_line(tmp_path, command):
    """VOXE_MAX_UPLOAD_BYTES=abc had ended `uvicorn api.main:app` and the Celery worker in a traceback of some thirty
    lines, the variable named on its last; as python -m api.admin does, one line on stderr now names it, exit 1."""
    from service_helpers import service_env

    env = {**os.environ, **service_env(tmp_path), "VOXE_MAX_UPLOAD_BYTES": "abc", "PYTHONPATH": str(ROOT)}
    refused = subprocess.run([sys.executable, *command], cwd=ROOT, env=env, capture_output=True, text=True,
                             timeout=120)
    program = "Vox-E API" if "uvicorn" in command else "Vox-E worker"
    assert refused.returncode == 1, refused.stderr
    assert refused.stderr == (f"{program}: bad service settings: VOXE_MAX_UPLOAD_BYTES='abc': Input should be a valid "
                              "integer, unable to parse string as an integer\n"), refused.stderr


@pytest.mark.parametrize("kind", ["work_dir", "storage_dir", "database_url", "auth"])
def test_the_api_refuses_a_setting_its_startup_finds_bad_in_one_line(tmp_path, kind):
    """A setting refused by the API's startup (its lifespan), not by the settings' parse: uvicorn had printed its
    "Application startup failed" traceback, the variable named on its last line; one line names it now, and uvicorn
    still exits with its startup failure's status (3)."""
    from service_helpers import service_env

    (tmp_path / "a-file").write_text("")
    setting, value, expected = {
        "work_dir": ("VOXE_WORK_DIR", str(tmp_path / "a-file"),
                     f"bad service settings: VOXE_WORK_DIR='{tmp_path / 'a-file'}': cannot make the upload staging "
                     f"folder '{tmp_path / 'a-file' / 'uploads'}': Not a directory"),
        "storage_dir": ("VOXE_STORAGE_DIR", str(tmp_path / "a-file"),
                        f"bad service settings: VOXE_STORAGE_DIR='{tmp_path / 'a-file'}': cannot make the storage "
                        "folder: File exists"),
        "database_url": ("VOXE_DATABASE_URL", "postgresql+psycopg://voxe:s3cret@127.0.0.1:1/voxe",
                         "the database cannot be reached or is locked (VOXE_DATABASE_URL): connection failed: "
                         'connection to server at "127.0.0.1", port 1 failed: Connection refused'),
        "auth": ("VOXE_AUTH", "off", "refusing to start: VOXE_AUTH=off on the non-loopback host '0.0.0.0'; "
                 "authentication may be off only on 127.0.0.1 / ::1 / localhost"),
    }[kind]
    env = {**os.environ, **service_env(tmp_path), setting: value, "VOXE_HOST": "0.0.0.0", "PYTHONPATH": str(ROOT)}
    refused = subprocess.run([sys.executable, "-m", "uvicorn", "api.main:app", "--port", "0"], cwd=ROOT, env=env,
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode == 3, refused.stderr
    assert f"\nVox-E API: {expected}\nERROR:    Application startup failed. Exiting.\n" in (
        refused.stderr), refused.stderr
    assert "Traceback" not in refused.stderr and len(refused.stderr.splitlines()) == 5 - (kind == "auth"), (
        refused.stderr)  # (auth: no "authentication OFF" line, it is refused)


def test_s3_endpoints_naming_a_host_are_accepted():
    for endpoint in ("http://minio:9000", "https://s3.eu-west-1.amazonaws.com", "http://[::1]:9000", "http://10.0.0.5",
                     "http://minio.", "https://s3.example.com/"):
        assert Settings(s3_endpoint_url=endpoint).s3_endpoint_url == endpoint


def test_s3_regions_botocore_takes_are_accepted():
    for region in (None, "us-east-1", "eu-west-1", "auto", "garage", "EU-WEST-1"):  # (R2's "auto", MinIO's own names)
        assert Settings(s3_region=region).s3_region == region
    assert Settings(s3_region="").s3_region is None


def test_s3_prefixes_naming_folders_are_accepted():
    for prefix in ("", "voxe", "voxe/prod", "voxe/prod/", "env_2.1-a"):
        assert Settings(s3_prefix=prefix).s3_prefix == prefix


def test_devices_a_worker_can_use_are_accepted():
    for device in ("auto", "cpu", "cuda", "cuda:3"):
        assert Settings(device=device).device == device


def test_a_visibility_timeout_within_the_hard_limit_is_a_warning_naming_both(caplog):
    redis = "redis://127.0.0.1:6379/0"
    with caplog.at_level(logging.WARNING, logger="voxe.queue"):
        assert broker_transport_options(Settings(broker_url=redis)) == {
            "visibility_timeout": 4 * 3600, "socket_timeout": 5.0, "socket_connect_timeout": 5.0}
        assert not caplog.records  # the defaults nest: 3 h soft, 3.5 h hard, 4 h visibility
        broker_transport_options(Settings(broker_url=redis, broker_visibility_timeout_s=3600))
    (record,) = caplog.records
    assert "VOXE_BROKER_VISIBILITY_TIMEOUT_S (3600 s) is not above VOXE_TASK_TIME_LIMIT_S (12600 s)" in record.message


def test_the_deployment_sets_only_variables_the_service_reads():
    fields = {f"VOXE_{name.upper()}" for name in Settings.model_fields}
    for name in DEPLOYMENT_FILES:
        used = set(re.findall(r"\bVOXE_[A-Z0-9_]+", (ROOT / name).read_text()))
        assert used and used <= fields, f"{name}: {sorted(used - fields)} are not settings"


def test_the_compose_files_fallbacks_are_the_settings_defaults():
    """What a deployment runs with where its .env says nothing (``${VOXE_X:-fallback}``) is the default the README's
    settings table gives for it: a default changed in settings.py alone would leave compose on the old one."""
    fallbacks = re.findall(r"\$\{(VOXE_[A-Z0-9_]+):-([^}]*)\}", (ROOT / "docker-compose.yml").read_text())
    assert fallbacks
    for name, value in fallbacks:
        field = Settings.model_fields[name.removeprefix("VOXE_").lower()]
        assert TypeAdapter(field.annotation).validate_python(value) == field.default, (name, value)


def test_the_readme_names_every_server_the_deployment_runs():
    """Where the README says what docker-compose.yml deploys (its Layout row and its deployment paragraph), each of
    the compose file's servers is named: the Layout row had left out MinIO, where the artifacts are kept."""
    readme = (ROOT / "README.md").read_text()
    layout_row = next(line for line in readme.splitlines() if line.startswith("| `docker/`, `docker-compose.yml` |"))
    deployment = next(line for line in readme.splitlines() if line.startswith("Deployment with "))
    servers = set(yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]) - {"api", "worker"}
    assert {"redis", "postgres", "minio"} <= servers
    for said in (layout_row, deployment):
        assert [server for server in sorted(servers) if server not in said.lower()] == [], said

def test_the_deployment_says_how_to_make_the_key_its_api_requires():
    """The API image listens on every interface, so VOXE_AUTH=auto turns authentication on and every /v1 request is
    a 401 until a key exists: the README's deployment paragraph and the compose file had not said so, nor how to make
    one there (only a comment in api.Dockerfile did). The command they name runs in the api service's image."""
    api_image = (ROOT / "docker/api.Dockerfile").read_text()
    host = re.search(r"^ENV VOXE_HOST=(\S+)$", api_image, re.M)
    assert host and Settings(host=host.group(1)).auth_enabled
    assert re.search(r"^COPY api \./api$", api_image, re.M)  # api/admin.py
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    assert "VOXE_AUTH" not in services["api"]["environment"] and services["api"]["build"]["dockerfile"] == (
        "docker/api.Dockerfile")
    readme = (ROOT / "README.md").read_text()
    deployment = readme.split("\nDeployment with ", 1)[1].split("\n\n", 1)[0]
    command = "docker compose exec api python -m api.admin create-key --name <who>"
    for name, said in (("README.md", " ".join(deployment.split())), ("docker-compose.yml",
                                                                    (ROOT / "docker-compose.yml").read_text())):
        assert command in said, name
    assert "authentication is on" in " ".join(deployment.split())


def test_the_deployments_api_records_the_device_its_workers_run_jobs_on():
    """A job's device is the API's VOXE_DEVICE until a worker starts it (``GET /v1/jobs/{id}``, the web UI's job line):
    compose had given the API cpu and the worker cuda, so every job waiting in the docker deployment said cpu."""
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    devices = {name: services[name]["environment"].get("VOXE_DEVICE") for name in ("api", "worker")}
    assert devices == {"api": "cuda", "worker": "cuda"}, devices


@pytest.mark.parametrize("name", ["docker/worker.Dockerfile", ".ci/serve"])
def test_the_workers_the_project_starts_consume_every_queue_a_task_is_sent_to(name):
    """A task routed to a queue no worker consumes waits there for ever, its job queued."""
    consumed = re.search(r'-Q"?,? ?"?([\w,]+)', (ROOT / name).read_text())
    assert consumed, f"{name} starts no worker with -Q"
    sent = {spec.queue for spec in (*STAGE_TASKS.values(), INGEST_TASK)}
    assert sent <= set(consumed.group(1).split(",")), (name, consumed.group(1))

def test_every_variable_the_service_its_cli_and_scripts_read_is_in_the_readme():
    """Every setting is a row of the README's settings table (and every row a setting, or .ci/serve's own), and every
    other VOXE_ variable the packages or the .ci scripts read is named somewhere in it: the CLI's VOXE_API_KEY, the
    only way besides --api-key to reach a service with authentication on, had been in no README line."""
    readme = (ROOT / "README.md").read_text()
    table = readme.split("### Service settings", 1)[1].split("\n\n| variable |", 1)[1].split("\n\n", 1)[0]
    in_table = {name for row in table.splitlines()[2:]
                for name in re.findall(r"`(VOXE_[A-Z0-9_]+)`", row.split("|")[1])}
    scripts = {name for path in (ROOT / ".ci").iterdir()
               for name in re.findall(r"\$\{?(VOXE_[A-Z0-9_]+)", path.read_text())}
    settings = {f"VOXE_{name.upper()}" for name in Settings.model_fields}
    assert settings <= in_table <= settings | scripts, (sorted(settings - in_table),
                                                         sorted(in_table - settings - scripts))
    for row in table.splitlines()[2:]:  # each default (`5` / `10` / `30`, 20 / 50 GiB, 3 h, –) read back as the settings'
        names, defaults = (cell.strip() for cell in row.split("|")[1:3])
        for name, written in zip(re.findall(r"`([^`]+)`", names), re.split(r" / |, ", defaults), strict=True):
            if name in settings:
                field = Settings.model_fields[name.removeprefix("VOXE_").lower()]
                unset = None if field.default == "" else field.default  # an empty string is as unset
                assert documented_default(written, field.annotation) == unset, (name, written)
    read = set(scripts)
    for package in ("voxe_core", "voxe_client", "voxe_service", "api", "worker"):
        for source in (ROOT / package).rglob("*.py"):
            read |= set(re.findall(r"""(?:environ\.get\(|getenv\(|environ\[)\s*["'](VOXE_[A-Z0-9_]+)""",
                                   source.read_text()))
    assert read and {name for name in read if name not in readme} == set()


UNITS = {"KiB": 1024, "MiB": 1024**2, "GiB": 1024**3, "h": 3600}


def documented_default(written: str, annotation):
    """A default as the settings table writes it: a value in backticks, a number with a unit (2 GiB, 3.5 h), or
    "–" / "(none)" for None, unset or empty (what follows in brackets says what that means)."""
    if re.fullmatch(r"`[^`]+`", written):
        return TypeAdapter(annotation).validate_python(written.strip("`"))
    if number := re.fullmatch(r"(\d+(?:\.\d+)?)(?: (KiB|MiB|GiB|h))?", written):
        return TypeAdapter(annotation).validate_python(float(number.group(1)) * UNITS.get(number.group(2), 1))
    assert re.fullmatch(r"(?:–|\(none\))(?: \(.*\))?", written), f"a default written as {written!r}"
    return None


def test_the_documented_weight_download_works_once_the_workers_are_offline():
    """env.example offers HF_HUB_OFFLINE=1 once the weights are fetched, and compose hands it to every worker
    container, `docker compose run` ones included: the documented `hf download` into the models volume had then
    failed ("offline mode is enabled") for the next model fetched. Each such command turns it off for its own
    container."""
    worker = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]["worker"]["environment"]
    assert worker["HF_HUB_OFFLINE"] == "${HF_HUB_OFFLINE:-0}"  # from .env
    assert re.search(r"^HF_HUB_OFFLINE=", (ROOT / "docker/env.example").read_text(), re.M)
    download = re.compile(r"docker compose run ([^`\n]*?)\bworker hf download ")
    commands = [(name, match.group(1)) for name in ("README.md", "docker-compose.yml", "docker/env.example")
                for match in download.finditer((ROOT / name).read_text())]
    assert len(commands) >= 3
    for name, options in commands:
        words = shlex.split(options)
        overrides = dict(words[i + 1].split("=", 1) for i, word in enumerate(words) if word in ("-e", "--env"))
        offline = subprocess.run(
            [sys.executable, "-c", "from huggingface_hub import constants; print(constants.HF_HUB_OFFLINE)"],
            env={**os.environ, "HF_HUB_OFFLINE": "1", **overrides}, capture_output=True, text=True, check=True)
        assert offline.stdout.strip() == "False", f"{name}: `docker compose run {options}worker hf download` is offline"


def test_the_worker_image_hands_a_running_stage_back_when_stopped():
    """docker stop / Kubernetes send SIGTERM: Celery's warm shutdown waited hours for the stage and was then
    killed with its message unacknowledged (the job left to the reaper); the cold shutdown requeues it at once.
    tests/test_service_faults.py stops a worker so on a real Redis."""
    assert re.search(r"^\s*REMAP_SIGTERM=SIGQUIT\b", (ROOT / "docker/worker.Dockerfile").read_text(), re.M)


def _docker_ignores(path: str, patterns: list[str]) -> bool:
    """Whether ``.dockerignore``'s ``patterns`` keep ``path`` (a file, '/'-separated, from the context's root) out of
    the build context, as Docker matches them: the last pattern matching the path or a folder above it decides
    ('!': kept in); '*' and '?' within a name, '**' across folders; a leading '/' means nothing."""
    def regex(pattern: str) -> str:
        parts = re.split(r"(\*\*/?|\*|\?)", pattern.strip("/"))
        return "".join({"**/": "(?:.*/)?", "**": ".*", "*": "[^/]*", "?": "[^/]"}.get(part, re.escape(part))
                       for part in parts)

    names = path.split("/")
    ignored = False
    for pattern in patterns:
        kept = pattern.startswith("!")
        folders = ("/".join(names[:end]) for end in range(1, len(names) + 1))
        if any(re.fullmatch(regex(pattern.removeprefix("!")), folder) for folder in folders):
            ignored = not kept
    return ignored


def test_the_docker_build_context_holds_what_the_images_copy_and_nothing_the_repository_ignores():
    """The build context had been sent with runs/, bench/.cache, tests/.artifacts, .pytest_cache, build/ and dist/
    (gigabytes of edit runs and caches, to the daemon at every `docker build`): every .gitignore entry, placed at the
    root and in a package, is kept out by .dockerignore, and every tracked file a Dockerfile COPYs is sent."""
    patterns = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
                if line.strip() and not line.startswith("#")]
    for entry in (line.strip() for line in (ROOT / ".gitignore").read_text().splitlines()):
        if not entry or entry.startswith(("#", "!")):
            continue
        name = entry.strip("/").replace("*", "x") + ("/file" if entry.endswith("/") else "")
        places = [name] if "/" in entry.rstrip("/") else [name, f"voxe_core/{name}"]  # (unanchored: at any depth)
        for place in places:
            assert _docker_ignores(place, patterns), f"{place} (.gitignore: {entry}) is sent to the docker daemon"
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for image in ("docker/api.Dockerfile", "docker/worker.Dockerfile"):
        for line in re.findall(r"^COPY\s+(.+)$", (ROOT / image).read_text(), re.M):
            sources = [word for word in line.split()[:-1] if not word.startswith("--")]
            assert sources, line
            for source in sources:
                files = [f for f in tracked if f == source or f.startswith(source.rstrip("/") + "/")]
                assert files, f"{image} copies {source}, which the repository does not hold"
                left_out = [f for f in files if _docker_ignores(f, patterns)]
                assert not left_out, f"{image} copies {source}, but .dockerignore leaves out {left_out[:5]}"


def test_the_images_install_the_torch_the_tests_run():
    """The worker image had installed whatever torch its CUDA index served last (TORCH_SPEC "torch"): a rebuild
    could bring a release nothing here was tested with, and the API and the worker different ones."""
    tested = re.search(r"^TORCH_SPEC=\$\{TORCH_SPEC:-(torch==[^}]+)\}$", (ROOT / ".ci/setup").read_text(), re.M)
    assert tested, ".ci/setup pins no torch version"
    images = ("docker/api.Dockerfile", "docker/worker.Dockerfile")
    pinned = {name: re.findall(r'^ARG TORCH_SPEC="([^"]*)"$', (ROOT / name).read_text(), re.M) for name in images}
    assert pinned == {name: [tested.group(1)] for name in images}
