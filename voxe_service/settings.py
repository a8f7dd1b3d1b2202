"""Service settings, shared by the API and the workers (environment variables prefixed ``VOXE_``).

Every default is the embedded single-machine setup of ``bash .ci/serve``: SQLite
metadata, a SQLite-backed Celery broker (kombu's SQLAlchemy transport), local
artifact storage under ``./var``. docker-compose swaps in PostgreSQL, Redis and
S3-compatible storage (MinIO) through the same variables.
"""

from __future__ import annotations

import ipaddress
import os
import re
import subprocess
import sys
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Literal
from urllib.parse import quote, unquote, urlsplit

from pydantic import Field, ValidationError, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from voxe_core.constants import ATTENTION_MODEL_ID, CLIP_MODEL_ID, INCEPTION_FILE, SDS_MODEL_ID, TINY_MODEL
from voxe_service.keys import is_key

if TYPE_CHECKING:
    from sqlalchemy.engine import URL

TINY_MODEL_LABEL = "tiny (smoke test, random weights)"


class Settings(BaseSettings):
    # inf (and nan) refused: VOXE_STAGE_LEASE_S=inf had started, then failed every stage in timedelta()
    model_config = SettingsConfigDict(env_prefix="VOXE_", extra="ignore", allow_inf_nan=False)

    # --- metadata and queue
    database_url: str = "sqlite:///./var/voxe.db"
    # Connections each process (an API process, a worker) may hold: the pool, plus overflow opened under load and
    # closed when returned. A deployment's processes together must stay under the server's max_connections
    # (PostgreSQL: 100 by default); a request finding all of them busy waits database_pool_timeout_s, then fails.
    database_pool_size: int = Field(5, ge=1)
    database_max_overflow: int = Field(10, ge=0)
    database_pool_timeout_s: float = Field(30.0, gt=0)
    broker_url: str = "sqla+sqlite:///./var/broker.db"
    broker_polling_interval: float = Field(0.5, gt=0, description="seconds between polls of a polling broker (SQL)")
    # Redis: how long a connect or a command may wait for the server. A server that accepts and never answers
    # (hung, partitioned) had blocked a submission for ever, and left a thread behind per /readyz.
    broker_socket_timeout_s: float = Field(5.0, gt=0)

    # --- storage
    storage_backend: Literal["local", "s3"] = "local"
    storage_dir: Path = Path("./var/storage")
    s3_bucket: str = "voxe"
    s3_endpoint_url: str | None = None
    s3_region: str | None = None
    s3_prefix: str = ""
    # S3: how long a connect or a read waits for the endpoint, each of a request's five tries (storage.S3_TRIES). One
    # that accepts and never answers (hung, partitioned) had held a request 60 s a try, six tries, then 503.
    s3_timeout_s: float = Field(10.0, gt=0)
    work_dir: Path = Path("./var/work")  # per-machine scratch: upload staging, worker caches
    model_dir: Path = Path("./var/models")  # where the `tiny` smoke-test model is built, per machine

    # --- models and compute
    sds_model: str = SDS_MODEL_ID
    attention_model: str = ATTENTION_MODEL_ID
    # Evaluation jobs (SPEC §4): a CLIPModel (hub id, folder or `tiny`) and a TorchScript Inception
    # file for FID (path, `tiny`, or empty: <model_dir>/inception-2015-12-05.pt).
    clip_model: str = CLIP_MODEL_ID
    fid_model: str = ""
    device: str = Field("auto", pattern=r"^(auto|cpu|cuda(:\d+)?)$")  # refused at start, not inside every job
    cuda_graphs: bool = True  # the SDS step's UNet (and its VAE encoder, when not compiled) from CUDA graphs on CUDA
    compile_encoder: bool = True  # the SDS step's VAE encoder compiled with torch.compile on CUDA
    # The edit's renders marched in one Triton kernel on CUDA (voxe_core.fused_render): off until bench/gpu.py's
    # section l has measured it against the packed renderer.
    fused_marcher: bool = False
    # Diffusion models (SDS, attention) a worker process keeps loaded; loading one more frees the least recently used.
    # 2: a local job's two, so the next job's edit neither reloads its model nor compiles its encoder again (39 s on
    # the H200) for ~2.1 GB of fp16 weights; 1 on a 12 GB card editing dense scenes (README, "Memory").
    guidance_cache_size: int = Field(2, ge=1)

    # --- uploads
    max_upload_bytes: int = Field(2 * 1024**3, gt=0)
    # A JSON body (a job, sweep or evaluation) is read whole and parsed on the API's event loop: the largest the
    # schemas allow, every string at its longest and each character \\u-escaped, is under 100 KiB.
    max_json_body_bytes: int = Field(1024**2, gt=0)
    max_extracted_bytes: int = Field(8 * 1024**3, gt=0)
    max_upload_files: int = Field(20_000, gt=0)
    validation_downsample: int = Field(8, ge=1)  # images are decoded at 1/8 size to validate an upload
    max_compression_ratio: float = Field(200.0, gt=1)  # a zip entry inflating more than this is a bomb
    max_image_pixels: int = Field(50_000_000, gt=0)  # per image, read from its header before decoding

    # --- access: API keys (python -m api.admin) and per-key quotas
    host: str = "127.0.0.1"  # the address the API listens on (.ci/serve passes it to uvicorn)
    auth: Literal["auto", "on", "off"] = "auto"  # auto: off on a loopback host, on anywhere else
    max_active_jobs_per_key: int = Field(20, ge=1)  # queued + running jobs; a key's own value wins
    max_upload_bytes_per_key: int = Field(50 * 1024**3, ge=1)  # stored scene bytes; a key's own value wins
    quota_retry_after_s: int = Field(60, ge=1)  # the concurrent-job quota's Retry-After (the upload quota has none)

    # --- worker behaviour
    progress_interval_s: float = Field(0.5, gt=0)  # at most one progress write per interval (2/s)
    cancel_check_interval_s: float = Field(0.5, gt=0)
    checkpoint_every: int = Field(200, ge=1)  # iterations between resumable checkpoints
    preview_interval_s: float = Field(30.0, gt=0)
    reconstruction_lease_s: float = Field(120.0, gt=0)  # a running reconstruction not heard from this long is taken over
    # A stage's run holds its job under a lease renewed every quarter of it: a message for a job another run
    # holds (a duplicate) waits for a renewal, then is dropped; a run that stopped renewing is taken over.
    stage_lease_s: float = Field(60.0, gt=0)
    # soft < hard (checked below); the broker's visibility timeout above the hard limit (voxe_service.queue warns).
    task_soft_time_limit_s: int = Field(3 * 3600, gt=0)
    task_time_limit_s: int = Field(int(3.5 * 3600), gt=0)
    broker_visibility_timeout_s: int = Field(4 * 3600, gt=0)
    worker_max_tasks_per_child: int = Field(20, ge=1)
    # Unpacked datasets a worker machine keeps (<work_dir>/scenes): past this, the least recently used that no stage
    # reads are deleted, and unpacked again when a job needs them (4 of the largest uploads VOXE_MAX_EXTRACTED_BYTES
    # allows by default).
    scene_cache_max_bytes: int = Field(32 * 1024**3, gt=0)
    worker_heartbeat_s: float = Field(5.0, gt=0)
    readiness_timeout_s: float = Field(1.0, gt=0)
    # A running job whose worker sent no heartbeat and the job no progress for this long was
    # not redelivered: the API's reaper sends its remaining stages again (api/reaper.py). Also
    # sends queued jobs the API never handed to the broker.
    job_stale_timeout_s: float = Field(900.0, gt=0)
    # A job between stages on a live worker whose next stage has not started for this long, or a queued one sent as
    # long ago: its message is taken as lost without the worker seeing it (a broker that lost what it had accepted)
    # and sent again. Long, as it may wait its turn behind other jobs' on a busy queue; a copy that still comes is
    # dropped or skipped. Doubled for each earlier such re-send of the job; on the SQL broker a job a waiting
    # message carries is never sent again.
    job_lost_message_timeout_s: float = Field(6 * 3600.0, gt=0)
    # A job whose worker stopped mid-stage is sent again (by the reaper, or by its worker restarting) at most
    # this many times; then it fails, so a job that kills its workers cannot loop for ever.
    job_max_requeues: int = Field(3, ge=0)
    # A job's stages (or a scene's ingest) a storage outage stopped are sent back uncounted above, after a pause
    # doubling to 320 s, at most this many times (about half an hour of pauses); the next fails it, naming the outage:
    # a storage object that answers 5xx every time must not be retried for ever.
    storage_outage_max_retries: int = Field(10, ge=0)
    reaper_interval_s: float = Field(60.0, gt=0)
    # What an API process killed while storing an upload (or before recording its scene) left under scenes/<id>/ with
    # no scene row, or a delete whose storage cleanup failed left under jobs/<id>/ or reconstructions/<id>/, an
    # unfinished S3 multipart upload included, is deleted by the reaper once this old: longer than any upload takes
    # to store, so one still being written (or about to be recorded) is never taken.
    orphaned_upload_age_s: float = Field(24 * 3600.0, gt=0)
    # A request's Idempotency-Key record (api.auth.Idempotency) is deleted by the reaper once this old, so the table
    # does not grow for good (voxe_client sends a key with every upload, job, evaluation and sweep): a retry with that
    # key afterwards is a new request. Far longer than a client's retries take (voxe_client's: minutes).
    idempotency_retention_s: float = Field(24 * 3600.0, gt=0)

    # --- webhooks (voxe_service.webhooks; sent from the API process, api/webhooks.py)
    webhook_allow_networks: str = ""  # comma-separated CIDRs a webhook may target though private (e.g. 10.0.0.0/8)
    webhook_timeout_s: float = Field(10.0, gt=0)  # an attempt's deadline: name lookup, connect, send, the whole answer
    webhook_backoff_s: float = Field(5.0, gt=0)  # before the first retry; doubling per attempt
    webhook_max_backoff_s: float = Field(3600.0, gt=0)
    webhook_retry_for_s: float = Field(24 * 3600.0, gt=0)  # after this long since the event, a delivery gives up
    webhook_poll_interval_s: float = Field(0.5, gt=0)
    webhook_concurrency: int = Field(8, ge=1)  # attempts in flight per API process

    @field_validator("s3_endpoint_url", "s3_region", mode="before")
    @classmethod
    def _empty_is_none(cls, value):
        return None if value == "" else value

    @field_validator("storage_dir", "work_dir", "model_dir", mode="before")
    @classmethod
    def _folder_named(cls, value):
        """An empty value (``VOXE_STORAGE_DIR=`` in an env file) had been Path(""), the working directory: the
        artifacts written among the service's own files (/app in the images). A '~' is the home folder, as a shell
        reads it: ``VOXE_STORAGE_DIR=~/voxe`` had stored the artifacts under a folder named '~' in the working one. The
        spaces around it are not the folder's, as a model's are not its (``' ./var'`` had made a folder named ' .')."""
        if isinstance(value, str) and not (value := value.strip()):
            raise ValueError("must name a folder (unset it for the default)")
        return home_expanded(value) if isinstance(value, str | Path) else value

    @field_validator("host")
    @classmethod
    def _host_named(cls, value: str) -> str:
        """An empty one (``VOXE_HOST=`` in an env file) had been taken as a host that is not loopback, authentication
        turned on, while ``bash .ci/serve`` listened on its default, 127.0.0.1, as for an unset one."""
        if not value.strip():
            raise ValueError("must name the address the API listens on (unset it for the default, 127.0.0.1)")
        return value

    @field_validator("sds_model", "attention_model", "clip_model", "fid_model")
    @classmethod
    def _model_named(cls, value: str, info: ValidationInfo) -> str:
        """A model stripped of the spaces around it: ``VOXE_SDS_MODEL=' CompVis/stable-diffusion-v1-4'`` (pasted) had been
        no hub id and no folder, every worker reporting it missing and every job refused, the advice to download what
        was already there. An empty one had been taken as a model's name (VOXE_FID_MODEL's is its default). The SDS and
        attention models are recorded in a job's columns: a longer one had been accepted, then every submission
        failed storing it (a 500 on PostgreSQL)."""
        value = value.strip()
        if not value and info.field_name != "fid_model":
            raise ValueError(f"must name a model: a hub id, a local folder, or {TINY_MODEL} (unset it for the default)")
        return _fits_a_jobs_column(value, info)

    @field_validator("device")
    @classmethod
    def _device_recorded(cls, value: str, info: ValidationInfo) -> str:
        """Recorded in a job's column: 'cuda:' and 28 digits had been accepted, then every submission failed storing
        it (a 500 on PostgreSQL)."""
        return _fits_a_jobs_column(value, info)

    @field_validator("database_url")
    @classmethod
    def _database_url(cls, value: str) -> str:
        return _shared_sqlalchemy_url(value, "./var/voxe.db")

    @field_validator("broker_url")
    @classmethod
    def _broker_url(cls, value: str) -> str:
        from kombu.transport import TRANSPORT_ALIASES

        scheme = value.split("://", 1)[0] if "://" in value else ""
        if scheme.split("+", 1)[0] not in TRANSPORT_ALIASES:
            raise ValueError("not a broker URL; e.g. redis://host:6379/0 or sqla+sqlite:///./var/broker.db")
        if _password_as_port(value):
            raise ValueError(f"{_NO_HOST}; e.g. redis://:password@host:6379/0 or sqla+sqlite:///./var/broker.db")
        transport, plus, url = value.partition("+")
        if transport in ("sqla", "sqlalchemy") and plus:  # the SQL transport's database, checked as the metadata's
            return transport + plus + _shared_sqlalchemy_url(url, "./var/broker.db", transport + plus)
        return value

    @field_validator("s3_endpoint_url")
    @classmethod
    def _endpoint(cls, value: str | None) -> str | None:
        if value is not None and not _http_url_with_host(value):  # (botocore: a bare "Invalid endpoint: http://")
            raise ValueError("an S3 endpoint is an http:// or https:// URL naming a host (an IP address, or names of "
                             "letters, digits and hyphens joined by dots) and a port up to 65535, if any, e.g. "
                             "http://minio:9000")
        if value is not None and "@" in urlsplit(value).netloc:  # (botocore sends none, and prints them in its errors:
            # 'Could not connect to the endpoint URL: "http://ak:S3cret@minio:9000/voxe"', in logs and /readyz)
            raise ValueError("an S3 endpoint holds no credentials: they come from AWS_ACCESS_KEY_ID and "
                             "AWS_SECRET_ACCESS_KEY (or a profile, an instance role), e.g. http://minio:9000")
        return value

    @field_validator("s3_region")
    @classmethod
    def _s3_region(cls, value: str | None) -> str | None:
        """botocore's rule for a region, checked at start: 'eu west 1' or 'eu-west-1 ' had been taken, then botocore's
        bare "Provided region_name ... doesn't match a supported format" failed the API's start and every stage a
        worker ran, naming no setting."""
        from botocore.exceptions import InvalidRegionError
        from botocore.utils import validate_region_name

        try:
            validate_region_name(value)
        except InvalidRegionError:
            raise ValueError("an S3 region is up to 63 letters, digits and hyphens (not all digits, no hyphen first "
                             "or last), e.g. eu-west-1") from None
        return value

    @field_validator("s3_prefix")
    @classmethod
    def _s3_prefix(cls, value: str) -> str:
        """Folders of the bucket, named as a key's are: "../x", "a//b" or "." had been taken, S3 then storing every
        object under those literal names, and "/x" quietly read as "x/"."""
        if value and not is_key(value.removesuffix("/")):
            raise ValueError("a key prefix is folder names of letters, digits, dots, hyphens and underscores joined "
                             "by '/' (none of them '.' or '..', no '/' in front), e.g. voxe/prod")
        return value

    @field_validator("webhook_allow_networks")
    @classmethod
    def _networks(cls, value: str) -> str:
        for network in filter(None, (n.strip() for n in value.split(","))):
            ipaddress.ip_network(network, strict=False)  # a typo fails at startup, not on the first webhook
        return value

    @field_validator("max_image_pixels")
    @classmethod
    def _pillow_decodes(cls, value: int) -> int:
        """At most what Pillow opens (it refuses an image over twice ``Image.MAX_IMAGE_PIXELS`` as a decompression
        bomb): above, an upload under the setting had been refused as "huge, over the limit", and its ingest failed."""
        from PIL import Image

        if Image.MAX_IMAGE_PIXELS is not None and value > 2 * Image.MAX_IMAGE_PIXELS:
            raise ValueError(f"must be at most {2 * Image.MAX_IMAGE_PIXELS} pixels, the most Pillow opens "
                             "(twice its Image.MAX_IMAGE_PIXELS; a larger image is refused as a decompression bomb)")
        return value

    @model_validator(mode="after")
    def _s3_bucket_named(self):
        # botocore's own rule: path-style stores (MinIO, Ceph, GCS interop, old us-east-1 buckets) take more than
        # AWS's 3-63 lowercase letters, digits, dots and hyphens.
        if self.storage_backend == "s3" and not re.fullmatch(r"[a-zA-Z0-9.\-_]{1,255}", self.s3_bucket):
            raise ValueError(f"VOXE_S3_BUCKET={self.s3_bucket!r} is not an S3 bucket name (1-255 letters, digits, "
                             "dots, hyphens and underscores)")
        return self

    @model_validator(mode="after")
    def _soft_limit_first(self):
        if not self.task_soft_time_limit_s < self.task_time_limit_s:
            raise ValueError(f"VOXE_TASK_SOFT_TIME_LIMIT_S ({self.task_soft_time_limit_s} s) must be below "
                             f"VOXE_TASK_TIME_LIMIT_S ({self.task_time_limit_s} s): the soft limit lets a stage "
                             "stop cleanly before the hard limit kills it")
        return self

    @property
    def auth_enabled(self) -> bool:
        return self.auth == "on" or (self.auth == "auto" and not is_loopback(self.host))

    @property
    def webhook_networks(self) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
        return [ipaddress.ip_network(n.strip(), strict=False) for n in self.webhook_allow_networks.split(",")
                if n.strip()]

    @property
    def resolved_device(self) -> str:
        if self.device != "auto":
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"


def _fits_a_jobs_column(value: str, info: ValidationInfo) -> str:
    """``value``, if the job's column of the setting (where there is one) holds it; ValueError otherwise."""
    from voxe_service.models import Job

    column = Job.__table__.columns.get(info.field_name)
    if column is not None and len(value) > column.type.length:
        raise ValueError(f"at most {column.type.length} characters, the most a job records ({len(value)} given)")
    return value


def _shared_sqlalchemy_url(url: str, example_file: str, transport: str = "") -> str:
    """``url`` as the API and the workers open it, a database they share: a SQLAlchemy URL whose dialect SQLAlchemy
    has (nothing connects), a SQLite one naming a file, its '~' expanded (:func:`_sqlite_home_expanded`); ValueError
    otherwise, its examples a SQLite file ``example_file`` and PostgreSQL, written after ``transport`` (the broker's
    ``sqla+``)."""
    from sqlalchemy.engine import make_url

    sqlite = f"{transport}sqlite:///{example_file}"
    examples = f"e.g. {sqlite} or {transport}postgresql+psycopg://user:password@host/db"
    if _password_as_port(url):  # (SQLAlchemy's own error printed it: "invalid literal for int() ...: 's3cret'")
        raise ValueError(f"{_NO_HOST}; {examples}")
    try:
        parsed = make_url(url)
        dialect = parsed.get_dialect()  # the dialect's module only: nothing connects
    except Exception as exc:  # noqa: BLE001 - unparsable, or a dialect SQLAlchemy does not know
        what = f"{transport!r} and a SQLAlchemy database URL" if transport else "a SQLAlchemy database URL"
        raise ValueError(f"not {what} ({exc}); {examples}") from None
    # (each had been taken, then failed the API's start, or every connection, naming no setting)
    if dialect.is_async:
        raise ValueError(f"{parsed.drivername} is an asyncio driver; the service connects synchronously: {examples}")
    try:
        dialect.import_dbapi()
    except ImportError as exc:
        raise ValueError(f"the driver of {parsed.drivername} is not installed ({exc}); {examples}") from None
    if parsed.get_backend_name() == "sqlite" and sqlite_file(parsed) is None:
        # (accepted, the API's request threads had found no tables, "no such table: jobs")
        raise ValueError("an in-memory SQLite database is each connection's own, empty one, that no other thread "
                         f"or process (the workers) sees; name a file, e.g. {sqlite}")
    if (path := sqlite_file(parsed)) is not None and (path.is_dir() or str(parsed.database).endswith("/")):
        # (accepted, the API's start had failed on SQLite's "unable to open database file", naming no setting)
        raise ValueError(f"names the folder {str(path)!r}, not a database file; name a file in it, e.g. {sqlite}")
    return _sqlite_home_expanded(url, parsed)


_NO_HOST = "no host: what follows its ':' is no port number (a password whose '@host' was left out?)"


def _password_as_port(url: str) -> bool:
    """Whether ``url``, holding no '@', has in its authority a ':' followed by no port number:
    ``postgresql://bob:s3cret/db`` (its '@host' forgotten) reads as host 'bob', port 's3cret', the password then
    printed in the parsers' errors."""
    authority = re.split(r"[/?#]", url.partition("://")[2], maxsplit=1)[0]
    port = (authority.partition("]")[2] if authority.startswith("[") else authority).partition(":")[2]
    return "://" in url and "@" not in url and bool(port) and not port.isdigit()


def sqlite_file(url: str | URL) -> Path | None:
    """The file SQLite opens for the SQLite database ``url``, None for another database or an in-memory one. A URI
    filename (``sqlite:///file:./var/voxe.db?uri=true``, SQLAlchemy's uri=true) is read as SQLite reads it: its path,
    percent-decoded, not the URI as written (whose folder had been made, literally 'file:.', beside the working
    directory's ./var)."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return None
    name = parsed.database or ""
    if _uri_filename(parsed):
        name = unquote(urlsplit(name).path)
    if name in ("", ":memory:") or parsed.query.get("mode") == "memory" or parsed.query.get("vfs") == "memdb":
        return None  # (the memdb VFS: a database in the memory of the process, as mode=memory)
    return home_expanded(name)


def home_expanded(name: str | Path) -> Path:
    """``name``, its '~' or '~user' the home folder, as a shell reads it; ValueError where the machine knows no such
    home folder (``~nouser/voxe``, a user it does not know): Path.expanduser's RuntimeError "Could not determine home
    directory" had stopped the service's start naming no setting."""
    path = Path(name)
    try:
        return path.expanduser()
    except RuntimeError:
        raise ValueError(f"{path.parts[0]!r} is no home folder this machine knows (no such user); name the folder "
                         "itself") from None


def _uri_filename(parsed: URL) -> bool:
    """Whether the SQLite URL ``parsed`` names a URI filename (``file:...`` with uri=true), which SQLite reads as a
    URI."""
    from sqlalchemy.util import asbool

    return asbool(parsed.query.get("uri", False)) and (parsed.database or "").startswith("file:")


def _sqlite_home_expanded(url: str, parsed: URL) -> str:
    """``url`` (read as ``parsed``) with the '~' of a SQLite file under the home folder expanded
    (``sqlite:///~/voxe.db``, or the URI filename ``sqlite:///file:~/voxe.db?uri=true``): SQLite opens the name as
    written, under a folder named '~' in the working directory ("unable to open database file"), where the service
    had made the folders and the migration lock under the home folder (:func:`sqlite_file`)."""
    scheme = "file:" if _uri_filename(parsed) else ""
    if parsed.get_backend_name() != "sqlite" or not (parsed.database or "").startswith(f"{scheme}~"):
        return url
    head, slash, rest = parsed.database.removeprefix(scheme).partition("/")
    home = os.path.expanduser(unquote(head) if scheme else head)
    database = f"{scheme}{quote(home) if scheme else home}{slash}{rest}"
    return parsed.set(database=database).render_as_string(hide_password=False)


def _http_url_with_host(url: str) -> bool:
    """Whether ``url`` is an http(s) URL with a host botocore takes (its own rule: 'minio_1' or 'mi nio' had been
    accepted, then its bare "Invalid endpoint" failed the storage's first use) and, if it has a port, a number from 0
    to 65535."""
    from botocore.utils import is_valid_uri

    try:
        parts = urlsplit(url)  # (ValueError for an unclosed '[')
        parts.port  # (raises ValueError for any other port)
    except ValueError:
        return False
    return url.startswith(("http://", "https://")) and bool(parts.hostname) and bool(is_valid_uri(url))


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses (127.0.0.0/8, ::1, and 127.x mapped into IPv6 as a dual-stack
    socket reports it), written with the root's trailing dot or without ("localhost.", as a browser sends it in
    Host); a name other than localhost is not."""
    name = host.strip().strip("[]").lower().removesuffix(".")
    if name == "localhost":
        return True
    try:
        address = ipaddress.ip_address(name)
    except ValueError:
        return False
    return address.is_loopback or (address.version == 6 and address.ipv4_mapped is not None
                                   and address.ipv4_mapped.is_loopback)


def model_label(model: str) -> str:
    """What job records show for a model setting (the smoke-test model is always labelled as such)."""
    return TINY_MODEL_LABEL if model == TINY_MODEL else model


def fid_model_label(model: str) -> str:
    """What job records and evaluation results show for a ``VOXE_FID_MODEL`` setting (empty: the default file)."""
    return model_label(model or f"{INCEPTION_FILE} in VOXE_MODEL_DIR")


def smoke_test_roles(*params: dict) -> list[str]:
    """The scorers ("CLIP", "FID") that evaluations of ``params`` (their ``clip_model`` / ``fid_model`` settings) ran
    as the smoke-test model, for their table to say so (``voxe_core.evaluate.format_table``'s ``smoke_test``): read
    from the settings, as the job records label them, not from the models' marks (a model built before them has
    none)."""
    return [role for role, setting in (("CLIP", "clip_model"), ("FID", "fid_model"))
            if any(p.get(setting) == TINY_MODEL for p in params)]


class SettingsError(ValueError):
    """Environment variables the service cannot start with, each named as it is set."""


def refuse_settings(program: str, error: SettingsError | str) -> int:
    """Say ``error`` in one line on stderr, prefixed with ``program``; the exit status to end with (1). The API, the
    worker and ``python -m api.admin`` share it: the API and the worker had ended in a traceback whose last line named
    the variable. A string: a database that cannot be reached at start (``voxe_service.db.outage_line``)."""
    print(f"{program}: {error}", file=sys.stderr)
    return 1


@lru_cache
def get_settings() -> Settings:
    try:
        return Settings()
    except ValidationError as exc:  # pydantic names the field (storage_backend); say the variable
        problems = [(f"VOXE_{'_'.join(map(str, e['loc'])).upper()}={_shown(e['input'])!r}: " if e["loc"] else "")
                    + e["msg"].removeprefix("Value error, ") for e in exc.errors()]
        raise SettingsError("bad service settings: " + "; ".join(problems)) from None


def check_worker_device(settings: Settings) -> None:
    """Refuse, as a worker starts, a CUDA VOXE_DEVICE this machine has no such device for: 'cuda:3' on a machine of
    one GPU (or of none) had started, then failed every job it took. The devices are counted in a child process:
    CUDA initialised in a prefork pool's parent is unusable in its children."""
    if not settings.device.startswith("cuda"):
        return
    count = int(subprocess.run([sys.executable, "-c", "import torch; print(torch.cuda.device_count())"],
                               capture_output=True, text=True, check=True).stdout)
    if int(settings.device.partition(":")[2] or 0) >= count:
        have = (f"this machine has {count} CUDA device{'s' if count > 1 else ''} (cuda:0 to cuda:{count - 1})"
                if count else "CUDA is unavailable on this machine (torch sees no CUDA device)")
        raise SettingsError(f"bad service settings: VOXE_DEVICE={settings.device!r}: {have}; name one it has, or cpu, "
                            "or auto (CUDA when available)")


def _shown(value):
    """A setting's value as an error may print it: a URL that may carry credentials (an '@' or a query: the database
    and broker URLs hold a password) as :func:`voxe_service.webhooks.log_safe_url` logs it. A rule hiding from the
    first ':' past '://' to the last '@' had printed the password of ``postgres://bob@s3cret@host/db``,
    ``postgres://ops@corp:s3cret@host/db``, ``redis//bob:s3cret@host`` and ``...?password=s3cret`` whole."""
    if isinstance(value, str) and _password_as_port(value):  # (had shown 'postgresql://bob:s3cret/db' whole)
        return value.partition("://")[0] + "://***"
    if isinstance(value, str) and ("@" in value or "?" in value):
        from voxe_service.webhooks import log_safe_url  # (it reads the models: not at the settings' import)

        scheme, written, rest = value.partition("://")
        if written and re.fullmatch(r"[A-Za-z][\w+.-]*", scheme):  # as written: urlsplit reads no scheme with a '_'
            # (had shown 'postgresql+psycopg_async://u:pw@db/voxe' as '/postgresql+psycopg_async:/***')
            return f"{scheme}://{log_safe_url('//' + rest).removeprefix('//')}"
        return log_safe_url(value)
    return value
