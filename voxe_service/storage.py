"""Artifact storage: a small interface with a local-directory and an S3-compatible implementation.

Both the API and the workers use it, so workers never need a filesystem shared with
the API: they download inputs (datasets, grids, checkpoints) by key and upload what
they produce. Writes are atomic (local: temporary name + rename; S3: a PUT is
all-or-nothing) and return the object's size and SHA-256.

Keys are relative POSIX paths (``scenes/<id>/dataset.zip``); ``..``, absolute paths
and backslashes are refused, so a key can never leave the storage root. A key too long
for its backend (a local file name or path, S3's 1024 bytes) is refused before anything
is written.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import re
import shutil
import tempfile
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Generator, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import BinaryIO

from voxe_service.keys import is_key

log = logging.getLogger("voxe.storage")
CHUNK = 1 << 20
S3_KEY_MAX_BYTES = 1024  # S3's (and MinIO's) longest object key, the prefix included


class StorageError(RuntimeError):
    pass


class ObjectNotFound(StorageError, KeyError):
    pass


class StorageUnavailable(StorageError):
    """The store could not serve now (unreachable, timed out, throttled, a 5xx): a retry may succeed. Other
    StorageErrors (a missing bucket, access denied, a bad key) are faults a retry would meet again."""


@dataclass(frozen=True)
class StoredObject:
    key: str
    size: int
    sha256: str


# The key layout: everything of a scene, a job or a reconstruction under its own prefix, so deleting
# one is deleting a prefix. ``name`` "" gives the prefix itself.
SCENES_PREFIX = "scenes/"
"""What every scene's objects lie under (:func:`scene_key`)."""
JOBS_PREFIX = "jobs/"
"""What every job's objects lie under (:func:`job_key`)."""
RECONSTRUCTIONS_PREFIX = "reconstructions/"
"""What every reconstruction's objects lie under (:func:`reconstruction_storage_key`)."""
PROBES_PREFIX = "_probe/"
"""What the readiness probe's object lies under: an older version's probes wrote ``_probe/<uuid>`` objects, one each,
a failed delete leaving it for good (the reaper's sweep takes those)."""
PROBE_KEY = f"{PROBES_PREFIX}ready"
"""The one object the readiness probe writes and reads back (:meth:`Storage.check_writable`)."""


def scene_key(scene_id: str, name: str = "") -> str:
    return f"{SCENES_PREFIX}{scene_id}/{name}"


def job_key(job_id: str, name: str = "") -> str:
    return f"{JOBS_PREFIX}{job_id}/{name}"


def reconstruction_storage_key(reconstruction_id: str, name: str = "") -> str:
    return f"{RECONSTRUCTIONS_PREFIX}{reconstruction_id}/{name}"


def check_key(key: str) -> str:
    if not is_key(key):
        raise StorageError(f"invalid storage key {key!r}")
    return key


def check_range_start(start: int) -> None:
    """ValueError for an ``open_range`` start before the first byte: a suffix range (the last N bytes) is the
    caller's to resolve against the size, as the API does. The local file's seek had failed with a bare EINVAL
    once read, and S3 ignored the malformed Range and sent the whole object."""
    if start < 0:
        raise ValueError(f"open_range: start must be at least 0, got {start} (for the last N bytes, start at "
                         "size - N)")


class Chunks(Iterator[bytes]):
    """An ``open_range`` stream: its chunks, and ``close()`` releasing what it reads from (a file, an S3 connection)
    also before the first chunk is read, when a generator's own ``close()`` runs none of its code."""

    def __init__(self, chunks: Generator[bytes, None, None], release: Callable[[], object]):
        self._chunks, self._release = chunks, release

    def __next__(self) -> bytes:
        return next(self._chunks)

    def close(self) -> None:
        try:
            self._chunks.close()
        finally:
            self._release()


def file_sha256(path: str | os.PathLike) -> tuple[int, str]:
    digest, size = hashlib.sha256(), 0
    with open(path, "rb") as handle:
        while chunk := handle.read(CHUNK):
            digest.update(chunk)
            size += len(chunk)
    return size, digest.hexdigest()


class Storage(ABC):
    """put / get / ranged read / list / delete by key."""

    @abstractmethod
    def put_file(self, key: str, path: str | os.PathLike, content_type: str | None = None) -> StoredObject: ...

    def put_bytes(self, key: str, data: bytes, content_type: str | None = None) -> StoredObject:
        handle = tempfile.NamedTemporaryFile(delete=False)
        try:  # also when the write fails (a full disk): check_writable runs this on every readiness probe
            with handle:
                handle.write(data)
            return self.put_file(key, handle.name, content_type)
        finally:
            os.unlink(handle.name)

    @abstractmethod
    def get_file(self, key: str, dest: str | os.PathLike) -> Path:
        """Download ``key`` to ``dest`` (atomically: a partial download never appears at ``dest``)."""

    @abstractmethod
    def size(self, key: str) -> int: ...

    @abstractmethod
    def open_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        """Bytes ``start`` .. ``end`` (inclusive; None: to the end) as a stream of chunks; none when ``start`` lies
        past the end or ``end`` before ``start``. ValueError for a negative ``start`` (:func:`check_range_start`).
        Read to its end or closed (:class:`Chunks`), it holds no file or connection."""

    @abstractmethod
    def list(self, prefix: str = "") -> list[str]: ...

    @abstractmethod
    def written_at(self, prefix: str = "") -> Iterator[tuple[str, datetime]]:
        """(key, when it was last written, timezone-aware) for each key under ``prefix``, unfinished writes included:
        a local writer's temporary file under its own name, an S3 multipart upload under its key, from its start (a
        key may come twice: an object and an upload). Read as listed (S3: a page at a time), not gathered whole: the
        reaper's sweep reads every stored object's."""

    @abstractmethod
    def discard_unfinished(self, prefix: str, before: datetime) -> list[str]:
        """Abandon each unfinished write under ``prefix`` started (local: last written) before ``before``: a writer
        killed mid-write left it, under a row that lives on (a job sent again after its worker was killed mid-upload)
        or in no ``<id>/`` folder, where only a delete of its prefix had taken it, billed for good (S3's parts) or
        taking disk. Local: its temporary file deleted; S3: its multipart upload aborted. Returns their keys; one
        that fails is logged and stays."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Delete one object; deleting a missing key is not an error."""

    def delete_prefix(self, prefix: str) -> int:
        keys = self.list(prefix)
        for key in keys:
            self.delete(key)
        return len(keys)

    def discard_prefixes(self, *prefixes: str) -> list[str]:
        """Delete what lies under each prefix as cleanup: objects no record refers to any more, so a failure is
        logged (the objects stay behind, harming nothing but space) rather than raised over the caller's answer.
        Returns the prefixes whose delete worked."""
        discarded = []
        for prefix in prefixes:
            try:
                self.delete_prefix(prefix)
            except Exception:  # noqa: BLE001 - see the docstring
                log.warning("could not delete the stored objects under %s", prefix, exc_info=True)
            else:
                discarded.append(prefix)
        return discarded

    def discard(self, key: str) -> None:
        """Delete one object as cleanup, as :meth:`discard_prefixes` deletes prefixes: a failure is logged (a replaced
        artifact's old bytes, a finished fit's checkpoint stay behind) rather than raised over a result already
        recorded."""
        try:
            self.delete(key)
        except Exception:  # noqa: BLE001 - see the docstring
            log.warning("could not delete the stored object %s", key, exc_info=True)

    def exists(self, key: str) -> bool:
        try:
            self.size(key)
            return True
        except ObjectNotFound:
            return False

    def check_writable(self) -> None:
        """Write and read back :data:`PROBE_KEY`; raises StorageError when that fails.

        Always that one object, kept: each probe had written its own ``_probe/<uuid>`` and deleted it, and where the
        delete was denied or failed one object a probe stayed for good (a probe every few seconds). Probes at once
        (threads, replicas) write the same bytes, and none deletes what another reads back."""
        try:
            self.put_bytes(PROBE_KEY, b"ok")
            if b"".join(self.open_range(PROBE_KEY)) != b"ok":
                raise StorageError("probe object read back wrong")
        except OSError as exc:  # a local disk (or an upload's temporary file) that cannot be written or read
            raise StorageError(f"storage probe failed: {exc}") from exc

    def describe(self) -> str:
        return type(self).__name__


class LocalStorage(Storage):
    """Objects are files under ``root``."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.name_max, self.path_max = _name_and_path_max(self.root)

    def path(self, key: str) -> Path:
        """The object's file; StorageError for a key no file can be named by."""
        return self._named(key)

    def _named(self, key: str, extra: int = 0) -> Path:
        """The key's file, StorageError naming the limit when it, or a name ``extra`` characters longer (the
        temporary file put_file writes first), is more than the filesystem takes: a bare ENAMETOOLONG had come from
        deep in a write, its folders already made."""
        path = self.root / check_key(key)
        *folders, name = key.split("/")
        why = f" ({self.name_max} less the {extra} of the temporary name it is written under)" if extra else ""
        if len(longest := max(folders, key=len, default="")) > self.name_max:
            raise _too_long(key, f"its folder {longest[:40]!r}... is {len(longest)} characters, the most a file "
                                 f"name takes here is {self.name_max}")
        if len(name) + extra > self.name_max:
            raise _too_long(key, f"its name is {len(name)} characters, the most here is {self.name_max - extra}{why}")
        if len(os.fsencode(path)) + extra >= self.path_max:
            raise _too_long(key, f"under {self.root} it makes a path of {len(os.fsencode(path))} bytes, the most "
                                 f"here is {self.path_max - extra - 1} ({self.path_max} less the terminating byte"
                                 + (f" and the temporary name's {extra})" if extra else ")"))
        return path

    def put_file(self, key, path, content_type=None) -> StoredObject:
        target = self._named(key, _TEMPORARY_EXTRA)
        tmp = _temporary_sibling(target)
        digest, size = hashlib.sha256(), 0
        try:
            with open(path, "rb") as src, _create_in_folder(tmp) as dst:
                while chunk := src.read(CHUNK):
                    digest.update(chunk)
                    size += len(chunk)
                    dst.write(chunk)
                dst.flush()
                os.fsync(dst.fileno())
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        _sync_folders(target.parent, self.root)
        return StoredObject(key, size, digest.hexdigest())

    def _open(self, key: str) -> BinaryIO:
        """The object's file, open for reading: opened at once, not after a check that it exists, which a
        concurrent delete() could make stale."""
        try:
            return open(self.path(key), "rb")
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError) as exc:
            raise ObjectNotFound(key) from exc

    def get_file(self, key, dest) -> Path:
        with self._open(key) as source:
            dest = Path(dest)
            dest.parent.mkdir(parents=True, exist_ok=True)
            tmp = _temporary_sibling(dest)
            try:
                with open(tmp, "wb") as copy:
                    shutil.copyfileobj(source, copy, CHUNK)
                os.replace(tmp, dest)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
        return dest

    def size(self, key) -> int:
        with self._open(key) as source:
            return os.fstat(source.fileno()).st_size

    def open_range(self, key, start=0, end=None) -> Iterator[bytes]:
        check_range_start(start)
        handle = self._open(key)

        def chunks() -> Iterator[bytes]:
            with handle:
                handle.seek(start)
                remaining = None if end is None else end - start + 1
                while remaining is None or remaining > 0:
                    chunk = handle.read(CHUNK if remaining is None else min(CHUNK, remaining))
                    if not chunk:
                        break
                    if remaining is not None:
                        remaining -= len(chunk)
                    yield chunk

        return Chunks(chunks(), handle.close)

    def _files(self, prefix: str) -> Iterator[tuple[str, bool]]:
        """(name under the root, whether it is a writer's temporary file) of each file whose name starts with
        ``prefix``; only the prefix's own folder is walked (a job's listing does not read every other job's), a
        folder at a time as read: the reaper's sweep reads every stored file's (the whole walk had been gathered
        first, some 260 bytes a file: a store of millions held hundreds of MB in the API process)."""
        folder = prefix.rpartition("/")[0]
        try:
            base = self.path(folder) if folder else self.root
        except StorageError:  # no key lies under a folder no key can name ("a//", "./")
            return
        if not base.is_dir():
            return
        for walked, _, names in os.walk(base, onerror=_unless_vanished):
            for name in names:
                if (key := (Path(walked) / name).relative_to(self.root).as_posix()).startswith(prefix):
                    yield key, bool(_WRITING.match(name))

    def list(self, prefix="") -> list[str]:
        return sorted(name for name, writing in self._files(prefix) if not writing)

    def written_at(self, prefix="") -> Iterator[tuple[str, datetime]]:
        for name, _writing in self._files(prefix):
            try:
                yield name, datetime.fromtimestamp((self.root / name).stat().st_mtime, timezone.utc)
            except FileNotFoundError:  # deleted (or renamed into place) since it was listed
                continue

    def discard_unfinished(self, prefix, before) -> list[str]:
        discarded = []
        for name, writing in self._files(prefix):
            try:
                if writing and datetime.fromtimestamp((self.root / name).stat().st_mtime, timezone.utc) < before:
                    (self.root / name).unlink()
                    discarded.append(name)
            except FileNotFoundError:  # renamed into place, or deleted, since it was listed
                continue
            except OSError:
                log.warning("could not delete the unfinished write %s", name, exc_info=True)
        return discarded

    def delete_prefix(self, prefix: str) -> int:
        """Also removes the temporary files of writers killed mid-write under ``prefix`` (never listed)."""
        count = super().delete_prefix(prefix)
        for name in [name for name, writing in self._files(prefix) if writing]:  # (not deleted as the walk goes on)
            self.delete(name)
        return count

    def delete(self, key) -> None:
        target = self.path(key)
        try:
            target.unlink(missing_ok=True)
        except (IsADirectoryError, NotADirectoryError):  # a folder's name, or a name under a file: no object, which
            return  # S3 deletes as quietly as a missing one (had raised, failing a cleanup the S3 storage let pass)
        parent = target.parent
        while parent != self.root:  # drop emptied folders
            try:
                parent.rmdir()
            except OSError:
                break
            parent = parent.parent

    def describe(self) -> str:
        return f"local:{self.root}"


def _temporary_sibling(path: Path) -> Path:
    """Where ``path`` is written before it is renamed into place: ``.<name>.<uuid hex>.tmp`` beside it."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")


_TEMPORARY_EXTRA = len(_temporary_sibling(Path("x")).name) - 1
"""What the temporary name adds to a name's length (38 characters)."""
_WRITING = re.compile(r"^\..+\.[0-9a-f]{32}\.tmp$")
"""The name of a file being written (:func:`_temporary_sibling`'s): never a key, whereas any other name ending in
``.tmp`` is one, as on S3."""


def _name_and_path_max(root: Path) -> tuple[int, int]:
    """The longest file name and path, in bytes, the filesystem under ``root`` takes (Linux's 255 and 4096 where it
    cannot be asked)."""
    try:
        return os.pathconf(root, "PC_NAME_MAX"), os.pathconf(root, "PC_PATH_MAX")
    except (AttributeError, OSError, ValueError):  # no pathconf (Windows), or a filesystem that does not say
        return 255, 4096


def _too_long(key: str, why: str) -> StorageError:
    """The error for a key over a backend's limit ``why``, a long key shown by its ends."""
    shown = key if len(key) <= 120 else f"{key[:100]}...{key[-16:]}"
    return StorageError(f"storage key {shown!r} ({len(key)} characters) is too long: {why}")


_CREATE_ATTEMPTS = 3


def _create_in_folder(path: Path) -> BinaryIO:
    """``path`` opened for writing, its folders made first. A concurrent delete() removes the folders it empties,
    which can be these: before the open (FileNotFoundError), or inside mkdir, after it found one there and before
    it checked that one is a folder (FileExistsError). Then all is done again."""
    attempts_left = _CREATE_ATTEMPTS
    while True:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            return open(path, "wb")
        except (FileNotFoundError, FileExistsError):
            attempts_left -= 1
            if not attempts_left:
                raise


def _sync_folders(folder: Path, root: Path) -> None:
    """fsync ``folder`` and each folder above it up to ``root``: a rename, and a folder made for it, reach the disk
    only with the folder holding their entries, and a power loss had been able to lose an object whose record was
    written. Skipped where a folder cannot be opened (Windows) or synced (EINVAL, ENOTSUP); a folder a concurrent
    delete() removed holds nothing left to keep."""
    if not hasattr(os, "O_DIRECTORY"):
        return
    while True:
        try:
            descriptor = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        except FileNotFoundError:
            return
        try:
            os.fsync(descriptor)
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.ENOTSUP):
                return
            raise
        finally:
            os.close(descriptor)
        if folder == root:
            return
        folder = folder.parent


def _unless_vanished(error: OSError) -> None:
    """os.walk's error handler: a folder a concurrent delete() removed while the walk went on holds no files; any
    other error is raised."""
    if not isinstance(error, FileNotFoundError):
        raise error


S3_TRIES = 5
"""Tries of each S3 request, the first included (botocore's ``max_attempts`` counts the retries alone: 5 had made 6,
a silent endpoint holding a request 6 times VOXE_S3_TIMEOUT_S)."""


class S3Storage(Storage):
    """Objects in an S3-compatible bucket (AWS S3, MinIO, ...) through boto3.

    Credentials come from boto3's usual chain (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY,
    a profile, an instance role); never from the service settings. The SHA-256 of each
    object is stored as object metadata. Keys are checked against S3's 1,024-byte limit
    (:data:`S3_KEY_MAX_BYTES`); a store may limit more (SeaweedFS takes each "/"-separated
    part up to 255 bytes, as a file name, and refuses a longer one with KeyTooLongError;
    the service's own keys' parts are far shorter). ``timeout``: the seconds a connect or a read
    waits for the endpoint, each of a request's :data:`S3_TRIES` tries (the service's VOXE_S3_TIMEOUT_S; 60 is
    botocore's own); a request with a body waits 1 s more a try, botocore's wait for the endpoint's 100 Continue.
    A read's timeout bounds each wait for the next bytes, not the request: an endpoint trickling its body holds it.
    """

    def __init__(self, bucket: str, endpoint_url: str | None = None, region: str | None = None,
                 prefix: str = "", create_bucket: bool = True, client=None, timeout: float = 60.0):
        import boto3
        from botocore.config import Config

        self.bucket = bucket
        self.prefix = prefix.strip("/") + "/" if prefix.strip("/") else ""
        self.client = client or boto3.client(
            "s3", endpoint_url=endpoint_url, region_name=region,
            config=Config(retries={"total_max_attempts": S3_TRIES, "mode": "standard"}, s3={"addressing_style": "path"},
                          connect_timeout=timeout, read_timeout=timeout),
        )
        if create_bucket:
            self._ensure_bucket()

    def _ensure_bucket(self) -> None:
        """Creates the bucket when it is missing; a failure is a StorageError naming the setting to look at."""
        from botocore.exceptions import BotoCoreError, ClientError

        region = self.client.meta.region_name
        try:
            try:
                self.client.head_bucket(Bucket=self.bucket)
                return
            except ClientError as exc:
                if _error_code(exc) not in _NO_SUCH_BUCKET:
                    raise StorageError(f"bucket {self.bucket!r} is not accessible (VOXE_S3_BUCKET and the S3 "
                                       f"credentials): {exc}") from exc
            # Outside us-east-1, S3 refuses to create a bucket whose request does not name its region.
            location = {} if region in (None, "us-east-1") else {
                "CreateBucketConfiguration": {"LocationConstraint": region}}
            try:
                self.client.create_bucket(Bucket=self.bucket, **location)
            except ClientError as exc:
                if _error_code(exc) not in ("BucketAlreadyOwnedByYou", "BucketAlreadyExists"):  # another was first
                    raise StorageError(f"could not create bucket {self.bucket!r} in region {region} "
                                       f"(VOXE_S3_BUCKET, VOXE_S3_REGION): {exc}") from exc
        except BotoCoreError as exc:  # no answer: a wrong or unreachable endpoint, missing credentials, ...
            raise StorageError(f"could not use S3 at {self.client.meta.endpoint_url} (VOXE_S3_ENDPOINT_URL, "
                               f"VOXE_S3_REGION): {exc}") from exc

    @contextmanager
    def _as_storage_errors(self, key: str | None = None) -> Iterator[None]:
        """Raises what boto3 raises as this module's errors: ObjectNotFound when ``key`` is missing, StorageError
        for anything else (a missing bucket, a refused request, an unreachable endpoint)."""
        from boto3.exceptions import Boto3Error, RetriesExceededError
        from botocore.exceptions import BotoCoreError, ClientError, ConnectionError, HTTPClientError

        try:
            yield
        except ClientError as exc:
            code = _error_code(exc)
            if key is not None and code in _HEAD_NOT_FOUND:
                # A HEAD answers a missing bucket with this same bare 404: ask the bucket.
                with self._as_storage_errors():
                    self.client.head_bucket(Bucket=self.bucket)
                raise ObjectNotFound(key) from exc
            if key is not None and code == "NoSuchKey":
                raise ObjectNotFound(key) from exc
            if code in _NO_SUCH_BUCKET:  # (a bare 404 with no key at stake is the bucket's)
                raise StorageError(f"bucket {self.bucket!r} does not exist (VOXE_S3_BUCKET)") from exc
            status = exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode") or 0
            transient = code in _TRANSIENT or status == 429 or status >= 500  # (429: Too Many Requests, any code)
            raise (StorageUnavailable if transient else StorageError)(f"S3 bucket {self.bucket!r}: {exc}") from exc
        except (ConnectionError, HTTPClientError) as exc:  # unreachable, refused, timed out: botocore's own
            raise StorageUnavailable(f"S3 bucket {self.bucket!r}: {exc}") from exc
        except RetriesExceededError as exc:  # a download whose body broke off (reset, timed out) on every retry
            raise StorageUnavailable(f"S3 bucket {self.bucket!r}: a download broke off on every retry: "
                                     f"{type(exc.last_exception).__name__}: {exc.last_exception}") from exc
        except (BotoCoreError, Boto3Error) as exc:
            raise StorageError(f"S3 bucket {self.bucket!r}: {exc}") from exc

    def _full(self, key: str) -> str:
        """The object's key in the bucket; StorageError for one over S3's limit (moto stores it, S3 refuses it)."""
        full = self.prefix + check_key(key)
        if len(full.encode()) > S3_KEY_MAX_BYTES:
            raise _too_long(key, f"with the prefix {self.prefix!r} it is {len(full.encode())} bytes, the most an S3 "
                                 f"key takes is {S3_KEY_MAX_BYTES}")
        return full

    def put_file(self, key, path, content_type=None) -> StoredObject:
        from boto3.exceptions import S3UploadFailedError
        from botocore.exceptions import ClientError

        size, sha = file_sha256(path)
        extra = {"Metadata": {"sha256": sha}}
        if content_type:
            extra["ContentType"] = content_type
        with self._as_storage_errors():
            try:
                self.client.upload_file(str(path), self.bucket, self._full(key), ExtraArgs=extra)
            except S3UploadFailedError as exc:
                # boto3 wraps a refused PUT's ClientError in this (keeping it only as the context): raised as itself,
                # a throttled or failing PUT is a StorageUnavailable and a missing bucket is named, as elsewhere
                if isinstance(exc.__context__, ClientError):
                    raise exc.__context__ from None
                raise
        return StoredObject(key, size, sha)

    def get_file(self, key, dest) -> Path:
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = _temporary_sibling(dest)
        try:
            with self._as_storage_errors(key):
                self.client.download_file(self.bucket, self._full(key), str(tmp))
            os.replace(tmp, dest)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return dest

    def size(self, key) -> int:
        with self._as_storage_errors(key):
            return int(self.client.head_object(Bucket=self.bucket, Key=self._full(key))["ContentLength"])

    def open_range(self, key, start=0, end=None) -> Iterator[bytes]:
        from botocore.exceptions import ClientError

        check_range_start(start)
        if end is not None and end < start:  # S3 would ignore such a range and send everything
            self.size(key)  # (ObjectNotFound still applies)
            return iter(())
        kwargs = {}
        if start or end is not None:
            kwargs["Range"] = f"bytes={start}-{'' if end is None else end}"
        with self._as_storage_errors(key):
            try:
                body = self.client.get_object(Bucket=self.bucket, Key=self._full(key), **kwargs)["Body"]
            except ClientError as exc:
                if _error_code(exc) != "InvalidRange":
                    raise
                return iter(())  # the range starts past the end: no bytes

        def chunks() -> Iterator[bytes]:
            with self._as_storage_errors():
                try:
                    yield from body.iter_chunks(CHUNK)
                finally:
                    body.close()

        return Chunks(chunks(), body.close)

    def list(self, prefix="") -> list[str]:
        if not _may_start_a_key(prefix):
            return []
        keys = []
        paginator = self.client.get_paginator("list_objects_v2")
        with self._as_storage_errors():
            for page in paginator.paginate(Bucket=self.bucket, Prefix=self.prefix + prefix):
                keys += [obj["Key"][len(self.prefix):] for obj in page.get("Contents", [])]
        return sorted(keys)

    def written_at(self, prefix="") -> Iterator[tuple[str, datetime]]:
        if not _may_start_a_key(prefix):
            return
        with self._as_storage_errors():
            for page in self.client.get_paginator("list_objects_v2").paginate(Bucket=self.bucket,
                                                                               Prefix=self.prefix + prefix):
                yield from ((obj["Key"][len(self.prefix):], obj["LastModified"]) for obj in page.get("Contents", []))
        try:
            with self._as_storage_errors():
                for page in self.client.get_paginator("list_multipart_uploads").paginate(Bucket=self.bucket,
                                                                                          Prefix=self.prefix + prefix):
                    yield from ((upload["Key"][len(self.prefix):], upload["Initiated"])
                                for upload in page.get("Uploads", []))
        except StorageError as exc:  # a role without the multipart permissions: the objects' times still count
            log.warning("could not list the unfinished uploads under %r (%s)", prefix, exc)

    def delete(self, key) -> None:
        with self._as_storage_errors():
            self.client.delete_object(Bucket=self.bucket, Key=self._full(key))

    def delete_prefix(self, prefix: str) -> int:
        if not _may_start_a_key(prefix):
            return 0
        try:
            self._abort_uploads(prefix)  # first: one completing meanwhile is an object, listed next
        except StorageError as exc:  # a best effort: a role without the multipart permissions must not keep objects
            log.warning("could not abort the unfinished uploads under %r (%s): their parts stay until a lifecycle "
                        "rule aborts them", prefix, exc)
        keys = self.list(prefix)
        for start in range(0, len(keys), 1000):
            batch = [{"Key": self.prefix + k} for k in keys[start:start + 1000]]
            with self._as_storage_errors():
                answer = self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})
            errors = answer.get("Errors", [])
            if errors:  # S3 answers 200 and lists the objects it kept: left behind, as a local failure raises
                shown = ", ".join(f"{e.get('Key')} ({e.get('Code')})" for e in errors[:3])
                raise StorageError(f"could not delete {len(errors)} object(s) under {prefix!r}: {shown}")
        return len(keys)

    def discard_unfinished(self, prefix, before) -> list[str]:
        if not _may_start_a_key(prefix):
            return []
        try:
            return self._abort_uploads(prefix, before)
        except StorageError as exc:  # (a role without the multipart permissions, the store down: the next sweep)
            log.warning("could not abort the unfinished uploads under %r (%s)", prefix, exc)
            return []

    def _abort_uploads(self, prefix: str, before: datetime | None = None) -> list[str]:
        """Abort the multipart uploads under ``prefix`` that never completed (those started before ``before``, if
        given): a writer killed mid-upload (a worker killed for memory) leaves its parts stored, and billed, under no
        object a listing shows, until aborted. Returns their keys."""
        from botocore.exceptions import ClientError

        aborted = []
        paginator = self.client.get_paginator("list_multipart_uploads")
        with self._as_storage_errors():
            for page in paginator.paginate(Bucket=self.bucket, Prefix=self.prefix + prefix):
                for upload in page.get("Uploads", []):
                    if before is not None and upload["Initiated"] >= before:
                        continue
                    try:
                        self.client.abort_multipart_upload(Bucket=self.bucket, Key=upload["Key"],
                                                           UploadId=upload["UploadId"])
                    except ClientError as exc:
                        if _error_code(exc) != "NoSuchUpload":  # (completed or aborted since it was listed)
                            raise
                    aborted.append(upload["Key"][len(self.prefix):])
        return aborted

    def describe(self) -> str:
        return f"s3:{self.bucket}/{self.prefix}"


def _may_start_a_key(prefix: str) -> bool:
    """Whether some key starts with ``prefix``. One no key can start with ("jobs//a", "./") is never sent: an
    S3-compatible store may read it as another (SeaweedFS lists "jobs//a" as the objects under "jobs/a", under keys
    that are not theirs, and a prefix's delete would take them), as a local folder no key names holds nothing."""
    return is_key(prefix + "x")


_HEAD_NOT_FOUND = ("404", "NotFound")
"""The codes of a 404 with no body (a HEAD's): a missing key or a missing bucket."""
_NO_SUCH_BUCKET = ("NoSuchBucket", *_HEAD_NOT_FOUND)
_TRANSIENT = ("SlowDown", "Throttling", "ThrottlingException", "RequestTimeout", "ServiceUnavailable", "InternalError")


def _error_code(exc) -> str | None:
    return exc.response.get("Error", {}).get("Code")


_instances: dict[tuple, Storage] = {}


def get_storage(settings=None) -> Storage:
    """The storage the settings describe (one instance per configuration and process); SettingsError naming
    VOXE_STORAGE_DIR where its folder cannot be made (the API's startup had ended in an OSError's traceback)."""
    from voxe_service.settings import SettingsError, get_settings

    settings = settings or get_settings()
    if settings.storage_backend == "s3":
        key = ("s3", settings.s3_bucket, settings.s3_endpoint_url, settings.s3_region, settings.s3_prefix,
               settings.s3_timeout_s)
        if key not in _instances:
            _instances[key] = S3Storage(settings.s3_bucket, settings.s3_endpoint_url, settings.s3_region,
                                        settings.s3_prefix, timeout=settings.s3_timeout_s)
    else:
        key = ("local", str(Path(settings.storage_dir).resolve()))
        if key not in _instances:
            try:
                _instances[key] = LocalStorage(settings.storage_dir)
            except OSError as exc:
                raise SettingsError(f"bad service settings: VOXE_STORAGE_DIR={str(settings.storage_dir)!r}: cannot "
                                    f"make the storage folder: {exc.strerror}") from None
    return _instances[key]
