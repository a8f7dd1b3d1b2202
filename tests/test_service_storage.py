"""The storage layer: the local-directory and the S3 implementation, the latter against moto's server (AWS's
emulator) and SeaweedFS (a real S3-compatible server), both over real HTTP."""

from __future__ import annotations

import builtins
import errno
import hashlib
import os
import stat
import tempfile
from pathlib import Path

import pytest

from voxe_service.storage import PROBE_KEY, LocalStorage, ObjectNotFound, S3Storage, StorageError, check_key
from service_helpers import free_port, moto_s3


@pytest.fixture(scope="module")
def moto_endpoint():
    with moto_s3() as env:
        yield env["VOXE_S3_ENDPOINT_URL"]


S3_SERVERS = ["moto", "seaweedfs"]  # AWS's emulator, and a real S3-compatible server


def s3_server_endpoint(request, server: str) -> str:
    if server == "moto":
        return request.getfixturevalue("moto_endpoint")
    return request.getfixturevalue("seaweedfs")["VOXE_S3_ENDPOINT_URL"]


@pytest.fixture(params=S3_SERVERS)
def s3_server(request) -> str:
    return request.param


@pytest.fixture
def s3_endpoint(request, s3_server) -> str:
    return s3_server_endpoint(request, s3_server)


@pytest.fixture
def aws_env(monkeypatch):
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    for name in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture(params=["local", *S3_SERVERS])
def storage(request, tmp_path):
    if request.param == "local":
        return LocalStorage(tmp_path / "store")
    request.getfixturevalue("aws_env")
    endpoint = s3_server_endpoint(request, request.param)
    return S3Storage(f"voxe-test-{request.node.name.split('[')[0].replace('_', '-')[:40]}", endpoint_url=endpoint,
                     region="us-east-1", prefix="svc")


def test_written_at_gives_each_keys_time_unfinished_writes_included(storage, tmp_path):
    """The reaper's sweep of uploads no scene records reads their ages here: each listed key's, and an unfinished
    write's (a killed local writer's temporary file; an S3 multipart upload, from its start) under its key, so the
    parts a killed API process left are found and aborted; the store's own prefix is not in the keys."""
    from datetime import datetime, timedelta, timezone

    storage.put_bytes("scenes/a/dataset.zip", b"zip")
    storage.put_bytes("jobs/b/x.bin", b"x")
    if isinstance(storage, LocalStorage):
        unfinished = "scenes/c/.dataset.zip.0123456789abcdef0123456789abcdef.tmp"
        storage.root.joinpath(unfinished).parent.mkdir(parents=True)
        storage.root.joinpath(unfinished).write_bytes(b"z")
    else:
        unfinished = "scenes/c/dataset.zip"
        upload = storage.client.create_multipart_upload(Bucket=storage.bucket, Key=storage.prefix + unfinished)
    try:
        times = dict(storage.written_at("scenes/"))
        assert times.keys() == {"scenes/a/dataset.zip", unfinished}
        now = datetime.now(timezone.utc)
        assert abs(times["scenes/a/dataset.zip"] - now) < timedelta(minutes=1)
        assert list(storage.written_at("scenes//")) == [] and list(storage.written_at("nothing/")) == []
    finally:
        if not isinstance(storage, LocalStorage):
            storage.client.abort_multipart_upload(Bucket=storage.bucket, Key=upload["Key"], UploadId=upload["UploadId"])


def test_put_get_range_list_delete(storage, tmp_path):
    data = bytes(range(256)) * 4100  # > one 1 MiB chunk
    source = tmp_path / "blob.bin"
    source.write_bytes(data)
    stored = storage.put_file("jobs/a/blob.bin", source, "application/octet-stream")
    assert stored.size == len(data) and stored.sha256 == hashlib.sha256(data).hexdigest()
    assert storage.size("jobs/a/blob.bin") == len(data) and storage.exists("jobs/a/blob.bin")
    assert b"".join(storage.open_range("jobs/a/blob.bin")) == data
    assert b"".join(storage.open_range("jobs/a/blob.bin", 1000, 1009)) == data[1000:1010]
    assert b"".join(storage.open_range("jobs/a/blob.bin", len(data) - 5)) == data[-5:]
    assert b"".join(storage.open_range("jobs/a/blob.bin", 5, 2 * 1024 * 1024)) == data[5:2 * 1024 * 1024 + 1]
    storage.get_file("jobs/a/blob.bin", tmp_path / "copy.bin")
    assert (tmp_path / "copy.bin").read_bytes() == data
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []

    storage.put_bytes("jobs/a/small.txt", b"one")
    storage.put_bytes("jobs/a/small.txt", b"two")  # replaced whole
    assert b"".join(storage.open_range("jobs/a/small.txt")) == b"two"
    storage.put_bytes("jobs/b/other.txt", b"x")
    assert storage.list("jobs/a/") == ["jobs/a/blob.bin", "jobs/a/small.txt"]
    assert storage.list() == ["jobs/a/blob.bin", "jobs/a/small.txt", "jobs/b/other.txt"]
    assert storage.delete_prefix("jobs/a/") == 2
    assert storage.list() == ["jobs/b/other.txt"]
    storage.delete("jobs/b/other.txt")
    storage.delete("jobs/b/other.txt")  # missing: not an error
    assert storage.list() == [] and not storage.exists("jobs/b/other.txt")
    with pytest.raises(ObjectNotFound):
        storage.size("nothing/here")
    with pytest.raises(ObjectNotFound):
        storage.get_file("nothing/here", tmp_path / "x")
    assert not (tmp_path / "x").exists()
    storage.check_writable()
    assert storage.list() == [PROBE_KEY]


def test_both_backends_agree_on_tmp_keys_and_empty_ranges(storage):
    """A key may end in .tmp (only a local writer's own temporary name is hidden), and a range that starts past
    the end or ends before its start holds no bytes, on either backend."""
    storage.put_bytes("jobs/t/notes.tmp", b"kept")
    storage.put_bytes("jobs/t/data.bin", b"0123456789")
    assert storage.list("jobs/t/") == ["jobs/t/data.bin", "jobs/t/notes.tmp"]
    assert b"".join(storage.open_range("jobs/t/data.bin", 10)) == b""
    assert b"".join(storage.open_range("jobs/t/data.bin", 50, 60)) == b""
    assert b"".join(storage.open_range("jobs/t/data.bin", 5, 4)) == b""
    with pytest.raises(ObjectNotFound):
        storage.open_range("jobs/t/missing.bin", 5, 4)
    assert storage.delete_prefix("jobs/t/") == 2 and storage.list() == []


def test_deleting_a_key_that_names_no_object_is_a_no_op_on_either_backend(storage):
    """A missing key, a folder's name and a name under an object's hold no object: S3 deletes them quietly, the
    local storage had raised IsADirectoryError and NotADirectoryError for the last two."""
    storage.put_bytes("jobs/f/sub/data.bin", b"kept")
    for key in ("jobs/f/missing.bin", "jobs/g/missing.bin", "jobs/f/sub", "jobs/f", "jobs/f/sub/data.bin/x"):
        storage.delete(key)
        assert storage.list() == ["jobs/f/sub/data.bin"], key
    assert b"".join(storage.open_range("jobs/f/sub/data.bin")) == b"kept"
    storage.delete("jobs/f/sub/data.bin")
    assert storage.list() == [] and not storage.exists("jobs/f/sub/data.bin")


def test_a_range_closed_before_its_first_chunk_holds_no_file_or_connection(storage, monkeypatch):
    """A download whose client left before its first chunk: closing the stream had run none of the generator's
    code, so the open file (the S3 response, its connection) stayed held until a garbage collection."""
    storage.put_bytes("jobs/c/data.bin", b"x" * 5000)
    held = []
    if isinstance(storage, LocalStorage):
        opened = LocalStorage._open
        monkeypatch.setattr(LocalStorage, "_open", lambda self, key: held.append(opened(self, key)) or held[-1])
    else:
        get_object = storage.client.get_object

        def recorded(**kwargs):
            answer = get_object(**kwargs)
            held.append(answer["Body"]._raw_stream)  # urllib3's response: closed, its connection is let go
            return answer

        monkeypatch.setattr(storage.client, "get_object", recorded)
    for end in (None, 99):
        chunks = storage.open_range("jobs/c/data.bin", 10, end)
        assert not held[-1].closed
        chunks.close()
        assert held[-1].closed, end


@pytest.mark.parametrize("end", [None, 5, 20])
def test_a_negative_range_start_is_refused_on_either_backend(storage, end):
    """The local seek had failed with a bare "[Errno 22] Invalid argument" once read, and S3 had ignored the
    malformed Range and sent the whole object."""
    storage.put_bytes("jobs/n/data.bin", b"0123456789")
    with pytest.raises(ValueError, match=r"^open_range: start must be at least 0, got -3 \(for the last N bytes, "
                                         r"start at size - N\)$"):
        storage.open_range("jobs/n/data.bin", -3, end)
    assert b"".join(storage.open_range("jobs/n/data.bin", 7)) == b"789"


def test_both_backends_list_by_plain_prefix(storage):
    """A prefix is a plain string prefix on either backend (a folder name may be cut short); the local one walks
    only the prefix's folder, and a prefix whose folder does not exist lists nothing. One no key starts with lists
    and deletes nothing: SeaweedFS had listed "jobs//a" as "jobs/a"'s objects, named "jobs//a.txt"."""
    for key in ("jobs/a/x.bin", "jobs/ab/y.bin", "jobs/a.txt", "jobsx/z.bin", "scenes/s/data.zip"):
        storage.put_bytes(key, b"1")
    assert storage.list("jobs/a") == ["jobs/a.txt", "jobs/a/x.bin", "jobs/ab/y.bin"]
    assert storage.list("jobs/a/") == ["jobs/a/x.bin"]
    assert storage.list("jobs/a/x") == ["jobs/a/x.bin"]
    assert storage.list("jobs") == ["jobs/a.txt", "jobs/a/x.bin", "jobs/ab/y.bin", "jobsx/z.bin"]
    assert storage.list("jobs/missing/") == [] and storage.list("nowhere/at/all") == []
    assert storage.list("jobs//a") == storage.list("./") == storage.list("a b/") == []
    assert storage.delete_prefix("jobs//a") == storage.delete_prefix("./") == 0  # (SeaweedFS: "jobs//a" is "jobs/a")
    assert storage.delete_prefix("jobs/a") == 3
    assert storage.list() == ["jobsx/z.bin", "scenes/s/data.zip"]


def test_s3_objects_a_delete_kept_are_an_error(caplog):
    """S3's DeleteObjects answers 200 and names the objects it could not delete: that is a failure, as a local
    delete that fails raises."""
    class Pages:
        def paginate(self, **kwargs):
            return [{"Contents": [{"Key": "svc/jobs/j/a.png"}, {"Key": "svc/jobs/j/b.png"}]}]

    class Client:
        def get_paginator(self, name):
            return Pages()

        def delete_objects(self, Bucket, Delete):
            return {"Errors": [{"Key": Delete["Objects"][1]["Key"], "Code": "AccessDenied"}]}

    store = S3Storage("bucket", prefix="svc", create_bucket=False, client=Client())
    with pytest.raises(StorageError, match=r"could not delete 1 object\(s\) under 'jobs/j/': svc/jobs/j/b.png "
                                           r"\(AccessDenied\)"):
        store.delete_prefix("jobs/j/")
    with caplog.at_level("WARNING", logger="voxe.storage"):  # cleanup of debris: said, not raised
        store.discard_prefixes("jobs/j/")
    assert "could not delete the stored objects under jobs/j/" in caplog.text


@pytest.mark.parametrize("key", ["../etc/passwd", "/abs", "a//b", "a/./b", "a/../b", "", "a\\b", "a/b c"])
def test_keys_cannot_escape(storage, key):
    with pytest.raises(StorageError):
        storage.put_bytes(key, b"x")
    with pytest.raises(StorageError):
        check_key(key)


def test_local_keys_up_to_the_filesystem_limits_are_stored_and_longer_ones_refused_naming_the_limit(tmp_path):
    """A key part over 217 characters (255 with the temporary name's 38), or a path over 4096 bytes, had failed
    with a bare ENAMETOOLONG from inside the write, the folders of a long path already made and left behind."""
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("jobs/j/" + "n" * 217, b"x")
    killed_writer = store.path("jobs/j/" + "n" * 217).with_name(f".{'n' * 217}.{'0' * 32}.tmp")
    killed_writer.write_bytes(b"half")  # 255 characters: still deleted with its prefix, below
    with pytest.raises(StorageError, match=r"^storage key 'jobs/j/n+\.\.\.n+' \(225 characters\) is too long: its "
                                           r"name is 218 characters, the most here is 217 \(255 less the 38 of the "
                                           r"temporary name it is written under\)$"):
        store.put_bytes("jobs/j/" + "n" * 218, b"x")
    store.put_bytes("f" * 255 + "/a", b"x")
    with pytest.raises(StorageError, match="its folder 'f+'... is 256 characters, the most a file name takes here "
                                           "is 255$"):
        store.put_bytes("f" * 256 + "/a", b"x")
    room = 4096 - 1 - 38 - len(os.fsencode(store.root / "deep"))  # for "/<folder>" * k + "/<name>"
    folders = (room - 17) // 200  # of 199 characters: a name of 17 to 216 characters fills the room
    longest = "deep" + ("/" + "d" * 199) * folders + "/" + "x" * (room - 200 * folders - 1)
    assert len(os.fsencode(store.root / longest)) == 4057
    store.put_bytes(longest, b"x")
    assert b"".join(store.open_range(longest)) == b"x"
    with pytest.raises(StorageError, match=f"is too long: under {store.root} it makes a path of 4058 bytes, the "
                                           r"most here is 4057 \(4096 less"):
        store.put_bytes(longest + "x", b"x")
    with pytest.raises(StorageError, match="is too long"):  # reads say so too, not ENAMETOOLONG
        store.size("jobs/j/" + "n" * 300)
    store.delete_prefix("deep/")
    store.delete_prefix("jobs/")
    store.delete_prefix("f")
    assert list(store.root.iterdir()) == []  # nothing of the refused writes left behind


def test_s3_keys_over_1024_bytes_with_the_prefix_are_refused_naming_the_limit(aws_env, s3_endpoint, s3_server):
    """S3 refuses them (KeyTooLongError) where moto stores them: refused here, before any request."""
    store = S3Storage("voxe-test-long-keys", endpoint_url=s3_endpoint, region="us-east-1", prefix="svc")
    longest = "jobs/" + "/".join(["k" * 253] * 4)  # 4 + 1020 bytes, in parts SeaweedFS takes (below)
    store.put_bytes(longest, b"x")
    with pytest.raises(StorageError, match=r"\(1021 characters\) is too long: with the prefix 'svc/' it is 1025 "
                                           "bytes, the most an S3 key takes is 1024$"):
        store.put_bytes(longest + "k", b"x")
    assert store.list("jobs/") == [longest]
    if s3_server == "seaweedfs":  # its filer takes a key's part up to 255 bytes (a file name): the store refuses
        with pytest.raises(StorageError, match=r"\(KeyTooLongError\) when calling the PutObject operation"):
            store.put_bytes("jobs/" + "k" * 256, b"x")


def test_local_writes_are_atomic(tmp_path, monkeypatch):
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("a/b.bin", b"old")

    class Boom(Exception):
        pass

    def failing_replace(src, dst):
        raise Boom()

    monkeypatch.setattr("voxe_service.storage.os.replace", failing_replace)
    with pytest.raises(Boom):
        store.put_bytes("a/b.bin", b"new")
    monkeypatch.undo()
    assert b"".join(store.open_range("a/b.bin")) == b"old"
    assert sorted(p.name for p in (tmp_path / "store" / "a").iterdir()) == ["b.bin"]


@pytest.fixture
def synced(monkeypatch):
    """What os.fsync is called on, in order with os.replace: ("file",), ("replace",) or ("folder", its inode)."""
    calls, real_fsync, real_replace = [], os.fsync, os.replace

    def fsync(descriptor):
        info = os.fstat(descriptor)
        calls.append(("folder", info.st_ino) if stat.S_ISDIR(info.st_mode) else ("file",))
        real_fsync(descriptor)

    def replace(source, target):
        calls.append(("replace",))
        real_replace(source, target)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return calls


def test_local_put_syncs_the_folders_holding_its_rename(tmp_path, synced):
    """Only the file's bytes had been synced: a power loss after put_file returned (its key recorded) could lose the
    rename, or the folders made for it, and with them the object."""
    root = tmp_path / "store"
    store = LocalStorage(root)
    store.put_bytes("jobs/j/a.bin", b"x")
    folders = [root / "jobs" / "j", root / "jobs", root]
    assert synced == [("file",), ("replace",), *(("folder", folder.stat().st_ino) for folder in folders)]


def test_local_put_goes_on_where_folders_cannot_be_synced(tmp_path, synced, monkeypatch):
    store = LocalStorage(tmp_path / "store")
    recording_fsync = os.fsync

    def fsync(descriptor, refused=errno.EINVAL):  # a filesystem that cannot sync a folder
        if stat.S_ISDIR(os.fstat(descriptor).st_mode):
            raise OSError(refused, os.strerror(refused))
        recording_fsync(descriptor)

    monkeypatch.setattr(os, "fsync", fsync)
    store.put_bytes("jobs/j/a.bin", b"a")
    monkeypatch.setattr(os, "fsync", lambda descriptor: fsync(descriptor, errno.EIO))
    with pytest.raises(OSError, match="Input/output error"):  # a failing disk is not a missing feature
        store.put_bytes("jobs/j/b.bin", b"b")
    monkeypatch.setattr(os, "fsync", recording_fsync)
    monkeypatch.delattr(os, "O_DIRECTORY")  # a platform that cannot open a folder (Windows)
    store.put_bytes("jobs/j/c.bin", b"c")
    assert synced[-2:] == [("file",), ("replace",)]  # no folder synced
    assert [b"".join(store.open_range(f"jobs/j/{name}.bin")) for name in "ac"] == [b"a", b"c"]


def test_api_stores_uploads_in_s3(tmp_path, monkeypatch, aws_env, s3_endpoint):
    """The API with VOXE_STORAGE_BACKEND=s3: an upload lands in the bucket, nothing on the local disk."""
    from fastapi.testclient import TestClient

    from needs import require_data
    from service_helpers import MIC, reset_service_caches, service_env, small_mic, zip_folder
    from voxe_service import storage as storage_module

    require_data(MIC)
    env = service_env(tmp_path, VOXE_STORAGE_BACKEND="s3", VOXE_S3_BUCKET="voxe-api", VOXE_S3_ENDPOINT_URL=s3_endpoint,
                      VOXE_S3_REGION="us-east-1")
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    try:
        from api.main import create_app

        archive = zip_folder(small_mic(tmp_path / "mic", frames=2), tmp_path / "mic.zip")
        with TestClient(create_app()) as client:
            with open(archive, "rb") as handle:
                response = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
            assert response.status_code == 201, response.text
            scene = response.json()
            s3 = storage_module.get_storage()
            assert isinstance(s3, S3Storage)
            assert s3.list("scenes/") == [f"scenes/{scene['id']}/dataset.zip"]
            assert hashlib.sha256(b"".join(s3.open_range(f"scenes/{scene['id']}/dataset.zip"))).hexdigest() \
                == scene["sha256"]
            assert client.get("/readyz").json()["checks"]["storage"]["ok"]
            assert client.delete(f"/v1/scenes/{scene['id']}").status_code == 204
            assert s3.list("scenes/") == []
        assert not (tmp_path / "storage").exists()
    finally:
        reset_service_caches()


def test_s3_creates_a_missing_bucket_outside_us_east_1(aws_env, s3_endpoint, s3_server):
    """Outside us-east-1, S3 creates a bucket only when the request names the region (SeaweedFS, which has no
    regions, takes the request and keeps none)."""
    store = S3Storage("voxe-test-eu-west-1", endpoint_url=s3_endpoint, region="eu-west-1")
    location = store.client.get_bucket_location(Bucket="voxe-test-eu-west-1")["LocationConstraint"]
    assert location == {"moto": "eu-west-1", "seaweedfs": None}[s3_server]
    store.put_bytes("jobs/a/x.bin", b"x")
    assert b"".join(store.open_range("jobs/a/x.bin")) == b"x"


def test_s3_bucket_that_cannot_be_created_or_reached_is_a_storage_error(aws_env, s3_endpoint):
    """At startup, a bucket that cannot be created or an endpoint that does not answer is a StorageError that names
    the setting to look at, not a raw botocore error."""
    with pytest.raises(StorageError, match=r"could not create bucket 'ab' in region us-east-1 \(VOXE_S3_BUCKET, "
                                           r"VOXE_S3_REGION\): .*InvalidBucketName"):
        S3Storage("ab", endpoint_url=s3_endpoint, region="us-east-1")  # too short a name
    unreachable = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(StorageError, match=rf"could not use S3 at {unreachable} \(VOXE_S3_ENDPOINT_URL.*"
                                           r"Could not connect"):
        S3Storage("voxe-test-unreachable", endpoint_url=unreachable, region="us-east-1")


def test_local_listing_survives_a_folder_deleted_mid_walk(tmp_path, monkeypatch):
    """delete() drops the folders it empties: one dropped by another request while a listing or a prefix cleanup
    walks its parent has nothing left to list, and everything else is still listed and deleted."""
    store = LocalStorage(tmp_path / "store")
    doomed = store.path("jobs/a/doomed")
    real_scandir = os.scandir

    def scandir_after_a_concurrent_delete(path):
        if Path(path) == doomed and store.exists("jobs/a/doomed/f.bin"):  # seen by its parent's scan, then deleted
            store.delete("jobs/a/doomed/f.bin")
        return real_scandir(path)

    for key in ("jobs/a/doomed/f.bin", "jobs/a/kept/g.bin", "jobs/a/h.bin"):
        store.put_bytes(key, b"x")
    monkeypatch.setattr(os, "scandir", scandir_after_a_concurrent_delete)
    assert store.list("jobs/") == ["jobs/a/h.bin", "jobs/a/kept/g.bin"] and not doomed.exists()

    store.put_bytes("jobs/a/doomed/f.bin", b"x")
    store.discard_prefixes("jobs/a/")  # an overlapping cleanup: it had left everything behind
    assert store.list() == [] and not doomed.exists()


def test_local_written_at_reads_a_folder_at_a_time_not_the_whole_store_first(tmp_path, monkeypatch):
    """The reaper's hourly sweep reads written_at("jobs/") and the others: every stored file. The local storage had
    walked the whole tree into a list before the first key came (some 260 bytes a file, measured: 5.3 MB for 20,000
    files, hundreds of MB in the API process for a store of millions). It now yields as it walks: the first key comes
    once its own folder is read, and the whole walk still gives every key, a writer's temporary file included."""
    store = LocalStorage(tmp_path / "store")
    jobs = [f"{n:032x}" for n in range(40)]
    for job in jobs:
        for name in ("grid.safetensors", "renders/ring_000.png"):
            store.put_bytes(f"jobs/{job}/{name}", b"x")
    store.path(f"jobs/{jobs[0]}/.grid.safetensors.{'0' * 32}.tmp").write_bytes(b"x")
    real_scandir, scanned = os.scandir, []

    def counting_scandir(path):
        scanned.append(Path(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", counting_scandir)
    listing = store.written_at("jobs/")
    first, _when = next(listing)
    assert first.startswith("jobs/") and len(scanned) == 2, scanned  # jobs/, then the first job's folder
    rest = [key for key, _when in listing]
    assert len(scanned) == 1 + 2 * len(jobs)  # (each job's folder and its renders/, read once)
    assert sorted([first, *rest]) == sorted([f"jobs/{job}/{name}" for job in jobs
                                             for name in ("grid.safetensors", "renders/ring_000.png")]
                                            + [f"jobs/{jobs[0]}/.grid.safetensors.{'0' * 32}.tmp"])


@pytest.mark.parametrize("step, deleted_first", [
    ("mkdir", False),  # the folder goes after put_file made it, before its temporary file is created
    ("is_dir", True),  # inside mkdir(exist_ok=True): after it found the folder there, before it checked it is one
])
def test_local_put_survives_its_folder_deleted_midway(tmp_path, monkeypatch, step, deleted_first):
    """Another request deleting the last object of a folder drops the folder: when that falls in the middle of
    put_file making the folder and its temporary file, the put makes the folder again."""
    store = LocalStorage(tmp_path / "store")
    store.put_bytes("jobs/j/old.bin", b"old")
    real_step = getattr(Path, step)

    def concurrent_delete():
        if store.exists("jobs/j/old.bin"):
            store.delete("jobs/j/old.bin")

    def step_with_a_concurrent_delete(self, *args, **kwargs):
        if deleted_first:
            concurrent_delete()
        result = real_step(self, *args, **kwargs)
        if not deleted_first:
            concurrent_delete()
        return result

    monkeypatch.setattr(Path, step, step_with_a_concurrent_delete)
    assert store.put_bytes("jobs/j/new.bin", b"new").size == 3
    assert store.list() == ["jobs/j/new.bin"] and b"".join(store.open_range("jobs/j/new.bin")) == b"new"


def test_local_reads_racing_a_delete_say_object_not_found(tmp_path, monkeypatch):
    """A delete that comes just before the object's file is opened is a missing object, and leaves no partial
    download behind."""
    store = LocalStorage(tmp_path / "store")
    object_path = str(store.path("jobs/a/x.bin"))
    real_open = builtins.open

    def open_after_a_concurrent_delete(file, *args, **kwargs):
        if str(file) == object_path:
            store.delete("jobs/a/x.bin")
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", open_after_a_concurrent_delete)
    for read in (lambda: store.get_file("jobs/a/x.bin", tmp_path / "download" / "x.bin"),
                 lambda: store.open_range("jobs/a/x.bin")):
        store.put_bytes("jobs/a/x.bin", b"x")
        with pytest.raises(ObjectNotFound):
            read()
    assert list((tmp_path / "download").glob("*")) == []


@pytest.fixture
def full_disk(tmp_path, monkeypatch):
    """A temporary-files folder (returned) on a disk where every write of a temporary file fails."""
    folder = tmp_path / "tmpdir"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    real_named_temporary_file = tempfile.NamedTemporaryFile

    def named_temporary_file_on_a_full_disk(*args, **kwargs):
        handle = real_named_temporary_file(*args, **kwargs)

        def write(data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        handle.write = write
        return handle

    monkeypatch.setattr(tempfile, "NamedTemporaryFile", named_temporary_file_on_a_full_disk)
    return folder


def test_put_bytes_that_fails_to_write_leaves_no_temporary_file(tmp_path, full_disk):
    """check_writable puts bytes on every readiness probe: on a full disk each one had left a file behind."""
    store = LocalStorage(tmp_path / "store")
    for _ in range(3):
        with pytest.raises(OSError, match="No space left on device"):
            store.put_bytes("jobs/a/x.bin", b"x")
    assert list(full_disk.iterdir()) == [] and store.list() == []


def test_readiness_probes_leave_one_object_where_deletes_are_denied_and_pass_at_once(storage, monkeypatch):
    """Each readiness probe had written its own _probe/<uuid> and deleted it: where the delete was denied (a role
    without s3:DeleteObject) or failed, one object a probe stayed for good. They write and read back one object,
    probes at once (threads, replicas) all passing."""
    from concurrent.futures import ThreadPoolExecutor

    def denied(key):
        raise StorageError(f"AccessDenied deleting {key}")

    monkeypatch.setattr(storage, "delete", denied)
    for _ in range(3):
        storage.check_writable()
    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(lambda _: storage.check_writable(), range(8))) == [None] * 8
    assert storage.list("_probe/") == [PROBE_KEY]


def test_local_check_writable_on_a_full_disk_is_a_storage_error(tmp_path, full_disk):
    """check_writable raises StorageError when storage cannot be written, as its docstring says."""
    with pytest.raises(StorageError, match="No space left on device"):
        LocalStorage(tmp_path / "store").check_writable()


def test_s3_unreachable_endpoint_is_a_storage_error(aws_env):
    """An S3 endpoint that does not answer is a StorageError (check_writable's promise), not botocore's error."""
    unreachable = S3Storage("voxe", endpoint_url=f"http://127.0.0.1:{free_port()}", region="us-east-1",
                            create_bucket=False)
    with pytest.raises(StorageError, match="Could not connect"):
        unreachable.size("jobs/a/x.bin")
    with pytest.raises(StorageError, match="Could not connect"):
        unreachable.check_writable()


def test_s3_endpoint_that_accepts_and_never_answers_is_unavailable_within_its_timeout(aws_env, monkeypatch):
    """A hung or partitioned S3 endpoint (the TCP connection made, no answer ever): each of boto3's tries had
    waited its 60 s read timeout, so an upload or a download held its request 6 minutes before its 503. Now each
    try waits VOXE_S3_TIMEOUT_S, and the request fails as a storage that cannot serve now (the API's 503) after
    the five tries the README states (botocore's max_attempts 5 had made six)."""
    import time

    from service_helpers import outcome_within, silent_server
    from voxe_service import storage as storage_module
    from voxe_service.settings import Settings
    from voxe_service.storage import StorageUnavailable, get_storage

    monkeypatch.setattr(S3Storage, "_ensure_bucket", lambda self: None)  # the bucket was there at the start
    monkeypatch.setattr(storage_module, "_instances", {})
    with silent_server() as (port, accepted):
        settings = Settings(storage_backend="s3", s3_endpoint_url=f"http://127.0.0.1:{port}", s3_region="us-east-1",
                            s3_timeout_s=0.5)
        started = time.monotonic()
        outcome = outcome_within(lambda: get_storage(settings).size("jobs/a/x.bin"), 60)
        assert outcome, "the read still waited on the silent endpoint after 60 s"
        assert isinstance(outcome[0], StorageUnavailable) and "Read timeout" in str(outcome[0]), outcome
        assert time.monotonic() - started < 30  # five tries of 0.5 s, and boto3's pauses between
        assert len(accepted) == 5


def test_s3_missing_bucket_is_a_storage_error_not_a_missing_key(aws_env, s3_endpoint, s3_server, tmp_path):
    """A HEAD answers a missing bucket with the bare 404 of a missing key: a bucket gone is still a StorageError,
    never ObjectNotFound (exists() saying False would have a worker start over without its checkpoint). The writes
    last, and on moto only: SeaweedFS makes the bucket again on an upload (for its admin identities; AccessDenied
    for others)."""
    store = S3Storage("voxe-test-gone", endpoint_url=s3_endpoint, region="us-east-1", prefix="svc")
    store.client.delete_bucket(Bucket="voxe-test-gone")
    said_missing = r"bucket 'voxe-test-gone' does not exist \(VOXE_S3_BUCKET\)"
    calls = {
        "size": (lambda: store.size("jobs/a/x.bin"), said_missing),
        "exists": (lambda: store.exists("jobs/a/x.bin"), said_missing),
        "get_file": (lambda: store.get_file("jobs/a/x.bin", tmp_path / "x.bin"), said_missing),
        "open_range": (lambda: store.open_range("jobs/a/x.bin"), said_missing),
        "list": (lambda: store.list("jobs/"), said_missing),
        "delete_prefix": (lambda: store.delete_prefix("jobs/"), said_missing),
    }
    if s3_server == "moto":
        calls["put_bytes"] = (lambda: store.put_bytes("jobs/a/x.bin", b"x"), said_missing)  # (boto3 wraps its error)
        calls["check_writable"] = (store.check_writable, said_missing)
    for name, (call, message) in calls.items():
        with pytest.raises(StorageError, match=message) as raised:
            call()
        assert not isinstance(raised.value, ObjectNotFound), name
    assert list(tmp_path.iterdir()) == []  # no partial download


class _Answer:
    """A canned HTTP body for botocore (``before-send`` handlers answer in S3's place: the tests that use them run
    against moto alone, botocore's retries' waits being most of their time; a multipart upload's abort on SeaweedFS is
    test_service_faults.py's)."""

    def __init__(self, body: bytes):
        self.body = body

    def read(self, amt=None):
        body, self.body = self.body, b""
        return body

    def stream(self, **_kwargs):
        yield self.read()


@pytest.mark.parametrize("size, refused", [(10, "PutObject"), (9 << 20, "UploadPart")])  # 9 MiB: a multipart upload
def test_s3_throttled_upload_is_unavailable_and_leaves_nothing(aws_env, moto_endpoint, tmp_path, size, refused):
    """An upload S3 throttles (503 SlowDown, after botocore's retries) is a StorageUnavailable, as a throttled read
    is: the API answers 503 with Retry-After, and a fit whose checkpoint it was hands the fit back rather than
    failing every job waiting on it. boto3 wraps an upload's error in its own S3UploadFailedError, which had been a
    plain StorageError. Nothing is listed, and a multipart upload is aborted."""
    from botocore.awsrequest import AWSResponse

    from voxe_service.storage import StorageUnavailable

    store = S3Storage("voxe-test-throttled", endpoint_url=moto_endpoint, region="us-east-1", prefix="svc")
    throttled = b"<?xml version='1.0'?><Error><Code>SlowDown</Code><Message>Reduce your request rate.</Message></Error>"
    store.client.meta.events.register(f"before-send.s3.{refused}",
                                      lambda request, **_: AWSResponse(request.url, 503, {}, _Answer(throttled)))
    source = tmp_path / "blob.bin"
    source.write_bytes(b"x" * size)
    with pytest.raises(StorageUnavailable, match=rf"\(SlowDown\) when calling the {refused} operation"):
        store.put_file("jobs/a/blob.bin", source)
    assert store.list() == []
    assert store.client.list_multipart_uploads(Bucket="voxe-test-throttled").get("Uploads", []) == []


def test_s3_answering_429_too_many_requests_is_unavailable(aws_env, moto_endpoint):
    """An S3-compatible store that rate-limits with HTTP 429 under a code of its own (TooManyRequests, not AWS's
    503 SlowDown) is throttling: a StorageUnavailable (the API's 503 + Retry-After, a fit handed back), where it had
    been a plain StorageError (a 500, a fit failed with every job waiting on it) though botocore had retried it."""
    from botocore.awsrequest import AWSResponse

    from voxe_service.storage import StorageUnavailable

    store = S3Storage("voxe-test-429", endpoint_url=moto_endpoint, region="us-east-1", prefix="svc")
    store.put_bytes("jobs/a/x.bin", b"x")
    limited = b"<?xml version='1.0'?><Error><Code>TooManyRequests</Code><Message>Slow down.</Message></Error>"
    store.client.meta.events.register("before-send.s3.HeadObject",
                                      lambda request, **_: AWSResponse(request.url, 429, {}, _Answer(limited)))
    with pytest.raises(StorageUnavailable, match=r"\(TooManyRequests\) when calling the HeadObject operation"):
        store.size("jobs/a/x.bin")


def test_s3_download_broken_off_on_every_retry_is_unavailable(aws_env, moto_endpoint, tmp_path):
    """A download whose body breaks off (a connection reset, a read timeout) through every retry is a
    StorageUnavailable naming what broke, not boto3's bare "Max Retries Exceeded" as a StorageError; nothing is
    left at the destination."""
    from botocore.awsrequest import AWSResponse

    from voxe_service.storage import StorageUnavailable

    store = S3Storage("voxe-test-broken-off", endpoint_url=moto_endpoint, region="us-east-1", prefix="svc")
    store.put_bytes("jobs/a/x.bin", b"0123456789")
    store.client.meta.events.register(  # 4 bytes of the 10 announced, then the connection ends
        "before-send.s3.GetObject",
        lambda request, **_: AWSResponse(request.url, 200, {"Content-Length": "10"}, _Answer(b"0123")))
    with pytest.raises(StorageUnavailable, match=r"a download broke off on every retry: IncompleteReadError: 4 read, "
                                                 r"but total bytes expected is 10"):
        store.get_file("jobs/a/x.bin", tmp_path / "x.bin")
    assert list(tmp_path.iterdir()) == []


def test_a_scratch_folder_the_sweep_could_not_delete_is_not_counted_removed(tmp_path, monkeypatch, caplog):
    """A dead process's scratch folder holding a file that could not be deleted had been counted removed all the
    same (the ingest logging 'removed 2 folder(s)' with one left): it is counted, and gone, once a sweep deletes it."""
    import logging

    from voxe_service.scratch import OWNER, sweep_unlocked

    for name in ("run-stuck", "run-dead"):  # folders whose processes died: no lock held
        (tmp_path / name).mkdir()
        (tmp_path / name / OWNER).touch()
        (tmp_path / name / f"{name}.bin").write_bytes(b"x")
    unlink = os.unlink

    def refusing(path, *args, **kwargs):
        if os.fspath(path).endswith("run-stuck.bin"):
            raise PermissionError(errno.EACCES, "Permission denied", path)
        return unlink(path, *args, **kwargs)

    monkeypatch.setattr(os, "unlink", refusing)
    with caplog.at_level(logging.WARNING, logger="voxe.scratch"):
        assert sweep_unlocked(tmp_path, "run-*") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run-stuck"]
    assert [r.getMessage() for r in caplog.records] == [
        f"scratch folder {tmp_path / 'run-stuck'} could not be removed whole; the next sweep tries again"]
    monkeypatch.setattr(os, "unlink", unlink)
    assert sweep_unlocked(tmp_path, "run-*") == 1 and list(tmp_path.iterdir()) == []
